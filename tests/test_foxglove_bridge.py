"""`./fluxdrive foxglove` at the protocol level: a WebSocket client (subprotocol
foxglove.sdk.v1) gets every topic of a running lockstep graph advertised with its ros2msg
schema and cdr encoding, subscribes, and decodes the CDR it receives (frames in sequence
with the scenario's DC bus voltage, estimates with wrapped angles); parameters read and a
refused set comes back as a status with the node's reason.  A client offering only the
older foxglove.websocket.v1 subprotocol is refused at the handshake."""

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

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")
pytest.importorskip("foxglove")
ws_client = pytest.importorskip("websockets.sync.client")


def _recv_json(ws, want_op: str, timeout: float, pred=lambda m: True) -> dict:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            m = ws.recv(timeout=max(0.05, t_end - time.monotonic()))
        except TimeoutError:
            break
        if isinstance(m, str):
            d = json.loads(m)
            if d.get("op") == want_op and pred(d):
                return d
    raise AssertionError(f"no '{want_op}' message within {timeout} s")


@pytest.mark.timeout(240)
def test_foxglove_client_receives_and_decodes_topics(tmp_path):
    from fluxdrive.core.scenario import load_scenario, scenario_path
    from fluxdrive_bringup.launch import Launcher
    from fluxdrive_bringup.runs import graph_for_scenario
    from fluxdrive_ros.cdr import Codec, Decoder

    from fluxdrive_ros import topics

    dom = 100 + (os.getpid() * 7) % 60
    sp = scenario_path("paper_2pct_150load")
    sc = load_scenario(sp)
    g = graph_for_scenario(sp, sc, None, "composed", duration_s=300.0, domain_id=dom)
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp_path / "logs")
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom), PYTHONUNBUFFERED="1")
    launcher.start()
    bridge = subprocess.Popen(
        [sys.executable, "-m", "fluxdrive_bringup.foxglove_bridge", "--port", "0"],
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

        # the older protocol alone is refused during the handshake
        with pytest.raises(Exception) as exc:  # websockets' InvalidStatus / InvalidHandshake
            ws_client.connect(url, subprotocols=["foxglove.websocket.v1"], open_timeout=5)
        assert "400" in str(exc.value) or "subprotocol" in str(exc.value).lower()

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
            t_end = time.monotonic() + 90  # a first run compiles the kernels first
            while (len(got[1]) < 200 or len(got[2]) < 200) and time.monotonic() < t_end:
                try:
                    m = ws.recv(timeout=2)
                except TimeoutError:
                    continue
                if isinstance(m, bytes) and m[0] == 0x01:  # message data
                    sub_id, _log_time = struct.unpack_from("<IQ", m, 1)
                    got[sub_id].append(m[13:])
            assert len(got[1]) >= 200 and len(got[2]) >= 200, {k: len(v) for k, v in got.items()}
            # the payload is the graph's CDR: decode with the project's codec
            dec = Decoder(topics.T_FRAME)
            c = Codec(topics.T_FRAME)
            frames = [dec.decode(b) for b in got[1]]
            seqs = [v[c.index("seq")] for v in frames]
            assert all(b > a for a, b in zip(seqs, seqs[1:], strict=False)), seqs[:20]
            vdc = {v[c.index("vdc")] for v in frames}
            assert all(abs(x - sc.machine.dc_bus_v) < 0.05 * sc.machine.dc_bus_v for x in vdc), vdc
            edec = Decoder(topics.T_ESTIMATE)
            ec = Codec(topics.T_ESTIMATE)
            th = [edec.decode(b)[ec.index("theta_e")] for b in got[2]]
            assert all(-math.pi <= x < math.pi for x in th)

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
    finally:
        bridge.terminate()
        try:
            bridge.wait(timeout=10)
        except subprocess.TimeoutExpired:
            bridge.kill()
        launcher.stop()
    assert Path(tmp_path).exists()
