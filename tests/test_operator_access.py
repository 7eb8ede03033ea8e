"""Who may open the operator's servers (fluxdrive_bringup.view.gate): the probe's
cross-origin client (Origin http://evil.example, no token), a DNS-rebinding page
(`Host: evil.example`) and a client without the token are refused with one line to the client
and one in the log; the holder of the token gets in; the connection after the cap is refused
at once (HTTP 503), not left hanging in its handshake; the Foxglove SDK's own port speaks only
TLS with a certificate of this launch, so a page that finds it cannot complete a handshake.
The scope: the same rules, an invalid service name for the fault reset is a one-line 400 (was a
500), and started by the launcher it keeps its token out of its log."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("fluxdrive_bringup")
ROOT = Path(__file__).resolve().parents[1]
TOKEN = "operator-test-token"


def _raw(port: int, head: str, timeout: float = 10.0) -> str:
    """Send one request head; the server's first answer (status line and body)."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(head.encode())
        out = b""
        while True:
            try:
                chunk = s.recv(4096)
            except TimeoutError:
                break
            if not chunk:
                break
            out += chunk
            if b"\r\n\r\n" in out and (b"refused" in out or b"HTTP/1.1 101" in out):
                break
    return out.decode(errors="replace")


def _ws_head(path: str, host: str, origin: str | None = None) -> str:
    extra = f"Origin: {origin}\r\n" if origin else ""
    return (
        f"GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
        f"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n{extra}\r\n"
    )


def test_access_rules():
    from fluxdrive_bringup.view.gate import Access

    logged: list[str] = []
    a = Access("x", TOKEN, log=logged.append)
    ok = {"Host": "127.0.0.1:8765"}
    assert a.check(f"/?token={TOKEN}", ok) is None
    assert a.check("/", {**ok, "X-Fluxdrive-Token": TOKEN}) is None
    assert a.check(f"/?token={TOKEN}", {"Host": "localhost"}) is None
    assert a.check(f"/?token={TOKEN}", {"Host": "[::1]:80"}) is None
    assert a.check(f"/?token={TOKEN}", {**ok, "Origin": "http://127.0.0.1:8765"}) is None
    assert a.check("/?token=wrong", ok)[0] == 403
    assert a.check("/", ok)[0] == 403
    assert a.check(f"/?token={TOKEN}", {})[0] == 400
    assert "evil.example" in a.check(f"/?token={TOKEN}", {"Host": "evil.example"})[1]
    for origin in ("http://evil.example", "null", "file://", "http://127.0.0.1.evil.example"):
        bad = a.check(f"/?token={TOKEN}", {**ok, "Origin": origin})
        assert bad is not None and bad[0] == 403, origin
    b = Access("x", TOKEN, allow_origins=("https://viewer.example/",), allow_hosts=("rig",))
    assert (
        b.check(f"/?token={TOKEN}", {"Host": "rig:1", "Origin": "https://viewer.example"}) is None
    )
    assert a.refused("1.2.3.4:5", 403, "why") == "x: refused: why\n"
    assert logged == ["x: refused 1.2.3.4:5: 403 why"]


def test_foxglove_gate_refuses_strangers_and_caps_connections():
    """The gate in front of a real Foxglove SDK server (no graph needed for the rules)."""
    foxglove = pytest.importorskip("foxglove")
    ws_client = pytest.importorskip("websockets.sync.client")
    from fluxdrive_bringup.view.gate import Access, FoxgloveGate
    from fluxdrive_ros.security import loopback_tls_pair

    cap = 100
    logged: list[str] = []
    cert, key = loopback_tls_pair()
    server = foxglove.start_server(host="127.0.0.1", port=0, tls_cert=cert, tls_key=key)
    gate = FoxgloveGate(Access("foxglove", TOKEN, max_clients=cap, log=logged.append), 0, cert)
    gate.upstream_port = server.port
    gate.start("127.0.0.1", 0)
    url = f"ws://127.0.0.1:{gate.port}/?token={TOKEN}"
    clients: list = []
    stack = contextlib.ExitStack()
    try:
        # the probe's cross-origin client, without and with the token; a rebinding page's
        # Host; no token at all: each one 403 with one line, nothing reaches the SDK
        cases = {
            "cross-origin, no token": ("/", "127.0.0.1", "http://evil.example"),
            "cross-origin, token": (f"/?token={TOKEN}", "127.0.0.1", "http://evil.example"),
            "Host evil.example": (f"/?token={TOKEN}", f"evil.example:{gate.port}", None),
            "no token": ("/", f"127.0.0.1:{gate.port}", None),
        }
        for what, (path, host, origin) in cases.items():
            reply = _raw(gate.port, _ws_head(path, host, origin))
            assert reply.startswith("HTTP/1.1 403"), (what, reply)
            body = reply.split("\r\n\r\n", 1)[1]
            assert body.count("\n") == 1 and body.startswith("foxglove: refused: "), body
        assert len(logged) == len(cases) and gate.accepted == 0, logged
        assert "Origin 'http://evil.example'" in logged[0] and "evil.example" in logged[2]
        # the SDK's own port: plain WebSocket (what a browser page could try) fails
        with pytest.raises(Exception):  # noqa: B017 - websockets' handshake error
            ws_client.connect(
                f"ws://127.0.0.1:{server.port}/", subprotocols=["foxglove.sdk.v1"], open_timeout=5
            )
        # the token's holder: the SDK's serverInfo comes through the gate
        for _ in range(cap):
            ws = ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=20)
            clients.append(stack.enter_context(ws))
        assert json.loads(clients[0].recv(timeout=10))["op"] == "serverInfo"
        assert gate.accepted == cap
        # the 101st: refused at once with one line, not left in its handshake
        t0 = time.monotonic()
        reply = _raw(gate.port, _ws_head(f"/?token={TOKEN}", "127.0.0.1"))
        dt = time.monotonic() - t0
        assert reply.startswith("HTTP/1.1 503"), reply
        assert "connection limit reached (100 clients" in reply
        print(f"client {cap + 1} refused with 503 in {dt * 1000:.1f} ms")
        assert dt < 5.0, dt
        assert logged[-1].startswith("foxglove: refused 127.0.0.1:") and " 503 " in logged[-1]
        # one leaves: the next gets in
        clients.pop().close()
        t_end = time.monotonic() + 10
        while gate.active >= cap and time.monotonic() < t_end:
            time.sleep(0.05)
        ws = ws_client.connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=20)
        clients.append(stack.enter_context(ws))
    finally:
        stack.close()
        gate.stop()
        server.stop()


def _get(url: str, headers: dict | None = None, data: bytes | None = None) -> tuple[int, str]:
    req = urllib.request.Request(url, headers=headers or {}, data=data)
    try:
        with urllib.request.urlopen(req, timeout=20) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


@pytest.mark.timeout(180)
def test_scope_refuses_strangers_in_one_line_and_keeps_its_token_out_of_the_log():
    pytest.importorskip("aiohttp")
    ws_client = pytest.importorskip("websockets.sync.client")
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain(54)),
        # as the launcher starts it: its stdout is the log file
        FLUXDRIVE_GRAPH_KEY="0123456789abcdef",
        PYTHONUNBUFFERED="1",
    )
    argv = [sys.executable, "-m", "fluxdrive.cli", "scope", "--port", "0", "--token", TOKEN]
    proc = subprocess.Popen(
        [*argv, "--attach-wait", "0.5", "--max-clients", "2"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out: list[str] = []
    stack = contextlib.ExitStack()
    try:
        url = ""
        t_end = time.monotonic() + 60
        while not url and time.monotonic() < t_end:
            line = proc.stdout.readline() if proc.stdout else ""
            if not line and proc.poll() is not None:
                break
            out.append(line)
            if line.startswith("@scope-url "):
                url = line.split()[1]
        assert url, "".join(out)
        base = url.split("/?")[0]
        port = int(base.rsplit(":", 1)[1])
        status = {
            "Host evil.example": _get(f"{url}", {"Host": f"evil.example:{port}"}),
            "cross-origin param set": _get(
                f"{base}/api/param",
                {"Origin": "http://evil.example", "Content-Type": "application/json"},
                json.dumps({"node": "/plant", "name": "load_scale", "value": "0.25"}).encode(),
            ),
            "cross-origin reset, token": _get(
                f"{base}/api/reset",
                {"Origin": "http://evil.example", "X-Fluxdrive-Token": TOKEN},
                b"",
            ),
            "no token": _get(f"{base}/api/status"),
            "invalid service": _get(
                f"{base}/api/reset?service=/controller/reset%20fault!",
                {"X-Fluxdrive-Token": TOKEN},
                b"",
            ),
        }
        ok_status = _get(f"{base}/api/status", {"X-Fluxdrive-Token": TOKEN})
        ws_url = url.replace("http://", "ws://").replace("/?token=", "/ws?token=")
        for _ in range(2):
            stack.enter_context(ws_client.connect(ws_url, open_timeout=20))
        t0 = time.monotonic()
        with pytest.raises(Exception) as exc:  # noqa: PT011 - websockets' InvalidStatus
            ws_client.connect(ws_url, open_timeout=20)
        assert time.monotonic() - t0 < 5.0
        assert "503" in str(exc.value), exc.value
    finally:
        stack.close()
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=30)
        out.append(rest)
    log = "".join(out)
    print(status)
    assert ok_status[0] == 200, ok_status
    assert {k: v[0] for k, v in status.items()} == {
        "Host evil.example": 403,
        "cross-origin param set": 403,
        "cross-origin reset, token": 403,
        "no token": 403,
        "invalid service": 400,
    }
    for _what, (_code, body) in status.items():
        text = json.loads(body)["error"] if body.startswith("{") else body
        assert text.strip().count("\n") == 0 and text.startswith("scope: refused: "), body
    assert "must be a ROS service name" in status["invalid service"][1]
    refusals = [ln for ln in log.splitlines() if ln.startswith("scope: refused ")]
    assert len(refusals) == len(status) + 1, log  # and the third page's 503
    assert "Traceback" not in log
    # what the launcher writes to the log file: everything but the @ lines
    log_file = "\n".join(ln for ln in log.splitlines() if not ln.startswith("@"))
    assert TOKEN not in log_file, log_file
