"""PNG pictures of results people would rather look at than read (matplotlib, the optional ``plot``
extra: ``pip install 'mocapd[plot]'``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from daemon.features import FEATURE_NAMES, SET_SLICES, BoolArray


class PlotUnavailable(RuntimeError):
    """matplotlib is not installed."""


def feature_matrix_png(
    matrix: BoolArray, frames: npt.NDArray[np.int64], path: str | Path, title: str, frame_rate: float
) -> None:
    """Draw a feature matrix shape ``(N, 39)`` as in the thesis' figures: features top to bottom,
    time left to right, black = 1, the lower, upper and mix sets in separate panels. ``frames`` shape
    ``(N,)`` labels the samples (AMC frame numbers); ``frame_rate`` is the samples' rate."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise PlotUnavailable("writing PNG needs matplotlib: pip install 'mocapd[plot]'") from None
    m = np.asarray(matrix, dtype=bool)
    n = m.shape[0]
    heights = [s.stop - s.start for s in SET_SLICES.values()]
    width = min(24.0, max(8.0, n / 60.0))
    fig, axes = plt.subplots(
        len(heights), 1, figsize=(width, 9.0), sharex=True, gridspec_kw={"height_ratios": heights}
    )
    seconds = n / frame_rate
    for ax, (name, part) in zip(axes, SET_SLICES.items(), strict=True):
        ax.imshow(
            m[:, part].T,
            aspect="auto",
            interpolation="nearest",
            cmap="gray_r",
            vmin=0,
            vmax=1,
            extent=(0.0, seconds, part.stop - part.start - 0.5, -0.5),
        )
        ax.set_yticks(range(part.stop - part.start))
        ax.set_yticklabels([f"{k + 1} {FEATURE_NAMES[k]}" for k in range(part.start, part.stop)], fontsize=6)
        ax.set_ylabel(name)
    axes[-1].set_xlabel(
        f"time in s at {frame_rate:g} Hz (AMC frames {int(frames[0])}-{int(frames[-1])})"
        if n
        else "time in s"
    )
    axes[0].set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
