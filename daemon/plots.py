"""PNG pictures of results people would rather look at than read (matplotlib, the optional ``plot``
extra: ``pip install 'mocapd[plot]'``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np
import numpy.typing as npt

from daemon.behaviours import GmmResult, PcaResult, PpcaResult
from daemon.errors import MocapdError
from daemon.features import FEATURE_NAMES, SET_SLICES
from daemon.storage import uninterrupted
from daemon.types import N_FEATURES, Band, BoolArray

Target = str | Path | IO[bytes]
"""Where a picture goes: a path, or a binary file open for writing (always PNG)."""


class PlotUnavailable(MocapdError, RuntimeError):
    """matplotlib is not installed."""


def _pyplot() -> Any:
    # a signal in the middle of importing matplotlib's extension modules left them half made (an
    # ImportError here, then a crash as Python exits): it waits until the import is over. Its
    # handler is held back, not the signal blocked: a signal blocked in the main thread still
    # reaches another thread (OpenBLAS's workers), and Python then runs the handler mid-import
    try:
        with uninterrupted():
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
    except ImportError:
        raise PlotUnavailable("writing PNG needs matplotlib: pip install 'mocapd[plot]'") from None
    return plt


def check_plotting() -> None:
    """Raise :class:`PlotUnavailable` unless PNGs can be drawn (before the work that would draw one)."""
    _pyplot()


def _save(fig: Any, target: Target) -> None:
    fig.savefig(target, dpi=110, format="png")


def feature_matrix_png(
    matrix: BoolArray, frames: npt.NDArray[np.int64], path: Target, title: str, frame_rate: float
) -> None:
    """Draw a feature matrix shape ``(N, 39)`` as in the thesis' figures: features top to bottom,
    time left to right, black = 1, the lower, upper and mix sets in separate panels. ``frames`` shape
    ``(N,)`` labels the samples (AMC frame numbers); ``frame_rate`` is the samples' rate."""
    plt = _pyplot()
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
    _save(fig, path)
    plt.close(fig)


def template_png(
    soft: npt.NDArray[np.float64],
    hard: npt.NDArray[np.float64],
    keyframe_columns: Sequence[int],
    path: Target,
    title: str,
    frame_rate: float,
) -> None:
    """Draw a class's soft MT ``(39, K)`` (white = 1, black = 0, grey between) above its hard MT
    ``(39, K')`` (grey = ½), as in thesis Fig. 3.10; ``keyframe_columns`` (hard MT columns) are
    marked by vertical lines as in Fig. 6.1."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(max(8.0, soft.shape[1] / 8), 12.0))
    for ax, (name, values) in zip(axes, (("soft MT", soft), ("hard MT", hard)), strict=True):
        k = values.shape[1]
        ax.imshow(
            values,
            aspect="auto",
            interpolation="nearest",
            cmap="gray",
            vmin=0,
            vmax=1,
            extent=(-0.5, k - 0.5, values.shape[0] - 0.5, -0.5),
        )
        for part in list(SET_SLICES.values())[1:]:
            ax.axhline(part.start - 0.5, color="tab:red", linewidth=0.8)
        ax.set_yticks(range(values.shape[0]))
        ax.set_yticklabels([f"{i + 1} {n}" for i, n in enumerate(FEATURE_NAMES)], fontsize=5)
        ax.set_xlabel(f"column ({k} at {frame_rate:g} Hz)")
        ax.set_title(f"{title}: {name}", fontsize=9)
    for c in keyframe_columns:
        axes[1].axvline(c, color="tab:green", linewidth=1.5)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def precision_recall_png(
    curves: Mapping[str, Sequence[tuple[float, float]]],
    taus: Sequence[float],
    path: Target,
    *,
    threshold: str = "τ",
) -> None:
    """Precision (y) against recall (x) per class, one point per value of the ``threshold`` in
    ``taus`` (``curves[class]`` = [(precision, recall), ...] in the order of ``taus``)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 6.0))
    for name, points in curves.items():
        precision = [p for p, _ in points]
        recall = [r for _, r in points]
        ax.plot(recall, precision, marker="o", label=name)
    ax.set_xlabel(f"recall ({threshold} = {', '.join(f'{t:g}' for t in taus)})")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def repetitions_png(
    matrix: BoolArray,
    frames: npt.NDArray[np.int64],
    frame_rate: float,
    curves: Mapping[str, npt.NDArray[np.float64]],
    runs: Sequence[tuple[int, int, str]],
    cuts: Sequence[int],
    path: Target,
    title: str,
) -> None:
    """Draw a trial's repetition cuts: above, the feature matrix shape ``(N, 39)`` (black = 1);
    below, ``curves`` (name -> shape ``(N,)``, e.g. joint heights), both against time with the
    labelled ``runs`` (first AMC frame, last AMC frame, label) shaded and named and the ``cuts`` (AMC
    frames) as vertical lines. ``frames`` shape ``(N,)`` are the samples' AMC frame numbers at
    ``frame_rate`` Hz; times are seconds from the first."""
    plt = _pyplot()
    m = np.asarray(matrix, dtype=bool)
    f = np.asarray(frames, dtype=np.int64)
    n = m.shape[0]
    first = int(f[0]) if n else 0
    native = frame_rate * (int(f[1] - f[0]) if n > 1 else 1)

    def seconds(frame: float) -> float:
        return (frame - first) / native

    width = min(40.0, max(10.0, n / frame_rate / 1.5))
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(width, 8.0), sharex=True, gridspec_kw={"height_ratios": [3, 2]}
    )
    end = seconds(float(f[-1])) if n else 0.0
    top.imshow(
        m.T,
        aspect="auto",
        interpolation="nearest",
        cmap="gray_r",
        vmin=0,
        vmax=1,
        extent=(0.0, end, N_FEATURES - 0.5, -0.5),
    )
    for part in list(SET_SLICES.values())[1:]:
        top.axhline(part.start - 0.5, color="tab:red", linewidth=0.6)
    top.set_ylabel("features (lower, upper, mix)")
    time = np.array([seconds(float(x)) for x in f])
    for name, values in curves.items():
        bottom.plot(time, values, linewidth=0.9, label=name)
    bottom.legend(fontsize=7, loc="upper right")
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:olive", "tab:cyan"]
    for i, (start, stop, label) in enumerate(runs):
        for ax in (top, bottom):
            ax.axvspan(
                seconds(start), seconds(stop), color=colours[i % len(colours)], alpha=0.15, linewidth=0
            )
        bottom.text(
            seconds((start + stop) / 2),
            1.0,
            label,
            transform=bottom.get_xaxis_transform(),
            ha="center",
            va="bottom",
            fontsize=8,
        )
    for c in cuts:
        for ax in (top, bottom):
            ax.axvline(seconds(c), color="tab:red", linewidth=0.8)
    bottom.set_xlabel(
        f"time in s (AMC frames {first}-{int(f[-1])}; red lines: repetition cuts)" if n else "time in s"
    )
    top.set_title(title, fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def timeline_png(
    detections: Sequence[tuple[str, int, int]],
    truth: Sequence[tuple[str, int, int]],
    frames: tuple[int, int],
    frame_rate: float,
    path: Target,
    title: str,
) -> None:
    """Draw detections over a recording: one row per class (those detected or labelled), each
    detection ``(class, first frame, last frame)`` as a bar; labelled segments ``truth`` (same form)
    as lighter bars beneath in the same row. ``frames``: the recording's first and last frame numbers,
    at ``frame_rate`` Hz (the axis is in seconds from the first frame)."""
    plt = _pyplot()
    names = sorted({c for c, _, _ in detections} | {c for c, _, _ in truth})
    row = {c: i for i, c in enumerate(names)}
    first, last = frames
    seconds = (last - first + 1) / frame_rate
    fig, ax = plt.subplots(figsize=(min(24.0, max(8.0, seconds / 5.0)), 1.2 + 0.45 * max(1, len(names))))
    for c, s, e in truth:
        ax.broken_barh(
            [((s - first) / frame_rate, (e - s + 1) / frame_rate)], (row[c] - 0.45, 0.4), color="0.75"
        )
    for c, s, e in detections:
        ax.broken_barh(
            [((s - first) / frame_rate, (e - s + 1) / frame_rate)], (row[c] - 0.05, 0.45), color="C0"
        )
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(-0.6, max(1, len(names)) - 0.4)
    ax.set_xlim(0, seconds)
    ax.invert_yaxis()
    ax.set_xlabel("seconds" + (" (grey: labelled, blue: detected)" if truth else " (blue: detected)"))
    ax.set_title(title)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def _broken(frame: npt.NDArray[np.int64], segment: npt.NDArray[np.int64], values: Any) -> tuple[Any, Any]:
    """``frame`` and ``values`` with a NaN between segments, so a line is not drawn across a cut."""
    if frame.shape[0] == 0:
        return frame.astype(np.float64), values
    gaps = np.flatnonzero(np.diff(segment)) + 1
    return (
        np.insert(frame.astype(np.float64), gaps, np.nan),
        np.insert(np.asarray(values, dtype=np.float64), gaps, np.nan),
    )


def segmentation_png(
    target: Target,
    title: str,
    rate: float,
    frames: tuple[int, int],
    results: Sequence[PcaResult | PpcaResult | GmmResult],
    bands: Sequence[Band] = (),
) -> None:
    """One panel per result, against seconds from the recording's first frame (``frames``: its first
    and last AMC frame numbers; the results count frames from 0): PCA's error derivative ``d`` and
    its threshold, PPCA's ``H`` (first forward pass, log scale), GMM's raw and merged labels; each
    method's cuts as red lines and the true boundaries ``bands`` (AMC frames) as green bands."""
    if not results:
        raise ValueError("segmentation_png needs at least one method's result")
    plt = _pyplot()
    first, last = frames
    seconds = (last - first + 1) / rate
    fig, axes = plt.subplots(
        len(results), 1, figsize=(min(24.0, max(10.0, seconds / 2)), 1.5 + 2.7 * len(results)), squeeze=False
    )
    for ax, result in zip(axes[:, 0], results, strict=True):
        if isinstance(result, PcaResult):
            t, d = _broken(result.frame, result.segment, result.d)
            ax.plot(t / rate, d, linewidth=0.8)
            t, threshold = _broken(result.frame, result.segment, result.threshold)
            ax.plot(t / rate, threshold, linewidth=0.8)
            label = "PCA: d_i (blue) and mean + kσ·std of the earlier d (orange)"
        elif isinstance(result, PpcaResult):
            t, h = _broken(result.frame, result.segment, result.h)
            ax.semilogy(t / rate, h, linewidth=0.8, marker=".", markersize=2)
            label = "PPCA: H (first forward pass; cuts of all passes)"
        else:
            n = result.labels.shape[0]
            ax.plot(np.arange(n) / rate, result.raw_labels, color="0.6", linewidth=0.6)
            ax.plot(np.arange(n) / rate, result.labels, color="C0", linewidth=1.2)
            label = "GMM: cluster of each frame (grey: most likely, blue: short runs merged)"
        for b in bands:
            ax.axvspan((b.lo - first) / rate, (b.hi - first) / rate, color="tab:green", alpha=0.25)
        for c in result.boundaries:
            ax.axvline(c.frame / rate, color="tab:red", linewidth=0.8)
        ax.set_xlim(0, seconds)
        ax.set_title(label, fontsize=9, loc="left")
    truth = "; green: true boundaries with their tolerance" if bands else ""
    axes[-1, 0].set_xlabel(f"seconds (red: cuts{truth})")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    _save(fig, target)
    plt.close(fig)
