"""``mocapd view`` checks who calls it (issue 36): a real view process, real HTTP and WebSocket
clients. ``/ws`` and ``/api/`` refuse another site's Origin and a Host that is not the served
address (DNS rebinding); with a token (given, or made when served beyond loopback, with a warning)
they refuse a caller without it; no response names the server's software."""

from __future__ import annotations

import http.client
from pathlib import Path

import aiohttp

from tests.helpers import View, assert_one_error_line, mocapd

TOKEN = "a-token-of-the-test-0123456789"


def get(view: View, path: str, headers: dict[str, str]) -> tuple[int, dict[str, str]]:
    """Status and headers of ``GET path`` with exactly these headers (``Host`` included)."""
    connection = http.client.HTTPConnection("127.0.0.1", view.port, timeout=5)
    try:
        connection.putrequest("GET", path, skip_host=True)
        for name, value in headers.items():
            connection.putheader(name, value)
        connection.endheaders()
        response = connection.getresponse()
        response.read()
        return response.status, dict(response.getheaders())
    finally:
        connection.close()


async def handshake(view: View, query: str = "", **headers: str) -> int:
    """The HTTP status of a WebSocket handshake on ``/ws`` (101: accepted)."""
    async with aiohttp.ClientSession() as session:
        try:
            async with session.ws_connect(f"{view.url}ws{query}", headers=headers) as ws:
                assert (await ws.receive_json(timeout=5))["type"] == "snapshot"
                return 101
        except aiohttp.WSServerHandshakeError as e:
            return e.status


async def test_another_sites_page_cannot_open_the_socket(tmp_path: Path) -> None:
    view = View(tmp_path, "mqtt://127.0.0.1:1").start()
    try:
        served = f"127.0.0.1:{view.port}"
        assert await handshake(view, Origin=f"http://{served}") == 101
        assert await handshake(view) == 101  # not a browser: no Origin
        assert await handshake(view, Origin="http://attacker.example") == 403
        assert await handshake(view, Origin="null") == 403
        assert await handshake(view, Origin=f"http://{served}.attacker.example") == 403
        assert view.process is not None and view.process.poll() is None
    finally:
        view.stop()


def test_the_api_checks_host_and_origin(tmp_path: Path) -> None:
    view = View(tmp_path, "mqtt://127.0.0.1:1").start()
    try:
        for host in (f"127.0.0.1:{view.port}", f"localhost:{view.port}", f"LOCALHOST:{view.port}"):
            assert get(view, "/api/status", {"Host": host})[0] == 200, host
        # a name that resolves here by DNS rebinding: the browser sends it as Host and Origin alike
        rebound = f"attacker.example:{view.port}"
        assert get(view, "/api/status", {"Host": rebound, "Origin": f"http://{rebound}"})[0] == 403
        assert get(view, "/api/status", {"Host": f"127.0.0.1:{view.port + 1}"})[0] == 403
        assert get(view, "/api/status", {})[0] in (400, 403)  # no Host at all
        cross = {"Host": f"127.0.0.1:{view.port}", "Origin": "http://attacker.example"}
        assert get(view, "/api/status", cross)[0] == 403
        # the page itself holds no data: served to anyone, and nothing names aiohttp or Python
        status, headers = get(view, "/", {"Host": rebound})
        assert status == 200
        for path in ("/", "/api/status", "/static/view.js", "/nothing"):
            _, headers = get(view, path, {"Host": f"127.0.0.1:{view.port}"})
            assert headers["Server"] == "mocapd", (path, headers)
        refused = view.status()
        assert refused is not None and sum(refused["callers_refused"].values()) >= 3
    finally:
        view.stop()


async def test_a_token_is_asked_for_when_given(tmp_path: Path) -> None:
    view = View(tmp_path, "mqtt://127.0.0.1:1", token=TOKEN).start()  # status() sends it
    try:
        host = {"Host": f"127.0.0.1:{view.port}"}
        assert get(view, "/api/status", host)[0] == 401
        assert get(view, "/api/status?token=wrong-token-0123456789", host)[0] == 401
        assert get(view, f"/api/status?token={TOKEN}", host)[0] == 200
        assert get(view, "/api/status", host | {"Authorization": f"Bearer {TOKEN}"})[0] == 200
        assert await handshake(view) == 401
        assert await handshake(view, f"?token={TOKEN}") == 101
        assert get(view, "/", host)[0] == 200  # the page, which passes on its URL's ?token=
    finally:
        view.stop()


async def test_served_beyond_loopback_it_makes_a_token_and_warns(tmp_path: Path) -> None:
    view = View(tmp_path, "mqtt://127.0.0.1:1", "--host", "0.0.0.0").start()
    try:
        (warning,) = [e for e in view.logs() if e["event"] == "served beyond loopback"]
        token = warning["open"].split("?token=", 1)[1]
        assert len(token) >= 16 and warning["level"] == "warning"
        assert view.status() is None  # asked without the token
        host = {"Host": f"192.0.2.7:{view.port}"}  # beyond loopback any name: the token guards
        assert get(view, "/api/status", host)[0] == 401
        assert get(view, f"/api/status?token={token}", host)[0] == 200
        assert await handshake(view, f"?token={token}") == 101
        assert await handshake(view, f"?token={token}", Origin="http://attacker.example") == 403
    finally:
        view.stop()


def test_a_bad_token_is_one_line() -> None:
    line = assert_one_error_line(
        mocapd("view", "--bus", "mqtt://127.0.0.1:1", "--token", "short", timeout=30)
    )
    assert "--token: must be 16 to 256 characters" in line
