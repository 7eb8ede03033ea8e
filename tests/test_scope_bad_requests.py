"""The scope server against hostile requests: an oversized header is answered (400) and
logged in one line naming the client (aiohttp logged a full traceback), and the page is not
served without its token under /static/ either (its scripts and styles are); the
instrument's calls (FFT, raw export, edge trigger) need the token and answer bad input
with one line naming it."""

from __future__ import annotations

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

pytest.importorskip("aiohttp")
pytest.importorskip("fluxdrive_bringup")

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "bad-request-test-token"


def _get(url: str) -> int:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def _answer(url: str, body: dict | None = None) -> tuple[int, str]:
    """Status and the JSON answer's one line (`error` or `reason`) of a GET (or a POST of
    body) with the token."""
    import json

    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(
        url, data=data, headers={"X-Fluxdrive-Token": TOKEN, "Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            status, text = r.status, r.read().decode()
    except urllib.error.HTTPError as exc:
        status, text = exc.code, exc.read().decode()
    j = json.loads(text)
    return status, str(j.get("error") or j.get("reason") or "")


def test_oversized_header_is_one_line_and_the_page_needs_its_token():
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain(53)),
    )
    argv = [sys.executable, "-m", "fluxdrive.cli", "scope", "--port", "0", "--token", TOKEN]
    proc = subprocess.Popen(
        [*argv, "--attach-wait", "0.5"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = ""
        t_end = time.monotonic() + 60
        while "scope: http" not in line and time.monotonic() < t_end:
            line = proc.stdout.readline() if proc.stdout else ""
            if not line and proc.poll() is not None:
                break
        assert "scope: http" in line, proc.stderr.read() if proc.stderr else ""
        base = line.split("scope: ", 1)[1].split("/?")[0]
        port = int(base.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
            sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 70_000 + b"\r\n\r\n")
            reply = sock.recv(200).decode(errors="replace")
        status = {
            "page without token": _get(f"{base}/static/index.html"),
            "page with token": _get(f"{base}/static/index.html?token={TOKEN}"),
            "root without token": _get(f"{base}/"),
            "script": _get(f"{base}/static/scope.js"),
        }
        # the instrument's calls: bad input is one line naming what is wrong
        instrument = {
            "fft without token": _get(f"{base}/api/fft?trace=frame:i_a&t0=0&t1=1"),
            "fft window": _answer(f"{base}/api/fft?trace=frame:i_a&t0=0&t1=1&window=kaiser"),
            "fft trace": _answer(f"{base}/api/fft?trace=i_a&t0=0&t1=1"),
            "raw view": _answer(f"{base}/api/raw.csv?trace=frame:i_a&t0=1&t1=0.5"),
            "raw no view": _answer(f"{base}/api/raw.mcap?trace=frame:i_a"),
            "edge mode": _answer(f"{base}/api/edge", {"trace": "frame:i_a", "mode": "repeat"}),
            "edge level": _answer(f"{base}/api/edge", {"trace": "frame:i_a", "level": "x"}),
        }
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    print(reply.splitlines()[0] if reply else "(no reply)", status)
    print(err)
    assert reply.startswith("HTTP/1.0 400")
    assert status == {
        "page without token": 403,
        "page with token": 200,
        "root without token": 403,
        "script": 200,
    }
    assert instrument == {
        "fft without token": 403,
        "fft window": (400, instrument["fft window"][1]),
        "fft trace": (400, instrument["fft trace"][1]),
        "raw view": (400, instrument["raw view"][1]),
        "raw no view": (400, instrument["raw no view"][1]),
        "edge mode": (
            400,
            "edge trigger: trigger mode: 'repeat' is not one of normal, auto, single",
        ),
        "edge level": (400, "edge trigger: could not convert string to float: 'x'"),
    }, instrument
    assert "'kaiser' is not one of rectangular, hann, flattop" in instrument["fft window"][1]
    assert "expected stream:field" in instrument["fft trace"][1]
    assert "is empty" in instrument["raw view"][1]
    assert "expected t0 and t1" in instrument["raw no view"][1]
    assert "Traceback" not in err
    bad = [ln for ln in err.splitlines() if "bad request" in ln]
    assert len(bad) == 1 and "refused a bad request from 127.0.0.1" in bad[0], err
