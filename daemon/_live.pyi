from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon._dtw import Competition
from daemon._features import FeatureCore
from replay._kinematics import FrameKinematics

NOTHING: int
NON_FINITE: int
NON_FINITE_CHANNELS: int

class LiveStream:
    kinematics: FrameKinematics | None
    features: FeatureCore
    width: int
    step: int
    per: int
    seen: int
    started: bool
    last: int
    def __init__(
        self,
        kinematics: FrameKinematics | None,
        features: FeatureCore,
        lengths: Callable[[npt.NDArray[np.float64]], npt.NDArray[np.float64]],
        order: npt.NDArray[np.intp] | None,
        width: int,
        step: int,
        per: int = 1,
    ) -> None: ...
    def push_channels(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
    ) -> int: ...
    def push_positions(self, positions: npt.NDArray[np.float64]) -> int: ...
    def state(self) -> tuple[int, bool, int]: ...
    def restore(self, state: Sequence[Any]) -> None: ...
    def attach(self, stage: Any, competition: Competition | None) -> None: ...
    def flush(self) -> list[int]: ...

def push_many(
    frames: list[tuple[Any, object, Any]],
    refused: type[Exception],
    streams: dict[str, Any] | None = None,
) -> tuple[list[Any], list[tuple[int, Any]]]: ...
