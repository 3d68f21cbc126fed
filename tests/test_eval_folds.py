"""The folds of ``bench.eval_segmentation --folds``: a setting is chosen on the other takes only."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from bench.eval_segmentation import Runs, Take, choose, f1, pooled
from daemon.types import Band


def take(name: str, boundaries: int) -> Take:
    bands = [Band(100 * i, 100 * i - 10, 100 * i + 10) for i in range(1, boundaries + 1)]
    return Take(name, np.zeros((1, 1)), 120.0, [1], bands, [])


@given(
    st.lists(st.integers(1, 6), min_size=2, max_size=5),
    st.integers(1, 5),
    st.data(),
)
def test_the_choice_is_the_best_pooled_f1_on_the_other_takes(
    boundaries: list[int], settings: int, data: st.DataObject
) -> None:
    takes = [take(f"t{i}", b) for i, b in enumerate(boundaries)]
    runs: Runs = {}
    for k in range(settings):
        for t in takes:
            hits = data.draw(st.integers(0, len(t.bands)))
            runs[k, t.trial] = (hits + data.draw(st.integers(0, 4)), hits)
    out, rest = takes[0], takes[1:]
    best = choose(runs, settings, rest)
    scores = [f1(*pooled(runs, k, rest)) for k in range(settings)]
    assert scores[best] == max(scores) and best == scores.index(max(scores))
    # what the held-out take scores never changes the choice
    spoiled = {**runs, **{(k, out.trial): (0, 0) for k in range(settings)}}
    assert choose(spoiled, settings, rest) == best


def test_pooled_sums_hits_cuts_and_boundaries() -> None:
    a, b = take("a", 2), take("b", 3)
    runs: Runs = {(0, "a"): (4, 2), (0, "b"): (1, 1)}
    assert pooled(runs, 0, [a, b]) == (3, 5, 5)
    assert f1(3, 5, 5) == 0.6
