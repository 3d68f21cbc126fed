from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from daemon._features import FeatureCore
from replay._kinematics import FrameKinematics

NOTHING: int
NON_FINITE: int

class LiveStream:
    kinematics: FrameKinematics | None
    features: FeatureCore
    width: int
    step: int
    seen: int
    def __init__(
        self,
        kinematics: FrameKinematics | None,
        features: FeatureCore,
        lengths: Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]],
        order: npt.NDArray[np.intp] | None,
        width: int,
        step: int,
    ) -> None: ...
    def push_channels(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
    ) -> int: ...
    def push_positions(self, positions: npt.NDArray[np.float64]) -> int: ...
    def flush(self) -> list[int]: ...

def push_channels_many(
    streams: list[LiveStream],
    channels: npt.NDArray[np.float64],
    cos: npt.NDArray[np.float64],
    sin: npt.NDArray[np.float64],
) -> list[int]: ...
