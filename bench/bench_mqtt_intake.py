"""The MQTT intake's cost per message: the receiving process's CPU time from its first message to its
last, through a real mosquitto on loopback, for S streams of pose-sized messages (1.5 kB) at 120 Hz,
each tick's messages in one write (as ``bench_service``'s load).

    python -m bench.bench_mqtt_intake [--streams 200] [--seconds 5]

Four receivers, each a process of its own on the first core (the load on the other), each putting
every message into the daemon's fair queue and taking it: ``transport``, the daemon's
:class:`protocols.mqtt.MqttTransport` (its subscriptions on a gmqtt connection, ``_Reader``);
``paho``, the transport's paho connection reading the same subscription (paho's external-loop API,
what the transport read with before); ``aiomqtt``, aiomqtt's public API (``Client.messages``);
``gmqtt``, gmqtt's public API alone (``on_message``), the floor the transport's reader adds to.
CPU time, not latency, so that a machine shared with other work still gives a fair comparison.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.bench_service import RATE, RawPublisher
from bench.machine import describe
from bench.processes import free_port, wait_port

PAYLOAD_BYTES = 1500
KINDS = ("transport", "paho", "aiomqtt", "gmqtt")


async def receive(kind: str, url: str, total: int) -> dict[str, float]:
    """Take ``total`` messages through ``kind``; its CPU time for them."""
    from daemon.config import MqttConfig
    from protocols.fair import FairQueue
    from protocols.mqtt import MqttTransport
    from protocols.transport import Incoming

    n, started = 0, 0.0
    queue = FairQueue(10 * total)
    done = asyncio.get_running_loop().create_future()

    def taken(topic: str, payload: bytes) -> None:
        """A message a callback delivered, into the fair queue and out (paho's and gmqtt's)."""
        nonlocal n, started
        started = started or time.process_time()
        queue.put(Incoming(topic, payload, time.time()))
        queue.take()
        n += 1
        if n == total and not done.done():
            done.set_result(None)

    if kind == "transport":
        transport = MqttTransport(
            MqttConfig(url=url, queue=10 * total),
            client_id="bench-intake",
            subscribe=[("mocap/+/pose", 0)],
            presence=None,
        )
        async with transport:
            await transport.wait_connected(10)
            print("ready", flush=True)
            async for _ in transport:
                started = started or time.process_time()
                n += 1
                if n == total:
                    break
    elif kind == "paho":
        transport = MqttTransport(MqttConfig(url=url), client_id="bench-intake", subscribe=[], presence=None)
        connection = transport.connection_to(
            None, client_id="bench-intake", clean_session=True, will=None, deliver=taken, timeout_s=10
        )
        async with connection:
            await connection.subscribe("mocap/+/pose", 0)
            serving = asyncio.create_task(connection.serve())
            print("ready", flush=True)
            await done
            cpu = time.process_time() - started
            serving.cancel()
        return {"messages": n, "cpu_s": round(cpu, 3), "us_per_message": round(1e6 * cpu / n, 2)}
    elif kind == "gmqtt":
        import gmqtt
        from gmqtt.mqtt.constants import MQTTv311

        client = gmqtt.Client("bench-intake")
        client.on_message = lambda client, topic, payload, qos, properties: taken(topic, payload)
        host, port = url.removeprefix("mqtt://").split(":")
        await client.connect(host, int(port), version=MQTTv311)
        subscribed = asyncio.Event()
        client.on_subscribe = lambda *_: subscribed.set()
        client.subscribe("mocap/+/pose", qos=0)
        await subscribed.wait()
        print("ready", flush=True)
        await done
        cpu = time.process_time() - started
        await client.disconnect()
        return {"messages": n, "cpu_s": round(cpu, 3), "us_per_message": round(1e6 * cpu / n, 2)}
    else:
        import aiomqtt

        host, port = url.removeprefix("mqtt://").split(":")
        async with aiomqtt.Client(host, int(port), identifier="bench-intake") as client:
            await client.subscribe("mocap/+/pose", qos=0)
            print("ready", flush=True)
            async for message in client.messages:
                assert isinstance(message.payload, bytes)
                taken(str(message.topic), message.payload)
                if done.done():
                    break
    cpu = time.process_time() - started
    return {"messages": n, "cpu_s": round(cpu, 3), "us_per_message": round(1e6 * cpu / n, 2)}


def load(port: int, streams: int, seconds: float) -> None:
    publisher = RawPublisher(port, f"bench-intake-load-{os.getpid()}")
    payload = os.urandom(PAYLOAD_BYTES)
    tick = [RawPublisher.packet(f"mocap/s{k}/pose", payload) for k in range(streams)]
    start = time.monotonic()
    for k in range(int(seconds * RATE)):
        wait = start + k / RATE - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        publisher.send(tick)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--streams", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--receive", choices=KINDS, help=argparse.SUPPRESS)
    parser.add_argument("--url", help=argparse.SUPPRESS)
    parser.add_argument("--total", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.receive is not None:  # the receiving process
        print(json.dumps(asyncio.run(receive(args.receive, args.url, args.total))), flush=True)
        return
    print(describe())
    total = int(args.seconds * RATE) * args.streams
    print(
        f"{args.streams} streams x {RATE:g} Hz x {args.seconds:g} s = {total:,} messages of "
        f"{PAYLOAD_BYTES} B through mosquitto on loopback; receiver on core 0, load on core 1"
    )
    work = Path(tempfile.mkdtemp(prefix="bench-intake-"))
    port = free_port()
    (work / "m.conf").write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\n"
        "max_queued_messages 10000000\n"
    )
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    broker = subprocess.Popen([mosquitto, "-c", str(work / "m.conf")], stderr=subprocess.DEVNULL)
    cores = sorted(os.sched_getaffinity(0))
    try:
        wait_port(port)
        for kind in KINDS:
            command = [sys.executable, "-m", "bench.bench_mqtt_intake", "--receive", kind]
            command += ["--url", f"mqtt://127.0.0.1:{port}", "--total", str(total)]
            receiver = subprocess.Popen(
                ["taskset", "-c", str(cores[0]), *command], stdout=subprocess.PIPE, text=True
            )
            assert receiver.stdout is not None
            if receiver.stdout.readline().strip() != "ready":
                raise SystemExit(f"the {kind} receiver did not start")
            os.sched_setaffinity(0, set(cores[1:] or cores))
            load(port, args.streams, args.seconds)
            out, _ = receiver.communicate(timeout=120)
            result = json.loads(out)
            print(
                f"{kind:>10s}: {result['us_per_message']:6.1f} us of CPU per message "
                f"({result['messages']:,} taken)"
            )
    finally:
        broker.terminate()
        broker.wait(10)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
