"""The assembler: the ``frame`` function the compiler writes (:mod:`daemon.features.compiler`), read
back from its syntax tree, as code for the register machine of :mod:`daemon._features`, the
stream's compiled path. Each arithmetic node becomes one instruction in Python's evaluation order,
so the machine computes the same doubles as the Python it was read from.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence

from daemon._features import Bytecode


def unsupported(what: str) -> ValueError:
    """The error for a catalog that uses ``what``, which the compiler or the machine lacks."""
    return ValueError(f"the catalog uses {what}, which the feature compiler does not support")


_BINARY = {ast.Add: 0, ast.Sub: 1, ast.Mult: 2, ast.Div: 3}
_UNARY = {"sqrt": 4, "abs": 5}
_REDUCE = {"minimum": 6, "maximum": 7}
_CONST = 8
_COMPARE = {ast.Lt: 0, ast.LtE: 1, ast.Gt: 2, ast.GtE: 3}


class _Assembler:
    """The generated ``frame`` function as register-machine code (:class:`daemon._features.Bytecode`):
    every arithmetic node of its syntax tree one instruction, in Python's evaluation order, and every
    threshold comparison one test of a feature bit. The first registers hold the pose components
    ``P`` and the smoothed velocities ``S``; each instruction writes a register of its own."""

    def __init__(self, slots: Sequence[int], n_rows: int, n_points: int) -> None:
        self.slots = slots
        self.n_rows, self.base = n_rows, n_rows + n_points  # registers: P, then S, then results
        self.ops: list[tuple[int, int, int, int]] = []
        self.args: list[int] = []
        self.consts: list[float] = []
        self.names: dict[str, int] = {}
        self.thresholds: dict[str, int] = {}
        self.tests: list[tuple[int, int, int, int, int]] = []

    def emit(self, op: int, a: int, b: int) -> int:
        self.ops.append((op, self.base + len(self.ops), a, b))
        return self.base + len(self.ops) - 1

    def expr(self, node: ast.expr) -> int:
        match node:
            case ast.Name(id=name) if name in self.names:
                return self.names[name]
            case ast.Subscript(value=ast.Name(id="P"), slice=ast.Constant(value=int(i))):
                return i
            case ast.Subscript(value=ast.Name(id="S"), slice=ast.Constant(value=int(i))):
                return self.n_rows + i
            case ast.BinOp(left, op, right) if type(op) in _BINARY:
                a = self.expr(left)
                return self.emit(_BINARY[type(op)], a, self.expr(right))
            case ast.Call(func=ast.Name(id=f), args=[arg]) if f in _UNARY:
                return self.emit(_UNARY[f], self.expr(arg), 0)
            case ast.Call(func=ast.Name(id=f), args=[ast.List(elts=items)]) if f in _REDUCE and items:
                registers = [self.expr(e) for e in items]
                self.args += registers
                return self.emit(_REDUCE[f], len(self.args) - len(registers), len(registers))
            case ast.Constant(value=float(v) | int(v)) if not isinstance(v, bool):
                self.consts.append(float(v))
                return self.emit(_CONST, len(self.consts) - 1, 0)
        raise unsupported(f"an expression the register machine lacks: {ast.unparse(node)}")

    def threshold(self, node: ast.expr) -> int:
        match node:
            case ast.Name(id=name) if name in self.thresholds:
                return self.slots[self.thresholds[name]]
            case ast.Subscript(value=ast.Name(id=name), slice=ast.Constant(value=int(j))) if j in (0, 1):
                return self.slots[self.thresholds[name]] + j
        raise unsupported(f"a threshold the register machine lacks: {ast.unparse(node)}")

    def track(self, node: ast.expr, track: int) -> None:
        """The tests of ``(tests) | (tests) << 1 | ...`` for ``track`` (0 loose, 1 strict)."""
        match node:
            case ast.BinOp(left, ast.BitOr(), right):
                self.track(left, track)
                self.track(right, track)
            case ast.BinOp(conjunction, ast.LShift(), ast.Constant(value=int(bit))):
                self.conjunction(conjunction, track, bit)
            case _:
                self.conjunction(node, track, 0)

    def conjunction(self, node: ast.expr, track: int, bit: int) -> None:
        match node:
            case ast.BinOp(left, ast.BitAnd(), right):
                self.conjunction(left, track, bit)
                self.conjunction(right, track, bit)
            case ast.Compare(left, [op], [reference]) if type(op) in _COMPARE:
                self.tests.append(
                    (track, bit, self.expr(left), _COMPARE[type(op)], self.threshold(reference))
                )
            case _:
                raise unsupported(f"a test the register machine lacks: {ast.unparse(node)}")


def assemble(
    source: str,
    slots: Sequence[int],
    n_slots: int,
    n_rows: int,
    points: Sequence[tuple[int, int]],
    windows: Sequence[tuple[int, int, int, int]],
    frame_rate: float,
) -> Bytecode:
    """The function ``frame`` of ``source`` as :class:`daemon._features.Bytecode`: its thresholds
    ``T`` in ``n_slots`` flat slots (threshold k from slot ``slots[k]``, a pair in two), ``n_rows``
    pose components, the velocity ``points`` (per component, the pose rows whose difference it is, -1
    for none) and the ``windows`` ``(L, h, first, end)`` smoothing the points ``first..end-1`` at
    ``frame_rate``."""
    (function,) = [f for f in ast.parse(source).body if isinstance(f, ast.FunctionDef) and f.name == "frame"]
    unpack, *assignments, result = function.body
    assert isinstance(unpack, ast.Assign) and isinstance(unpack.targets[0], ast.Tuple)
    asm = _Assembler(slots, n_rows, len(points))
    for k, name in enumerate(unpack.targets[0].elts):
        assert isinstance(name, ast.Name)
        asm.thresholds[name.id] = k
    for a in assignments:
        assert isinstance(a, ast.Assign) and isinstance(a.targets[0], ast.Name)
        asm.names[a.targets[0].id] = asm.expr(a.value)
    assert isinstance(result, ast.Return) and isinstance(result.value, ast.Tuple)
    for track, node in enumerate(result.value.elts):
        asm.track(node, track)
    return Bytecode(
        asm.ops,
        asm.args,
        asm.consts,
        asm.tests,
        points,
        [(big_l - h + 1, 1 - h, first, end) for big_l, h, first, end in windows],
        [frame_rate / big_l for big_l, _, _, _ in windows],
        asm.base + len(asm.ops),
        n_rows,
        n_slots,
    )
