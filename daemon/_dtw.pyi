from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon._automaton import AutomatonSet

def subsequence_codes(
    masks: npt.NDArray[np.uint64],
    values: npt.NDArray[np.uint64],
    tables: npt.NDArray[np.int64],
    codes: npt.NDArray[np.uint64],
    blocked: npt.NDArray[np.uint8],
    toolbox: bool,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]: ...
def minima_codes(
    masks: npt.NDArray[np.uint64],
    values: npt.NDArray[np.uint64],
    tables: npt.NDArray[np.int64],
    codes: npt.NDArray[np.uint64],
    blocked: npt.NDArray[np.uint8],
    toolbox: bool,
    threshold: int,
) -> list[tuple[int, int, int]]: ...

class StreamDTW:
    n: int
    def __init__(
        self,
        templates: list[
            tuple[npt.NDArray[np.uint64], npt.NDArray[np.uint64], npt.NDArray[np.int64], int, bool]
        ],
    ) -> None: ...
    def reset(self) -> None: ...
    def state(self) -> tuple[int, bytes, bytes, bytes]: ...
    def restore(self, state: Sequence[Any]) -> None: ...
    def push(self, code: int) -> list[tuple[int, int, int, int]] | None: ...
    def finish(self) -> list[tuple[int, int, int, int]] | None: ...
    def delta(self, template: int, frame: int) -> tuple[int, int]: ...
    def progress(self, template: int, since: int = -1) -> tuple[int, int]: ...
    def blocks(self, cost: int, start: int, end: int, lo: int, hi: int) -> bool: ...

def accumulated(cost: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]: ...

class Competition:
    dtw: StreamDTW
    automata: AutomatonSet | None
    compete: bool
    hold: int
    memory: int
    n: int
    def __init__(
        self,
        dtw: StreamDTW,
        owner: Sequence[int],
        lo: Sequence[int],
        hi: Sequence[int],
        compete: bool,
        hold: int,
        memory: int,
        automata: AutomatonSet | None,
        gated: Sequence[int],
        before: Sequence[int] = (),
        after: Sequence[int] = (),
        back: int = 0,
    ) -> None: ...
    @property
    def state_size(self) -> int: ...
    def state(self) -> tuple[Any, ...]: ...
    def restore(self, state: Sequence[Any]) -> None: ...
    def push(self, code: int) -> list[tuple[int, int, int, int, int]] | None: ...
    def flush(self) -> list[tuple[int, int, int, int, int]] | None: ...
    def progress(self, floor: float) -> list[tuple[int, int, int, int, tuple[int, ...]]]: ...
