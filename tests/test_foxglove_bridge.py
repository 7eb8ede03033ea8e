"""`./fluxdrive foxglove` at the protocol level: a WebSocket client (subprotocol
foxglove.sdk.v1) gets every topic of a running lockstep graph advertised with its ros2msg
schema and cdr encoding, subscribes, and decodes the CDR it receives (frames in sequence
with the scenario's DC bus voltage, estimates with wrapped angles); parameters read and a
refused set comes back as a status with the node's reason; a parameter subscription
receives a change made with `./fluxdrive param set` (another process); the controller's
reset_fault is called as a service (cdr request and response); the server's time and the
messages' log times follow the graph's /clock.  A client offering only the older name of
the protocol, foxglove.websocket.v1, is served under that name: it lists the channels and a
frame it receives decodes with rosbags' CDR reader from the advertised ros2msg schema."""

from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")
pytest.importorskip("foxglove")
ws_client = pytest.importorskip("websockets.sync.client")
ROOT = Path(__file__).resolve().parents[1]


SERVICES: list[dict] = []  # every advertised service, whenever it came


def _note(d: dict) -> dict:
    if d.get("op") == "advertiseServices":
        SERVICES.extend(d["services"])
    return d


def _recv_json(ws, want_op: str, timeout: float, pred=lambda m: True) -> dict:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            m = ws.recv(timeout=max(0.05, t_end - time.monotonic()))
        except TimeoutError:
            break
        if isinstance(m, str):
            d = _note(json.loads(m))
            if d.get("op") == want_op and pred(d):
                return d
    raise AssertionError(f"no '{want_op}' message within {timeout} s")


def _handshake(port: int, path: str, host: str, origin: str | None) -> str:
    """A raw WebSocket handshake (any Host and Origin header); the server's answer."""
    import socket

    head = (
        f"GET {path} HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
        f"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n"
        + (f"Origin: {origin}\r\n" if origin else "")
        + "\r\n"
    )
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(head.encode())
        out = b""
        while b"\r\n\r\n" not in out:
            chunk = sock.recv(4096)
            if not chunk:
                break
            out += chunk
    return out.decode(errors="replace")


def _legacy_client_decodes_a_frame(url: str, frame_topic: str, vdc: float) -> None:
    """A client of the protocol's older name (foxglove.websocket.v1 only, as Lichtblick
    <= 1.21 offers): served under that name, it lists the channels, subscribes to the
    frames and decodes one with rosbags' CDR reader built from the advertised schema --
    nothing of the project's decodes it."""
    from rosbags.typesys import Stores, get_typestore
    from rosbags.typesys.msg import get_types_from_msg

    with ws_client.connect(
        url, subprotocols=["foxglove.websocket.v1"], max_size=None, open_timeout=10
    ) as ws:
        assert ws.subprotocol == "foxglove.websocket.v1"
        _recv_json(ws, "serverInfo", 10)
        chans: dict[str, dict] = {}
        t_end = time.monotonic() + 30
        while frame_topic not in chans and time.monotonic() < t_end:
            d = _recv_json(ws, "advertise", t_end - time.monotonic())
            chans.update({c["topic"]: c for c in d["channels"]})
        ch = chans[frame_topic]
        ws.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": ch["id"]}]})
        )
        data = None
        t_end = time.monotonic() + 60
        while data is None and time.monotonic() < t_end:
            try:
                m = ws.recv(timeout=2)
            except TimeoutError:
                continue
            if isinstance(m, bytes) and m[0] == 0x01 and struct.unpack_from("<I", m, 1)[0] == 7:
                data = m[13:]
        assert data is not None, "no frame on the legacy connection"
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    # the ros2msg schema: the type's definition, then each dependency after a line of '='
    name, schema = ch["schemaName"], ch["schema"]
    parts = schema.split("\n" + "=" * 80 + "\n")
    types.update(get_types_from_msg(parts[0], name))
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        dep = head.removeprefix("MSG: ").strip()
        pkg, _, typ = dep.partition("/")
        types.update(get_types_from_msg(body, dep if "/msg/" in dep else f"{pkg}/msg/{typ}"))
    store.register(types)
    msg = store.deserialize_cdr(data, name)
    assert msg.seq >= 0 and abs(msg.vdc - vdc) < 0.05 * vdc, (msg.seq, msg.vdc)


@pytest.mark.timeout(240)
def test_foxglove_client_receives_and_decodes_topics(tmp_path):
    from fluxdrive.drive.scenario import load_scenario, scenario_path
    from fluxdrive_bringup.launch.launcher import Launcher
    from fluxdrive_bringup.launch.runs import graph_for_scenario
    from fluxdrive_ros.cdr import Codec, Decoder

    from fluxdrive_ros import topics

    SERVICES.clear()
    dom = domain(36)
    sp = scenario_path("paper_2pct_150load")
    sc = load_scenario(sp)
    g = graph_for_scenario(sp, sc, None, "composed", duration_s=300.0, domain_id=dom)
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp_path / "logs")
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom), PYTHONUNBUFFERED="1")
    launcher.start()
    bridge = subprocess.Popen(
        [sys.executable, "-m", "fluxdrive_bringup.view.foxglove_bridge", "--port", "0"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(bridge.stdout), daemon=True).start()
    try:
        t0 = time.monotonic()
        while not any(ln.startswith("foxglove: ws://") for ln in lines):
            assert time.monotonic() - t0 < 30, f"bridge printed no URL: {lines}"
            assert bridge.poll() is None, f"bridge exited: {lines}"
            time.sleep(0.1)
        line = next(ln for ln in lines if ln.startswith("foxglove: ws://"))
        url = line.split()[1]
        assert url.startswith("ws://127.0.0.1:") and "subprotocol foxglove.sdk.v1" in line
        assert "/?token=" in url

        # only the operator: the probe's cross-origin client (a page of another site, with
        # or without the token), a DNS-rebinding page's Host, no token -- refused (403)
        port = int(url.split("/?")[0].rsplit(":", 1)[1])
        token = url.split("token=", 1)[1]
        refused = {
            "cross-origin": ("/", "127.0.0.1", "http://evil.example"),
            "cross-origin with token": (f"/?token={token}", "127.0.0.1", "http://evil.example"),
            "Host evil.example": (f"/?token={token}", f"evil.example:{port}", None),
            "no token": ("/", f"127.0.0.1:{port}", None),
        }
        for what, (path, host, origin) in refused.items():
            reply = _handshake(port, path, host, origin)
            assert reply.startswith("HTTP/1.1 403"), (what, reply)

        with ws_client.connect(
            url, subprotocols=["foxglove.sdk.v1"], max_size=None, open_timeout=10
        ) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            info = _recv_json(ws, "serverInfo", 10)
            assert "parameters" in info["capabilities"]
            chans: dict[str, dict] = {}
            est_topic = topics.estimate_topic(sc.driving)
            t_end = time.monotonic() + 30
            while not {topics.FRAME, est_topic} <= set(chans) and time.monotonic() < t_end:
                d = _recv_json(ws, "advertise", t_end - time.monotonic())
                chans.update({c["topic"]: c for c in d["channels"]})
            fr, es = chans[topics.FRAME], chans[est_topic]
            assert fr["encoding"] == "cdr" and fr["schemaEncoding"] == "ros2msg"
            assert fr["schemaName"] == topics.T_FRAME
            assert "float64[3] i_abc" in fr["schema"] and "MSG: std_msgs/Header" in fr["schema"]
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [
                            {"id": 1, "channelId": fr["id"]},
                            {"id": 2, "channelId": es["id"]},
                        ],
                    }
                )
            )
            got: dict[int, list[bytes]] = {1: [], 2: []}
            log_times: list[int] = []  # of the frames
            server_times: list[int] = []
            t_end = time.monotonic() + 90  # a first run compiles the kernels first
            while (len(got[1]) < 200 or len(got[2]) < 200) and time.monotonic() < t_end:
                try:
                    m = ws.recv(timeout=2)
                except TimeoutError:
                    continue
                if isinstance(m, bytes) and m[0] == 0x01:  # message data
                    sub_id, log_time = struct.unpack_from("<IQ", m, 1)
                    got[sub_id].append(m[13:])
                    if sub_id == 1:
                        log_times.append(log_time)
                elif isinstance(m, bytes) and m[0] == 0x02:  # server time
                    server_times.append(struct.unpack_from("<Q", m, 1)[0])
                elif isinstance(m, str):
                    _note(json.loads(m))
            assert len(got[1]) >= 200 and len(got[2]) >= 200, {k: len(v) for k, v in got.items()}
            # the graph runs now (its kernels compiled): a client of the older protocol name
            _legacy_client_decodes_a_frame(url, topics.FRAME, sc.machine.dc_bus_v)
            # the payload is the graph's CDR: decode with the project's codec
            dec = Decoder(topics.T_FRAME)
            c = Codec(topics.T_FRAME)
            frames = [dec.decode(b) for b in got[1]]
            seqs = [v[c.index("seq")] for v in frames]
            assert all(b > a for a, b in zip(seqs, seqs[1:], strict=False)), seqs[:20]
            vdc = {v[c.index("vdc")] for v in frames}
            assert all(abs(x - sc.machine.dc_bus_v) < 0.05 * sc.machine.dc_bus_v for x in vdc), vdc
            # time: the server's time is the graph's /clock (sample time, not the epoch),
            # and each frame's log time is the /clock of its moment: within 10 ms of the
            # frame's own stamp (/clock comes every 1 ms of sample time; the rest is the
            # order in which DDS delivers the two topics to the bridge under load)
            assert "time" in info["capabilities"] and server_times, info["capabilities"]
            assert server_times == sorted(server_times) and max(server_times) < 300e9
            stamps = [
                v[c.index("header.stamp.sec")] * 1_000_000_000 + v[c.index("header.stamp.nanosec")]
                for v in frames
            ]
            lag = [abs(lt - st) for lt, st in zip(log_times, stamps, strict=True)]
            assert max(log_times) < 300e9 and max(lag) < 10e6, (max(lag), log_times[:3])
            edec = Decoder(topics.T_ESTIMATE)
            ec = Codec(topics.T_ESTIMATE)
            th = [edec.decode(b)[ec.index("theta_e")] for b in got[2]]
            assert all(-math.pi <= x < math.pi for x in th)

            # the token's holder is the operator: sets a parameter
            ws.send(
                json.dumps(
                    {
                        "op": "setParameters",
                        "id": "s0",
                        "parameters": [{"name": "/plant.load_scale", "value": 0.5}],
                    }
                )
            )
            d = _recv_json(ws, "parameterValues", 20, lambda d: d.get("id") == "s0")
            assert d["parameters"][0]["value"] == pytest.approx(0.5)

            # parameters: read one, a refused set comes back as a status with the reason
            ws.send(
                json.dumps(
                    {
                        "op": "getParameters",
                        "id": "q1",
                        "parameterNames": ["/controller.position_timeout_s"],
                    }
                )
            )
            d = _recv_json(ws, "parameterValues", 20, lambda d: d.get("id") == "q1")
            assert d["parameters"][0]["name"] == "/controller.position_timeout_s"
            assert d["parameters"][0]["value"] == pytest.approx(0.05)
            ws.send(
                json.dumps(
                    {
                        "op": "setParameters",
                        "id": "s1",
                        "parameters": [{"name": "/controller.position_timeout_s", "value": 99.0}],
                    }
                )
            )
            st = _recv_json(ws, "status", 20)
            assert "out of range" in st["message"] and st["level"] == 1  # warning
            d = _recv_json(ws, "parameterValues", 20, lambda d: d.get("id") == "s1")
            assert d["parameters"][0]["value"] == pytest.approx(0.05)  # unchanged

            # a parameter subscription gets a change made elsewhere: the CLI, another process
            name = "/obs/flux_measured.cutoff_hz"
            ws.send(json.dumps({"op": "subscribeParameterUpdates", "parameterNames": [name]}))
            # the server takes a client's requests in order: once it has answered the next
            # one, it has taken the subscription
            ws.send(json.dumps({"op": "getParameters", "id": "g2", "parameterNames": [name]}))
            _recv_json(ws, "parameterValues", 20, lambda d: d.get("id") == "g2")
            r = subprocess.run(
                [
                    str(ROOT / "fluxdrive"),
                    "param",
                    "set",
                    "/obs/flux_measured",
                    "cutoff_hz",
                    "60.0",
                ],
                env={**env, "FLUXDRIVE_SKIP_BOOTSTRAP": "1"},
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert r.returncode == 0, r.stderr
            d = _recv_json(
                ws,
                "parameterValues",
                20,
                lambda d: any(p["name"] == name for p in d["parameters"]) and "id" not in d,
            )
            assert next(p["value"] for p in d["parameters"] if p["name"] == name) == 60.0

            # services: the controller's reset_fault, called with a cdr request
            from rclpy.serialization import deserialize_message, serialize_message

            from flux_drive_msgs.srv import ResetFault

            def advertised(d: dict) -> bool:
                return any(s["name"] == "/controller/reset_fault" for s in d["services"])

            if not advertised({"services": SERVICES}):
                _recv_json(ws, "advertiseServices", 30, advertised)
            svc = next(s for s in SERVICES if s["name"] == "/controller/reset_fault")
            assert svc["type"] == "flux_drive_msgs/srv/ResetFault"
            assert "services" in info["capabilities"]
            enc = b"cdr"
            payload = serialize_message(ResetFault.Request())
            ws.send(struct.pack("<BIII", 0x02, svc["id"], 7, len(enc)) + enc + payload)
            t_end = time.monotonic() + 30
            resp = None
            while resp is None and time.monotonic() < t_end:
                m = ws.recv(timeout=max(0.05, t_end - time.monotonic()))
                if isinstance(m, bytes) and m[0] == 0x03:  # service call response
                    sid, call_id, n = struct.unpack_from("<III", m, 1)
                    assert (sid, call_id, m[13 : 13 + n]) == (svc["id"], 7, enc)
                    resp = deserialize_message(m[13 + n :], ResetFault.Response)
                elif isinstance(m, str) and _note(json.loads(m)).get("op") == "serviceCallFailure":
                    raise AssertionError(m)
            assert resp is not None and resp.success, resp
        refusals = [ln for ln in lines if ln.startswith("foxglove: refused ")]
        assert len(refusals) == len(refused), lines
    finally:
        bridge.terminate()
        try:
            bridge.wait(timeout=10)
        except subprocess.TimeoutExpired:
            bridge.kill()
        launcher.stop()
    assert Path(tmp_path).exists()


def test_gate_renames_the_legacy_subprotocol_both_ways():
    """The rename alone, on handshake bytes: only a client offering the old name and not
    the new is rewritten; the answer names the old protocol back; anything else untouched."""
    from fluxdrive_bringup.view.gate import legacy_subprotocol_answer, legacy_subprotocol_request

    def req(protocols: str) -> bytes:
        return (
            b"GET /?token=x HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
            b"Sec-WebSocket-Protocol: " + protocols.encode() + b"\r\nX-Other: 1\r\n\r\n"
        )

    out, legacy = legacy_subprotocol_request(req("foxglove.websocket.v1"))
    assert legacy and out == req("foxglove.sdk.v1")
    for same in ("foxglove.sdk.v1", "foxglove.sdk.v1, foxglove.websocket.v1", "other.v2"):
        assert legacy_subprotocol_request(req(same)) == (req(same), False), same
    answer = (
        b"HTTP/1.1 101 Switching Protocols\r\nupgrade: websocket\r\n"
        b"sec-websocket-protocol: foxglove.sdk.v1\r\nsec-websocket-accept: abc=\r\n\r\n"
    )
    assert legacy_subprotocol_answer(answer) == answer.replace(b"sdk.v1", b"websocket.v1")
