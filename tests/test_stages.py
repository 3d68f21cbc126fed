"""The stage contract (daemon/stages.py): every streaming stage is a ``Stage`` (checked by mypy on
the assignments below), and stages chained with :class:`Chain` give what their batch twins give
one after another: features -> decimation -> F-segments, on a real recording and on random
feature streams, including a second stream after the flush."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.dtw import Match, SubsequenceStream, disjoint_matches
from daemon.features import Decimator, FeatureStream, decimate, features
from daemon.search.segments import Segment, Segmenter, segment
from daemon.stages import Chain, Stage, run
from daemon.types import FEATURE_SETS, BoolArray, FeatureSet, FloatArray
from replay import JOINT_NAMES
from tests.helpers import HDM_AMC, HDM_ASF, joints_cm

# Each streaming stage is a Stage of its item types (mypy checks these assignments).
FEATURES: Stage[FloatArray, BoolArray] = FeatureStream(JOINT_NAMES, 120.0)
DECIMATOR: Stage[BoolArray, BoolArray] = Decimator(4)
SEGMENTER: Stage[BoolArray, Segment] = Segmenter("lower")
SPRING: Stage[FloatArray, Match] = SubsequenceStream(3, 0.5)


def test_chained_stages_equal_the_batch_on_a_real_recording() -> None:
    """FeatureStream -> Decimator -> Segmenter, pushed one pose at a time, gives the F-segments of
    the decimated batch feature matrix, for every set; twice, the second stream after the flush."""
    joints = joints_cm(HDM_ASF, HDM_AMC)
    batch30 = decimate(features(joints, JOINT_NAMES, 120.0), 4)
    for feature_set in FEATURE_SETS:
        chain = Chain(Chain(FeatureStream(JOINT_NAMES, 120.0), Decimator(4)), Segmenter(feature_set))
        expected = list(segment(batch30, feature_set))
        assert len(expected) > 3  # the squat changes the features
        for _ in range(2):
            assert run(chain, joints) == expected


@settings(max_examples=150, deadline=None)
@given(
    hnp.arrays(np.bool_, st.tuples(st.integers(0, 40), st.just(39))),
    st.integers(1, 5),
    st.sampled_from(FEATURE_SETS),
    st.lists(st.integers(0, 40), max_size=3),
)
def test_decimator_then_segmenter_equals_batch(
    matrix: BoolArray, factor: int, feature_set: FeatureSet, flushes: list[int]
) -> None:
    """Any split of the stream into pieces, each ended by a flush, gives each piece's batch result."""
    chain = Chain(Decimator(factor), Segmenter(feature_set))
    cuts = sorted({min(c, len(matrix)) for c in flushes} | {len(matrix)})
    begin = 0
    for end in cuts:
        piece = matrix[begin:end]
        got = [s for v in piece for s in chain.push(v)] + chain.flush()
        assert got == list(segment(decimate(piece, factor), feature_set))
        begin = end


@settings(max_examples=100, deadline=None)
@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 4), st.integers(0, 25)), elements=st.floats(0, 2)))
def test_run_of_the_dtw_stream_equals_its_batch_twin(cost: FloatArray) -> None:
    stream = SubsequenceStream(cost.shape[0], 0.8, "toolbox")
    assert run(stream, list(cost.T)) == (disjoint_matches(cost, 0.8, "toolbox") if cost.shape[1] else [])
