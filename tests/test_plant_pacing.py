"""The paced plant's clock under live changes: lowering `rate_factor` mid-run re-anchors the
pacing clock, so frames go on at the new rate from the next sample (with the start-of-run
anchor a 10x lower rate put the next frame's due time ~9x the elapsed run into the future:
the probe's plant gave no frame for >= 180 s); and a paced plant that publishes no frame
for `stall_warn_s` of wall time says so in one line (here: a controller that never answers).

A real plant node, alone, on an executor of its own: without a controller it runs on with
the PWM off after `first_duty_timeout_s`, paced exactly as with one (the frames are due at
the same times; only their duty differs)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from ros_domains import domain

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("spm_plant_sim")

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")
TS_S = 1e-4  # the default card's PWM period


class Plant:
    """A paced plant node spun in a thread."""

    def __init__(self, plant_params: dict):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter import Parameter
        from spm_plant_sim.node import PlantNode

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain(50))
        base = {
            "scenario": SCENARIO,
            "mode": "paced",
            "start_delay_s": 0.0,
            "progress_interval_s": 0.0,
            "wait_frame_subscribers": 0,
            "wait_duty_publishers": 0,
        }
        over = [Parameter(k, value=v) for k, v in {**base, **plant_params}.items()]
        self.plant = PlantNode("plant", context=self.ctx, parameter_overrides=over)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.plant)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while self.ctx.ok():
            try:
                self.ex.spin_once(timeout_sec=0.01)
            except Exception:  # noqa: BLE001 - shutting down
                return

    def wait_frame(self, k: int, timeout_s: float) -> float:
        t_end = time.monotonic() + timeout_s
        while self.plant.k < k and time.monotonic() < t_end:
            time.sleep(0.002)
        return time.monotonic()

    def close(self) -> None:
        self.ctx.try_shutdown()
        self.thread.join(5)
        self.plant.destroy_node()


def test_lowering_rate_factor_live_keeps_frames_coming():
    from rclpy.parameter import Parameter

    rate0, rate1 = 0.1, 0.01  # 1000, then 100 frames per wall second
    g = Plant({"rate_factor": rate0, "first_duty_timeout_s": 0.0})
    try:
        g.wait_frame(3000, 60.0)
        assert g.plant.k >= 3000, f"the graph reached frame {g.plant.k} only"
        res = g.plant.set_parameters([Parameter("rate_factor", value=rate1)])[0]
        assert res.successful, res.reason
        k0, t0 = g.plant.k, time.monotonic()
        t_next = g.wait_frame(k0 + 1, 30.0)
        g.wait_frame(k0 + 100, 10.0)
        k1, t1 = g.plant.k, time.monotonic()
    finally:
        g.close()
    first_ms = (t_next - t0) * 1e3
    rate = (k1 - k0) * TS_S / (t1 - t0)  # simulated seconds per wall second after the change
    print(f"after rate_factor {rate0} -> {rate1} at frame {k0}: next frame in {first_ms:.1f} ms,")
    print(f"  {k1 - k0} frames in {t1 - t0:.2f} s wall = rate {rate:.4f}")
    # the next frame is one new period (10 ms) away, give or take the scheduler; the old
    # anchor put it (rate0 / rate1 - 1) x the elapsed run (>= 2.7 s here) away
    assert first_ms < 500.0
    assert k1 - k0 >= 100, "frames stopped after the change"
    assert rate <= 1.5 * rate1, "the new rate is not in effect"


def test_paced_plant_without_frames_says_so(capfd):
    """No controller: frames 0 and 1 go out, then the plant waits for duty(0) (up to
    first_duty_timeout_s = 30 s, for a graph still starting); after stall_warn_s it says
    so, once."""
    g = Plant({"rate_factor": 1.0, "stall_warn_s": 0.3})
    try:
        g.wait_frame(1, 10.0)
        time.sleep(1.5)
        k = g.plant.k
    finally:
        g.close()
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if "pacing: no frame for" in ln]
    print("\n".join(lines))
    assert k == 1
    assert len(lines) == 1
    assert "after frame 1 (rate_factor 1, stall_warn_s 0.3): waiting for duty command 0" in lines[0]


def test_paced_plant_reports_lateness_on_diagnostics():
    """The pacing source of the plant's /diagnostics: lateness p50/p99/max (in periods of
    paced wall time) over the frames since the last report, and the run's holds, slips and
    watchdog trips.  diagnostics_period_s 0: no timer, the statuses are taken here, exactly
    as the timer would publish them -- while the plant runs on in its thread, so each report
    is bracketed by the frame counts read just before and just after it (one lateness entry
    per frame after frame 0, appended just after the frame goes out: a report taken between
    counts a and b covers a - 1 .. b of them)."""
    rate = 0.1  # 1 000 frames per wall second, period 1 ms
    g = Plant({"rate_factor": rate, "first_duty_timeout_s": 0.0, "diagnostics_period_s": 0.0})
    try:
        g.wait_frame(1000, 60.0)

        def pacing() -> dict[str, str]:
            st = next(s for s in g.plant.diag.statuses() if s.name.endswith(": pacing"))
            return {kv.key: kv.value for kv in st.values}

        ka = g.plant.k
        first = pacing()
        kb = g.plant.k
        g.wait_frame(kb + 500, 30.0)
        kc = g.plant.k
        second = pacing()
        kd = g.plant.k
    finally:
        g.close()
    print(first, second, sep="\n")
    assert float(first["period_s"]) == pytest.approx(TS_S / rate)
    assert ka - 1 <= int(first["frames"]) <= kb
    p50, p99, pmax = (float(first[f"lateness_{q}_periods"]) for q in ("p50", "p99", "max"))
    assert p50 <= p99 <= pmax
    # the second report covers only the frames since the first one
    assert kc - 1 - kb <= int(second["frames"]) <= kd - ka + 1
    assert int(second["watchdog_trips"]) == 1  # no controller: PWM off, one trip
