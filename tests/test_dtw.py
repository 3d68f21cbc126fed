"""daemon/dtw.py against slow, cell-by-cell readings of its docstrings in fixed point: full DTW and its
warping path (thesis Alg. 3.1/3.2, Def. 3.1), subsequence DTW with starts for both step kinds, local
minima, the toolbox's non-maximum suppression, SPRING's disjoint matches (stream and batch twin) and
the cost functions of thesis eq. (3.2)/(3.3).

The references work on the integer matrix ``dtw.fixed(C)`` with plain Python loops and clamp every sum
at ``INF`` (unreachable), so they must agree with the vectorised module bit for bit, ties included."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from daemon import dtw
from daemon._dtw import StreamDTW
from daemon.dtw import INF, SCALE, Match, Steps
from daemon.types import FloatArray
from tests.naive import (
    WarpPath,
    as_cost,
    brute_and,
    ceil_div,
    grid,
    ref_full,
    ref_local_minima,
    ref_spring,
    ref_subsequence,
    ref_suppress,
    slow_blocks,
    slow_minimum,
)

SETTINGS = settings(max_examples=300, deadline=None)

# ---------------------------------------------------------------------------------- references


def is_warping_path(path: WarpPath, m: int, n: int) -> bool:
    """Def. 3.1 (0-based): from (0, 0) to (m-1, n-1) with steps (1,0), (0,1), (1,1)."""
    steps = {(a2 - a1, b2 - b1) for (a1, b1), (a2, b2) in pairwise(path)}
    return path[0] == (0, 0) and path[-1] == (m - 1, n - 1) and steps <= {(1, 0), (0, 1), (1, 1)}


def run_stream(stream: dtw.SubsequenceStream, cost: FloatArray) -> list[Match]:
    """Push every column of ``cost``, then flush: all the matches reported (at most one a call)."""
    reported = [stream.push(cost[:, t]) for t in range(cost.shape[1])] + [stream.flush()]
    assert all(len(r) <= 1 for r in reported)
    return [m for r in reported for m in r]


# ---------------------------------------------------------------------------------- strategies


@st.composite
def cost_matrices(
    draw: st.DrawFn, min_m: int = 1, max_m: int = 6, min_n: int = 1, max_n: int = 25
) -> FloatArray:
    """(M, N) costs: small integers or halves (many ties) or floats, with a few whole inf columns
    (separators between documents) and single inf/NaN cells."""
    m, n = draw(st.integers(min_m, max_m)), draw(st.integers(min_n, max_n))
    values = draw(
        st.sampled_from(
            [
                st.integers(0, 3).map(float),
                st.sampled_from([0.0, 0.5, 1.0]),
                st.floats(0, 4),
                st.floats(0, 64),
            ]
        )
    )
    c = np.array(draw(st.lists(values, min_size=m * n, max_size=m * n)), dtype=np.float64).reshape(m, n)
    c[:, draw(st.lists(st.integers(0, n - 1), max_size=3))] = np.inf
    for i, j in draw(st.lists(st.tuples(st.integers(0, m - 1), st.integers(0, n - 1)), max_size=3)):
        c[i, j] = draw(st.sampled_from([np.inf, np.nan]))
    return c


taus = st.one_of(st.integers(0, 12).map(float), st.floats(0, 12))
steps_kinds = st.sampled_from(dtw.STEPS)


def ternary(f: int, n: int) -> st.SearchStrategy[FloatArray]:
    """(f, n) arrays over {0, ½, 1}."""
    return st.lists(st.sampled_from([0.0, 0.5, 1.0]), min_size=f * n, max_size=f * n).map(
        lambda v: np.array(v, dtype=np.float64).reshape(f, n)
    )


# ---------------------------------------------------------------------------------- fixed point, errors


def test_fixed_point() -> None:
    assert dtw.fixed([0.0, 1.0, 0.5, 64.0]).tolist() == [0, SCALE, SCALE // 2, 64 * SCALE]
    assert dtw.fixed([np.inf, np.nan]).tolist() == [INF, INF]
    assert dtw.fixed(3 * 2.0**-26).tolist() == 1  # round(0.75) = 1
    assert dtw.to_cost(np.array([SCALE, INF, INF + 1])).tolist() == [1.0, np.inf, np.inf]


@pytest.mark.parametrize("bad", [-1.0, -1e-12, 64.000001, 100.0])
def test_fixed_rejects_out_of_range(bad: float) -> None:
    with pytest.raises(ValueError, match=r"\[0, 64\]"):
        dtw.fixed(np.array([[0.0, bad]]))


def test_errors() -> None:
    with pytest.raises(ValueError, match=r"thesis, toolbox, got 'foo'"):
        dtw.check_steps("foo")
    with pytest.raises(ValueError, match="thesis, toolbox"):
        dtw.subsequence_dtw(np.zeros((2, 2)), "foo")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="thesis, toolbox"):
        dtw.SubsequenceStream(2, 1.0, "foo")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="at least one"):
        dtw.SubsequenceStream(0, 1.0)
    stream = dtw.SubsequenceStream(3, 1.0)
    for wrong in (np.zeros(2), np.zeros(4), np.zeros((3, 1))):
        with pytest.raises(ValueError, match="expected 3 template costs"):
            stream.push(wrong)
    for empty in (np.zeros((0, 3)), np.zeros((3, 0)), np.zeros(3)):
        with pytest.raises(ValueError, match="non-empty"):
            dtw.full_dtw(empty)


# ---------------------------------------------------------------------------------- full DTW


def test_thesis_definition_3_1_example() -> None:
    """Def. 3.1's example path for N = 7, M = 5 (1-based pairs (n, m)) is a warping path."""
    p = [(1, 1), (2, 2), (3, 3), (4, 3), (5, 4), (6, 4), (7, 5)]
    assert is_warping_path([(a - 1, b - 1) for a, b in p], 7, 5)
    # The checker does reject what Def. 3.1 forbids: a jump, a step back, a wrong end, a wrong start.
    assert not is_warping_path([(0, 0), (2, 2), (3, 3), (4, 4)], 5, 5)
    assert not is_warping_path([(0, 0), (1, 1), (1, 0), (2, 1)], 3, 2)
    assert not is_warping_path([(0, 0), (1, 1)], 3, 2)
    assert not is_warping_path([(0, 1), (1, 1)], 2, 2)


def test_full_dtw_hand_examples() -> None:
    # D = [[0, 1], [1, 0]]: the diagonal, cost 0.
    a = dtw.full_dtw(np.array([[0.0, 1.0], [1.0, 0.0]]))
    assert a.cost == 0.0 and a.path.tolist() == [[0, 0], [1, 1]]
    # All zeros, 2 x 3: D = 0 everywhere. From (1, 2) the three predecessors tie: the diagonal wins
    # -> (0, 1), then row 0 goes left. Preferring the database step would give (0,0), (1,1), (1,2).
    a = dtw.full_dtw(np.zeros((2, 3)))
    assert a.cost == 0.0 and a.path.tolist() == [[0, 0], [0, 1], [1, 2]]
    # C = [[0, 0], [1, 2], [0, 0]]: D = [[0, 0], [1, 2], [1, 1]]. From (2, 1): diagonal D(1,0) = 1 and
    # database step D(2,0) = 1 tie -> diagonal; from (1, 0) up. Cost 1.
    a = dtw.full_dtw(np.array([[0.0, 0.0], [1.0, 2.0], [0.0, 0.0]]))
    assert a.cost == 1.0 and a.path.tolist() == [[0, 0], [1, 0], [2, 1]]
    # Blocked cells: every path crosses an inf column, so the cost is inf, and the path is still one.
    a = dtw.full_dtw(np.array([[0.0, np.inf, 0.0], [0.0, np.inf, 0.0]]))
    assert a.cost == np.inf and is_warping_path([(i, j) for i, j in a.path.tolist()], 2, 3)


@settings(SETTINGS, max_examples=200)
@given(cost_matrices())
def test_full_dtw_equals_reference(cost: FloatArray) -> None:
    c = grid(cost)
    d, path = ref_full(c)
    got = dtw.full_dtw(cost)
    assert got.cost == as_cost(d[-1][-1])
    assert got.path.dtype == np.int64 and got.path.shape == (len(path), 2)
    assert [(int(i), int(j)) for i, j in got.path] == path
    assert dtw.accumulated(dtw.fixed(cost)).tolist() == d
    assert is_warping_path(path, len(c), len(c[0]))
    assert min(sum(c[i][j] for i, j in path), INF) == d[-1][-1]


# ---------------------------------------------------------------------------------- subsequence DTW


def test_subsequence_tie_order_thesis() -> None:
    # C = [[0, 5, 0], [0, 0, 0]]: D row 0 = [0, 5, 0], starts [0, 1, 2]; D(1,0) = 0 (start 0),
    # D(1,1) = 0 + min(D(0,0)=0, D(1,0)=0, D(0,1)=5) = 0 (start 0), D(1,2) = 0 + min(D(0,1)=5,
    # D(1,1)=0, D(0,2)=0): the database step beats the template step -> start 0 (wrong order: 2).
    sub = dtw.subsequence_dtw(np.array([[0.0, 5.0, 0.0], [0.0, 0.0, 0.0]]))
    assert sub.delta.tolist() == [0.0, 0.0, 0.0] and sub.start.tolist() == [0, 0, 0]
    # C = [[0, 1, 9], [1, 1, 0]]: row 0 = [0, 1, 9]; D(1,0) = 1 (start 0); D(1,1) = 1 + min(0, 1, 1)
    # = 1 from the diagonal (start 0); D(1,2) = 0 + min(D(0,1)=1 start 1, D(1,1)=1 start 0, 9): the
    # diagonal beats the database step -> start 1 (wrong order: 0).
    sub = dtw.subsequence_dtw(np.array([[0.0, 1.0, 9.0], [1.0, 1.0, 0.0]]))
    assert sub.delta.tolist() == [1.0, 1.0, 1.0] and sub.start.tolist() == [0, 0, 1]
    ref = ref_subsequence(grid(np.array([[0.0, 1.0, 9.0], [1.0, 1.0, 0.0]])), "thesis")
    assert ref[1][-1] == [0, 0, 1]  # the reference agrees with the hand computation


def test_subsequence_tie_order_and_weights_toolbox() -> None:
    # C = [[0, 0, 5], [9, 9, 1]]: D(1,0) has no predecessor -> inf; D(1,1) = 9 + D(0,0) (start 0);
    # D(1,2) = 1 + min(D(0,1)=0 start 1, D(0,0)=0 start 0): step (1,1) beats (1,2) -> start 1.
    sub = dtw.subsequence_dtw(np.array([[0.0, 0.0, 5.0], [9.0, 9.0, 1.0]]), "toolbox")
    assert sub.delta.tolist() == [np.inf, 9.0, 1.0] and sub.start.tolist() == [-1, 0, 1]
    # C = [[3, 0, 9], [9, 1, 9], [9, 9, 5]]: D(1,1) = 1 + 3 = 4 (start 0). D(2,2): predecessors
    # D(1,1)=4 (w 1), D(1,0)=inf, D(0,1)=0 (w 2): the smallest is D(0,1), then the weight: 0 + 2*5 = 10,
    # start 1 (weighting before choosing would pick 4 + 5 = 9, start 0). D(2,1) = D(0,0) + 2*9 = 21.
    sub = dtw.subsequence_dtw(np.array([[3.0, 0.0, 9.0], [9.0, 1.0, 9.0], [9.0, 9.0, 5.0]]), "toolbox")
    assert sub.delta.tolist() == [np.inf, 21.0, 10.0] and sub.start.tolist() == [-1, 0, 1]


@pytest.mark.slow
@SETTINGS
@given(cost_matrices(), steps_kinds)
def test_subsequence_equals_reference(cost: FloatArray, steps: Steps) -> None:
    c = grid(cost)
    d, s = ref_subsequence(c, steps)
    got = dtw.subsequence_dtw(cost, steps)
    assert got.delta.tolist() == [as_cost(v) for v in d[-1]]
    assert got.start.tolist() == s[-1]
    delta, start = dtw.subsequence_fixed(iter(dtw.fixed(cost)), steps)
    assert delta.tolist() == d[-1] and start.tolist() == s[-1]


@settings(SETTINGS, max_examples=80)
@given(cost_matrices(max_n=10))
def test_subsequence_thesis_is_best_full_dtw_of_a_slice(cost: FloatArray) -> None:
    """With the thesis steps, Δ(b) is the smallest full DTW of C[:, a:b+1] over a, and the start found
    is such an a."""
    sub = dtw.subsequence_dtw(cost)
    for b in range(cost.shape[1]):
        full = [dtw.full_dtw(cost[:, a : b + 1]).cost for a in range(b + 1)]
        assert sub.delta[b] == min(full)
        if sub.delta[b] < np.inf:
            assert full[sub.start[b]] == sub.delta[b]
        else:
            assert sub.start[b] == -1


# ---------------------------------------------------------------------------------- local minima, suppression


@settings(SETTINGS, max_examples=200)
@given(
    st.lists(st.one_of(st.integers(0, 3).map(float), st.just(np.inf), st.floats(0, 4)), max_size=25),
    taus,
)
def test_local_minima_equal_brute_force(values: list[float], tau: float) -> None:
    delta = np.array(values, dtype=np.float64)
    start = np.arange(len(values), dtype=np.int64) * 7 - 3
    assert dtw.local_minima(delta, start, tau) == ref_local_minima(delta, start, tau)


def test_local_minima_plateau() -> None:
    delta = np.array([2.0, 1.0, 1.0, 3.0, 0.0, 0.0, np.inf, 1.0])
    got = dtw.local_minima(delta, np.arange(8, dtype=np.int64), 1.0)
    assert got == [Match(1, 1, 1.0), Match(4, 4, 0.0), Match(7, 7, 1.0)]
    # An unreachable column is no minimum, even for tau = inf (the column before the first counts as
    # inf, and inf < inf is false).
    got = dtw.local_minima(np.array([np.inf, np.inf, 2.0]), np.array([-1, -1, 2]), np.inf)
    assert got == [Match(2, 2, 2.0)]


def test_suppress_hand_example() -> None:
    # First kept (L = 10): starts masked in [-1, 5], ends in [4, 10]. (2, 12): start in that zone ->
    # dropped, masks ends [12 - 5, 12 + 1] = [7, 13] with L = 10. (11, 13): end masked. (20, 29) kept.
    a, b, c, d = Match(0, 9, 1.0), Match(2, 12, 2.0), Match(11, 13, 2.5), Match(20, 29, 3.0)
    assert dtw.suppress([d, c, b, a]) == [a, d]
    assert dtw.suppress([d, c, b, a], limit=1) == [a]
    assert dtw.suppress([]) == []
    # Equal costs: the earlier end goes first.
    assert dtw.suppress([Match(3, 6, 1.0), Match(0, 5, 1.0)]) == [Match(0, 5, 1.0)]


matches = st.builds(
    lambda s, length, cost: Match(s, s + length - 1, float(cost)),
    st.integers(0, 80),
    st.integers(1, 45),
    st.integers(0, 5),
)


@SETTINGS
@given(st.lists(matches, max_size=30), st.one_of(st.none(), st.integers(0, 6)))
def test_suppress_equals_brute_force(candidates: list[Match], limit: int | None) -> None:
    kept = dtw.suppress(candidates, limit)
    assert kept == ref_suppress(candidates, limit)
    assert kept == dtw.suppress(candidates)[:limit]
    assert limit is None or len(kept) <= limit
    assert all(a.cost <= b.cost for a, b in pairwise(kept))
    for k, later in enumerate(kept):
        for earlier in kept[:k]:
            length = earlier.end - earlier.start + 1
            zone = range(earlier.start - ceil_div(length, 10), earlier.start + ceil_div(length, 2) + 1)
            assert later.start not in zone
            assert later.end not in range(
                earlier.end - ceil_div(length, 2), earlier.end + ceil_div(length, 10) + 1
            )


@settings(SETTINGS, max_examples=150)
@given(cost_matrices(), steps_kinds, taus)
def test_subsequence_matches_pipeline(cost: FloatArray, steps: Steps, tau: float) -> None:
    sub = dtw.subsequence_dtw(cost, steps)
    expected = ref_suppress(ref_local_minima(sub.delta, sub.start, tau), 3)
    assert dtw.subsequence_matches(cost, tau, steps, limit=3) == expected


# ---------------------------------------------------------------------------------- SPRING


def test_spring_tie_order_thesis() -> None:
    # C = [[0, 5, 0], [1, 0, 0]], tau 0. t=0: D(1,0) = 1 > tau. t=1: D(1,1) = 0 (diagonal, start 0):
    # candidate (0, start 0, end 1). t=2: D(0,2) = 0 (start 2), D(1,2) = 0 + min(5, D(1,1)=0 start 0,
    # D(0,2)=0 start 2) -> database step, start 0. Every live D >= 0: report (0, 1); then the path
    # starting at 0 dies and nothing is pending. Preferring the template step would give D(1,2) start
    # 2, survive the kill and add a match (2, 2).
    cost = np.array([[0.0, 5.0, 0.0], [1.0, 0.0, 0.0]])
    expected = [Match(0, 1, 0.0)]
    assert ref_spring(cost, 0.0, "thesis") == expected
    assert run_stream(dtw.SubsequenceStream(2, 0.0), cost) == expected
    assert dtw.disjoint_matches(cost, 0.0) == expected


def test_spring_tie_order_toolbox() -> None:
    # C = [[0, 0, 5], [9, 9, 1]] (see test_subsequence_tie_order_and_weights_toolbox), tau 1: only
    # D(1,2) = 1 qualifies, with start 1 from the (1,1) step (the (1,2) step ties with start 0).
    cost = np.array([[0.0, 0.0, 5.0], [9.0, 9.0, 1.0]])
    expected = [Match(1, 2, 1.0)]
    assert ref_spring(cost, 1.0, "toolbox") == expected
    assert run_stream(dtw.SubsequenceStream(2, 1.0, "toolbox"), cost) == expected
    assert dtw.disjoint_matches(cost, 1.0, "toolbox") == expected


def test_references_see_a_wrong_tie_order() -> None:
    """Mutation check: the references with the database and template steps (thesis) or the (1,1) and
    (1,2) steps (toolbox) swapped disagree with the module on the hand examples above, so a module
    with that wrong tie order would fail the comparisons."""
    thesis = np.array([[0.0, 5.0, 0.0], [0.0, 0.0, 0.0]])
    assert ref_subsequence(grid(thesis), "thesis")[1][-1] == dtw.subsequence_dtw(thesis).start.tolist()
    assert ref_subsequence(grid(thesis), "thesis", (0, 2, 1))[1][-1] == [0, 0, 2]
    thesis = np.array([[0.0, 5.0, 0.0], [1.0, 0.0, 0.0]])
    assert ref_spring(thesis, 0.0, "thesis", (0, 2, 1)) == [Match(0, 1, 0.0), Match(2, 2, 0.0)]
    diagonal = np.array([[0.0, 1.0, 9.0], [1.0, 1.0, 0.0]])
    assert ref_subsequence(grid(diagonal), "thesis", (1, 0, 2))[1][-1] == [0, 0, 0]
    toolbox = np.array([[0.0, 0.0, 5.0], [9.0, 9.0, 1.0]])
    assert ref_subsequence(grid(toolbox), "toolbox", (1, 0, 2))[1][-1] == [-1, 0, 0]
    assert ref_spring(toolbox, 1.0, "toolbox", (1, 0, 2)) == [Match(0, 2, 1.0)]


def test_spring_waits_for_live_paths() -> None:
    # M = 1, tau 2: D(0, t) = C(0, t) with start t. t=0: candidate (2, 0..0). t=1: the live cell costs
    # 1 < 2 but starts at 1 > 0: report (0, 0), then (1, 1..1) is the candidate. t=2: likewise report
    # (1, 1), candidate (0, 2..2). t=3: 3 >= 0: report (2, 2); 3 > tau.
    cost = np.array([[2.0, 1.0, 0.0, 3.0]])
    expected = [Match(0, 0, 2.0), Match(1, 1, 1.0), Match(2, 2, 0.0)]
    assert ref_spring(cost, 2.0, "thesis") == expected
    assert run_stream(dtw.SubsequenceStream(1, 2.0), cost) == expected
    assert dtw.disjoint_matches(cost, 2.0) == expected
    # M = 2, tau 1, C = [[0, 0, 9], [1, 0, 9]]. t=0: D = (0, 1), starts (0, 0): candidate (1, 0..0).
    # t=1: D(0,1) = 0 (start 1), D(1,1) = 0 + min(D(0,0)=0, ...) = 0 (start 0): a live path cheaper than
    # the candidate starts inside it, so no report; it becomes the candidate (0, 0..1). t=2: D = (9, 9),
    # both >= 0: report (0, 1) only, and the path from start 1 dies (1 <= end 1).
    cost = np.array([[0.0, 0.0, 9.0], [1.0, 0.0, 9.0]])
    expected = [Match(0, 1, 0.0)]
    assert ref_spring(cost, 1.0, "thesis") == expected
    assert run_stream(dtw.SubsequenceStream(2, 1.0), cost) == expected
    assert dtw.disjoint_matches(cost, 1.0) == expected


def check_matches(matches: list[Match], n: int, tau: float) -> None:
    """Reported matches lie in the database, cost at most tau (both rounded to fixed point: the match
    may exceed tau by less than 2^-25) and are disjoint, in time order."""
    for match in matches:
        assert 0 <= match.start <= match.end < n and match.cost <= as_cost(int(dtw.fixed(tau)))
    assert all(b.start > a.end for a, b in pairwise(matches))


@pytest.mark.slow
@SETTINGS
@given(cost_matrices(), steps_kinds, taus)
def test_spring_batch_equals_reference(cost: FloatArray, steps: Steps, tau: float) -> None:
    expected = ref_spring(cost, tau, steps)
    assert dtw.disjoint_matches(cost, tau, steps) == expected
    check_matches(expected, cost.shape[1], tau)


@pytest.mark.slow
@pytest.mark.parametrize("steps", dtw.STEPS)
@settings(SETTINGS, max_examples=150, phases=[Phase.explicit, Phase.reuse, Phase.generate])
@given(cost=cost_matrices(), tau=taus)  # no shrinking: test_spring_stream_thesis_one_live_column is minimal
def test_spring_stream_equals_reference(cost: FloatArray, tau: float, steps: Steps) -> None:
    expected = ref_spring(cost, tau, steps)
    stream = dtw.SubsequenceStream(cost.shape[0], tau, steps)
    assert run_stream(stream, cost) == expected
    assert run_stream(stream, cost) == expected  # flush starts over


# ---------------------------------------------------------------------------------- cost functions


def test_and_cost_thesis_examples() -> None:
    x, y = np.array([[1.0], [0.0], [1.0], [1.0]]), np.array([[1.0], [1.0], [0.0], [0.0]])
    assert dtw.and_cost(x, y).tolist() == [[3.0]]
    x, y = np.array([[0.5], [0.0], [1.0], [0.5]]), np.array([[1.0], [1.0], [0.5], [0.5]])
    assert dtw.and_cost(x, y).tolist() == [[1.0]]


@settings(SETTINGS, max_examples=120)
@given(st.integers(1, 6), st.integers(1, 6), st.integers(1, 8), st.data())
def test_and_and_l1_costs_equal_brute_force(f: int, m: int, n: int, data: st.DataObject) -> None:
    t, s = data.draw(ternary(f, m)), data.draw(ternary(f, n))
    assert dtw.and_cost(t, s).tolist() == brute_and(t, s)
    soft = data.draw(st.lists(st.floats(0, 1), min_size=f * n, max_size=f * n))
    u = np.array(soft, dtype=np.float64).reshape(f, n)
    l1 = [[sum(abs(t[k, a] - u[k, b]) for k in range(f)) / f for b in range(n)] for a in range(m)]
    np.testing.assert_allclose(dtw.l1_cost(t, u), l1, rtol=1e-12, atol=1e-15)


def check_retrieval(
    t: FloatArray, w: FloatArray, frames: npt.NDArray[np.bool_], blocked: npt.NDArray[np.bool_]
) -> None:
    """retrieval_cost against the brute force, retrieval_rows against fixed(retrieval_cost) row by row."""
    f, m = t.shape
    cost = dtw.retrieval_cost(t, w, frames.astype(np.float64))
    counts = brute_and(t, frames.astype(np.float64))
    for a in range(m):
        fixed_entries = sum(t[k, a] != 0.5 for k in range(f))
        expected = [x / (m * max(1, fixed_entries)) * (w[a] + 1) / 2 for x in counts[a]]
        np.testing.assert_allclose(cost[a], expected, rtol=1e-12, atol=0)
    codes = dtw.pack(frames.T)
    rows = list(dtw.retrieval_rows(t, w, codes, blocked))
    assert len(rows) == m
    for row, want in zip(rows, dtw.fixed(cost), strict=True):
        assert row.tolist() == np.where(blocked, INF, want).tolist()
    assert [r.tolist() for r in dtw.retrieval_rows(t, w, codes)] == dtw.fixed(cost).tolist()
    assert dtw.retrieval_matrix(dtw.retrieval_tables(t, w), codes).tolist() == dtw.fixed(cost).tolist()
    # the compiled subsequence DTW over packed frames: the cell-by-cell reference, both steps
    rows_blocked = [r.tolist() for r in dtw.retrieval_rows(t, w, codes, blocked)]
    for steps in dtw.STEPS:
        d, s = ref_subsequence(rows_blocked, steps)
        delta, start = dtw.subsequence_codes(dtw.retrieval_tables(t, w), codes, blocked, steps)
        assert delta.tolist() == d[-1] and start.tolist() == s[-1], steps


@settings(SETTINGS, max_examples=120)
@given(st.integers(1, 8), st.integers(1, 6), st.integers(1, 10), st.data())
def test_retrieval_costs_equal_brute_force(f: int, m: int, n: int, data: st.DataObject) -> None:
    t = data.draw(ternary(f, m))
    w = np.array(data.draw(st.lists(st.floats(0, 4), min_size=m, max_size=m)), dtype=np.float64)
    frames = np.array(data.draw(st.lists(st.booleans(), min_size=f * n, max_size=f * n)), dtype=bool)
    blocked = np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)), dtype=bool)
    check_retrieval(t, w, frames.reshape(f, n), blocked)


@pytest.mark.parametrize("f", [39, 63, 64])
def test_retrieval_costs_wide_frames(f: int) -> None:
    rng = np.random.default_rng(f)
    for m, n in ((1, 1), (5, 20), (13, 40)):
        t = rng.choice([0.0, 0.5, 1.0], size=(f, m), p=[0.3, 0.4, 0.3])
        frames = rng.random((f, n)) < 0.5
        check_retrieval(t, rng.random(m) * 3, frames, rng.random(n) < 0.2)


@settings(SETTINGS, max_examples=100)
@given(st.integers(0, 64), st.integers(0, 4), st.data())
def test_pack_bit_order(f: int, n: int, data: st.DataObject) -> None:
    bits = data.draw(st.lists(st.lists(st.booleans(), min_size=f, max_size=f), min_size=n, max_size=n))
    codes = dtw.pack(np.array(bits, dtype=bool).reshape(n, f))
    assert codes.dtype == np.uint64
    assert [int(v) for v in codes] == [sum(1 << i for i, b in enumerate(frame) if b) for frame in bits]


def test_pack_examples_and_errors() -> None:
    assert dtw.pack(np.array([[True, False, True], [False, True, False]])).tolist() == [5, 2]
    assert dtw.pack(np.eye(64, dtype=bool)).tolist() == [1 << i for i in range(64)]
    for bad in (np.zeros((2, 65), dtype=bool), np.zeros(3, dtype=bool)):
        with pytest.raises(ValueError, match="boolean frames"):
            dtw.pack(bad)


# ---------------------------------------------------------------------------------- known defects
# These fail against daemon/dtw.py as committed (51f6846); see each docstring.


def test_spring_stream_thesis_one_live_column() -> None:
    """With the thesis steps only column t feeds column t+1, so only it is live (the batch twin uses
    width 1). C = [[1, 0], [1, 0]], tau 2: t=0: D = (1, 2), starts (0, 0): candidate (0..0, 2).
    t=1: D(0,1) = 0 (start 1), D(1,1) = 0 + min(D(0,0)=1, D(1,0)=2, D(0,1)=0) = 0 (start 1): both
    live cells start after 0, so report (0..0, 2), then (1..1, 0) is the candidate, reported by flush.
    The stream also checks the dead column 0 (D(0,0) = 1 < 2, start 0), holds the report, and the
    cheaper (1..1, 0) replaces the candidate: the match (0..0, 2) is lost."""
    cost = np.array([[1.0, 0.0], [1.0, 0.0]])
    expected = [Match(0, 0, 2.0), Match(1, 1, 0.0)]
    assert ref_spring(cost, 2.0, "thesis") == expected
    assert dtw.disjoint_matches(cost, 2.0) == expected
    assert run_stream(dtw.SubsequenceStream(2, 2.0), cost) == expected


LONG = (1 << 17) + 2  # more than 2^63 / INF = 2^17 blocked cells in one row


def test_long_blocked_row_subsequence() -> None:
    """Row 1 blocked except its last cell: D(1, n-1) = 0 + min(D(0, n-2)=0, D(1, n-2)=inf, D(0, n-1)=0)
    = 0 from the diagonal, start n-2. The row scan's unclamped cumsum over 2^17 + 1 INF cells
    overflows int64 and loses the path."""
    cost = np.zeros((2, LONG))
    cost[1, :-1] = np.inf
    sub = dtw.subsequence_dtw(cost)
    assert (float(sub.delta[-1]), int(sub.start[-1])) == (0.0, LONG - 2)
    assert dtw.disjoint_matches(cost, 0.0) == [Match(LONG - 2, LONG - 1, 0.0)]


def test_long_blocked_row_full_dtw() -> None:
    """A 1 x n all-inf matrix has no finite path: DTW = inf, not a negative number (int64 overflow of
    the first row's cumsum before the clamp)."""
    assert dtw.full_dtw(np.full((1, LONG), np.inf)).cost == np.inf


def test_infinite_tau_reports_no_unreachable_match() -> None:
    """tau = inf means "no threshold", but fixed(inf) = INF makes unreachable ends (D = INF, start -1)
    candidates: [[inf, 0]] gives Match(-1, 0, inf) before the real Match(1, 1, 0.0)."""
    cost = np.array([[np.inf, 0.0]])
    assert dtw.subsequence_matches(cost, np.inf) == [Match(1, 1, 0.0)]
    assert run_stream(dtw.SubsequenceStream(1, np.inf), cost) == [Match(1, 1, 0.0)]
    assert dtw.disjoint_matches(cost, np.inf) == [Match(1, 1, 0.0)]


def test_tau_above_cell_cost_range() -> None:
    """tau bounds an accumulated cost, which may exceed the cell range [0, 64] (2 cells of 64 cost
    128); subsequence_matches accepts tau = 200, but the stream and its batch twin reject it through
    fixed()'s cell-range check."""
    cost = np.full((2, 1), 64.0)
    assert dtw.subsequence_matches(cost, 200.0) == [Match(0, 0, 128.0)]
    assert dtw.disjoint_matches(cost, 200.0) == [Match(0, 0, 128.0)]
    assert run_stream(dtw.SubsequenceStream(2, 200.0), cost) == [Match(0, 0, 128.0)]


# ------------------------------------------------------------------- streaming DTW of many templates


@pytest.mark.slow
@settings(SETTINGS, max_examples=400)
@given(st.integers(1, 4), st.integers(1, 40), st.data())
def test_stream_dtw_equals_batch_and_its_minima_and_blocks_read_their_definition(
    k: int, n: int, data: st.DataObject
) -> None:
    """:class:`StreamDTW` pushed frame by frame gives each template's Δ and starts of the cell-by-
    cell recursion (the toolbox's steps keeping only cells within the threshold); each push returns
    the local minima it completes and ``finish`` those at the last frame; ``blocks`` is a
    brute-force reading of its docstring (few features: many ties)."""
    f = 4
    templates = []
    for _ in range(k):
        m = data.draw(st.integers(1, 9))
        t = data.draw(ternary(f, m))
        w = np.array(data.draw(st.lists(st.floats(0.5, 1.5), min_size=m, max_size=m)))
        templates.append((dtw.retrieval_tables(t, w), data.draw(st.sampled_from(dtw.STEPS))))
    thresholds = data.draw(
        st.lists(st.sampled_from([0, SCALE // 10, SCALE // 2, 3 * SCALE]), min_size=k, max_size=k)
    )
    codes = np.array(data.draw(st.lists(st.integers(0, 2**f - 1), min_size=n, max_size=n)), dtype=np.uint64)
    stream = StreamDTW(
        [
            (tb.masks, tb.values, tb.tables, h, s == "toolbox")
            for (tb, s), h in zip(templates, thresholds, strict=True)
        ]
    )
    full = []
    for (tb, kind), thr in zip(templates, thresholds, strict=True):
        d, starts = ref_subsequence([[int(v) for v in row] for row in dtw.retrieval_matrix(tb, codes)], kind)
        full.append((d, starts, kind == "toolbox", thr))
    for j, code in enumerate(codes.tolist()):
        found = stream.push(code) or []
        expected = [
            (i, s[-1][j - 1], j - 1, d[-1][j - 1])
            for i, (d, s, _, thr) in enumerate(full)
            if j >= 1 and slow_minimum(d[-1], thr, j - 1, j)
        ]
        assert found == expected
        for i, (d, s, toolbox, thr) in enumerate(full):
            for e in range(max(0, j - 2), j + 1):
                kept = not toolbox or d[-1][e] <= thr
                assert stream.delta(i, e) == ((d[-1][e], s[-1][e]) if kept and d[-1][e] < INF else (INF, -1))
        for _ in range(3 if j >= 1 else 0):
            end = data.draw(st.integers(max(0, j - 8), j - 1))
            first = data.draw(st.integers(max(0, end - 8), end))
            cost = data.draw(st.sampled_from([0, SCALE // 10, SCALE // 2, SCALE, 2 * SCALE]))
            lo = data.draw(st.integers(0, k))
            hi = data.draw(st.integers(lo, k))
            assert stream.blocks(cost, first, end, lo, hi) == slow_blocks(full, cost, first, end, j, lo, hi)
    last = len(codes) - 1
    assert (stream.finish() or []) == [
        (i, s[-1][last], last, d[-1][last])
        for i, (d, s, _, thr) in enumerate(full)
        if slow_minimum(d[-1], thr, last, last)
    ]
    stream.reset()
    assert stream.n == 0


@pytest.mark.slow
@settings(SETTINGS, max_examples=300)
@given(st.integers(1, 3), st.integers(2, 40), st.data())
def test_a_range_not_blocked_is_never_beaten_later(k: int, n: int, data: st.DataObject) -> None:
    """What ``blocks`` is for: when it says no at frame j, no template of the range has a local
    minimum ending at j or later, at most its threshold and below the cost, whose match is the same
    motion as the range (more than half of the shorter one's frames shared)."""
    f = 3
    templates = []
    for _ in range(k):
        m = data.draw(st.integers(1, 8))
        tb = dtw.retrieval_tables(data.draw(ternary(f, m)), np.ones(m))
        templates.append(
            (
                tb,
                data.draw(st.sampled_from(dtw.STEPS)),
                data.draw(st.sampled_from([SCALE // 4, SCALE, 3 * SCALE])),
            )
        )
    codes = np.array(data.draw(st.lists(st.integers(0, 2**f - 1), min_size=n, max_size=n)), dtype=np.uint64)
    stream = StreamDTW([(tb.masks, tb.values, tb.tables, h, s == "toolbox") for tb, s, h in templates])
    batch = [dtw.subsequence_codes(tb, codes, None, s) for tb, s, _ in templates]
    for j, code in enumerate(codes.tolist()):
        stream.push(code)
        if j == 0:
            continue
        end = data.draw(st.integers(max(0, j - 6), j - 1))
        first = data.draw(st.integers(max(0, end - 6), end))
        cost = data.draw(st.sampled_from([SCALE // 8, SCALE // 2, SCALE, 2 * SCALE]))
        if stream.blocks(cost, first, end, 0, k):
            continue
        for (delta, start), (_, _, thr) in zip(batch, templates, strict=True):
            for e in range(j, n):
                d = [int(x) for x in delta]
                if slow_minimum(d, thr, e, n - 1) and d[e] < cost:
                    s = int(start[e])
                    assert not 2 * (min(end, e) - max(first, s) + 1) > min(end - first, e - s) + 1


def test_stream_dtw_refuses_what_it_cannot_answer() -> None:
    tb = dtw.retrieval_tables(np.array([[1.0, 0.0]]), np.ones(2))
    stream = StreamDTW([(tb.masks, tb.values, tb.tables, SCALE, True)])
    assert stream.finish() is None  # nothing pushed
    for code in (0, 1, 0, 1, 0):
        stream.push(code)
    with pytest.raises(IndexError, match="not among the last 3 of 5"):
        stream.delta(0, 1)
    with pytest.raises(ValueError, match="must end before the last frame pushed"):
        stream.blocks(SCALE, 2, 4, 0, 1)
    with pytest.raises(IndexError, match="templates"):
        stream.blocks(SCALE, 2, 3, 0, 2)
    with pytest.raises(ValueError, match="needs templates"):
        StreamDTW([])


def test_compiled_accumulation_equals_the_row_scans() -> None:
    rng = np.random.default_rng(7)
    for _ in range(500):
        m, n = (int(x) for x in rng.integers(1, 25, 2))
        c = rng.integers(0, 40, (m, n)).astype(np.int64)
        c[rng.random((m, n)) < 0.1] = INF
        assert (dtw.accumulated(c) == dtw.accumulated_rows(c)).all()
        assert dtw.accumulated(c)[-1, -1] == min(ref_full(c.tolist())[0][-1][-1], INF)


@pytest.mark.slow
@settings(SETTINGS, max_examples=300)
@given(st.integers(1, 6), st.integers(1, 60), st.sampled_from(dtw.STEPS), st.data())
def test_subsequence_minima_are_the_local_minima_of_the_whole_pass(
    m: int, n: int, steps: Steps, data: st.DataObject
) -> None:
    """The compiled pass's minima (the toolbox's keeping only cells within the threshold) are
    :func:`local_minima` of the full Δ (few features: many ties)."""
    f = 3
    t = dtw.retrieval_tables(
        data.draw(ternary(f, m)), np.array(data.draw(st.lists(st.floats(0.5, 1.5), min_size=m, max_size=m)))
    )
    codes = np.array(data.draw(st.lists(st.integers(0, 2**f - 1), min_size=n, max_size=n)), dtype=np.uint64)
    tau = data.draw(st.sampled_from([0.0, 0.01, 0.1, 0.3, 1.0, 5.0]))
    delta, start = dtw.subsequence_codes(t, codes, None, steps)
    expected = dtw.local_minima(dtw.to_cost(delta), start, dtw.threshold(tau) / SCALE)
    assert dtw.subsequence_minima(t, codes, tau, steps) == expected
