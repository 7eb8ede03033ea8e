"""One study task: a payload (plain data, see spec.StudySpec.tasks) -> one table row.

Scenario tasks build the scenario (a builder of the experiments, or a scenario file through
the one scenario loader), apply the task's grid values and its random draw, run it with
`run_scenario` and keep the metrics of the one metrics module.  Bag tasks replay the recorded
frames through the variant (`replay_bag`).  Only small dicts travel back.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import time
from pathlib import Path
from typing import Any

from fluxdrive.analysis.metrics import compute, observer_metrics, steady_window
from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError, load_machine
from fluxdrive.drive.plant import TR_THETA_E
from fluxdrive.drive.scenario import CONFIG_DIR, Scenario, load_scenario
from fluxdrive.drive.sim import run_scenario
from fluxdrive.io.bagio import read_run_bag
from fluxdrive.replay.lab import VariantSpec, live_changes, replay_bag
from fluxdrive.study.spec import BUILDERS, PERTURBATIONS, axis_kind, scenario_axis_value

ALPHA_CU_PER_K = 0.00393  # copper resistance
ALPHA_NDFEB_PER_K = -0.0012  # remanence of NdFeB magnets
T_CARD_C = 20.0  # the machine card's values are at this temperature

# the row's outputs (besides the inputs): name -> arrow type name
OUTPUTS: dict[str, str] = {
    "stable": "bool_",
    "fault_code": "int64",
    "theta_err_rms_deg": "float64",
    "theta_err_peak_deg": "float64",
    "theta_err_mean_deg": "float64",
    "theta_err_h1_deg": "float64",
    "theta_err_h6_deg": "float64",
    "flux_radius_spread": "float64",
    "valid_fraction": "float64",
    "mean_rpm": "float64",
    "mean_error_rpm": "float64",
    "ripple_rpm": "float64",
    "i_q_mean_a": "float64",
    "sim_s": "float64",
    "wall_s": "float64",
    "cpu_s": "float64",
}
OBS_KEYS = [
    "theta_err_rms_deg",
    "theta_err_peak_deg",
    "theta_err_mean_deg",
    "theta_err_h1_deg",
    "theta_err_h6_deg",
    "flux_radius_spread",
    "valid_fraction",
]


def run_task(p: dict[str, Any]) -> dict[str, Any]:
    """The task function every runner mode calls (module-level: pickled by reference)."""
    t0, c0 = time.perf_counter(), time.process_time()
    if "bag" in p["scenario"]:
        out = _bag_task(p)
    else:
        sc = build_task_scenario(p)
        r = run_scenario(sc, progress=False)
        m = compute(r)
        o = m["observers"][p["variant"]]
        out = {
            "stable": bool(m["stable"]),
            "fault_code": int(m["fault_code"]),
            **{k: float(o[k]) for k in OBS_KEYS},
            "mean_rpm": m["speed"]["mean_rpm"],
            "mean_error_rpm": m["speed"]["mean_error_rpm"],
            "ripple_rpm": m["speed"]["ripple_rpm"],
            "i_q_mean_a": m["currents"]["i_q_mean_a"],
            "sim_s": sc.duration_s,
        }
    out["wall_s"] = time.perf_counter() - t0
    out["cpu_s"] = time.process_time() - c0  # what the run costs on an idle core
    return out


def warm_kernels() -> None:
    """Compile (or load from the on-disk cache) the closed-loop kernels in this process: run
    before starting local workers, so that they load the cache instead of each compiling."""

    sc = load_scenario(
        CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml",
        overrides={"duration_s": 0.01, "steady_window_s": [0.0, 0.01]},
    )
    run_scenario(sc, progress=False)


def _builder(name: str):
    mod, fn = BUILDERS[name].split(":")
    return getattr(importlib.import_module(mod), fn)


def build_task_scenario(p: dict[str, Any]) -> Scenario:
    """The task's scenario: grid values of kind 'scenario' and 'observer' go into the build
    (so the controller's speed-path design follows the observer), then controller settings,
    then the perturbations (grid or random) on the built scenario."""
    spec = p["scenario"]
    vname = p["variant"]
    values: dict[str, Any] = {**p["grid"], **p["random"]}
    obs = dict(p["variant_cfg"])
    scen_kw = dict(spec.get("params", {}))
    for k, v in p["grid"].items():
        kind = axis_kind(k)
        if kind == "observer":
            obs[k] = v
        elif kind == "scenario":
            scen_kw[k] = v
    if "builder" in spec:
        fn = _builder(spec["builder"])
        kw = dict(scen_kw)
        speed, load = kw.pop("speed_rpm", None), kw.pop("load_pu", None)
        if speed is None or load is None:
            raise ConfigError(
                f"builder {spec['builder']} needs speed_rpm and load_pu "
                f"(a grid axis or scenario.params)"
            )
        if spec["builder"] != "encoder_run":
            kw["driving"] = vname
        if spec.get("machine"):  # `study --machine` or scenario.machine: the builder's card
            kw["card"] = spec["machine"]
        sc = fn(
            float(speed),
            float(load),
            observers={vname: obs},
            seed=p["seed"],
            name=f"study_{vname}",
            **kw,
        )
    else:
        raw = yamlio.load_file(spec["file"]) or {}
        driving = "encoder" if raw.get("driving", "encoder") == "encoder" else vname
        # a level on a profile key scales the file's profile (spec.scenario_axis_value)
        scen_kw = {k: scenario_axis_value(raw, k, v)[0] for k, v in scen_kw.items()}
        over = {**scen_kw, "observers": {vname: obs}, "driving": driving, "seed": p["seed"]}
        sc = load_scenario(spec["file"], machine=spec.get("machine"), overrides=over)
    for k, v in p["grid"].items():
        if axis_kind(k) == "control":
            sc.control = dataclasses.replace(sc.control, **{k[8:]: v}).validate()
    perturb(sc, vname, {k: v for k, v in values.items() if k in PERTURBATIONS})
    return sc


def perturb(sc: Scenario, vname: str, values: dict[str, Any]) -> Scenario:
    """Apply uncertainty values (see spec.PERTURBATIONS) to a built scenario in place."""
    card = sc.machine
    cfg = sc.observers[vname]
    # what the observer and the controller believe: their own settings, else the card's
    r0 = card.resistance_ohm if cfg.r_hat_ohm is None else cfg.r_hat_ohm
    l0 = card.inductance_h if cfg.l_hat_h is None else cfg.l_hat_h
    lam0 = card.flux_linkage_vs if cfg.lambda_hat_vs is None else cfg.lambda_hat_vs
    cfg = dataclasses.replace(
        cfg,
        r_hat_ohm=r0 * (1.0 + values.get("r_hat_err", 0.0)),
        l_hat_h=l0 * (1.0 + values.get("l_hat_err", 0.0)),
        lambda_hat_vs=lam0 * (1.0 + values.get("lambda_hat_err", 0.0)),
    )
    sc.observers[vname] = cfg.validate(f"study variant {vname}")
    ctrl = sc.control
    sc.control = dataclasses.replace(
        ctrl,
        r_hat_ohm=card.resistance_ohm if ctrl.r_hat_ohm is None else ctrl.r_hat_ohm,
        l_hat_h=card.inductance_h if ctrl.l_hat_h is None else ctrl.l_hat_h,
        lambda_hat_vs=card.flux_linkage_vs if ctrl.lambda_hat_vs is None else ctrl.lambda_hat_vs,
    )
    rated = card.rated_current_a
    if "current_offset_pu" in values:
        sc.current_offset_a = tuple(float(x) * rated for x in values["current_offset_pu"])
    if "current_gain_err" in values:
        sc.current_gain = tuple(1.0 + float(x) for x in values["current_gain_err"])
    if "deadtime_s" in values:
        sc.plant_deadtime_s = float(values["deadtime_s"])
    new: dict[str, Any] = {}
    if "current_noise_a" in values:
        new["current_noise_a"] = float(values["current_noise_a"])
    if "temperature_c" in values:
        dt = float(values["temperature_c"]) - T_CARD_C
        new["resistance_ohm"] = card.resistance_ohm * (1.0 + ALPHA_CU_PER_K * dt)
        k_lam = 1.0 + ALPHA_NDFEB_PER_K * dt
        new["flux_linkage_vs"] = card.flux_linkage_vs * k_lam
        # loads are per unit of the card's rated torque, which follows lambda: keep the
        # load in N m what it was (a hot motor brakes against the same dyno)
        sc.load_profile_pu = sc.load_profile_pu.copy()
        sc.load_profile_pu[:, 1] /= k_lam
        sc.dyno_pu_per_rpm /= k_lam
    if new:
        sc.machine = dataclasses.replace(card, **new).validate("study perturbation")
    return sc


# ---------------------------------------------------------------- replay (bag) tasks
_BAGS: dict[str, Any] = {}  # per worker process: a bag is read once


def cache_bag(path: str, bag: Any) -> None:
    """Hand the bag tasks of this process a bag already read (an in-process sweep reads it
    once); worker processes read theirs on first use."""
    _BAGS.clear()
    _BAGS[path] = bag


def clear_bag_cache() -> None:
    """Forget the bag this process holds (the end of a sweep)."""
    _BAGS.clear()


def _bag(path: str):
    if path not in _BAGS:
        cache_bag(path, read_run_bag(Path(path)))
    return _BAGS[path]


def _bag_task(p: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    spec = p["scenario"]
    bag = _bag(spec["bag"])
    machine = load_machine(spec["machine"]) if spec.get("machine") else None
    card = bag.machine(machine)
    params = {k: v for k, v in p["variant_cfg"].items() if k != "variant"}
    params.update(p["grid"])
    for key, field_, base in (
        ("r_hat_err", "r_hat_ohm", card.resistance_ohm),
        ("l_hat_err", "l_hat_h", card.inductance_h),
        ("lambda_hat_err", "lambda_hat_vs", card.flux_linkage_vs),
    ):
        if key in params or key in p["random"]:
            x = params.pop(key, None)
            x = p["random"].get(key, x)
            params[field_] = float(params.get(field_, base)) * (1.0 + float(x))
    vs = VariantSpec(p["variant"], p["variant_cfg"].get("variant", "paper"), params)
    win = spec.get("window_s")
    res = replay_bag(
        bag, [vs], machine, tuple(win) if win else None, float(spec.get("encoder_offset_deg", 0.0))
    )
    w = steady_window(res.t, res.scenario.steady_window_s)
    th = res.truth[:, TR_THETA_E]
    sl = slice(w.k0, w.k1)
    m = observer_metrics(res.est[0, sl], th[sl], np.unwrap(th)[sl])
    out: dict[str, Any] = {k: float(m[k]) for k in OBS_KEYS}
    out["stable"] = bool(m["theta_err_peak_deg"] < 60.0)  # the driving-observer criterion
    out["fault_code"] = 0
    for k in ("mean_rpm", "mean_error_rpm", "ripple_rpm", "i_q_mean_a"):
        out[k] = math.nan
    out["sim_s"] = float(res.t[-1] - res.t[0])
    out["replay_s"] = float(res.wall_s.get(p["variant"], 0.0))
    out["metrics"] = m
    if vs.recorded is not None:  # the bag's live changes applied, and (same settings) exactness
        out["markers_applied"] = len(live_changes(bag, vs))
        out["recorded_max_abs_diff"] = res.recorded_diff.get(p["variant"])
    return out
