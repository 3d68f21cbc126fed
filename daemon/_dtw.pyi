import numpy as np
import numpy.typing as npt

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
    def push(self, code: int) -> list[tuple[int, int, int, int]] | None: ...
    def finish(self) -> list[tuple[int, int, int, int]] | None: ...
    def delta(self, template: int, frame: int) -> tuple[int, int]: ...
    def blocks(self, cost: int, start: int, end: int, lo: int, hi: int) -> bool: ...

def accumulated(cost: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]: ...
