from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

class Bytecode:
    registers: int
    n_rows: int
    n_points: int
    n_slots: int
    def __init__(
        self,
        ops: Sequence[tuple[int, int, int, int]],
        args: Sequence[int],
        consts: Sequence[float],
        tests: Sequence[tuple[int, int, int, int, int]],
        points: Sequence[tuple[int, int]],
        windows: Sequence[tuple[int, int, int, int]],
        scales: Sequence[float],
        registers: int,
        n_rows: int,
        n_slots: int,
    ) -> None: ...

class FeatureCore:
    ring: npt.NDArray[np.float64]
    keep: int
    latency: int
    n: int
    emitted: int
    previous: int
    def __init__(self, code: Bytecode, keep: int, latency: int) -> None: ...
    code: Bytecode
    def set_thresholds(self, thresholds: npt.NDArray[np.float64]) -> None: ...
    def reset(self) -> None: ...
    def state(self) -> tuple[int, int, int, bytes, bytes]: ...
    def restore(self, state: Sequence[object]) -> None: ...
    def push(self, rows: npt.NDArray[np.float64]) -> int: ...
    def flush(self) -> list[int]: ...
