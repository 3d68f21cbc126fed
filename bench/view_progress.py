"""What the live view's progress bars tell an operator (issue 36), on the four CMU trials of the
view's picture (:data:`bench.view_figure.CLIPS`) with the shipped library: the progress events
the daemon publishes (:func:`daemon.progress.detect_progress`, the live path's batch twin, at
``progress.per_s`` 10), each held until the next, drawn as the page draws them.

    python -m bench.view_progress

Printed per trial, for the bar the page draws now (:func:`daemon.service.view.state.closeness`,
position * (1 - cost/τ)) and, as the baseline, the bar it drew before (the position alone, here
on today's events, whose paths start after the class's last spent candidate):

* per class never detected in the trial, the share of the trial's time its bar is at 95 % or
  more ("nearly complete"; the aim: under 5 %);
* of the detections, how many had their class rise between the motion's first frame and the
  detection's publication: its bar, or (a class with keyframes) its keyframes matched, above
  where they stood at the first event of that span. When the class's previous motion was
  published during this one, the span starts at that publication: the previous motion's bar
  stands until then.

Nothing is tuned: the bar is the issue's own formula and 95 % its "nearly complete".
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable

from bench.common import DATA
from bench.machine import describe
from bench.view_figure import CLIPS
from daemon.library import default_library_path, load_library
from daemon.progress import ClassState, ProgressEvent, detect_progress
from daemon.recognizer import Detection
from daemon.recordings import read_recording
from daemon.service.view.state import closeness

NEAR = 0.95
Bar = Callable[[ClassState], float]
BARS: dict[str, Bar] = {
    "closeness (now)": lambda c: closeness(c.position, c.cost, c.tau),
    "position alone": lambda c: c.position,
}


def near_shares(events: list[ProgressEvent], frames: int, bar: Bar) -> dict[str, float]:
    """Per class, the share of ``frames`` its ``bar`` is at :data:`NEAR` or more."""
    held: dict[str, float] = defaultdict(float)
    for event, following in zip(events, [*events[1:], None], strict=True):
        until = following.frame if following is not None else frames
        for c in event.classes:
            if bar(c) >= NEAR:
                held[c.class_name] += until - event.frame
    return {name: t / frames for name, t in held.items()}


def rose(events: list[ProgressEvent], d: Detection, bar: Bar, since: int) -> bool:
    """Whether ``d``'s class rose between its first frame (or frame ``since``, if later) and its
    publication (module docstring)."""

    def of(e: ProgressEvent) -> tuple[float, float]:
        c = next((c for c in e.classes if c.class_name == d.class_name), None)
        return (0.0, 0.0) if c is None else (bar(c), len(c.matched) / c.keyframes if c.keyframes else 0.0)

    span = [of(e) for e in events if max(d.start_frame, since) <= e.frame <= d.emitted_at_frame]
    return bool(span) and any(max(v[i] for v in span) > span[0][i] for i in (0, 1))


def previous(found: list[Detection], d: Detection) -> int:
    """The last frame within ``d``'s motion at which a detection of an earlier motion of its class
    was published (-1: none)."""
    return max(
        (
            x.emitted_at_frame
            for x in found
            if x.class_name == d.class_name
            and x.start_frame < d.start_frame
            and d.start_frame <= x.emitted_at_frame <= d.end_frame
        ),
        default=-1,
    )


def main() -> None:
    print(describe())
    library = load_library(default_library_path())
    risen_all = dict.fromkeys(BARS, 0)
    worst_all = dict.fromkeys(BARS, 0.0)
    detections = 0
    for asf, amc, _ in CLIPS:
        motion = read_recording(DATA / asf, DATA / amc)
        out = detect_progress(motion, library, 120.0)
        events = [e for e in out if isinstance(e, ProgressEvent)]
        found = [e for e in out if isinstance(e, Detection)]
        detected = {d.class_name for d in found}
        print(f"{amc}: {len(motion)} frames, {len(found)} detections of {sorted(detected)}")
        for name, bar in BARS.items():
            never = {c: s for c, s in near_shares(events, len(motion), bar).items() if c not in detected}
            risen = sum(rose(events, d, bar, previous(found, d)) for d in found)
            worst = max(never.values(), default=0.0)
            risen_all[name] += risen
            worst_all[name] = max(worst_all[name], worst)
            listed = ", ".join(f"{c} {s:.0%}" for c, s in sorted(never.items(), key=lambda x: -x[1]) if s > 0)
            print(
                f"  {name:<18} never-detected classes nearly complete: worst {worst:.1%}"
                f"{f' ({listed})' if listed else ''}; detections preceded by their class rising "
                f"{risen}/{len(found)}"
            )
        detections += len(found)
    for name in BARS:
        print(
            f"all four, {name}: worst never-detected share {worst_all[name]:.1%}; "
            f"rising before {risen_all[name]}/{detections}"
        )


if __name__ == "__main__":
    main()
