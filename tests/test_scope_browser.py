"""The scope page in a real browser (Debian's chromium, driven by playwright) against a
running lockstep graph with the scope tap: the page loads, its traces advance, a parameter
set in the panel reaches the node, a refused one shows the node's reason, the reset button
gets the controller's answer, and every set leaves a marker in the bag.  Saves a
screenshot (FLUXDRIVE_SCOPE_SCREENSHOT=path to keep it; docs/img/scope.png is one)."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("fluxdrive_bringup")
sync_api = pytest.importorskip("playwright.sync_api")

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
TOKEN = "scope-test-token"


def _param(node: str, name: str, domain_id: int):
    from fluxdrive_bringup.inspect_cli import Session, _get

    s = Session(domain_id=domain_id, wait_s=3.0)
    try:
        ((_, v),) = _get(s, node, [name])
        return v
    finally:
        s.close()


@pytest.mark.timeout(300)
def test_scope_page_in_chromium(tmp_path):
    if not Path(CHROMIUM).exists():
        pytest.skip("chromium not installed (tools/bootstrap.sh installs Debian's package)")
    from fluxdrive.core.scenario import load_scenario, scenario_path
    from fluxdrive_bringup.launch import Launcher, add_scope
    from fluxdrive_bringup.runs import graph_for_scenario

    dom = 160 + os.getpid() % 60
    sp = scenario_path("paper_2pct_150load")
    sc = load_scenario(sp)
    bag = tmp_path / "bag"
    g = graph_for_scenario(sp, sc, bag, "composed", duration_s=300.0, domain_id=dom)
    add_scope(g, port=0, token=TOKEN, observers=list(sc.observers))
    launcher = Launcher(g, quiet=True, progress=False, log_dir=tmp_path / "logs")
    t0 = time.monotonic()
    launcher.start()
    shot = Path(os.environ.get("FLUXDRIVE_SCOPE_SCREENSHOT", tmp_path / "scope.png"))
    try:
        while not launcher.scope_urls and time.monotonic() - t0 < 30:
            time.sleep(0.1)
        assert launcher.scope_urls, f"the scope printed no URL; logs in {tmp_path / 'logs'}"
        url = launcher.scope_urls[0]
        assert url.startswith("http://127.0.0.1:") and f"token={TOKEN}" in url
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1600, "height": 1150})
            # without the token: refused
            bad = page.goto(url.split("?")[0])
            assert bad is not None and bad.status == 403
            page.goto(url)
            page.wait_for_function(
                "window.scopeStats.envelopes > 10 && window.scopeStats.lastSeq > 0", timeout=120_000
            )
            s1 = page.evaluate("({...window.scopeStats})")
            page.wait_for_timeout(2000)
            s2 = page.evaluate("({...window.scopeStats})")
            assert s2["lastSeq"] > s1["lastSeq"], (s1, s2)  # the traces advance
            assert s2["redraws"] > s1["redraws"]
            n_pts = page.evaluate("window.scopeDebug.points()")
            # every chart holds data: the driving observer's angle, error, speed, flux;
            # currents, speed, duty
            for key in (
                "est/flux_measured:theta",
                "est/flux_measured:err",
                "state:i_q",
                "state:speed_fb",
                "duty:a",
                "truth:theta",
            ):
                assert n_pts.get(key, 0) > 10, (key, n_pts)
            print(
                f"page: {s2['fps']} redraws/s ({s2.get('drawMs', 0):.1f} ms each), "
                f"{s2['dataRate']} envelopes/s; points {n_pts}"
            )

            # parameter panel: a live change reaches the node ...
            row = page.locator('tr[data-node="/controller"][data-name="position_timeout_s"]')
            for _ in range(3):  # a node too busy to answer in time (loaded machine): reload
                page.wait_for_selector("body[data-params=loaded]", timeout=60_000)
                if row.count():
                    break
                page.click("#reload")
            page.locator('details[data-node="/controller"]').evaluate("e => e.open = true")
            row.locator("input").fill("0.07")
            row.locator("input").press("Enter")
            status = row.locator(".status")
            sync_api.expect(status).to_contain_text("✓", timeout=15_000)
            assert _param("/controller", "position_timeout_s", dom) == pytest.approx(0.07)
            # ... a refused one shows the node's reason, the value stays
            row.locator("input").fill("99")
            row.locator("input").press("Enter")
            sync_api.expect(status).to_contain_text("out of range", timeout=15_000)
            assert "✗" in status.inner_text()
            assert _param("/controller", "position_timeout_s", dom) == pytest.approx(0.07)
            # the reset button asks the controller as the operator (nothing latched: ok)
            page.click("#reset")
            sync_api.expect(page.locator("#resetmsg")).to_contain_text("ok", timeout=20_000)
            # the EMF observers' flux estimates dwarf the flux observers' at 2 % speed:
            # hide them in the flux charts (legend click) for the screenshot
            for chart in ("flux", "locus"):
                for name in ("emf_measured", "emf_commanded"):
                    page.click(f'#chart-{chart} .lg:has-text("{name}")')
            assert page.locator("#chart-flux .lg.off").count() == 2
            row.evaluate("e => e.scrollIntoView({block: 'center'})")  # the refusal in view
            page.wait_for_timeout(700)
            page.screenshot(path=str(shot), full_page=True)
            browser.close()
    finally:
        launcher.stop()
    assert shot.stat().st_size > 20_000
    # the two sets are markers in the bag, at the sample they happened
    from fluxdrive.io.bagio import typestore
    from rosbags.highlevel import AnyReader

    with AnyReader([bag], default_typestore=typestore()) as r:
        conns = [c for c in r.connections if c.topic == "/drive/param_marker"]
        assert conns
        marks = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    assert [(m.name, m.value, m.successful) for m in marks] == [
        ("position_timeout_s", "0.07", True),
        ("position_timeout_s", "99", False),
    ]
    assert "out of range" in marks[1].reason and marks[0].node == "/controller"
    assert 0 < marks[0].seq <= marks[1].seq
