"""``daemon.config``: the shipped config.yaml, bad configurations, and the CLI's ``--config``."""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from daemon.config import (
    Config,
    ConfigError,
    ProgressConfig,
    RecognizerConfig,
    ReplayConfig,
    load_config,
    parse_config,
)
from daemon.errors import FileAccessError, MocapdError
from daemon.types import RecognitionSettings
from replay import KinematicModel, read_amc, read_asf
from tests.helpers import CMU_AMC, CMU_ASF, REPO, mocapd

SHIPPED = REPO / "config.yaml"


def write(tmp_path: Path, text: str, name: str = "config.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


# --------------------------------------------------------------------------------------------------
# good configurations


def test_shipped_config_is_the_defaults() -> None:
    assert load_config(SHIPPED) == Config()
    assert Config() == Config(replay=ReplayConfig(frame_rate_hz=120.0, units="asf"))
    assert load_config(None) == Config()


def test_shipped_config_shows_every_field() -> None:
    """config.yaml writes out every field of every section (with the defaults' values, above): the
    dataclasses are where the defaults are, the file shows them all."""
    shipped = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    sections = {f.name: getattr(Config(), f.name) for f in dataclasses.fields(Config)}
    assert {name: list(fields) for name, fields in shipped.items()} == {
        name: [f.name for f in dataclasses.fields(section)] for name, section in sections.items()
    }


@pytest.mark.parametrize("text", ["", "# nothing\n", "---\n...\n", "replay: {}\n"])
def test_empty_config_is_the_defaults(tmp_path: Path, text: str) -> None:
    assert load_config(write(tmp_path, text)) == Config()


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("replay:\n  units: cm\n", ReplayConfig(units="cm")),
        ("replay:\n  frame_rate_hz: 60\n", ReplayConfig(frame_rate_hz=60.0)),
        ("replay:\n  frame_rate_hz: 29.97\n  units: asf\n", ReplayConfig(frame_rate_hz=29.97)),
        ("replay: {frame_rate_hz: 240.0, units: cm}\n", ReplayConfig(frame_rate_hz=240.0, units="cm")),
    ],
)
def test_good_config(tmp_path: Path, text: str, expected: ReplayConfig) -> None:
    config = load_config(write(tmp_path, text))
    assert config == Config(replay=expected)
    assert isinstance(config.replay.frame_rate_hz, float)


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp://127.0.0.1:0",
        "bind tcp://*:*",
        "tcp://[::1]:65535",
        "connect tcp://h:1",
        "ipc:///tmp/p",
        "hello",
    ],
)
def test_zmq_endpoints_config_takes(endpoint: str) -> None:
    """A free port to bind (0 or ZeroMQ's ``*``: the "online" log line says which was bound), any
    port in 1..65535, and what is not TCP (ZeroMQ checks that when it binds)."""
    config = parse_config({"zmq": {"poses": endpoint}})
    assert config.zmq.poses == endpoint


def test_progress_section(tmp_path: Path) -> None:
    """Off by default, 10 a second; the file and MOCAPD_PROGRESS_<FIELD> set it, the variable wins
    and is named in its error."""
    assert Config().progress == ProgressConfig(enabled=False, per_s=10.0)
    path = write(tmp_path, "progress:\n  enabled: true\n  per_s: 4\n")
    assert load_config(path).progress == ProgressConfig(True, 4.0)
    env = {"MOCAPD_PROGRESS_PER_S": "2.5", "MOCAPD_PROGRESS_ENABLED": "false"}
    assert load_config(path, env).progress == ProgressConfig(False, 2.5)
    with pytest.raises(ConfigError, match="MOCAPD_PROGRESS_PER_S"):
        load_config(path, {"MOCAPD_PROGRESS_PER_S": "-1"})


def test_recognizer_section(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, "recognizer:\n  max_gap_s: 1.5\n  compete: false\n"))
    assert config == Config(recognizer=RecognizerConfig(max_gap_s=1.5, compete=False))
    assert load_config(write(tmp_path, "recognizer: {}\n")).recognizer.compete


def test_recognition_settings(tmp_path: Path) -> None:
    """The recogniser's settings are built from the config once, frozen, and refuse values out of
    range as the config does (and a class named twice)."""
    config = load_config(write(tmp_path, "recognizer:\n  max_gap_s: 1.5\n  compete: false\n  hold_s: 0\n"))
    settings = config.recognizer.settings(["squat1Reps", "kickLFront1Reps"])
    assert settings == RecognitionSettings(("squat1Reps", "kickLFront1Reps"), 1.5, False, 0.0)
    assert RecognizerConfig().settings() == RecognitionSettings()
    assert (settings.max_gap(30.0), settings.hold(30.0)) == (45, 0)
    assert (RecognitionSettings(max_gap_s=0.001).max_gap(30.0), RecognitionSettings().hold(30.0)) == (1, 150)
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.compete = True  # type: ignore[misc]
    assert hash(settings) == hash(dataclasses.replace(settings))
    bad: list[tuple[dict[str, Any], str]] = [
        ({"max_gap_s": 0.0}, "max_gap_s"),
        ({"max_gap_s": -1.0}, "max_gap_s"),
        ({"max_gap_s": math.nan}, "max_gap_s"),
        ({"max_gap_s": math.inf}, "max_gap_s"),
        ({"max_gap_s": "2"}, "max_gap_s"),
        ({"max_gap_s": True}, "max_gap_s"),
        ({"hold_s": -0.5}, "hold_s"),
        ({"hold_s": math.nan}, "hold_s"),
        ({"hold_s": math.inf}, "hold_s"),
        ({"compete": "yes"}, "compete"),
        ({"compete": 1}, "compete"),
        ({"classes": ["squat1Reps"]}, "classes"),
        ({"classes": ("squat1Reps", "")}, "classes"),
        ({"classes": ("squat1Reps", 3)}, "classes"),
        ({"classes": ("squat1Reps", "squat1Reps")}, "named twice"),
        ({"mode": "gated"}, "mode must be one of library, keyframes, dtw"),
    ]
    for fields, message in bad:
        with pytest.raises(ValueError, match=message):
            RecognitionSettings(**fields)
    with pytest.raises(ValueError, match="named twice"):
        config.recognizer.settings(["a", "a"])
    assert load_config(write(tmp_path, "recognizer:\n  mode: dtw\n")).recognizer.settings().mode == "dtw"
    with pytest.raises(ConfigError, match=r"recognizer\.mode"):
        load_config(write(tmp_path, "recognizer:\n  mode: stream\n"))


# --------------------------------------------------------------------------------------------------
# bad configurations: ConfigError naming the file and the field


BAD = [
    # unknown fields
    (
        "unknown-top",
        "replay: {}\nextra: 1\n",
        "extra: unknown field (allowed: cluster, logging, metrics, mqtt, progress, recognizer",
    ),
    (
        "unknown-recognizer",
        "recognizer:\n  gap: 2\n",
        "recognizer.gap: unknown field (allowed: compete, hold_s, max_gap_s, mode)",
    ),
    ("gap-zero", "recognizer:\n  max_gap_s: 0\n", "recognizer.max_gap_s"),
    ("gap-string", "recognizer:\n  max_gap_s: 2s\n", "recognizer.max_gap_s"),
    ("gap-huge", "recognizer:\n  max_gap_s: 1e9\n", "recognizer.max_gap_s"),
    ("gap-nan", "recognizer:\n  max_gap_s: .nan\n", "recognizer.max_gap_s"),
    ("compete-string", "recognizer:\n  compete: 'yes'\n", "recognizer.compete"),
    ("progress-per-s-zero", "progress:\n  per_s: 0\n", "progress.per_s"),
    ("progress-per-s-huge", "progress:\n  per_s: 1e6\n", "progress.per_s"),
    ("progress-enabled-string", "progress:\n  enabled: 'on'\n", "progress.enabled"),
    (
        "progress-unknown",
        "progress:\n  floor: 0.2\n",
        "progress.floor: unknown field (allowed: enabled, per_s)",
    ),
    (
        "unknown-replay",
        "replay:\n  fps: 60\n",
        "replay.fps: unknown field (allowed: frame_rate_hz, rig_maps, units)",
    ),
    ("misspelt", "replay:\n  frame_rate: 60\n", "replay.frame_rate: unknown field"),
    # wrong types and non-positive frame rates
    ("rate-string", "replay:\n  frame_rate_hz: '120'\n", "replay.frame_rate_hz"),
    ("rate-bool", "replay:\n  frame_rate_hz: true\n", "replay.frame_rate_hz"),
    ("rate-list", "replay:\n  frame_rate_hz: [120]\n", "replay.frame_rate_hz"),
    ("rate-null", "replay:\n  frame_rate_hz:\n", "replay.frame_rate_hz"),
    ("rate-zero", "replay:\n  frame_rate_hz: 0\n", "replay.frame_rate_hz"),
    ("rate-zero-float", "replay:\n  frame_rate_hz: 0.0\n", "replay.frame_rate_hz"),
    ("rate-negative", "replay:\n  frame_rate_hz: -120\n", "replay.frame_rate_hz"),
    ("rate-nan", "replay:\n  frame_rate_hz: .nan\n", "replay.frame_rate_hz"),
    ("rate-inf", "replay:\n  frame_rate_hz: .inf\n", "replay.frame_rate_hz"),
    # bad units
    ("units-upper", "replay:\n  units: CM\n", "replay.units"),
    ("units-other", "replay:\n  units: metres\n", "replay.units"),
    ("units-number", "replay:\n  units: 1\n", "replay.units"),
    ("units-list", "replay:\n  units: [cm]\n", "replay.units"),
    # a daemon that could not be told apart on the bus, or would do nothing
    ("instance-slash", "service:\n  instance: a/b\n", "service.instance: letters, digits"),
    ("instance-plus", "service:\n  instance: a+\n", "service.instance: letters, digits"),
    ("instance-hash", "service:\n  instance: '#'\n", "service.instance: letters, digits"),
    ("instance-space", "service:\n  instance: a b\n", "service.instance: letters, digits"),
    ("no-sources", "service:\n  sources: []\n", "service.sources: must name at least one transport"),
    ("no-sinks", "service:\n  sinks: []\n", "service.sinks: must name at least one transport"),
    # ports outside 1..65535, which libzmq took modulo 65536 (":99999" bound 34463), and more
    # recognition processes than a machine can use (500 on 2 cores once started, and took 54 s to
    # stop): refused at parse (issue 32)
    (
        "zmq-port-past-65535",
        "zmq:\n  poses: tcp://127.0.0.1:99999\n",
        "zmq.poses: tcp://127.0.0.1:99999: the port must be in 1..65535 (or 0 or * to bind any free "
        "port), got '99999'",
    ),
    ("zmq-port-65536", "zmq:\n  detections: tcp://*:65536\n", "zmq.detections: tcp://*:65536: the port"),
    ("zmq-port-negative", "zmq:\n  poses: bind tcp://127.0.0.1:-1\n", "zmq.poses: bind tcp://127.0.0.1:-1:"),
    (
        "zmq-connect-to-port-0",
        "zmq:\n  poses: connect tcp://127.0.0.1:0\n",
        "zmq.poses: connect tcp://127.0.0.1:0: the port must be in 1..65535, got '0'",
    ),
    (
        "mqtt-port-past-65535",
        "service:\n  sources: [mqtt]\nmqtt:\n  url: mqtt://127.0.0.1:99999\n",
        "mqtt.url: an MQTT broker is mqtt://HOST[:PORT] or mqtts://HOST[:PORT], the port in 1..65535, "
        "got 'mqtt://127.0.0.1:99999'",
    ),
    ("mqtt-port-0", "service:\n  sinks: [mqtt]\nmqtt:\n  url: mqtt://127.0.0.1:0\n", "mqtt.url: an MQTT"),
    (
        "nats-port",
        "cluster:\n  nats: nats://h:70000\n",
        "cluster.nats: must be nats://HOST:PORT[,nats://HOST:PORT...] (a port",
    ),
    ("etcd-port", "cluster:\n  coordinator: etcd://h:70000\n", "cluster.coordinator: an etcd coordinator"),
    ("workers-too-many", "service:\n  workers: 1000\n", "service.workers: must be 0 (one per core) to "),
    # non-mapping sections
    ("replay-number", "replay: 3\n", "replay: must be a mapping"),
    ("replay-list", "replay:\n  - frame_rate_hz: 60\n", "replay: must be a mapping"),
    ("replay-string", "replay: cm\n", "replay: must be a mapping"),
    ("top-list", "- replay\n", "top level: must be a mapping"),
    ("top-string", "replay\n", "top level: must be a mapping"),
]


@pytest.mark.parametrize(("text", "field"), [(t, f) for _, t, f in BAD], ids=[i for i, _, _ in BAD])
def test_bad_config(tmp_path: Path, text: str, field: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: {re.escape(field)}") as caught:
        load_config(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: "), message
    assert field in message, message
    assert "\n" not in message


def test_bad_field_reports_the_value(tmp_path: Path) -> None:
    path = write(tmp_path, "replay:\n  frame_rate_hz: -120\n  units: asf\n")
    rate = r"replay\.frame_rate_hz: must be a number in \(0, 10000\], got -120$"
    with pytest.raises(ConfigError, match=rate):
        load_config(path)
    with pytest.raises(ConfigError, match=r"replay\.units: must be one of asf, cm, got 'inch'$"):
        load_config(write(tmp_path, "replay:\n  units: inch\n"))


def test_huge_integer_frame_rate(tmp_path: Path) -> None:
    """An integer too large for a float (YAML has no size limit on ints) is a bad value like any other:
    ConfigError naming the field, not an OverflowError from ``math.isfinite``."""
    path = write(tmp_path, "replay:\n  frame_rate_hz: 1" + "0" * 400 + "\n")
    with pytest.raises(
        ConfigError,
        match=rf"^{re.escape(str(path))}: replay\.frame_rate_hz: must be .*, got 10+$",  # the value
    ) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: replay.frame_rate_hz")


def test_invalid_yaml(tmp_path: Path) -> None:
    path = write(tmp_path, "replay:\n  frame_rate_hz: [120\n  units: cm\n")
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}:[23]: not valid YAML: ") as caught:
        load_config(path)
    message = str(caught.value)
    assert re.match(rf"{re.escape(str(path))}:[23]: not valid YAML: ", message), message
    assert caught.value.line in (2, 3)


def test_missing_config_file(tmp_path: Path) -> None:
    path = tmp_path / "absent.yaml"
    with pytest.raises(FileAccessError, match=r"No such file or directory$") as caught:
        load_config(path)
    assert str(caught.value) == f"{path}: No such file or directory"
    assert isinstance(caught.value, MocapdError)


def test_parse_config_names_its_source() -> None:
    with pytest.raises(ConfigError, match=r"^settings: replay\.speed: unknown field"):
        parse_config({"replay": {"speed": 1}}, "settings")
    assert parse_config({}, "settings") == Config()


# --------------------------------------------------------------------------------------------------
# the CLI's --config


def test_cli_bad_config_exits_2_naming_the_field(tmp_path: Path) -> None:
    path = write(tmp_path, "replay:\n  frame_rate_hz: 0\n", "bad.yaml")
    result = mocapd("--config", path, "info", "--asf", CMU_ASF, "--amc", CMU_AMC)
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == f"mocapd: {path}: replay.frame_rate_hz: must be a number in (0, 10000], got 0\n"


def test_cli_unknown_field_exits_2(tmp_path: Path) -> None:
    path = write(tmp_path, "replay:\n  unit: cm\n", "bad.yaml")
    result = mocapd("--config", path, "info", "--asf", CMU_ASF, "--amc", CMU_AMC)
    assert result.returncode == 2
    assert result.stderr.startswith(f"mocapd: {path}: replay.unit: unknown field")
    assert result.stderr.count("\n") == 1


def test_cli_invalid_yaml_exits_2_with_one_line(tmp_path: Path) -> None:
    """README: bad input exits with status 2 and *one* line naming the file and line."""
    path = write(tmp_path, "replay:\n  frame_rate_hz: [120\n  units: cm\n", "bad.yaml")
    result = mocapd("--config", path, "info", "--asf", CMU_ASF, "--amc", CMU_AMC)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert re.match(rf"mocapd: {re.escape(str(path))}:[23]: not valid YAML: ", result.stderr), result.stderr
    assert result.stderr.count("\n") == 1, result.stderr


@pytest.mark.slow
def test_cli_run_takes_config_after_the_command(tmp_path: Path) -> None:
    """``mocapd run --config C`` reads C as ``mocapd --config C run`` does (the README's table)."""
    path = write(tmp_path, "service:\n  sinks: []\n", "bad.yaml")
    for argv in (("run", "--config", path), ("--config", path, "run")):
        result = mocapd(*argv)
        assert result.returncode == 2
        assert result.stderr.startswith(f"mocapd: {path}: service.sinks: must name at least one transport")
        assert result.stderr.count("\n") == 1


def test_cli_config_frame_rate(tmp_path: Path) -> None:
    path = write(tmp_path, "replay:\n  frame_rate_hz: 60\n")
    result = mocapd("--config", path, "info", "--asf", CMU_ASF, "--amc", CMU_AMC)
    assert (result.returncode, result.stderr) == (0, "")
    assert "duration:   5.717 s at 60 Hz (assumed)" in result.stdout.splitlines()


@pytest.mark.slow
def test_cli_config_units_cm(tmp_path: Path) -> None:
    """``units: cm`` in the config makes ``positions`` write centimetres, as ``--cm`` does."""
    config = write(tmp_path, "replay:\n  units: cm\n")
    from_config, from_flag = tmp_path / "config.csv", tmp_path / "flag.csv"
    for extra, out in (([], from_config), (["--cm"], from_flag)):
        result = mocapd(
            "--config", config, "positions", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", out, *extra
        )
        assert (result.returncode, result.stderr) == (0, "")
    text = from_config.read_text(encoding="utf-8")
    assert text == from_flag.read_text(encoding="utf-8")

    rows = list(csv.reader(text.splitlines()))[1:]
    got = np.array([[float(v) for v in r[2:]] for r in rows])
    motion = read_amc(CMU_AMC, read_asf(CMU_ASF))
    model = KinematicModel(motion.skeleton)
    cm = model.joints(model.positions(motion.channels, "cm")).reshape(-1, 3)
    asf = model.joints(model.positions(motion.channels, "asf")).reshape(-1, 3)
    assert np.max(np.abs(got - cm)) <= 1e-6
    assert np.max(np.abs(got - asf)) > 1.0  # really not ASF units
