"""The feature compiler's assembler (daemon.features.assembler) refuses, naming it, any part of a
generated ``frame`` function its register machine lacks, rather than computing something else.
(What it does assemble is tested through the streams equalling the batch features.)"""

from __future__ import annotations

import pytest

from daemon._features import Bytecode
from daemon.features.assembler import assemble

FRAME = """
def frame(P, S, T):
    (t0,) = T
    a = {expr}
    return ({test},)
"""


def assembled(expr: str, test: str = "(a < t0[0])") -> Bytecode:
    return assemble(FRAME.format(expr=expr, test=test), [0], 2, 3, [(0, 1)], [(5, 2, 0, 1)], 120.0)


def test_every_arithmetic_node_is_one_register() -> None:
    """3 pose rows and 1 velocity point, then one register per node: *, abs, +, sqrt, 1.5, maximum,
    2, /, -."""
    code = assembled("sqrt(P[0] * P[1] + abs(S[0])) - maximum([P[2], 1.5]) / 2")
    assert (code.n_rows, code.n_points, code.registers) == (3, 1, 3 + 1 + 9)


@pytest.mark.parametrize(
    ("expr", "test", "named"),
    [
        ("P[0] ** 2", "(a < t0[0])", "an expression the register machine lacks: P[0] ** 2"),
        ("minimum([])", "(a < t0[0])", "an expression the register machine lacks: minimum([])"),
        ("True", "(a < t0[0])", "an expression the register machine lacks: True"),
        ("P[0]", "(a == t0[0])", "a test the register machine lacks: a == t0[0]"),
        ("P[0]", "(a < t0[2])", "a threshold the register machine lacks: t0[2]"),
    ],
)
def test_what_it_lacks_is_refused_by_name(expr: str, test: str, named: str) -> None:
    with pytest.raises(ValueError, match=r"the catalog uses .*, which the feature compiler") as caught:
        assembled(expr, test)
    assert named in str(caught.value)
