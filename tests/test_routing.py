"""Which worker of ``mocapd run --workers N`` takes a stream (:mod:`protocols.routing`): always the
same one, in this process and in another with another hash seed, and the streams spread evenly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocols.routing import Routes, mine, split, stream_of, worker_of
from tests.helpers import REPO

ID_CHARS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_:@-"
stream_ids = st.text(ID_CHARS, min_size=1, max_size=128)


@given(stream_ids, st.sampled_from(["pose", "skeleton", "detections"]), st.integers(1, 64))
def test_a_stream_has_one_worker_whatever_its_message(stream: str, word: str, workers: int) -> None:
    k = worker_of(stream_of(f"mocap/{stream}/{word}"), workers)
    assert 0 <= k < workers
    assert k == worker_of(stream, workers) == worker_of(stream_of(f"mocap/{stream}/pose"), workers)


@given(st.text(max_size=40))
def test_any_topic_has_a_worker(topic: str) -> None:
    assert 0 <= worker_of(stream_of(topic), 3) < 3


def test_one_worker_takes_everything() -> None:
    assert {worker_of(f"s{k}", 1) for k in range(100)} == {0}
    with pytest.raises(ValueError, match="workers must be at least 1"):
        worker_of("s", 0)


def test_the_same_in_another_process_with_another_hash_seed() -> None:
    """Not Python's salted hash(): a restarted daemon sends every stream where it went before."""
    names = [f"studio-{k}" for k in range(200)]
    code = (
        "import json, sys; from protocols.routing import worker_of; "
        "print(json.dumps([worker_of(n, 7) for n in json.load(sys.stdin)]))"
    )
    theirs = subprocess.run(
        [sys.executable, "-c", code],
        input=json.dumps(names),
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
        env={**os.environ, "PYTHONHASHSEED": "12345", "PYTHONPATH": str(REPO)},
    )
    assert json.loads(theirs.stdout) == [worker_of(n, 7) for n in names]


@pytest.mark.parametrize("workers", [2, 3, 4, 8])
@pytest.mark.parametrize("pattern", ["w150-{}", "studio-{}", "{}", "cam{:04d}@hall.a"])
def test_numbered_ids_spread_evenly(workers: int, pattern: str) -> None:
    """1200 ids of one naming pattern: every worker gets its share within 25% (a binomial's 4
    standard deviations at 8 workers are about 15%)."""
    counts = Counter(worker_of(pattern.format(k), workers) for k in range(1200))
    share = 1200 / workers
    assert set(counts) == set(range(workers))
    assert all(abs(n - share) < 0.25 * share for n in counts.values()), counts


@settings(max_examples=20)
@given(st.lists(stream_ids, min_size=400, max_size=400, unique=True))
def test_random_ids_spread_over_two_workers(names: list[str]) -> None:
    """No set of distinct ids lands lopsided: of 400, each of two workers gets 120 or more (a
    binomial's 8 standard deviations)."""
    ones = sum(worker_of(n, 2) for n in names)
    assert 120 <= ones <= 280


@given(stream_ids, st.lists(stream_ids, max_size=20), st.integers(1, 6))
def test_a_frame_message_reaches_every_worker_and_each_takes_its_own_subjects(
    source: str, subjects: list[str], workers: int
) -> None:
    """A frame message (``mocap/<source>/frame``) goes to every worker; of its subjects, each worker
    takes exactly those :func:`worker_of` gives it, so every subject is taken once."""
    message = [f"mocap/{source}/frame".encode(), b"payload"]
    assert split([message], Routes(workers, 100), workers) == [message] * workers
    owners = [mine(k, workers, cached=3) for k in range(workers)]
    for stream in subjects * 2:  # twice: the second time remembered (or forgotten: 3 at most)
        assert [k for k, owned in enumerate(owners) if owned(stream)] == [worker_of(stream, workers)]
