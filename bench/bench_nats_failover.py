"""What a killed NATS server costs a replicated JetStream stream it leads (``docs/cluster.md``, "No
single point of failure").

    python -m bench.bench_nats_failover [--repeat 3] [--rate 1000] [--seconds 12]

The shipped three-server cluster (``deploy/nats/cluster``, on free loopback ports, as the tests
start it) ``--repeat`` times: a memory stream of 3 replicas on ``probe.>``, a publisher on a server
that does not lead it sending ``--rate`` plain NATS messages a second (numbered, no
acknowledgement: as an MQTT publisher's poses reach a partition's buffer), the leader killed (kill
-9) 3 s in. Printed per run: the messages sent, those the stream stored, and the numbers missing,
as seconds of the publisher's messages: how long no leader stored them.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import statistics
import tempfile
import time
from pathlib import Path

from bench.machine import describe
from tests.nats_server import NatsCluster


async def one(cluster: NatsCluster, rate: float, seconds: float) -> dict[str, float]:
    import nats
    from nats.js.api import StorageType, StreamConfig

    servers = {s.url: s for s in cluster.servers}
    admin = await nats.connect(servers=[s.url for s in cluster.servers])
    js = admin.jetstream()
    await js.add_stream(
        StreamConfig(name="PROBE", subjects=["probe.>"], storage=StorageType.MEMORY, num_replicas=3)
    )
    made = await js.stream_info("PROBE")
    assert made.cluster is not None, "the stream is not replicated: is this a cluster?"
    name = f"server_name: {made.cluster.leader}\n"
    leader = next(s for s in cluster.servers if name in s.config.read_text(encoding="utf-8"))
    publisher_url = next(url for url, s in servers.items() if s is not leader)
    await admin.close()
    pub = await nats.connect(publisher_url)
    sent, killed, started = 0, False, time.monotonic()
    while (now := time.monotonic()) - started < seconds:
        while sent < (now - started) * rate:
            await pub.publish(f"probe.{sent}", b"p")
            sent += 1
        if not killed and now - started >= 3.0:
            leader.kill()
            killed = True
        await asyncio.sleep(0.001)
    await pub.flush()
    await pub.close()
    survivor = await nats.connect(publisher_url)
    js = survivor.jetstream()
    deadline = time.monotonic() + 60
    info = None
    while info is None and time.monotonic() < deadline:  # a new leader answers
        with contextlib.suppress(Exception):
            info = await js.stream_info("PROBE")
        await asyncio.sleep(0.1)
    assert info is not None, "the stream did not answer within a minute of the kill"
    stored: list[int] = []
    sub = None
    while sub is None and time.monotonic() < deadline:  # consumers are made slowly while it recovers
        with contextlib.suppress(Exception):
            sub = await js.subscribe("probe.>", ordered_consumer=True)
    assert sub is not None, "no consumer of the stream could be made within a minute"
    with contextlib.suppress(Exception):
        while len(stored) < info.state.messages:
            msg = await sub.next_msg(timeout=2)
            stored.append(int(msg.subject.split(".")[1]))
    await survivor.close()
    missing = sent - len(set(stored))
    return {
        "sent": sent,
        "stored": len(set(stored)),
        "missing": missing,
        "gap_s": missing / rate,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=12.0)
    args = parser.parse_args()
    print(describe())
    gaps = []
    for k in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="bench-nats-failover-") as where:
            cluster = NatsCluster(Path(where)).start()
            try:
                r = asyncio.run(one(cluster, args.rate, args.seconds))
            finally:
                cluster.stop()
        gaps.append(r["gap_s"])
        print(
            f"run {k + 1}: sent {r['sent']:.0f}, stored {r['stored']:.0f}, missing {r['missing']:.0f} "
            f"({r['gap_s']:.2f} s of the publisher's messages)",
            flush=True,
        )
    print(f"gap: median {statistics.median(gaps):.2f} s, most {max(gaps):.2f} s")


if __name__ == "__main__":
    main()
