import numpy as np
import numpy.typing as npt

class FrameKinematics:
    n_nodes: int
    width: int
    scale: float
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
        scale: float,
    ) -> None: ...
    def positions(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
        scaled: bool,
        out: npt.NDArray[np.float64],
    ) -> None: ...
    def joints(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
        out: npt.NDArray[np.float64],
    ) -> bool: ...
    def local_rotations(
        self,
        channels: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
        out: npt.NDArray[np.float64],
    ) -> None: ...

class BvhFrameKinematics:
    n_joints: int
    def __init__(
        self,
        parent: object,
        rotations: object,
        rot_start: object,
        translations: object,
        pos_start: object,
        offsets: object,
    ) -> None: ...
    def positions(
        self,
        row: npt.NDArray[np.float64],
        cos: npt.NDArray[np.float64],
        sin: npt.NDArray[np.float64],
        out: npt.NDArray[np.float64],
    ) -> None: ...
