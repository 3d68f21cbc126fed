"""A publisher of many looping streams for cluster mode (``tests/test_cluster_e2e.py``,
``bench/bench_cluster.py``): real CMU and HDM05 recordings, stream ``i`` looping recording
``i mod n`` (:data:`RECORDINGS`) with its sequence numbers continuing across loops and an epoch of its
own, its skeleton announced every second (over MQTT at QoS 0, not retained), its poses at ``rate``
Hz, all the streams' poses of one tick sent together; over MQTT (``mqtt://HOST:PORT``, e.g. NATS's MQTT port)
or NATS (``nats://HOST:PORT``). At the end it prints one JSON object: per stream its recording, epoch
and first and last sequence numbers sent.

    python -m bench.cluster_load --to mqtt://127.0.0.1:1883 --streams 30 --seconds 30
"""

from __future__ import annotations

import argparse
import asyncio
import json
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from daemon.recordings import read_recording
from protocols.messages import PoseMessage, SkeletonMessage, encode, topic
from replay import Motion

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap"
RECORDINGS: tuple[tuple[str, str], ...] = (
    ("cmu/13/13.asf", "cmu/13/13_30.amc.gz"),
    ("cmu/13/13.asf", "cmu/13/13_29.amc.gz"),
    ("cmu/86/86.asf", "cmu/86/86_01.amc.gz"),
    ("cmu/13/13.asf", "cmu/13/13_17.amc.gz"),
    ("cmu/02/02.asf", "cmu/02/02_05.amc.gz"),
    ("hdm05/asf/HDM_bd.asf", "hdm05/cut/squat1Reps/HDM_bd_squat1Reps_001_120.amc.gz"),
    ("cmu/13/13.asf", "cmu/13/13_34.amc.gz"),
    ("cmu/135/135.asf", "cmu/135/135_06.amc.gz"),
    ("hdm05/asf/HDM_bk.asf", "hdm05/cut/hopBothLegs1hops/HDM_bk_hopBothLegs1hops_020_120.amc.gz"),
    ("cmu/19/19.asf", "cmu/19/19_15.amc.gz"),
)
"""(ASF, AMC) below the shared data, 120 Hz each."""
RATE = 120.0
ANNOUNCE_S = 1.0


def stream_id(i: int, amc: str) -> str:
    name = Path(amc).name.removesuffix(".gz").removesuffix(".amc")
    return f"s{i:02d}-{name}"


def recording(i: int) -> tuple[Path, Path]:
    asf, amc = RECORDINGS[i % len(RECORDINGS)]
    return DATA / asf, DATA / amc


class Stream:
    """One looping stream: its skeleton message and its poses, sequence numbers from 0."""

    def __init__(self, i: int, motion: Motion, asf_text: str) -> None:
        self.id = stream_id(i, RECORDINGS[i % len(RECORDINGS)][1])
        self.epoch = uuid.uuid4().hex[:16]
        self.motion = motion
        skeleton = SkeletonMessage(self.id, RATE, asf=asf_text, angle_unit="rad", epoch=self.epoch)
        self.skeleton = (topic(skeleton), encode(skeleton))
        self.next = 0

    def pose(self) -> tuple[str, bytes]:
        channels = self.motion.channels[self.next % len(self.motion.channels)]
        m = PoseMessage(self.id, self.next, time.time(), channels=channels, epoch=self.epoch)
        self.next += 1
        return topic(m), encode(m)


def streams(n: int) -> list[Stream]:
    loaded: dict[int, tuple[Motion, str]] = {}
    out = []
    for i in range(n):
        k = i % len(RECORDINGS)
        if k not in loaded:
            asf, amc = recording(i)
            loaded[k] = (read_recording(asf, amc), asf.read_text(encoding="utf-8", errors="replace"))
        out.append(Stream(i, *loaded[k]))
    return out


async def run(
    send: Callable[[str, bytes, bool], Any], items: list[Stream], seconds: float, rate: float
) -> None:
    """Every stream's pose each tick for ``seconds``, the skeletons every :data:`ANNOUNCE_S`;
    ``send(topic, payload, is_skeleton)``."""
    for s in items:  # the skeletons first, so that every stream is recognised from its first pose
        await send(*s.skeleton, True)
    await asyncio.sleep(0.5)
    start = announced = time.monotonic()
    tick = 0
    while True:
        now = time.monotonic()
        if now - start >= seconds:
            return
        if now - announced >= ANNOUNCE_S:
            announced = now
            for s in items:
                await send(*s.skeleton, True)
        for s in items:
            await send(*s.pose(), False)
        tick += 1
        wait = start + tick / rate - time.monotonic()
        await asyncio.sleep(max(0.0, wait))


async def over_mqtt(url: str, items: list[Stream], seconds: float, rate: float) -> None:
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    host, port = url.removeprefix("mqtt://").split(":")
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"load-{uuid.uuid4().hex[:8]}")
    client.max_queued_messages_set(0)
    client.max_inflight_messages_set(1000)
    connected = threading.Event()
    client.on_connect = lambda *a: connected.set()
    client.connect(host, int(port), keepalive=30)
    client.loop_start()
    if not connected.wait(10):
        raise TimeoutError(f"no MQTT connection to {url}")

    async def send(name: str, payload: bytes, skeleton: bool) -> None:
        # QoS 0, not retained: a NATS cluster's MQTT listener stores QoS 1 and retained messages in
        # JetStream while it holds the connection (docs/cluster.md), which a killed server stalls
        client.publish(name, payload, qos=0)

    try:
        await run(send, items, seconds, rate)
        await asyncio.sleep(0.5)
    finally:
        client.loop_stop()
        client.disconnect()


async def over_nats(url: str, items: list[Stream], seconds: float, rate: float) -> None:
    import nats

    nc = await nats.connect(url)

    async def send(name: str, payload: bytes, skeleton: bool) -> None:
        await nc.publish(name.replace("/", "."), payload)

    try:
        await run(send, items, seconds, rate)
        await nc.flush()
    finally:
        await nc.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--to", required=True, help="mqtt://HOST:PORT or nats://HOST:PORT")
    parser.add_argument("--streams", type=int, default=30)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=RATE, help="poses per second per stream")
    args = parser.parse_args()
    items = streams(args.streams)
    go = over_mqtt if args.to.startswith("mqtt://") else over_nats
    asyncio.run(go(args.to, items, args.seconds, args.rate))
    report = {
        s.id: {
            "asf": str(recording(i)[0]),
            "amc": str(recording(i)[1]),
            "epoch": s.epoch,
            "first": 0,
            "last": s.next - 1,
        }
        for i, s in enumerate(items)
    }
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    main()
