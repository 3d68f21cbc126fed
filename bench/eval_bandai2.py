"""The user's path on a studio's BVH takes (issue 35): ``mocapd learn`` with its defaults on four
styles of Bandai Namco Research's motion dataset 2 (``bandai2``, CC BY-NC-ND 4.0, read unmodified),
then the recogniser over the other three styles' takes joined into one stream.

    python -m bench.eval_bandai2 [--train active,elderly,exhausted,feminine] [--seed 0] [--keep DIR]
                                 [--repetitions N] [--costs]

The training manifest names each take whole (``class, bvh, actor``, the style as the actor, so that
calibration leaves one style out). ``mocapd learn --manifest M --out LIB`` runs in a process of its
own with no other option (with ``--repetitions N``, that option of ``mocapd learn`` as well: 0
learns every class from whole takes).
The left-out styles' takes (each rig mapped onto the standard joints, :mod:`replay.rigs`) are
joined in random order into one 30 Hz stream, each moved on the floor to start where the previous
one ended, with 0.25 s of linear blending between them, and go through the batch twin of the live
recogniser (:func:`daemon.recognizer.detect_positions`). A detection is right when at least half of
it lies inside a take of its class; a take is found when it holds a right detection. Printed: per
class and pooled precision (detections) and recall (takes), the machine and the time. The styles
are split alphabetically by default; nothing is tuned on the takes reported.

Then the same per class without competition (``recognizer.compete: false``: every class on its own
τ), and with ``--costs``, why a class is lost: per class and left-out style, the best cost of the
class's template over each of its takes alone (the worst of them) against its τ, and the class whose
template costs least there (what competition gives the motion to).
"""

from __future__ import annotations

import argparse
import random
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from bench.machine import describe
from daemon.features.stream import sampled_features
from daemon.learn.calibration import clip_costs
from daemon.library import Library, load_library
from daemon.recognizer import Detection, detect_positions
from daemon.types import BoolArray, FloatArray, RecognitionSettings
from replay.joints import JOINT_NAMES
from replay.rigs import read_bvh_take

BANDAI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "bandai2"
STYLES = ("active", "elderly", "exhausted", "feminine", "masculine", "normal", "youthful")
BLEND_S = 0.25


def takes() -> list[tuple[str, str, Path]]:
    """Every take as (action, style, path)."""
    out = []
    for path in sorted(BANDAI.glob("dataset-2_*.bvh.gz")):
        action, style, _ = path.name.removeprefix("dataset-2_").removesuffix(".bvh.gz").rsplit("_", 2)
        out.append((action, style, path))
    return out


def joined(clips: list[tuple[str, Path]], rate: float) -> tuple[FloatArray, list[tuple[str, int, int]]]:
    """The clips' standard joints in one stream (each moved on the floor to start where the last
    ended, :data:`BLEND_S` of linear blending between them) and each clip's (class, first, last)
    frame numbers, from 1."""
    parts: list[FloatArray] = []
    spans = []
    frame = 1
    for action, path in clips:
        joints = read_bvh_take(path).joints
        if parts:
            last = parts[-1][-1]
            joints = joints + np.array([last[0, 0] - joints[0, 0, 0], 0.0, last[0, 2] - joints[0, 0, 2]])
            k = round(BLEND_S * rate)
            w = (np.arange(1, k + 1) / (k + 1))[:, None, None]
            parts.append((1 - w) * last + w * joints[0])
            frame += k
        parts.append(joints)
        spans.append((action, frame, frame + len(joints) - 1))
        frame += len(joints)
    return np.concatenate(parts), spans


def report(found: list[Detection], spans: list[tuple[str, int, int]]) -> None:
    """Per class and pooled precision (detections) and recall (takes) of ``found`` against ``spans``."""

    def right(cls: str, start: int, end: int) -> bool:
        return any(c == cls and 2 * (min(end, b) - max(start, a) + 1) >= end - start + 1 for c, a, b in spans)

    detections, correct, takes_of, hit = Counter[str](), Counter[str](), Counter[str](), Counter[str]()
    for d in found:
        detections[d.class_name] += 1
        correct[d.class_name] += right(d.class_name, d.start_frame, d.end_frame)
    for cls, first, last in spans:
        takes_of[cls] += 1
        hit[cls] += any(
            d.class_name == cls
            and right(cls, d.start_frame, d.end_frame)
            and d.start_frame <= last
            and d.end_frame >= first
            for d in found
        )
    print(f"{'class':<22} {'precision':>9} {'recall':>7} {'detections':>10} {'takes':>6}")
    for c in sorted(takes_of):
        precision = correct[c] / detections[c] if detections[c] else float("nan")
        print(f"{c:<22} {precision:>9.2f} {hit[c] / takes_of[c]:>7.2f} {detections[c]:>10} {takes_of[c]:>6}")
    total = sum(detections.values())
    print(
        f"{'pooled':<22} {sum(correct.values()) / total if total else float('nan'):>9.2f} "
        f"{sum(hit.values()) / sum(takes_of.values()):>7.2f} {total:>10} {sum(takes_of.values()):>6}"
    )


def print_costs(library: Library, held_out: list[tuple[str, str, Path]]) -> None:
    """Per class (of ``library``) and style of ``held_out`` (action, style, path): the worst over
    the style's takes of the class's best subsequence-DTW cost on the take alone, its τ, and the
    class whose template costs least on those takes."""
    features: list[BoolArray] = [
        sampled_features(read_bvh_take(p).joints, JOINT_NAMES, 30.0, 1) for _, _, p in held_out
    ]
    names = sorted(library.classes)
    costs = np.array(
        [clip_costs(library.classes[n].quantised, features, library.classes[n].steps) for n in names]
    )
    print(f"{'class':<22} {'style':<10} {'own cost':>8} {'tau':>6}  cheapest there")
    for action, style in sorted({(a, s) for a, s, _ in held_out}):
        at = [i for i, (a, s, _) in enumerate(held_out) if a == action and s == style]
        worst = costs[:, at].max(axis=1)
        own, winner = worst[names.index(action)], int(np.argmin(worst))
        tau = library.classes[action].tau
        print(f"{action:<22} {style:<10} {own:>8.3f} {tau:>6.3f}  {names[winner]} ({worst[winner]:.3f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", default="active,elderly,exhausted,feminine")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keep", type=Path, default=None, help="keep the manifest and library here")
    parser.add_argument(
        "--repetitions", type=int, default=None, metavar="N", help="give mocapd learn --repetitions N"
    )
    parser.add_argument("--costs", action="store_true", help="print each class's costs on the left-out takes")
    args = parser.parse_args()
    train = set(args.train.split(","))
    print(describe())
    where = args.keep or Path(tempfile.mkdtemp(prefix="bandai2-"))
    where.mkdir(parents=True, exist_ok=True)
    rows = ["class,bvh,actor"] + [f"{a},{p.resolve()},{s}" for a, s, p in takes() if s in train]
    (where / "train.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    began = time.perf_counter()
    learned = subprocess.run(
        [
            sys.executable,
            "-m",
            "daemon",
            "learn",
            "--manifest",
            str(where / "train.csv"),
            "--out",
            str(where / "lib"),
            *([] if args.repetitions is None else ["--repetitions", str(args.repetitions)]),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    if learned.returncode != 0:
        raise SystemExit(learned.stderr)
    learn_s = time.perf_counter() - began
    print(
        "".join(line for line in learned.stderr.splitlines(keepends=True) if line.startswith("[repetitions]"))
    )
    library = load_library(where / "lib")
    held_out = [(a, s, p) for a, s, p in takes() if s not in train]
    clips = [(a, p) for a, _, p in held_out]
    random.Random(args.seed).shuffle(clips)
    stream, spans = joined(clips, 30.0)
    numbers = np.arange(1, len(stream) + 1)
    print(
        f"trained on {sorted(train)} ({len(rows) - 1} takes, "
        f"{sum(len(c.training) for c in library.classes.values())} examples, learn {learn_s:.0f} s); "
        f"detected on {len(clips)} takes of the other styles joined ({len(stream) / 30:.0f} s at 30 Hz)"
    )
    report(detect_positions(stream, numbers, library, 30.0), spans)
    print("without competition (recognizer.compete: false):")
    report(
        detect_positions(stream, numbers, library, 30.0, settings=RecognitionSettings(compete=False)), spans
    )
    if args.costs:
        print_costs(library, held_out)
    print(f"library and manifest in {where}")


if __name__ == "__main__":
    main()
