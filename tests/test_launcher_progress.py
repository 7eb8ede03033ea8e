"""The launcher's progress line counts simulated time in the plant's own PWM periods: a
20 kHz card's frames are 50 us each, so 20 000 frames are 1 s, not 2 s."""

from __future__ import annotations

import io

import pytest
from fluxdrive_bringup.launch.launcher import Graph, Launcher


@pytest.mark.parametrize("ts_s", [1e-4, 5e-5])
def test_progress_uses_the_plants_period(ts_s):
    out = io.StringIO()
    launcher = Launcher(Graph(name="g", nodes=[]), out=out, progress=True)
    launcher.tty = False
    frames, wall_s = 20000, 4.0
    launcher._on_progress(f"@progress {frames} {frames} {wall_s:.3f} {ts_s!r}")
    sim_s = frames * ts_s
    text = out.getvalue()
    assert f"{sim_s:7.2f}/{sim_s:.2f} s simulated" in text
    assert f"real-time factor {sim_s / wall_s:.3f}" in text


def test_progress_without_a_period_keeps_the_default():
    out = io.StringIO()
    launcher = Launcher(Graph(name="g", nodes=[]), out=out, progress=True)
    launcher.tty = False
    launcher._on_progress("@progress 10000 10000 2.000")
    assert "   1.00/1.00 s simulated" in out.getvalue()
