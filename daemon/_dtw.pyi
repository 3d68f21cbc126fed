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
