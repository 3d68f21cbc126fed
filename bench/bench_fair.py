"""The MQTT intake's fair queue (``protocols/fair.py``) under floods, on one core.

    python -m bench.bench_fair [--repeat 3] [--messages 30000] [--size 10000]

Puts ``--messages`` messages into a queue of ``--size`` with nothing taken (so every put past the
size drops one), then takes them all: under one stream id (the baseline), under a distinct id each
(a flood of new ids), and round-robin over 100 ids. Prints messages/s and the ratio to the
baseline; a queue whose drop looked at every stream held would fall behind it by orders of
magnitude for distinct ids.
"""

from __future__ import annotations

from bench.common import arguments, best_of
from bench.machine import describe
from protocols.fair import FairQueue
from protocols.transport import Incoming


def main() -> None:
    args = arguments(__doc__, messages=30_000, size=10_000)
    print(describe())
    print(
        f"{args.messages:,} puts into a queue of {args.size:,}, then taken; one core, best of {args.repeat}"
    )
    cases = {
        "one stream id (baseline)": [Incoming("mocap/one/pose", b"x", 0.0)] * args.messages,
        "a new id per message": [Incoming(f"mocap/id{k}/pose", b"x", 0.0) for k in range(args.messages)],
        "100 ids in turn": [Incoming(f"mocap/id{k % 100}/pose", b"x", 0.0) for k in range(args.messages)],
    }
    times = {}
    for name, messages in cases.items():

        def run(messages: list[Incoming] = messages) -> None:
            queue = FairQueue(args.size)
            for m in messages:
                queue.put(m)
            while queue.take() is not None:
                pass

        times[name] = best_of(args.repeat, run)
    base = times["one stream id (baseline)"]
    for name, t in times.items():
        print(f"{name:28s} {args.messages / t:12,.0f} messages/s  {base / t:5.2f}x")


if __name__ == "__main__":
    main()
