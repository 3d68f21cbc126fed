"""The live view's page in a real browser (Playwright driving Debian's Chromium, headless): a real
mosquitto, a real daemon, ``mocapd view`` and ``mocapd replay`` as real processes; what the page
shows is read from its DOM and from what it records on ``window.mocapdView``."""

from __future__ import annotations

import contextlib
import csv
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from playwright.sync_api import Browser, Page, sync_playwright

from bench.bench_view import CHROMIUM, CHROMIUM_ARGS
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from protocols.messages import (
    ClassProgress,
    DetectionMessage,
    Message,
    PoseMessage,
    ProgressMessage,
    SkeletonMessage,
    StatusMessage,
    encode,
    topic,
)
from replay import JOINT_NAMES
from tests.helpers import DATA, Broker, Daemon, View, finished, replay, wait_for

TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
XSS = ("<script>window.__xss=1</script>", '<img src=x onerror="window.__xss=1">')


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


class Publisher:
    def __init__(self, url: str) -> None:
        host, port = url.removeprefix("mqtt://").split(":")
        self.client = paho.Client(
            CallbackAPIVersion.VERSION2, client_id=f"test-browser-{time.monotonic_ns()}"
        )
        self.client.connect(host, int(port))
        self.client.loop_start()

    def send(self, message: Message, on: str | None = None, retain: bool = False) -> None:
        self.client.publish(on or topic(message), encode(message), qos=1, retain=retain).wait_for_publish(5)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


@contextlib.contextmanager
def a_page(
    tmp_path: Path, browser: Browser, *, token: str | None = None
) -> Iterator[tuple[Page, Publisher, View]]:
    """A real mosquitto, ``mocapd view`` on it (with ``token``), a publisher and a tab on the page
    (its URL with the token), once the page has its first snapshot; all stopped after."""
    broker = Broker(tmp_path).start()
    view = View(tmp_path, broker.url, token=token).start()
    pub = Publisher(broker.url)
    page = browser.new_page()
    try:
        opened(page, view.url if token is None else f"{view.url}?token={token}")
        yield page, pub, view
    finally:
        page.close()
        pub.close()
        view.stop()
        broker.stop()


def tab(browser: Browser) -> tuple[Page, list[str]]:
    """A new tab of 1280x900 and the errors its scripts raise (appended as they come)."""
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    return page, errors


def opened(page: Page, url: str) -> None:
    """``page`` at ``url``, once the view has sent it its first snapshot."""
    page.goto(url)
    until(page, "window.mocapdView && window.mocapdView.snapshots >= 1")


def until(page: Page, expression: str, timeout: float = 10.0) -> None:
    """Wait until ``expression`` holds in the page, asked through the DevTools protocol (Playwright's
    ``wait_for_function`` evaluates with ``eval`` in the page, which the view's CSP refuses)."""
    wait_for(lambda: bool(page.evaluate(expression)), timeout, expression)


def loopback_only(page: Page) -> list[str]:
    """Every URL the page asks for, its WebSockets too (checked loopback by the caller)."""
    urls: list[str] = []
    page.on("request", lambda r: urls.append(r.url))
    page.on("websocket", lambda ws: urls.append(ws.url))
    return urls


def card_of(page: Page, stream: str) -> Any:
    """The DOM facts of ``stream``'s card (None while it has none)."""
    return page.evaluate(
        """(id) => {
            const card = [...document.querySelectorAll('section.card')].find((c) => c.dataset.stream === id);
            if (!card) return null;
            return {
                title: card.querySelector('h2').textContent,
                detections: [...card.querySelectorAll('li.detection')].map((li) => ({
                    class: li.dataset.class, start: Number(li.dataset.start), end: Number(li.dataset.end),
                    text: li.querySelector('.class-name').textContent,
                })),
                progress: [...card.querySelectorAll('.class-progress')].map((row) => ({
                    class: row.dataset.class, position: Number(row.dataset.position),
                    matched: Number(row.dataset.matched), keyframes: Number(row.dataset.keyframes),
                    width: row.querySelector('.fill').style.width,
                    ticks: row.querySelectorAll('.tick.on').length,
                    keys: row.querySelector('.keys').textContent,
                    still: row.classList.contains('still'),
                    text: row.querySelector('.class-name').textContent,
                })),
                canvas: card.querySelector('canvas').toDataURL(),
                idle: ((p) => (p.hidden ? null : p.textContent))(card.querySelector('.progress > p')),
            };
        }""",
        stream,
    )


SAMPLE_BARS = """(id) => {
    window.__bars = {};
    const sample = () => {
        const card = [...document.querySelectorAll('section.card')].find((c) => c.dataset.stream === id);
        for (const row of card ? card.querySelectorAll('.class-progress') : []) {
            const seen = (window.__bars[row.dataset.class] ??= []);
            const width = row.querySelector('.fill').style.width;
            if (!seen.includes(width)) seen.push(width);
        }
        requestAnimationFrame(sample);
    };
    sample();
}"""
"""Record in the page, every frame it draws, the widths each class's progress bar of a card shows."""


def progress(stream: str, frame: int, position: float, matched: tuple[int, ...]) -> ProgressMessage:
    c = ClassProgress("Squat", 3, matched, position, 0.4 * position * 0.25, 0.25)
    return ProgressMessage(stream, frame, (c,), time.time(), time.time())


@pytest.mark.slow
@pytest.mark.parametrize("bus", ["mqtt", "zmq"])
def test_the_page_shows_a_replay_through_the_daemon(tmp_path: Path, browser: Browser, bus: str) -> None:
    """A replay of CMU 13_30 through a daemon with its progress on, over MQTT (mosquitto carries the
    poses) or ZeroMQ (the daemon relays 30 poses a second to the view): its card appears, its figure
    moves, progress bars move with the daemon's progress events (a class of each detection shown
    before it), the detections ``mocapd detect`` gives on the recording land in its timeline with
    the same classes and frames; every request the page makes is to loopback; a closed tab frees
    the view's client."""
    want = trial_detections()
    config: dict[str, dict[str, object]] = {
        # a detection held to the trial's last frame is published when the daemon flushes the
        # silent stream: before the view drops the card (10 s)
        "service": {"queue_frames": 100_000, "idle_s": 3},
        "progress": {"enabled": True},
    }
    broker = None
    if bus == "mqtt":
        broker = Broker(tmp_path).start()
        daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=config).start()
        watched, into = broker.url, broker.url
    else:
        config["zmq"] = {"relay_per_s": 30}
        daemon = Daemon(tmp_path, sinks=["zmq"], config=config).start()
        watched, into = "zmq+" + daemon.detections, "zmq+" + daemon.poses
    try:
        view = View(tmp_path, watched, metrics=f"http://127.0.0.1:{daemon.metrics_port}").start()
        try:
            watch_the_replay(browser, view, into, want)
        finally:
            view.stop()
    finally:
        daemon.stop()
        if broker is not None:
            broker.stop()


def trial_detections() -> list[tuple[str, int, int]]:
    """(class, start, end) of what ``mocapd detect`` finds in the trial, with the shipped library."""
    found = detect(read_recording(*TRIAL), load_library(default_library_path()), 120.0)
    return [(d.class_name, d.start_frame, d.end_frame) for d in found]


def watch_the_replay(browser: Browser, view: View, into: str, want: list[tuple[str, int, int]]) -> None:
    """The page of ``view`` while CMU 13_30 is replayed ``into`` the daemon (see the test above)."""
    page, errors = tab(browser)
    urls = loopback_only(page)
    replaying = None
    try:
        opened(page, view.url)
        page.wait_for_selector('#health[data-healthy="true"]', timeout=10_000)
        page.evaluate(SAMPLE_BARS, "13_30")
        replaying = replay(*TRIAL, into, speed="3")
        wait_for(lambda: card_of(page, "13_30") is not None, 15, "the stream's card")
        page.wait_for_selector('#daemons .pill[data-state="online"]', timeout=10_000)
        first = card_of(page, "13_30")["canvas"]
        page.wait_for_timeout(250)
        assert card_of(page, "13_30")["canvas"] != first, "the figure did not change between frames"
        finished(replaying)
        wait_for(lambda: len(card_of(page, "13_30")["detections"]) >= len(want), 20, "the detections")
        card = card_of(page, "13_30")
        shown = [(d["class"], d["start"], d["end"]) for d in reversed(card["detections"])]  # newest first
        recorded = page.evaluate("window.mocapdView.streams['13_30'].detections")
        assert shown == want == [(d["class"], d["start"], d["end"]) for d in recorded]
        assert [d["text"] for d in reversed(card["detections"])] == [c for c, _, _ in want]
        bars: dict[str, list[str]] = page.evaluate("window.__bars")
        assert {c for c, _, _ in want} <= set(bars), bars  # every detected class had a bar
        assert max(len(widths) for widths in bars.values()) >= 3, bars  # and bars moved
        facts = page.evaluate(
            """() => { const s = window.mocapdView.streams['13_30'];
                       return {drawn: s.posesDrawn, latency: s.latencyMs, fps: window.mocapdView.fps}; }"""
        )
        assert facts["drawn"] >= 100 and 0 <= facts["latency"] < 1000 and facts["fps"] > 5
        assert view.status()["clients"] == 1  # type: ignore[index]
    finally:
        if replaying is not None and replaying.poll() is None:
            replaying.kill()
            replaying.communicate()
        page.close()
    wait_for(lambda: view.status()["clients"] == 0, 10, "the closed tab's client freed")  # type: ignore[index]
    assert errors == []
    assert urls and all(urlsplit(u).hostname == "127.0.0.1" for u in urls), urls


def test_progress_bars_follow_the_progress_messages(tmp_path: Path, browser: Browser) -> None:
    """Until a stream's first progress message the card says none came (the daemon may not publish
    any); each sets its class's bar to its position and lights its keyframes matched; an empty one
    clears the stream's bars: no motion under way."""
    with a_page(tmp_path, browser) as (page, pub, _):
        pub.send(SkeletonMessage("s", 120.0, JOINT_NAMES))
        pub.send(PoseMessage("s", 1, time.time(), positions=np.zeros((26, 3), np.float32)))
        wait_for(lambda: card_of(page, "s") is not None, 10, "the stream's card")
        assert card_of(page, "s")["idle"] == "no progress yet (mocapd run --progress)"
        seen = []
        for k, (position, matched) in enumerate([(0.2, ()), (0.55, (600,)), (0.9, (600, 640))]):
            pub.send(progress("s", 600 + 40 * k, position, matched))
            until(page, f"(window.mocapdView.streams['s']?.progress.Squat?.position ?? -1) === {position}")
            (row,) = card_of(page, "s")["progress"]
            seen.append((row["position"], row["matched"], row["ticks"], row["width"]))
        # the bar is the closeness, position * (1 - cost/τ), and cost/τ is 0.4·position here
        widths = [f"{round(p * (1 - 0.4 * p) * 100, 1):g}%" for p in (0.2, 0.55, 0.9)]
        assert seen == [(0.2, 0, 0, widths[0]), (0.55, 1, 1, widths[1]), (0.9, 2, 2, widths[2])]
        pub.send(ProgressMessage("s", 800, (), time.time(), time.time()))  # nothing under way
        until(page, "Object.keys(window.mocapdView.streams['s'].progress).length === 0")
        assert card_of(page, "s")["idle"] == "no motion under way"
        (row,) = card_of(page, "s")["progress"]  # its slot stays, at zero: nothing jumps
        assert (row["class"], row["width"], row["still"]) == ("Squat", "0%", True)
        # more classes than slots: six rows, the rest counted; 64 keyframes said, not drawn
        many = tuple(ClassProgress(f"c{i}", 64, tuple(range(1, 41)), 0.5, 0.0, 0.2) for i in range(9))
        pub.send(ProgressMessage("s", 840, many, time.time(), time.time()))
        until(page, "window.mocapdView.streams['s'].progressHidden === 3")
        rows = card_of(page, "s")["progress"]
        assert [r["class"] for r in rows] == ["c5", "c0", "c1", "c2", "c3", "c4"]  # Squat's slot given up
        assert all(r["ticks"] == 0 and r["keys"] == "40/64 keyframes" for r in rows)
        box = page.evaluate("document.querySelector('section.card').getBoundingClientRect().width")
        inner = page.evaluate(
            "Math.max(...[...document.querySelectorAll('.class-progress')].map((r) => r.scrollWidth))"
        )
        assert inner <= box


def test_bus_text_is_shown_as_text(tmp_path: Path, browser: Browser) -> None:
    """A topic level, class names and a version holding markup, and stream ids that are names of
    JavaScript's object prototype, are shown as text: nothing runs, no element is made of them."""
    broker = Broker(tmp_path).start()
    view = View(tmp_path, broker.url).start()
    pub = Publisher(broker.url)
    page = browser.new_page()
    urls = loopback_only(page)
    try:
        opened(page, view.url)
        pose = PoseMessage("evil", 1, time.time(), positions=np.zeros((26, 3), np.float32))
        pub.send(pose, on=f"mocap/{XSS[1]}/pose")  # refused (not a stream id), listed
        pub.send(StatusMessage("d-x", "online", XSS[0], 1, 1.0), retain=False)
        for stream in ("evil", "__proto__", "constructor"):
            pub.send(SkeletonMessage(stream, 120.0, JOINT_NAMES))
            pub.send(PoseMessage(stream, 1, time.time(), positions=pose.positions))
        for k, name in enumerate(XSS):
            pub.send(
                DetectionMessage(f"x{k}", "evil", name, 10 * k, 10 * k + 5, 0.01, 0.1, 10 * k + 9, 1.0, 2.0)
            )
        c = ClassProgress(XSS[1], 2, (3,), 0.5, 0.01, 0.1)
        pub.send(ProgressMessage("evil", 12, (c, ClassProgress(XSS[0], 0, (), 0.25, 0.2, 0.1)), 1.0, 2.0))
        wait_for(
            lambda: len((card_of(page, "evil") or {"detections": []})["detections"]) == 2, 10, "detections"
        )
        wait_for(lambda: len(card_of(page, "evil")["progress"]) == 2, 10, "progress")
        until(page, "document.querySelectorAll('#refused li').length >= 1")
        page.wait_for_selector('#daemons .pill[data-instance="d-x"]', timeout=10_000)
        page.wait_for_timeout(300)
        card = card_of(page, "evil")
        assert sorted(d["text"] for d in card["detections"]) == sorted(XSS)
        assert sorted(p["text"] for p in card["progress"]) == sorted(XSS)
        facts = page.evaluate(
            """() => ({
                xss: typeof window.__xss,
                scripts: [...document.scripts].map((s) => s.getAttribute('src')),
                images: document.images.length,
                refused: [...document.querySelectorAll('#refused li .topic')].map((e) => e.textContent),
                daemon: document.querySelector('#daemons .pill[data-instance="d-x"]').textContent,
                titles: [...document.querySelectorAll('section.card h2')].map((h) => h.textContent).sort(),
                recorded: Object.keys(window.mocapdView.streams).sort(),
                protoIntact: ({}).constructor === Object && typeof ({}).hasOwnProperty === "function",
            })"""
        )
        assert facts["xss"] == "undefined"
        assert facts["scripts"] == ["/static/view.js"] and facts["images"] == 0
        assert facts["refused"] == [f"mocap/{XSS[1]}/pose"]
        assert XSS[0] in facts["daemon"]
        assert facts["titles"] == facts["recorded"] == ["__proto__", "constructor", "evil"]
        assert facts["protoIntact"]
        assert all(urlsplit(u).hostname == "127.0.0.1" for u in urls), urls
    finally:
        page.close()
        pub.close()
        view.stop()
        broker.stop()


def test_the_page_passes_its_token_on_and_shows_no_invalid_date(tmp_path: Path, browser: Browser) -> None:
    """With ``--token`` the page opened with ``?token=`` connects and one opened without it does
    not; a status whose start time lies beyond what a Date can hold shows a dash."""
    token = "the-page-token-0123456789"
    with a_page(tmp_path, browser, token=token) as (page, pub, view):
        without = browser.new_page()
        without.goto(view.url)
        pub.send(StatusMessage("d-far", "online", "1", 0, 1e300), retain=False)
        page.wait_for_selector('#daemons .pill[data-instance="d-far"]', timeout=10_000)
        text = page.evaluate("document.querySelector('#daemons .pill[data-instance=\"d-far\"]').textContent")
        assert "Invalid" not in text and "started \u2013" in text
        assert without.evaluate("window.mocapdView.snapshots") == 0
        assert not without.evaluate("window.mocapdView.connected")
        without.close()


FACING = {  # a figure facing +z (its left at +x), centimetres, the left arm raised above the head
    "root": (0, 100, 0), "lhip": (10, 95, 0), "lknee": (10, 50, 0), "lankle": (10, 8, 0),
    "ltoes": (10, 0, 12), "rhip": (-10, 95, 0), "rknee": (-10, 50, 0), "rankle": (-10, 8, 0),
    "rtoes": (-10, 0, 12), "belly": (0, 110, 0), "chest": (0, 130, 0), "neck": (0, 150, 0),
    "head": (0, 160, 0), "headtop": (0, 175, 0), "lclavicle": (0, 150, 0), "lshoulder": (18, 148, 0),
    "lelbow": (20, 175, 0), "lwrist": (22, 200, 0), "lfingers": (22, 210, 0), "lthumb": (22, 205, 3),
    "rclavicle": (0, 150, 0), "rshoulder": (-18, 148, 0), "relbow": (-20, 120, 0),
    "rwrist": (-22, 95, 0), "rfingers": (-22, 85, 0), "rthumb": (-22, 90, 3),
}  # fmt: skip


def test_the_figure_is_drawn_in_true_perspective_and_handedness(tmp_path: Path, browser: Browser) -> None:
    """The camera (``mocapdView.projection``): facing it, a figure's left (+x) is on the screen's
    right and a nearer point is drawn larger; seen from above, the floor ring's near edge is wider
    than its far edge. The page's own drawing of a pose facing +z with the left arm raised: the
    left wrist is above the head and on the side of the screen that the figure's turn (the drawn
    yaw) puts it, at every draw."""
    camera = "{cx: 0, cy: 0, cz: 0, scale: 1, w: 400, h: 400, depth: 4000, yaw: 0, pitch: %s}"
    with a_page(tmp_path, browser) as (page, pub, _):
        facing = page.evaluate(
            f"""() => {{
                const p = window.mocapdView.projection({camera % 0});
                return {{left: p(100, 0, 0), near: p(100, 0, 500), far: p(100, 0, -500)}};
            }}"""
        )
        assert facing["left"][0] > 200  # the figure's left on the screen's right
        assert facing["near"][0] - 200 > facing["left"][0] - 200 > facing["far"][0] - 200 > 0
        above = page.evaluate(
            f"""() => {{
                const p = window.mocapdView.projection({camera % 0.6});
                const width = (z) => p(500, -900, z)[0] - p(-500, -900, z)[0];
                const v = (z) => p(0, -900, z)[1];
                return {{near: width(500), far: width(-500), nearV: v(500), farV: v(-500)}};
            }}"""
        )
        assert above["near"] > 1.2 * above["far"] and above["nearV"] > above["farV"]  # near: lower, wider
        pub.send(SkeletonMessage("facing", 120.0, JOINT_NAMES))
        pose = np.array([FACING[j] for j in JOINT_NAMES], np.float32)
        draws: list[dict[str, Any]] = []
        for k in range(40):
            pub.send(PoseMessage("facing", k + 1, time.time(), positions=pose))
            page.wait_for_timeout(50)
            drawn = page.evaluate("(window.mocapdView.streams['facing'] || {}).drawn || null")
            if drawn is not None:
                draws.append(drawn)
        assert draws, "the figure was never drawn"
        lw, head, root = (JOINT_NAMES.index(j) for j in ("lwrist", "head", "root"))
        for d in draws:
            screen = d["screen"]
            assert screen[lw][1] < screen[head][1]  # up is up
            side = np.cos(d["yaw"])  # the left's x on screen: x·cos(yaw) before perspective
            if abs(side) > 0.2:
                assert np.sign(screen[lw][0] - screen[root][0]) == np.sign(side), d


def test_daemon_pills_are_bounded_live_ones_first(tmp_path: Path, browser: Browser) -> None:
    """A flood of statuses draws at most four pills, live ones first (most recently heard), and
    one summary of the rest."""
    with a_page(tmp_path, browser) as (page, pub, _):
        pub.send(StatusMessage("d-offline", "offline", "1", 0, 1.0), retain=False)
        for k in range(7):
            pub.send(StatusMessage(f"d-{k}", "online", "1", 0, 1.0), retain=False)
        page.wait_for_selector("#daemons-more", timeout=10_000)
        until(page, "document.querySelector('#daemons-more').textContent.startsWith('+4 more')")
        shown = page.evaluate(
            "[...document.querySelectorAll('#daemons .pill[data-instance]')].map((p) => p.dataset.instance)"
        )
        assert shown == ["d-6", "d-5", "d-4", "d-3"]
        assert page.evaluate("document.querySelector('#daemons-more').textContent") == "+4 more (3 online)"


@pytest.mark.slow
def test_history_outlives_the_stream_and_a_view_restart(tmp_path: Path, browser: Browser) -> None:
    """CMU 13_30 replayed to its end through a daemon on MQTT that publishes the trial's last
    detection only when it forgets the silent stream (``idle_s`` 12, after the view's 10): the
    card stays, greyed, and takes that detection too; the view restarted mid-replay loses none
    (the broker keeps its session); the page's log and its CSV and JSON exports are exactly the
    detections of ``mocapd detect``."""
    want = trial_detections()
    broker = Broker(tmp_path).start()
    config: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000, "idle_s": 12}}
    daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=config).start()
    view = View(tmp_path, broker.url).start()
    page, errors = tab(browser)
    replaying = None
    try:
        opened(page, view.url)
        replaying = replay(*TRIAL, broker.url, speed="2")
        wait_for(lambda: len((card_of(page, "13_30") or {"detections": []})["detections"]) >= 3, 20, "three")
        view.stop()  # mid-replay: the page loses its server, which comes back on the same port
        view.start()
        until(page, "window.mocapdView.snapshots >= 2", 20)
        finished(replaying)
        page.wait_for_selector('section.card[data-stream="13_30"][data-ended="true"]', timeout=20_000)
        wait_for(lambda: len(card_of(page, "13_30")["detections"]) >= len(want), 30, "the last detection")
        card = card_of(page, "13_30")
        assert [(d["class"], d["start"], d["end"]) for d in reversed(card["detections"])] == want
        logged = page.evaluate("window.mocapdView.log()")
        assert [(d["class"], d["start_frame"], d["end_frame"]) for d in logged] == want
        with page.expect_download() as csv_download:
            page.click("#log-csv")
        rows = list(csv.DictReader(Path(csv_download.value.path()).read_text().splitlines()))
        assert [(r["class"], int(r["start_frame"]), int(r["end_frame"])) for r in rows] == want
        assert {r["stream"] for r in rows} == {"13_30"}
        with page.expect_download() as json_download:
            page.click("#log-json")
        items = json.loads(Path(json_download.value.path()).read_text())
        assert [(d["class"], d["start_frame"], d["end_frame"]) for d in items] == want
        page.click('section.card[data-stream="13_30"] button.dismiss')
        assert card_of(page, "13_30") is None and len(page.evaluate("window.mocapdView.log()")) == len(want)
        assert errors == []
    finally:
        if replaying is not None and replaying.poll() is None:
            replaying.kill()
            replaying.communicate()
        page.close()
        view.stop()
        daemon.stop()
        broker.stop()
