"""A user's observer (a Python class: module:Class or an entry point) in every role: it drives
or shadows the in-process closed loop, the graph's observer node runs it, and the per-period
Python loop that carries it is the compiled loop's period exactly."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from fluxdrive.analysis.metrics import wrap
from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.control import CO_MODE, MODE_CLOSED_LOOP
from fluxdrive.drive.observers import ES_TH, observer_config
from fluxdrive.drive.plant import TR_THETA_E, TR_WM
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
from fluxdrive.drive.sim import run_scenario
from ros_domains import domain

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "my_observer"
PLUGIN = "my_observer:ClampedFluxObserver"  # the replay worked example (docs/replay.md)
DRIVER = "my_observer.flux_pll:FluxPllObserver"  # the one that closes the loop
SCENARIO = CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml"


@pytest.fixture
def example_importable(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.setenv("PYTHONPATH", f"{EXAMPLE}:{os.environ.get('PYTHONPATH', '')}")


def _case(driving: str, observers: dict, **over):
    """The 2 %/150 % scenario (Fig. 14) with the given observers and driving one."""
    return load_scenario(SCENARIO, overrides={"observers": observers, "driving": driving, **over})


def test_plugin_drives_2pct_150load_in_sim(example_importable):
    """A user variant in plain Python (examples/my_observer/flux_pll.py: LPF + inverse HPF +
    PLL written from docs/engine.md) drives the shipped 2 %/150 % case (paper bench,
    sensorless start, brake ramped to 150 %): in the steady window the rotor turns at the
    commanded 2 % of rated speed under the load, and its angle error is the built-in
    paper_robust's (the same equations, riding along in shadow on the same frames)."""
    sc = _case("user", {"user": {"variant": DRIVER}, "flux_measured": {"variant": "paper_robust"}})
    res = run_scenario(sc, progress=False)
    assert (res.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP).any()
    k0, k1 = (int(round(t / sc.machine.ts_s)) for t in sc.steady_window_s)
    rpm = res.truth[k0:k1, TR_WM].mean() * 60.0 / (2.0 * math.pi)
    target = 0.02 * sc.machine.rated_speed_rpm
    assert abs(rpm - target) < 0.02 * target, rpm
    th = res.truth[k0:k1, TR_THETA_E]
    rms = {}
    for name in ("user", "flux_measured"):
        err = np.degrees(wrap(res.estimate(name)[k0:k1, ES_TH] - th))
        rms[name] = float(np.sqrt(np.mean(err**2)))
    print(f"θ̃ RMS: plugin {rms['user']:.3f}°, paper_robust {rms['flux_measured']:.3f}°")
    assert rms["user"] == pytest.approx(rms["flux_measured"], abs=0.1)


def test_python_loop_is_the_compiled_loop(example_importable):
    """A plugin in shadow switches the run to the per-period Python loop; the drive it does
    not touch (kernel observer driving) is the compiled loop's bit for bit."""
    obs = {"flux_measured": {"variant": "paper_robust"}}
    over = {"duration_s": 0.4, "steady_window_s": [0.2, 0.4]}
    ref = run_scenario(_case("flux_measured", obs, **over), progress=False)
    with_user = run_scenario(
        _case("flux_measured", {**obs, "user": {"variant": PLUGIN}}, **over), progress=False
    )
    for name in ("frames", "truth", "ctrl"):
        assert np.array_equal(getattr(ref, name), getattr(with_user, name)), name
    assert np.array_equal(ref.estimate("flux_measured"), with_user.estimate("flux_measured"))


def test_plugin_gets_the_observer_model(example_importable):
    """A plugin is built with the observer's model (R^, L^, lambda^: the bench's model errors),
    not the true machine values a built-in variant would not see either."""
    from fluxdrive.drive.observers import build_observer

    sc = _case("flux_measured", {"flux_measured": {}, "user": {"variant": PLUGIN}})
    obs = build_observer(sc.observers["user"], sc.machine, "user")
    assert obs.r == pytest.approx(sc.observers["flux_measured"].r_hat_ohm)
    assert obs.l == pytest.approx(sc.observers["flux_measured"].l_hat_h)
    assert obs.r != pytest.approx(sc.machine.resistance_ohm)  # the paper bench's R^ error


def test_unknown_plugin_is_one_line():
    with pytest.raises(ConfigError, match="unknown variant 'no_such_observer'"):
        observer_config("no_such_observer")
    with pytest.raises(ConfigError, match="cannot load observer class 'no_such_mod:X'"):
        observer_config("no_such_mod:X")


def test_plugin_drives_in_the_graph(tmp_path, example_importable):
    """The graph's observer node runs the plugin as the driving observer: the lockstep graph
    (ideal bench, sensorless start and handover within the first second) gives the in-process
    run's numbers exactly."""
    pytest.importorskip("rclpy")
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive.drive.scenario import save_scenario
    from fluxdrive_bringup.launch.runs import result_from_bag, run_graph

    duration = 1.0
    sc = _case(
        "user",
        {"user": {"variant": DRIVER}},
        bench={},
        duration_s=duration,
        steady_window_s=[0.5, duration],
    )
    path = save_scenario(sc, tmp_path / "plugin_drives.yaml")
    bag = tmp_path / "bag"
    r = run_graph(
        path,
        out=tmp_path / "run",
        bag=bag,
        layout="composed",
        domain_id=domain(38),
        quiet=True,
        timeout=240,
        progress=False,
    )
    assert r["code"] == 0, tmp_path / "run" / "logs"
    res, arr = result_from_bag(bag, load_scenario(path), duration)
    assert all(v == 0 for v in arr["missing"].values()), arr["missing"]
    ref = run_scenario(load_scenario(path), progress=False)
    for name in ("frames", "truth", "est", "ctrl"):
        assert np.array_equal(getattr(res, name), getattr(ref, name)), name
    assert (res.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP).any()


def test_benchmark_plugin_prints_its_figures(capsys):
    """`./fluxdrive benchmark plugin` (tiny sizes here: the figures are the benchmark's)."""
    from fluxdrive.cli.bench import bench_plugin

    out = bench_plugin(["--samples", "2000", "--seconds", "0.02"])
    assert out["plugin"] == DRIVER
    for key in ("replay_us_per_sample", "closed_loop_us_per_period"):
        assert out[key] > 0.0
    assert "[bench] closed loop" in capsys.readouterr().err


def test_numba_plugin_is_the_python_plugin_compiled(example_importable):
    """examples/my_observer/flux_pll_numba.py (the driving example's equations in one numba
    kernel) gives the plain-Python class's estimates over a recorded bag, through its block
    `run()` and frame by frame through `step()`."""
    from fluxdrive.drive.observers import make_observer
    from fluxdrive.io.bagio import read_run_bag
    from fluxdrive.replay.lab import SAMPLES_DIR

    bag = read_run_bag(SAMPLES_DIR / "paper_2pct_150load")
    card, frames = bag.machine(), bag.frames[:20000]
    ref = make_observer(DRIVER, card, pll_hz=20.0).run(frames)
    fast = make_observer("my_observer.flux_pll_numba:FluxPllNumbaObserver", card, pll_hz=20.0)
    assert np.allclose(fast.run(frames), ref, rtol=0.0, atol=1e-9)
    fast.reset()
    stepped = np.array([fast.step(fr) for fr in frames[:2000]])
    assert np.allclose(stepped, ref[:2000], rtol=0.0, atol=1e-9)
