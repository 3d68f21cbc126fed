"""Reading and forward kinematics over every AMC file in ../shared/data/mocap, on one core.

    python -m bench.bench_io [--repeat 3]

Prints frames/s for: gzip inflate alone, the streaming reader (the baseline the others are compared
with), the whole-file reader, batch forward kinematics, per-frame forward kinematics, and whole-file
reading + batch forward kinematics together. Each figure is the best of ``--repeat`` runs.
"""

from __future__ import annotations

from bench.common import arguments, best_of, load
from bench.machine import describe
from replay import iter_amc, read_amc
from replay.textio import read_bytes


def main() -> None:
    args = arguments(__doc__)
    data = load(args.data)
    pairs, skeletons, models, frames = data.pairs, data.skeletons, data.models, data.frames
    print(describe())
    print(f"data: {len(pairs)} AMC files, {frames} frames, pinned to one core, best of {args.repeat}")

    def inflate() -> None:
        for _, amc in pairs:
            read_bytes(amc)

    def stream() -> None:
        for asf, amc in pairs:
            for _ in iter_amc(amc, skeletons[asf]):
                pass

    def whole() -> None:
        for asf, amc in pairs:
            read_amc(amc, skeletons[asf])

    def fk() -> None:
        for model, m in data.with_models():
            model.positions(m.channels)

    sample_frames, fk_frame = data.fk_per_frame()

    def whole_and_fk() -> None:
        for asf, amc in pairs:
            models[asf].positions(read_amc(amc, skeletons[asf]).channels)

    t_inflate = best_of(args.repeat, inflate)
    t_stream = best_of(args.repeat, stream)
    t_whole = best_of(args.repeat, whole)
    t_fk = best_of(args.repeat, fk)
    t_fk_frame = best_of(args.repeat, fk_frame)
    t_both = best_of(args.repeat, whole_and_fk)

    rows = [
        ("gzip inflate only", frames / t_inflate, ""),
        ("streaming reader (baseline)", frames / t_stream, "1.00x"),
        ("whole-file reader", frames / t_whole, f"{t_stream / t_whole:.2f}x"),
        ("  of which parsing (minus inflate)", frames / (t_whole - t_inflate), ""),
        ("forward kinematics, batch", frames / t_fk, ""),
        ("forward kinematics, per frame", sample_frames / t_fk_frame, ""),
        ("whole-file reader + batch FK", frames / t_both, f"{t_stream / t_both:.2f}x"),
    ]
    print(f"{'stage':38s} {'frames/s':>12s} {'vs stream':>10s}")
    for name, rate, ratio in rows:
        print(f"{name:38s} {rate:12,.0f} {ratio:>10s}")
    fk_ratio = (frames / t_fk) / (sample_frames / t_fk_frame)
    print(f"batch FK is {fk_ratio:.0f}x per-frame FK")
    print(f"2005 system: 1.29 M frames in 71 s = {1.29e6 / 71:,.0f} frames/s")
    print(f"(per-frame FK: {1e6 * t_fk_frame / sample_frames:.0f} us/frame; a 120 Hz frame lasts 8333 us)")


if __name__ == "__main__":
    main()
