import numpy as np
import numpy.typing as npt

class FrameKinematics:
    n_nodes: int
    width: int
    def __init__(
        self,
        nodes: object,
        chans: object,
        first: object,
        axes: object,
        orientation: object,
        position: object,
        translation: object,
        pairs: object,
        offsets: object,
        joint_nodes: object,
    ) -> None: ...
    def positions(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
        scale: float,
        scaled: bool,
        out: npt.NDArray[np.float64],
    ) -> None: ...
    def joints(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
        scale: float,
        out: npt.NDArray[np.float64],
    ) -> bool: ...
