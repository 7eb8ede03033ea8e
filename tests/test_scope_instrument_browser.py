"""The scope as an instrument, in a real browser (Debian's chromium via playwright): a known
tone published on /drive/frame (i_a = 2 A sin(2π 250 Hz t), every sample, seq and stamp
of a 10 kHz drive) by a process with the scope tap in it (tests/scope_tone.py: as in a
graph started with --scope), and the scope server.  On the page: the FFT in Hz of i_a
shows the tone at its bin with its amplitude (flat-top window), the FFT cursors read it;
an edge trigger (rising through 1 A, hysteresis 0.5 A, normal mode) fires twice, at the
samples the tone crosses the level, re-arming in between (single: once; auto on a level
never reached: free runs at its timeout); the raw CSV and MCAP exports of the held view
hold exactly the samples in view, each equal to the published value (the MCAP read back
with the project's bag reader and with mcap).  Saves a screenshot of the instrument panel
(FLUXDRIVE_SCOPE_SCREENSHOT=docs/img/scope.png renews docs/img/scope-instrument.png next
to it)."""

from __future__ import annotations

import csv
import io
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from ros_domains import domain
from scope_tone import AMP_A, TONE_HZ, TS_S, VDC_V, i_abc

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")
# a publisher, a scope server and chromium at once, waited on in wall time: alone
pytestmark = pytest.mark.serial
sync_api = pytest.importorskip("playwright.sync_api")

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
TOKEN = "scope-instrument-token"
LEVEL_A, HYST_A = 1.0, 0.5


def expected_edges(seq0: int, seq1: int) -> set[int]:
    """Samples at which the tone crosses LEVEL_A upwards (first sample at or above it)."""
    s = np.arange(max(seq0, 1), seq1 + 1)
    x, prev = i_abc(s)[0], i_abc(s - 1)[0]
    return set(s[(x >= LEVEL_A) & (prev < LEVEL_A)].tolist())


@pytest.mark.timeout(300)
def test_fft_edge_trigger_and_raw_export_in_chromium(tmp_path):
    if not Path(CHROMIUM).exists():
        pytest.skip("chromium not installed (tools/bootstrap.sh installs Debian's package)")
    dom = domain(49)  # apart from every serial test's domain, also modulo the slice (60)
    exports = tmp_path / "exports"
    env = {**os.environ, "ROS_DOMAIN_ID": str(dom)}
    src = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("scope_tone.py")), "--domain-id", str(dom)],
        env=env,
    )
    server = subprocess.Popen(
        [sys.executable, "-m", "fluxdrive_bringup.view.scope", "--port", "0"]
        + ["--token", TOKEN, "--domain-id", str(dom), "--attach-wait", "60"]
        + ["--export-dir", str(exports)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    lines: list[str] = []
    threading.Thread(
        target=lambda: lines.extend(iter(server.stdout.readline, "")), daemon=True
    ).start()
    shot = Path(os.environ.get("FLUXDRIVE_SCOPE_SCREENSHOT", tmp_path / "scope.png"))
    shot = shot.with_name(shot.stem + "-instrument.png")
    try:
        t0 = time.monotonic()
        url = None
        while url is None and time.monotonic() - t0 < 60 and server.poll() is None:
            url = next((ln.split()[1] for ln in lines if ln.startswith("scope: http")), None)
            time.sleep(0.1)
        assert url, f"the scope printed no URL: {lines}"
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1400, "height": 1100})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            page.wait_for_function(
                "window.scopeStats.envelopes > 3 && window.scopeStats.lastSeq > 0", timeout=120_000
            )
            page.select_option("#win", "0.5")
            page.wait_for_selector('#itrace option[value="frame:i_a"]', state="attached")
            page.select_option("#itrace", "frame:i_a")
            _fft(page)
            _edges(page)
            try:
                _raw_export(page, exports)
            except AssertionError:
                print("".join(lines[-40:]))
                raise
            page.locator("#instrument").screenshot(path=str(shot))
            assert not errors, errors
            browser.close()
    finally:
        server.terminate()
        try:
            server.wait(timeout=15)
        except subprocess.TimeoutExpired:
            server.kill()
        src.terminate()
        try:
            src.wait(timeout=15)
        except subprocess.TimeoutExpired:
            src.kill()
    assert shot.stat().st_size > 10_000


def _fft(page) -> None:
    """The FFT of i_a over the view, flat-top window: the peak at the tone's bin in Hz with
    its amplitude; cursors A and B read the bins under them and their difference."""
    page.select_option("#fftwin", "flattop")
    page.check("#fften")
    page.wait_for_function(
        "(() => { const f = window.scopeFft();"
        " return f && f.window === 'flattop' && f.n >= 4900; })()",
        timeout=120_000,
    )
    f = page.evaluate("window.scopeFft()")
    amp, f_hz = np.array(f["amp"], dtype=float), np.array(f["f_hz"])
    assert f["df_hz"] == pytest.approx(1.0 / (f["n"] * TS_S))
    assert f_hz[-1] == pytest.approx(5000.0, abs=f["df_hz"])  # up to Nyquist, in Hz
    k = int(np.argmax(amp[1:])) + 1
    # the nearest bin, or either of two when the tone lies half-way (bins rounded to 1 µHz)
    assert abs(f_hz[k] - TONE_HZ) <= f["df_hz"] / 2 + 1e-5, (f_hz[k], f["df_hz"])
    # flat-top: the amplitude within its scalloping (0.11 %) whatever the span
    assert amp[k] == pytest.approx(AMP_A, rel=2e-3)
    assert amp[0] < 1e-2 * AMP_A  # no DC
    # cursors on a held view (pause; the FFT above spans a whole view, so the server holds
    # every sample of the one held): its FFT is computed once, so the bins under the
    # cursors stay those of one FFT (a scrolling view renews it every second)
    page.check("#pause")
    page.wait_for_function(
        """(() => { const f = window.scopeFft(), v = window.scopeDebug.view();
           return f && v && Math.abs(f.t1_s - v[1]) < 2e-4
             && Math.abs(f.t0_s - v[0]) < 2e-4; })()""",
        timeout=60_000,
    )
    f = page.evaluate("window.scopeFft()")
    over = page.locator("#fftplot .u-over")
    box = over.bounding_box()
    assert box is not None
    x_a, x_b = page.evaluate(
        f"[window.scopeDebug.fftChart().valToPos({TONE_HZ}, 'x'),"
        f" window.scopeDebug.fftChart().valToPos({2 * TONE_HZ}, 'x')]"
    )
    over.click(position={"x": x_a, "y": box["height"] / 2})
    over.click(position={"x": x_b, "y": box["height"] / 2}, modifiers=["Shift"])
    cur = page.evaluate("window.scopeFftCursors()")
    # a cursor goes to the highest bin within 3 pixels: A onto the tone, B somewhere there
    px_hz = page.evaluate(
        f"window.scopeDebug.fftChart().posToVal({x_b} + 1, 'x')"
        f" - window.scopeDebug.fftChart().posToVal({x_b}, 'x')"
    )
    assert abs(cur["a"] - TONE_HZ) <= f["df_hz"] / 2 + 1e-5
    assert abs(cur["b"] - 2 * TONE_HZ) <= 4 * px_hz
    text = page.locator("#fftcursors").inner_text()
    a_amp = float(text.split("A f=")[1].split("amp=")[1].split()[0])
    assert a_amp == pytest.approx(AMP_A, rel=2e-3), text
    assert "Δf=" in text
    f_a = float(text.split("A f=")[1].split()[0])
    f_b = float(text.split("B f=")[1].split()[0])
    assert abs(f_a - TONE_HZ) <= f["df_hz"]
    df = float(text.split("Δf=")[1].split()[0])
    assert df == pytest.approx(f_b - f_a, rel=1e-4, abs=1e-3)
    page.uncheck("#pause")


def _edges(page) -> None:
    """Single: one firing at a crossing, then done; auto on a level never reached: free
    runs at its timeout; normal (rising through LEVEL_A with hysteresis): fires, re-arms,
    fires again, each time at a sample where the tone crosses the level."""
    page.fill("#elevel", str(LEVEL_A))
    page.fill("#ehyst", str(HYST_A))
    page.select_option("#edge", "rising")
    page.fill("#epre", "0.002")
    page.fill("#epost", "0.004")
    # single: one firing at a crossing, then done while the tone keeps crossing
    page.select_option("#emode", "single")
    page.click("#earm")
    page.wait_for_function(
        "(() => { const e = window.scopeEdge();"
        " return e && e.config.mode === 'single' && e.events.length >= 1; })()",
        timeout=120_000,
    )
    (first,) = page.evaluate("window.scopeEdge()")["events"]
    assert first["seq"] in expected_edges(first["seq"] - 100, first["seq"])
    _wait_newest(page, first["seq"] + 400)  # ten more crossings held by the server
    st = page.evaluate("window.scopeEdge()")
    assert not st["armed"] and st["fired"] == 1 and len(st["events"]) == 1
    # auto: a level the tone never reaches; it free-runs every `auto after` (200 samples)
    page.fill("#elevel", str(1.5 * AMP_A))
    page.fill("#eauto", "0.02")
    page.select_option("#emode", "auto")
    page.click("#earm")
    page.wait_for_function(
        "(() => { const e = window.scopeEdge();"
        " return e && e.config.mode === 'auto' && e.events.length >= 2; })()",
        timeout=120_000,
    )
    ev = page.evaluate("window.scopeEdge()")["events"][:2]
    assert all(e["auto"] for e in ev) and ev[1]["seq"] - ev[0]["seq"] == 200
    # normal: every edge after the acquisition
    page.fill("#elevel", str(LEVEL_A))
    page.select_option("#emode", "normal")
    page.click("#earm")
    page.wait_for_function(
        "(() => { const e = window.scopeEdge();"
        " return e && e.config.mode === 'normal' && e.events.length >= 2; })()",
        timeout=120_000,
    )
    st = page.evaluate("window.scopeEdge()")
    ev = st["events"][:2]
    # two consecutive firings (the server keeps the newest 20 for a page that polls late)
    assert st["armed"] and st["fired"] >= 2 and ev[1]["n"] == ev[0]["n"] + 1
    edges = expected_edges(ev[0]["seq"] - 100, ev[1]["seq"])
    assert {e["seq"] for e in ev} <= edges, (ev, sorted(edges)[:5])
    # re-armed after the acquisition (4 ms = 40 samples after the first): the next edge
    assert ev[1]["seq"] == min(e for e in edges if e > ev[0]["seq"] + 40)
    for e in ev:
        assert not e["auto"]
        t = np.array(e["t"])
        seq = np.round(t / TS_S).astype(np.int64)
        assert seq[0] == e["seq"] - 20 and seq[-1] == e["seq"] + 40  # 2 ms before, 4 after
        assert np.allclose(e["v"], i_abc(seq)[0], rtol=1e-6, atol=1e-6)
    page.wait_for_function("window.scopeEdge().fired >= 3", timeout=60_000)  # drawn one
    page.click("#estop")
    sync_api.expect(page.locator("#estate")).to_contain_text("stopped", timeout=20_000)
    st = page.evaluate("window.scopeEdge()")
    assert st["stopped"] and not st["armed"] and st["fired"] >= 2


def _wait_newest(page, seq: int) -> None:
    """Until the server holds i_a's samples up to seq."""
    js = """async ([token, t]) => {
         const r = await fetch("api/status", { headers: { "X-Fluxdrive-Token": token } });
         const h = (await r.json()).raw.frame; return Boolean(h && h[1] >= t); }"""
    t_end = time.monotonic() + 120
    while not page.evaluate(js, [TOKEN, seq * TS_S]):
        assert time.monotonic() < t_end
        page.wait_for_timeout(250)


def _raw_export(page, exports: Path) -> None:
    """Hold the view (pause) once the server holds all of it; export raw CSV and MCAP:
    exactly the samples in view, each the published value."""
    held_js = """async (token) => { const v = window.scopeDebug.view();
         const r = await fetch("api/status", { headers: { "X-Fluxdrive-Token": token } });
         const s = await r.json(), h = s.raw && s.raw.frame;
         return Boolean(v && h && h[0] < v[0] - 0.01); }"""
    t_end = time.monotonic() + 120
    while not page.evaluate(held_js, TOKEN):  # the server holds the whole view
        assert time.monotonic() < t_end, page.evaluate("window.scopeDebug.view()")
        page.wait_for_timeout(500)
    page.check("#pause")
    page.wait_for_timeout(200)  # the frame in flight: the view holds from here on
    view = page.evaluate("window.scopeDebug.view()")
    lo = math.ceil(view[0] / TS_S - 1e-6)
    hi = math.floor(view[1] / TS_S + 1e-6)
    want = np.arange(lo, hi + 1)
    with page.expect_download(timeout=60_000) as dl:
        page.click("#rawcsv")
    assert page.evaluate("window.scopeRawView") == view
    text = Path(dl.value.path()).read_text()
    rows = list(csv.reader(io.StringIO(text)))
    head = rows[0]
    assert head[:3] == ["t_s", "seq", "frame:i_a"], head
    seq = np.array([int(r[1]) for r in rows[1:]])
    assert np.array_equal(seq, want), (seq[:3], seq[-3:], want[:3], want[-3:])
    got = np.array([float(r[2]) for r in rows[1:]])
    assert np.array_equal(got, i_abc(want)[0])  # bit for bit the published float64
    vdc = np.array([float(r[head.index("frame:vdc")]) for r in rows[1:]])
    assert (vdc == VDC_V).all()
    with page.expect_download(timeout=60_000) as dl:
        page.click("#rawmcap")
    data = Path(dl.value.path()).read_bytes()
    assert data[:8] == b"\x89MCAP0\r\n"
    (bag,) = exports.iterdir()
    (mcap_file,) = bag.glob("*.mcap")
    assert data == mcap_file.read_bytes()
    # the project's bag reader
    from fluxdrive.io.scope_export import read_raw_bag

    back = read_raw_bag(bag)
    assert np.array_equal(back["frame"][0], want)
    assert np.array_equal(back["frame"][1]["i_a"], i_abc(want)[0])
    # an independent reader: mcap with its ROS 2 decoder, on the downloaded file
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(dl.value.path(), "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        rows2 = [
            list(m.data) for _s, _c, _m, m in reader.iter_decoded_messages(["/scope/raw/frame"])
        ]
    assert [int(r[0]) for r in rows2] == want.tolist()
    assert [r[1] for r in rows2] == i_abc(want)[0].tolist()
