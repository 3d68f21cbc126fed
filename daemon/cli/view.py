"""``mocapd view``: the live view, a web page of what the daemon sees on its bus."""

from __future__ import annotations

import argparse
import os
from typing import Any

from daemon.cli.common import positive_float
from daemon.config import Config


def register(sub: Any) -> None:
    view = sub.add_parser(
        "view",
        help="a live view in the browser: the streams, their skeletons, motions under way and detections",
    )
    view.add_argument(
        "--bus",
        required=True,
        metavar="URL",
        help="mqtt://HOST:PORT (the broker) or zmq+tcp://HOST:PORT (the daemon's detections socket, "
        "where it relays skeletons and poses with zmq.relay_per_s)",
    )
    view.add_argument("--host", default="127.0.0.1", help="address to serve the page on (default 127.0.0.1)")
    view.add_argument(
        "--port", type=int, default=8080, help="port to serve the page on (default 8080; 0: any)"
    )
    view.add_argument(
        "--metrics",
        default=None,
        metavar="http://HOST:PORT",
        help="the daemon's metrics server, for its health and drops (/healthz, /metrics)",
    )
    view.add_argument(
        "--poses-per-s",
        type=positive_float,
        default=30.0,
        metavar="N",
        help="the most poses a second per stream sent to the browsers (default 30)",
    )
    view.add_argument(
        "--token",
        default=None,
        help="a token /ws and /api/ then ask for (the page passes on its URL's ?token=); default: "
        "the environment's MOCAPD_VIEW_TOKEN, else none on loopback and a new one, logged, beyond it",
    )
    view.set_defaults(func=_view)


def _view(args: argparse.Namespace, config: Config) -> int:
    from daemon.cli import package_version
    from daemon.extras import require
    from daemon.recordings import read_rig_maps

    require("view", "mocapd view")
    from daemon.service.view.server import serve_view
    from daemon.service.view.settings import view_settings

    token = args.token if args.token is not None else os.environ.get("MOCAPD_VIEW_TOKEN") or None
    settings = view_settings(args.bus, args.host, args.port, args.metrics, args.poses_per_s, token)
    rigs = read_rig_maps(config.replay.rig_maps)  # the daemon's, so that the view maps rigs as it does
    return serve_view(settings, version=package_version(), rigs=rigs)
