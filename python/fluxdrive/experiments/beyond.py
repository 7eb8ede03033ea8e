"""Past the paper: lowest sustainable speed per variant, parameter mismatch and offsets,
sensitivity per variant, online R_s, sensorless speed reversal, where peers fail.

  lowest_speed    sensorless start at 16 % speed, load ramped in, descent under load to the
                  speed; grid + bisection per variant, 100 % and 150 % load, against the bound
                  (0.2 R I + V_dt)/lambda
  mismatch        the paper observer under R^/L^/lambda^ errors and current offsets, shadow
                  and driving (2 %/150 %)
  sensitivity     the same errors plus the cut-off, for every variant, against a
                  steady-state fundamental model of each (shadow observers on one encoder run)
  rs_adapt        online R_s estimate for R^ 30 % off
  speed_reversal  +2 % -> -2 % speed under brake/active load: hand-back to I-f, through zero,
                  handover again
  peers_fail      2 % speed, rated load, the card's deadtime: the loop closed on each observer

The online R_s estimate runs *outside* the compiled kernels: the closed loop is stepped in
1 ms chunks (the same `closed_loop_chunk` the runner uses) and between chunks an adapter
reads the driving observer's flux magnitude and rewrites its R^ parameter.  Mechanism
(SPM, i_d = 0): an R^ error puts (R - R^) i along q into the EMF; integrated over the
rotation it lands along d, so |lambda^| = lambda + (R - R^) |i_q| / |w|: the flux
magnitude measures the resistance error.  dR^/dt = g (|lambda^| - lambda^_pm) w^ / i_q.
rs_adapt and peers_fail's loop-closing runs are in-process only (they change parameters or
the position source mid-run, which the node graph does not do); every other run goes through
ctx.run (parallel, or the node graph with --graph).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.analysis.metrics import RAD_S_TO_RPM, compute, harmonic, whole_periods
from fluxdrive.core.machine import MachineCard, card_current_bandwidth_hz
from fluxdrive.drive.control import (
    CO_FAULT,
    CO_ID,
    CO_IQ,
    CO_MODE,
    CO_TH,
    CO_W_REF,
    FAULT_NAMES,
    MODE_CLOSED_LOOP,
    MODE_IF_RAMP,
)
from fluxdrive.drive.control.config import SPEED_OF_CURRENT_BW
from fluxdrive.drive.observers import ES_LA, ES_LB, ES_TH, ES_W, OP_LAM, OP_R, observer_config
from fluxdrive.drive.plant import TR_THETA_E, TR_WM
from fluxdrive.experiments.common import (
    HANDBACK_MAX_PU,
    OBS4,
    SPEED_STEP_PU_S,
    START_PU,
    CardValues,
    build,
    card_values,
    claim,
    plt,
    pu_rpm,
    rated_rpm,
)

RPM = 2 * math.pi / 60
# the descent protocol (lowest_speed, peers_fail) in per unit of the card's rated speed: start
# at 16 %, decelerate at 1/15 of the rated speed per second
DESCENT_START_PU = 0.16
DESCENT_DECEL_PU_S = 1.0 / 15.0


# ======================================================================== shared
# the observer variants compared past the paper (names are ROS-safe: they become nodes);
# flux_*: paper_robust, the flux observer that can drive (the literal `paper` loses lock
# after a sensorless start: experiment paper_robust)
VARIANTS: dict[str, dict[str, Any]] = {
    **OBS4,  # the project's observer set (declared once: fluxdrive.drive.scenario.observer_set)
    "hl_measured": {"variant": "hinkkanen_luomi", "voltage_source": "measured"},
    "ortega_measured": {"variant": "ortega", "voltage_source": "measured"},
    "ortega_commanded": {"variant": "ortega", "voltage_source": "commanded"},
    # the bound's 0.2 R I term is a 20 % resistance error: the paper observer with R^ 20 % high
    "flux_measured_rhat120": {
        "variant": "paper_robust",
        "voltage_source": "measured",
        "r_hat_pu": 1.2,
    },
}


def variant_spec(name: str, mc: CardValues) -> dict:
    """VARIANTS[name] as an observer spec: a model error given relative to the card
    (r_hat_pu) becomes the observer's own R^ [ohm]."""
    spec = dict(VARIANTS[name])
    if "r_hat_pu" in spec:
        spec["r_hat_ohm"] = spec.pop("r_hat_pu") * mc.r
    return spec


def speed_bound_rpm(mc: CardValues, load_pu: float, commanded: bool) -> float:
    """Rule-of-thumb lowest speed w_min = (0.2 R I + V_dt)/lambda (electrical) at the current
    I that carries the load; V_dt only where the observer uses commanded voltages."""
    v = 0.2 * mc.r * load_pu * mc.i_rated + (mc.vdt if commanded else 0.0)
    return v / mc.lam / mc.p * RAD_S_TO_RPM


def descent(
    speed_rpm: float,
    load_pu: float,
    *,
    driving: str,
    observers: dict | None = None,
    start_rpm: float | None = None,
    decel_rpm_s: float | None = None,
    ramp_pu_s: float = 0.19,
    settle_s: float = 0.5,
    window_s: float = 1.5,
    seed: int = 1,
    name: str = "descent",
    card: str | Path | None = None,
    **extra,
):
    """Sensorless start (align, I-f, handover) at start_rpm (default 16 % of the rated speed
    of `card`, whose rpm the speeds are) unloaded -- every variant can hand over there --
    then the brake load ramped in at that speed, then a closed-loop deceleration (default
    1/15 of the rated speed per second) under load to `speed_rpm`, a settle and the steady
    window.  Loading at the target speed instead would measure the speed loop's ramp lag
    (i_q ramp / K_i), not the observer; decelerating under a constant load leaves no lag
    (type-2 loop)."""
    obs = dict(observers or {driving: variant_spec(driving, card_values(card))})
    start_rpm = pu_rpm(DESCENT_START_PU, card) if start_rpm is None else start_rpm
    decel_rpm_s = pu_rpm(DESCENT_DECEL_PU_S, card) if decel_rpm_s is None else decel_rpm_s
    s0 = max(start_rpm, speed_rpm)
    t_load = 1.0 + s0 / (rated_rpm(card) * SPEED_STEP_PU_S)
    t_full = t_load + (load_pu / ramp_pu_s if load_pu > 0 else 0.0)
    t_dec = t_full + 0.3
    t_at = t_dec + (s0 - speed_rpm) / decel_rpm_s
    w0 = t_at + settle_s
    dur = w0 + window_s
    ctrl = {
        "if_current_pu": 0.6,
        "handover_rpm": pu_rpm(START_PU, card),
        "handback_rpm": min(pu_rpm(HANDBACK_MAX_PU, card), 0.5 * speed_rpm),
        "handover_agree_lpf_hz": 2.0,
    }
    load = [[0.0, 0.0], [t_load, 0.0], [t_full, load_pu]] if load_pu > 0 else 0.0
    return build(
        card=card,
        name=name,
        duration_s=round(dur, 4),
        seed=seed,
        speed_rpm=[[0.0, s0], [round(t_dec, 4), s0], [round(t_at, 4), speed_rpm]],
        load_type="brake",
        load_pu=load,
        steady_window_s=[round(w0, 4), round(dur, 4)],
        driving=driving,
        control=ctrl,
        observers=obs,
        **extra,
    )


def _x_hold(r, m):
    """Did the sensorless drive hold: metrics' verdict, where it closed the loop, and where
    (time, speed reference, load) it first lost the rotor (|theta~| > 60 deg or a fault)."""
    d = r.driving
    err = np.degrees(np.angle(np.exp(1j * (r.estimate(d)[:, ES_TH] - r.truth[:, TR_THETA_E]))))
    mode = r.ctrl[:, CO_MODE]
    kc = np.nonzero(mode == MODE_CLOSED_LOOP)[0]
    lost = None
    if kc.size:
        k0 = kc[0] + int(0.3 / r.scenario.machine.ts_s)  # the handover transient
        bad = np.nonzero((np.abs(err[k0:]) > 60.0) | (r.ctrl[k0:, CO_FAULT] > 0))[0]
        if bad.size:
            k = k0 + int(bad[0])
            lp = r.scenario.load_profile_pu
            lost = {
                "t_s": float(r.t[k]),
                "ref_rpm": float(r.w_ref[k] * RAD_S_TO_RPM),
                "load_pu": float(np.interp(r.t[k], lp[:, 0], lp[:, 1])),
                "fault": FAULT_NAMES.get(int(r.ctrl[:, CO_FAULT].max()), "none"),
            }
    o = m["observers"][d]
    return {
        "stable": m["stable"],
        "rms_deg": o["theta_err_rms_deg"],
        "mean_rpm": m["speed"]["mean_rpm"],
        "closed_at_s": float(r.t[kc[0]]) if kc.size else None,
        "lost": lost,
        "fault": FAULT_NAMES.get(m["fault_code"], str(m["fault_code"])),
    }


# the search loads the drive at 16 % speed, where the ramp's speed lag (rate/(K_t K_i), ≈90 rpm at
# 0.5 pu/s) costs nothing: a faster ramp than the paper scenarios' 0.19 pu/s shortens every
# run by 3-5 s of the ≈12-15 s it took (the experiment ran 5 min; the whole set must run in 3)
LOW_RAMP_PU_S = 0.5


def _search_lowest(ctx, cases, grid, seeds, bisect_steps):
    """Per case (variant, load): walk down the speed grid while every seed holds, then bisect
    (geometrically) between the lowest held and the first lost grid speed.  Each step runs
    every live case at once (parallel)."""
    st = {c: {"runs": {}, "alive": True, "hi": None, "lo": None} for c in cases}

    def step(speeds_by_case):
        jobs, keys = [], []
        for c, s in speeds_by_case.items():
            v, load = c
            for seed in seeds:
                jobs.append(
                    (
                        descent(
                            s,
                            load,
                            driving=v,
                            seed=seed,
                            name=f"low_{v}",
                            ramp_pu_s=LOW_RAMP_PU_S,
                            card=ctx.machine,
                        ),
                        _x_hold,
                        None,
                    )
                )
                keys.append((c, s))
        for (c, s), res in zip(keys, ctx.run(jobs), strict=True):
            st[c]["runs"].setdefault(s, []).append(res)
        return {c: all(x["stable"] for x in st[c]["runs"][s]) for c, s in speeds_by_case.items()}

    for s in grid:
        todo = {c: s for c in cases if st[c]["alive"]}
        if not todo:
            break
        for c, ok in step(todo).items():
            if ok:
                st[c]["hi"] = s
            else:
                st[c]["alive"] = False
                st[c]["lo"] = s
    for _ in range(bisect_steps):
        todo = {
            c: round(math.sqrt(v["hi"] * v["lo"]), 1)
            for c, v in st.items()
            if v["hi"] is not None and v["lo"] is not None
        }
        if not todo:
            break
        for c, ok in step(todo).items():
            st[c]["hi" if ok else "lo"] = todo[c]
    return st


def _lowest_cases(ctx) -> tuple[list, list, list, int]:
    """Build: (cases (variant, load), speed grid [rpm], seeds, bisection steps)."""
    if ctx.quick:
        cases = [("flux_measured", 1.0), ("flux_measured", 1.5), ("emf_commanded", 1.0)]
        return cases, [ctx.rpm(x) for x in (0.08, 0.02, 0.01)], [1], 0
    names = [
        "flux_measured",
        "flux_commanded",
        "emf_measured",
        "emf_commanded",
        "hl_measured",
        "ortega_measured",
        "flux_measured_rhat120",
    ]
    cases = [(v, load) for v in names for load in (1.0, 1.5)]
    # one seed: a second one (last run) disagreed only at two bisection points (emf_measured
    # 100 % at 35.7 rpm, hl_measured 150 % at 12.6 rpm), one bisection step, no verdict
    grid = [ctx.rpm(x) for x in (0.16, 0.08, 0.04, 0.02, 0.01, 0.005, 0.0025)]
    return cases, grid, [1], 2


def _lowest_first_loss(s: dict) -> dict | None:
    """Where the first lost run at the first lost speed lost the rotor."""
    if s["lo"] is None:
        return None
    lost_runs = [x for x in s["runs"][s["lo"]] if not x["stable"]]
    if not lost_runs:
        return None
    x = lost_runs[0]
    return {
        "lost": x["lost"],
        "fault": x["fault"],
        "closed_at_s": x["closed_at_s"],
        "rms_deg": x["rms_deg"],
    }


def _lowest_table(ctx, st: dict) -> dict:
    """Analyse the search: variant -> "100%"/"150%" -> lowest held, first lost, bound."""
    lowest: dict = {}
    for (v, load), s in st.items():
        commanded = VARIANTS[v]["voltage_source"] == "commanded"
        lowest.setdefault(v, {})[f"{int(load * 100)}%"] = {
            "lowest_rpm": s["hi"],
            "first_lost_rpm": s["lo"],
            "tested": {str(k): [x["stable"] for x in runs] for k, runs in s["runs"].items()},
            "rms_deg_at_lowest": (
                float(np.mean([x["rms_deg"] for x in s["runs"][s["hi"]]]))
                if s["hi"] is not None
                else None
            ),
            "loss": _lowest_first_loss(s),
            "bound_rpm": speed_bound_rpm(ctx.cv, load, commanded),
        }
    return lowest


def _lowest_txt(d: dict) -> str:
    """One case's result: lowest held, first lost, bound, where it lost the rotor."""
    low = d["lowest_rpm"]
    s = f"{low:g} rpm" if low is not None else f"none (lost at {d['first_lost_rpm']:g})"
    if d["first_lost_rpm"] is not None and low is not None:
        s += f", lost at {d['first_lost_rpm']:g}"
    elif d["first_lost_rpm"] is None:
        s += " (held down to the grid's end)"
    s += f"; bound {d['bound_rpm']:.0f} rpm"
    if d["loss"] and d["loss"]["lost"]:
        lo = d["loss"]["lost"]
        s += (
            f" (loss at ref {lo['ref_rpm']:.0f} rpm, load {lo['load_pu']:.2f} pu, "
            f"fault {lo['fault']})"
        )
    elif d["loss"] and d["loss"]["closed_at_s"] is None:
        s += " (never handed over)"
    return s


def card_rates(ctx) -> dict[str, float]:
    """The card's numbers the texts quote, from the card and the variants' defaults on it:
    electrical rad/s at 2 % and 1 % speed, the flux observer's cut-off w_c, the magnitude
    loops' gains k (hinkkanen_luomi w_c, ortega gamma lambda^2) [rad/s], the per-sample EMF
    noise L/Ts sigma_i [V], the speed where |lambda^| = lambda + (4/pi)V_dt/w reaches 3 lambda."""
    mc = ctx.cv
    w3 = mc.v1_dt / (2.0 * mc.lam)
    return {
        "w2": ctx.rpm(0.02) * RPM * mc.p,
        "w1": ctx.rpm(0.01) * RPM * mc.p,
        "wc": _default_k(ctx.card, "paper_robust")[0],
        "k_hl": _default_k(ctx.card, "hinkkanen_luomi")[1],
        "k_ortega": _default_k(ctx.card, "ortega")[1],
        "emf_noise_v": mc.l / mc.ts * ctx.card.current_noise_a,
        "rpm_3lam": w3 / (mc.p * RPM),
    }


def _deg_per_mv(mc: CardValues, k: float, w: float) -> float:
    """Angle error of a magnitude-forcing observer per mV of q-axis EMF residue: k d/(w^2 lam)."""
    return math.degrees(k * 1e-3 / (w * w * mc.lam))


def lowest_notes(ctx, lowest: dict) -> dict[str, str]:
    """Why each variant stops where it does (the lowest_speed claims' notes), in the card's
    numbers: the speeds are the card's 2 % and 1 %, the gains its variants' defaults."""
    mc, cr = ctx.cv, card_rates(ctx)
    r2, r1 = ctx.rpm(0.02), ctx.rpm(0.01)
    held = [x["lowest_rpm"] for x in lowest.get("flux_measured", {}).values() if x["lowest_rpm"]]
    w_low = max(held) * RPM * mc.p if held else cr["w2"]
    at_low = f"{w_low / (mc.p * RPM):.3g} rpm" if held else f"{r2:.0f} rpm"
    k_or, w2 = cr["k_ortega"], cr["w2"]
    return {
        "flux_measured": "measured voltages carry the deadtime, and R^ = R: neither term of the "
        "bound applies.  What ends it was not isolated; candidates are what the measured "
        "voltage still gets wrong (the deadtime residue of the sensitivity experiment) and "
        f"noise, both amplified by the inverse HPF gain ω_c/ω (≈{cr['wc'] / w_low:.0f} at "
        f"{at_low})",
        "flux_commanded": f"the deadtime fundamental (4/π)V_dt = {mc.v1_dt:.2f} V lies along "
        "the current, so it integrates into a flux-magnitude error (4/π)V_dt/ω (Fig. 4): |λ̂| "
        f"leaves the 3λ validity band below ≈{cr['rpm_3lam']:.0f} rpm and the drive trips on "
        "loss of lock",
        "emf_measured": "no integration: the per-sample EMF carries L/Ts·σ_i ≈ "
        f"{cr['emf_noise_v']:.2g} V of noise against ωλ ({w2 * mc.lam:.2g} V at {r2:.0f} rpm, "
        f"{cr['w1'] * mc.lam:.2g} V at {r1:.0f} rpm): the SNR runs out first (the paper's "
        "argument)",
        "emf_commanded": "the deadtime error (4/π)V_dt follows the current; once the loop is "
        "closed on the estimate it rotates with the estimated frame and hides "
        "(4/π)V_dt/(ωλ+(4/π)V_dt) of every angle error from the PLL (peers_fail)",
        "hl_measured": "the modified integrator's angle-error pole is ω²/k for k = "
        f"{cr['k_hl']:.3g} rad/s: slow but unbiased with measured voltages (sensitivity)",
        "ortega_measured": f"its magnitude loop (γλ² = {k_or:.0f} s⁻¹) turns any q-axis EMF "
        f"residue δ into an angle error k δ/(ω² λ), ≈ {_deg_per_mv(mc, k_or, w2):.2g}° per mV "
        f"at {r2:.0f} rpm and growing as 1/ω² (the deadtime residue: sensitivity "
        f"experiment); its angle pole ω²/k is {w2 * w2 / k_or:.2g} s⁻¹ there",
        "flux_measured_rhat120": "R^ 20 % high: |λ̂| = λ − 0.2 R I/ω, which leaves the 0.3λ "
        "validity band at ω = 0.2 R I/(0.7 λ) = 1.43× the bound and "
        "flips sign at the bound itself",
    }


def _lowest_variant_claims(lowest: dict, start_rpm: float, notes: dict) -> list[dict]:
    """One unjudged row per variant: its lowest speed per load against the bound."""
    claims = []
    for v in lowest:
        keys = list(lowest[v])
        claims.append(
            claim(
                f"{v}: lowest speed holding {' / '.join(keys)} load (sensorless, descent under "
                f"load from {start_rpm:.0f} rpm) vs ω_min ≈ (0.2 R I + V_dt)/λ",
                "; ".join(f"{k}: {_lowest_txt(lowest[v][k])}" for k in keys),
                None,
                notes.get(v, ""),
            )
        )
    return claims


def _low(lowest: dict, v: str, key: str) -> float | None:
    d = lowest.get(v, {}).get(key)
    return None if d is None else d["lowest_rpm"]


def _lowest_flux_claim(lowest: dict, loads: list[str]) -> list[dict]:
    """Judge: with measured voltages and R^ = R the flux observer beats the bound."""
    if "flux_measured" not in lowest:
        return []
    fm = [
        (k, _low(lowest, "flux_measured", k), lowest["flux_measured"][k]["bound_rpm"])
        for k in loads
        if k in lowest["flux_measured"]
    ]
    return [
        claim(
            "With measured voltages and R^ = R the flux observer holds the load well below the "
            "bound (neither of its terms applies)",
            "; ".join(
                f"{k}: {x:g} rpm vs bound {b:.0f}" if x is not None else f"{k}: none"
                for k, x, b in fm
            ),
            all(x is not None and x < 0.5 * b for _, x, b in fm),
        )
    ]


def _lowest_rhat_claim(lowest: dict, loads: list[str]) -> list[dict]:
    """Judge: the bound's 0.2 R I term as an R^ error of 20 %."""
    v = "flux_measured_rhat120"
    if v not in lowest:
        return []
    rows = [
        (k, _low(lowest, v, k), lowest[v][k]["first_lost_rpm"], lowest[v][k]["bound_rpm"])
        for k in loads
    ]
    return [
        claim(
            "The bound's 0.2 R I term is a 20 % R^ error: with R^ = 1.2 R the flux observer "
            "fails between the bound and 2× the bound (predicted 1.43×: |λ̂| = λ − 0.2RI/ω "
            "leaves the 0.3λ validity band)",
            "; ".join(
                f"{k}: lost at {lo}, held at {hi} rpm (bound {b:.0f}, 1.43× = {1.43 * b:.0f})"
                for k, hi, lo, b in rows
            ),
            all(
                lo is not None and hi is not None and lo < 2.0 * b and hi > b
                for _, hi, lo, b in rows
            ),
            "the search brackets the loss between two tested speeds; a bracket straddling "
            "the predicted band edge counts",
        )
    ]


def _lowest_bound_claims(ctx, lowest: dict, loads: list[str]) -> list[dict]:
    """Judge: the bound's V_dt term (full runs only) and the paper's SNR argument."""
    claims = []
    com = [v for v in ("flux_commanded", "emf_commanded") if v in lowest]
    if com and not ctx.quick:
        rows = [(v, k, _low(lowest, v, k), lowest[v][k]["bound_rpm"]) for v in com for k in loads]
        claims.append(
            claim(
                "The bound's V_dt term: commanded-voltage observers stop holding the load near "
                "(0.2 R I + V_dt)/λ (within a factor of 2)",
                "; ".join(f"{v} {k}: {x} rpm vs {b:.0f}" for v, k, x, b in rows),
                all(x is not None and 0.5 * b <= x <= 2.0 * b for _, _, x, b in rows),
                "the bound is a rule of thumb: flux_commanded's loss is set by the flux-magnitude "
                "validity band (3λ at ω ≈ (4/π)V_dt/2λ), emf_commanded's by the closed-loop "
                "feedback of the deadtime error",
            )
        )
    if "emf_measured" in lowest:
        rows2 = [
            (k, _low(lowest, "flux_measured", k), _low(lowest, "emf_measured", k)) for k in loads
        ]
        claims.append(
            claim(
                "The paper's SNR argument as a speed range: with measured voltages the flux "
                "observer holds the load lower than the EMF observer",
                "; ".join(f"{k}: flux {a} vs EMF {b} rpm" for k, a, b in rows2),
                all(a is not None and (b is None or a < b) for _, a, b in rows2),
            )
        )
    return claims


def lowest_speed(ctx):
    """Lowest speed each variant holds under load: build -> run (grid + bisection) ->
    analyse -> judge -> plot."""
    cases, grid, seeds, nbis = _lowest_cases(ctx)
    st = _search_lowest(ctx, cases, grid, seeds, nbis)
    lowest = _lowest_table(ctx, st)
    loads = sorted({k for v in lowest.values() for k in v})
    claims = _lowest_variant_claims(lowest, ctx.rpm(DESCENT_START_PU), lowest_notes(ctx, lowest))
    claims += _lowest_flux_claim(lowest, loads) + _lowest_rhat_claim(lowest, loads)
    claims += _lowest_bound_claims(ctx, lowest, loads)
    figs = [_plot_lowest(ctx, lowest, grid)]
    return {
        "claims": claims,
        "figures": figs,
        "data": {
            "lowest": lowest,
            "grid_rpm": grid,
            "seeds": seeds,
            "protocol": f"sensorless start at {ctx.rpm(DESCENT_START_PU):.0f} rpm unloaded, "
            f"brake load ramp {LOW_RAMP_PU_S} pu/s, decel {ctx.rpm(DESCENT_DECEL_PU_S):.0f} "
            "rpm/s, 0.5 s settle, 1.5 s window",
        },
    }


def _plot_lowest(ctx, lowest, grid):
    p = plt()
    loads = sorted({k for v in lowest.values() for k in v})
    fig, axs = p.subplots(
        1, len(loads), figsize=(6 * len(loads), 0.55 * len(lowest) + 1.8), squeeze=False
    )
    names = list(lowest)
    for ax, key in zip(axs[0], loads, strict=True):
        for i, v in enumerate(names):
            d = lowest[v].get(key)
            if d is None:
                continue
            for s, sts in d["tested"].items():
                ax.plot(float(s), i, "o", color="C2" if all(sts) else "C3", ms=6)
            if d["lowest_rpm"] is not None:
                ax.plot(d["lowest_rpm"], i, "*", color="k", ms=9)
            ax.plot([d["bound_rpm"]], [i], "|", color="k", ms=16, mew=2)
        lp = float(key.rstrip("%")) / 100
        for com, ls in ((False, "--"), (True, ":")):
            ax.axvline(
                speed_bound_rpm(ctx.cv, lp, com),
                color="0.4",
                ls=ls,
                lw=1,
                label=f"(0.2RI{'+V_dt' if com else ''})/λ = "
                f"{speed_bound_rpm(ctx.cv, lp, com):.0f} rpm",
            )
        ax.set_yticks(range(len(names)))
        ax.set_yticklabels(names, fontsize=8)
        ax.set_ylim(-1.6, len(names) - 0.5)  # a free band at the bottom for the legend
        ax.set_xscale("log")
        ax.set_xlim(min(grid) * 0.6, max(grid) * 1.6)
        ax.set_xlabel("speed [rpm] (green held, red lost, ★ lowest held, | own bound)")
        start = ctx.rpm(DESCENT_START_PU)
        ax.set_title(f"{key} load: sensorless, descent under load from {start:.0f} rpm", fontsize=9)
        ax.legend(fontsize=7, loc="lower left", ncol=2)
        ax.grid(alpha=0.3, which="both", axis="x")
    return ctx.fig(fig, "beyond_lowest_speed")


# ======================================================================== mismatch / offsets
def _x_mismatch(r, m):
    from fluxdrive.analysis.metrics import steady_window

    w = steady_window(r.t, r.scenario.steady_window_s)
    sl = slice(w.k0, w.k1)
    we = float(np.mean(r.truth[sl, TR_WM])) * r.scenario.machine.pole_pairs
    iq = float(np.mean(r.ctrl[sl, CO_IQ]))
    out = {"metrics": m, "we": we, "iq": iq, "obs": {}}
    for i, nm in enumerate(r.names):
        e = r.est[i, sl]
        th_err = np.angle(np.exp(1j * (e[:, ES_TH] - r.truth[sl, TR_THETA_E])))
        out["obs"][nm] = {
            "mag": float(np.mean(np.hypot(e[:, ES_LA], e[:, ES_LB]))),
            "mean_deg": float(np.degrees(np.mean(th_err))),
            "rms_deg": m["observers"][nm]["theta_err_rms_deg"],
            "valid": m["observers"][nm]["valid_fraction"],
        }
    return out


# the shadow errors of the mismatch experiment, relative to the card
MISMATCH_RS = [0.7, 0.85, 1.15, 1.3]
MISMATCH_LS = [0.5, 0.8, 1.25, 1.5]
MISMATCH_LAMS = [0.8, 1.2]


def _mismatch_observers(mc: CardValues, base: dict) -> dict:
    """The shadow set: the reference, each R^/L^/lambda^ error, the driving observer last."""
    obs: dict[str, dict] = {"ref": OBS4["flux_measured"]}
    for k in MISMATCH_RS:
        obs[f"R{k}"] = {**base, "r_hat_ohm": mc.r * k}
    for k in MISMATCH_LS:
        obs[f"L{k}"] = {**base, "l_hat_h": mc.l * k}
    for k in MISMATCH_LAMS:
        obs[f"lam{k}"] = {**base, "lambda_hat_vs": mc.lam * k}
    obs["flux_measured"] = base
    return obs


def _mismatch_closed(ctx) -> list[tuple[str, float]]:
    """The parameter errors the flux drive is driven with (none in quick mode)."""
    mc = ctx.cv
    if ctx.quick:
        return []
    return [
        ("r_hat_ohm", mc.r * 1.15),
        ("r_hat_ohm", mc.r * 0.85),
        ("l_hat_h", mc.l * 1.5),
        ("l_hat_h", mc.l * 0.5),
    ]


def _mismatch_jobs(ctx, base: dict, offs, closed) -> list:
    """Build: the shadow run, one driving run per current offset, one per driven error; all
    on the ideal bench: the paper bench's own model errors and winding heating would mix with
    the single error under study."""
    sc = "paper_2pct_150load"
    runs = [ctx.build(base=sc, observers=_mismatch_observers(ctx.cv, base), bench={})]
    for o in offs:
        faults = {"current_offset_pu": [0.0, o, 0.0]}
        runs.append(ctx.build(base=sc, bench={}, faults=faults, observers={"flux_measured": base}))
    for key, val in closed:
        runs.append(ctx.build(base=sc, bench={}, observers={"flux_measured": {**base, key: val}}))
    return [(run, _x_mismatch, None) for run in runs]


def _mismatch_rows(mc: CardValues, r0: dict) -> list[dict]:
    """Analyse the shadow run: each error row with its model prediction."""
    we, iq = r0["we"], r0["iq"]
    rows = []
    for k in MISMATCH_RS:
        o = r0["obs"][f"R{k}"]
        pred = mc.lam + (mc.r - mc.r * k) * iq / we
        rows.append({"param": f"R^={k}R", **o, "pred_mag": pred})
    for k in MISMATCH_LS:
        o = r0["obs"][f"L{k}"]
        pred = math.degrees(math.atan2((mc.l - mc.l * k) * iq, mc.lam))
        rows.append({"param": f"L^={k}L", **o, "pred_mean_deg": pred})
    for k in MISMATCH_LAMS:
        rows.append({"param": f"λ^={k}λ", **r0["obs"][f"lam{k}"], "pred_mean_deg": 0.0})
    return rows


def _mismatch_r_claim(mc: CardValues, rr: dict, we: float, iq: float, rpm: float) -> dict:
    rs = MISMATCH_RS
    return claim(
        "R^ error (i_d = 0) is a flux-magnitude error |λ̂| = λ + (R − R^)|i_q|/ω, not an "
        "angle error, at 2 %/150 %",
        "; ".join(
            f"R^={k}R: |λ̂| {1e3 * rr[f'R^={k}R']['mag']:.1f} mV·s (pred "
            f"{1e3 * abs(rr[f'R^={k}R']['pred_mag']):.1f}), θ̃ mean "
            f"{rr[f'R^={k}R']['mean_deg']:.1f}°, valid {rr[f'R^={k}R']['valid']:.2f}"
            for k in rs
        ),
        all(
            abs(rr[f"R^={k}R"]["mag"] - abs(rr[f"R^={k}R"]["pred_mag"]))
            < 0.2 * abs(rr[f"R^={k}R"]["pred_mag"]) + 2e-3
            for k in rs
        ),
        f"R^ > {mc.r + mc.lam * we / iq:.3f} Ω ({100 * mc.lam * we / iq / mc.r:.0f} % high) "
        "flips the "
        "sign of λ̂ (a 180° estimate: the mean θ̃ of those rows is meaningless) at 150 % "
        f"load and {rpm:.0f} rpm; R^ ≤ 0.8 R leaves |λ̂| outside the 0.3-3 λ validity band",
    )


def _mismatch_shadow_claims(mc: CardValues, rr: dict, we: float, iq: float, rpm) -> list[dict]:
    """Judge the shadow rows: R^ moves the magnitude, L^ the angle, lambda^ nothing."""
    ls, lams = MISMATCH_LS, MISMATCH_LAMS
    l_claim = claim(
        "L^ error is an angle error atan((L − L^) i_q / λ)",
        "; ".join(
            f"L^={k}L: θ̃ mean {rr[f'L^={k}L']['mean_deg']:.1f}° (pred "
            f"{rr[f'L^={k}L']['pred_mean_deg']:.1f}°)"
            for k in ls
        ),
        all(abs(rr[f"L^={k}L"]["mean_deg"] - rr[f"L^={k}L"]["pred_mean_deg"]) < 3.0 for k in ls),
    )
    lam_claim = claim(
        "λ^ error does not move the angle (it only scales the PLL's normalisation/validity)",
        "; ".join(f"λ^={k}λ: θ̃ mean {rr[f'λ^={k}λ']['mean_deg']:.2f}°" for k in lams),
        all(abs(rr[f"λ^={k}λ"]["mean_deg"]) < 1.0 for k in lams),
    )
    return [_mismatch_r_claim(mc, rr, we, iq, rpm), l_claim, lam_claim]


def _mismatch_offset_rows(mc: CardValues, offs, res_offs) -> list[dict]:
    """Analyse the offset runs: first-order theta~ against asin(R|di_ab|/(w lam))."""
    off_rows = []
    for o, r in zip(offs, res_offs, strict=True):
        d_ab = o * mc.i_rated * math.sqrt(1 / 9 + 1 / 3)
        ratio = mc.r * d_ab / (abs(r["we"]) * mc.lam) if abs(r["we"]) > 1.0 else 1.0
        pred = math.degrees(math.asin(min(1.0, ratio)))
        mm = r["metrics"]
        off_rows.append(
            {
                "offset_pu": o,
                "stable": mm["stable"],
                "h1_deg": mm["observers"]["flux_measured"]["theta_err_h1_deg"],
                "pred_h1_deg": pred,
                "ripple_rpm": mm["speed"]["ripple_rpm"],
            }
        )
    return off_rows


def _mismatch_offset_claim(off_rows: list[dict]) -> dict:
    return claim(
        "Current-sensor offset on i_b (closed loop, flux drive, 2 %/150 %): 1st-order θ̃ ≈ "
        "asin(R|Δi_αβ|/(ωλ))",
        "; ".join(
            f"{100 * x['offset_pu']:.1f} %: h1 {x['h1_deg']:.2f}° (pred "
            f"{x['pred_h1_deg']:.2f}°), stable {x['stable']}, ripple "
            f"{x['ripple_rpm']:.1f} rpm"
            for x in off_rows
        ),
        all(
            abs(x["h1_deg"] - x["pred_h1_deg"]) < 0.5 * x["pred_h1_deg"] + 0.3
            for x in off_rows
            if x["stable"]
        ),
    )


def _mismatch_closed_claims(mc: CardValues, cl_rows: list[dict], we, iq, rpm) -> list[dict]:
    if not cl_rows:
        return []
    return [
        claim(
            "Driving with mismatched R^/L^ (2 %/150 %, flux drive, measured voltages)",
            "; ".join(f"{x['param']}={x['value']:.4g}: stable {x['stable']}" for x in cl_rows),
            None,
            f"at {rpm:.0f} rpm / 150 % load the R̂ tolerance is tiny (the "
            "flux flips at "
            f"{100 * mc.lam * we / iq / mc.r:.0f} % high; the start-up's I-f angle check also "
            "fails), so R̂ must be tracked online (experiment rs_adapt); L̂ errors only tilt "
            "the angle by atan((L−L̂)i_q/λ)",
        )
    ]


def _plot_mismatch(ctx, rr: dict, we: float, iq: float) -> str:
    mc, rs, ls = ctx.cv, MISMATCH_RS, MISMATCH_LS
    p = plt()
    fig, ax = p.subplots(1, 2, figsize=(10, 3.8))
    ax[0].plot(
        [x * 100 - 100 for x in rs], [1e3 * rr[f"R^={k}R"]["mag"] for k in rs], "o", label="|λ̂| sim"
    )
    kk = np.linspace(0.65, 1.35, 50)
    ax[0].plot(
        kk * 100 - 100,
        [1e3 * abs(mc.lam + (mc.r - mc.r * k) * iq / we) for k in kk],
        "-",
        label="λ + (R−R̂)i_q/ω",
    )
    ax[0].set_xlabel("R̂ error [%]")
    ax[0].set_ylabel("|λ̂| [mV·s]")
    ax[0].legend(fontsize=7)
    ax[1].plot(
        [x * 100 - 100 for x in ls],
        [rr[f"L^={k}L"]["mean_deg"] for k in ls],
        "o",
        label="θ̃ mean sim",
    )
    kk = np.linspace(0.45, 1.55, 50)
    ax[1].plot(
        kk * 100 - 100,
        [math.degrees(math.atan2((mc.l - mc.l * k) * iq, mc.lam)) for k in kk],
        label="atan((L−L̂)i_q/λ)",
    )
    ax[1].set_xlabel("L̂ error [%]")
    ax[1].set_ylabel("θ̃ mean [deg]")
    ax[1].legend(fontsize=7)
    fig.suptitle("Mismatch at 2 % speed, 150 % load (flux observer, measured voltages)", fontsize=9)
    return ctx.fig(fig, "beyond_mismatch")


def mismatch(ctx):
    """The paper observer under R^/L^/lambda^ errors (shadow), current offsets and driven
    errors at 2 %/150 %: build -> run -> analyse -> judge -> plot."""
    mc = ctx.cv  # the card's values (see CardValues)
    base = dict(OBS4["flux_measured"])
    offs = [0.01] if ctx.quick else [0.005, 0.01, 0.02]
    closed = _mismatch_closed(ctx)
    res = ctx.run(_mismatch_jobs(ctx, base, offs, closed))
    r0 = res[0]
    we, iq = r0["we"], r0["iq"]
    rows = _mismatch_rows(mc, r0)
    rr = {x["param"]: x for x in rows}
    off_rows = _mismatch_offset_rows(mc, offs, res[1 : 1 + len(offs)])
    cl_rows = [
        {"param": key, "value": val, "stable": r["metrics"]["stable"]}
        for (key, val), r in zip(closed, res[1 + len(offs) :], strict=True)
    ]
    rpm = ctx.rpm(0.02)  # paper_2pct_150load's speed
    claims = _mismatch_shadow_claims(mc, rr, we, iq, rpm)
    claims.append(_mismatch_offset_claim(off_rows))
    claims += _mismatch_closed_claims(mc, cl_rows, we, iq, rpm)
    figs = [_plot_mismatch(ctx, rr, we, iq)]
    return {
        "claims": claims,
        "figures": figs,
        "data": {"shadow": rows, "offsets": off_rows, "closed_loop": cl_rows, "we": we, "iq": iq},
    }


# ======================================================================== sensitivity
# Steady-state fundamental model of every variant (rotor frame, i_d = 0, i = j i_q).  What the
# observer integrates is x = v - R^ i - L^ di/dt = j(w lam + (R - R^) i_q) - (L - L^) w i_q
# (+ what the voltage source gets wrong); each variant turns x into a flux estimate eta:
#   pure/paper/programmable_lpf : eta = x/(jw)             (inverse HPF exact at w^ = w)
#   lpf             : eta = x/(jw + w_c)
#   emf             : angle of x, minus 90 deg
#   hinkkanen_luomi : eta = x/(jw + c), c = k (|eta| - lam^)/|eta|, k = w_c
#   ortega          : eta = x/(jw + c), c = k (|eta|^2 - lam^2)/(2 lam^2), k = gamma lam^2
# so a *magnitude* error of x (R^ error, deadtime fundamental along the current) is a flux
# magnitude error for the linear observers but an angle error atan(c/w) for the
# magnitude-forcing ones, which also turn a lam^ error into an angle error.
SENS_VARIANTS = ["paper", "lpf", "hinkkanen_luomi", "ortega", "emf"]
# the kernel variant run for each kind: the LPF + inverse HPF kind runs as paper_robust (the
# literal observer's loss of lock after transients would hide the steady-state model; at the
# fundamental both are the same 1/(jw))
SENS_RUN = {"paper": "paper_robust"}


def _mag_forced_rhs(
    kind: str, eta: complex, x: complex, w: float, k: float, lam_hat: float
) -> complex:
    m = abs(eta)
    if kind == "hinkkanen_luomi":
        c = k * (m - lam_hat) / max(m, 1e-12)
    else:  # ortega, gamma = k / lam^2
        c = 0.5 * k / lam_hat**2 * (m * m - lam_hat**2)
    return x - (1j * w + c) * eta


def _mag_forced_eq(kind: str, x: complex, w: float, k: float, lam_hat: float) -> complex | None:
    """Stable equilibrium of eta' = x - (jw + c(|eta|)) eta nearest to lam^ (the correct
    estimate), or None if there is none (the estimate then keeps moving: slips)."""
    xm = abs(x)
    if kind == "hinkkanen_luomi":
        # m^2 w^2 + k^2 (m - lam^)^2 = |x|^2: a quadratic in m
        roots = np.roots([w * w + k * k, -2.0 * k * k * lam_hat, k * k * lam_hat**2 - xm**2])
        ms = [float(r.real) for r in roots if abs(r.imag) < 1e-12 and r.real > 0]
        cs = [k * (m - lam_hat) / m for m in ms]
    else:
        # u = m^2: u (w^2 + g^2 (u - lam^2)^2) = |x|^2, g = k/(2 lam^2): a cubic in u
        g = 0.5 * k / lam_hat**2
        roots = np.roots([g * g, -2 * g * g * lam_hat**2, w * w + g * g * lam_hat**4, -(xm**2)])
        us = [float(r.real) for r in roots if abs(r.imag) < 1e-9 * max(1.0, abs(r)) and r.real > 0]
        cs = [g * (u - lam_hat**2) for u in us]
    best = None
    for c in cs:
        eta = x / (1j * w + c)
        h = 1e-7 * lam_hat  # numerical Jacobian of the real 2-state system
        jac = np.zeros((2, 2))
        for j, dz in enumerate((h, 1j * h)):
            df = (
                _mag_forced_rhs(kind, eta + dz, x, w, k, lam_hat)
                - _mag_forced_rhs(kind, eta - dz, x, w, k, lam_hat)
            ) / (2 * h)
            jac[:, j] = [df.real, df.imag]
        if np.all(np.linalg.eigvals(jac).real < 0) and (
            best is None or abs(eta - lam_hat) < abs(best - lam_hat)
        ):
            best = eta
    return best


def fundamental_estimate(
    mc: CardValues,
    kind: str,
    w: float,
    iq: float,
    *,
    r_err: float = 0.0,
    l_err: float = 0.0,
    lam_hat: float | None = None,
    wc: float = 0.0,
    k: float = 0.0,
    v_err_q: float = 0.0,
) -> complex | None:
    """Rotor-frame flux estimate (true magnet flux = lambda along +real) of a variant in steady
    state; r_err = R - R^, l_err = L - L^, v_err_q an extra EMF error along q [V] (e.g. the
    deadtime fundamental (4/pi) V_dt with commanded voltages).  None: no stable equilibrium."""
    lam_hat = mc.lam if lam_hat is None else lam_hat
    x = 1j * (w * mc.lam + r_err * iq + v_err_q) - l_err * w * iq
    if kind in ("paper", "pure_integrator", "programmable_lpf", "emf"):
        return x / (1j * w)
    if kind == "lpf":
        return x / (1j * w + wc)
    return _mag_forced_eq(kind, x, w, k, lam_hat)


def predicted_angle_deg(mc: CardValues, kind: str, w: float, iq: float, **kw) -> float | None:
    est = fundamental_estimate(mc, kind, w, iq, **kw)
    return None if est is None else math.degrees(np.angle(est))


def offset_h1_pred_deg(
    mc: CardValues, kind: str, w: float, d_ab: float, *, wc: float = 0.0, k: float = 0.0
) -> float | None:
    """First-order theta~ from a DC current-sensor offset |Delta i_ab| = d_ab: the observer
    sees a DC EMF error R^ d_ab; its DC response over the fundamental's magnitude.  For the
    magnitude-forcing observers the linearised (radial r, angle e) dynamics
    r' = -k r + w lam e + Re u,  lam e' = -w r + Im u  are driven at the rotor frequency."""
    d = mc.r * d_ab
    if kind == "pure_integrator":
        return None  # drifts (unbounded)
    if kind in ("paper", "programmable_lpf"):
        ratio = d * math.sqrt(1 / wc**2 + 1 / w**2) / mc.lam
    elif kind == "lpf":
        ratio = (d / wc) / (mc.lam * w / math.hypot(w, wc))
    elif kind == "emf":
        ratio = d / (w * mc.lam)
    else:
        a = np.array([[-k, w * mc.lam], [-w / mc.lam, 0.0]])
        b = np.array([1.0, 1j / mc.lam]) * d
        xs = np.linalg.solve(1j * w * np.eye(2) - a, b)
        return math.degrees(abs(xs[1]))
    return math.degrees(math.asin(min(ratio, 1.0)))


def _x_sens(r, m):
    """Per observer over the steady window: circular mean of theta~, RMS (about zero and
    about the mean), |lambda^|, first-order amplitude, validity."""
    from fluxdrive.analysis.metrics import steady_window

    w = steady_window(r.t, r.scenario.steady_window_s)
    sl = slice(w.k0, w.k1)
    out = {
        "we": float(np.mean(r.truth[sl, TR_WM])) * r.scenario.machine.pole_pairs,
        "iq": float(np.mean(r.ctrl[sl, CO_IQ])),
        "speed": m["speed"],
        "obs": {},
    }
    thu = np.unwrap(r.truth[sl, TR_THETA_E])
    ws = whole_periods(thu)
    for i, nm in enumerate(r.names):
        e = r.est[i, sl]
        err = np.angle(np.exp(1j * (e[:, ES_TH] - r.truth[sl, TR_THETA_E])))
        cm = float(np.angle(np.mean(np.exp(1j * err))))
        ac = np.angle(np.exp(1j * (err - cm)))
        om = m["observers"][nm]
        # first order about the mean: a large mean (lpf: 51 deg) would otherwise leak into
        # order 1 through the speed ripple (time average != angle average)
        out["obs"][nm] = {
            "mean_deg": math.degrees(cm),
            "rms_deg": om["theta_err_rms_deg"],
            "ac_rms_deg": float(np.degrees(np.sqrt(np.mean(ac**2)))),
            "mag": float(np.mean(np.hypot(e[:, ES_LA], e[:, ES_LB]))),
            "h1_deg": math.degrees(abs(harmonic(ac[ws], thu[ws], 1))),
            "valid": om["valid_fraction"],
        }
    return out


def _sens_lists(quick: bool):
    if quick:
        return ([0.85, 1.15], [0.7, 1.3], [0.9, 1.1], [5.0, 20.0, 100.0, 300.0], [0.01])
    return (
        [0.7, 0.85, 1.15, 1.3],
        [0.7, 0.85, 1.15, 1.3],
        [0.9, 0.95, 1.05, 1.1],
        [2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 300.0],
        [0.0025, 0.005, 0.01, 0.02],
    )


def _cut(kind: str, f_hz: float) -> dict:
    """The variant's cut-off knob at f_hz: w_c for paper/lpf/hinkkanen_luomi, the equivalent
    magnitude-loop rate gamma lam^2 = 2 pi f for ortega."""
    return {"gamma_bw_rad_s": 2 * math.pi * f_hz} if kind == "ortega" else {"cutoff_hz": f_hz}


def _default_k(card: MachineCard, kind: str) -> tuple[float, float]:
    """(w_c, k) of a variant's defaults on the runs' card [rad/s]."""
    c = observer_config(kind, card=card)
    wc = 2 * math.pi * float(c.cutoff_hz or 0.0)
    return wc, float(c.gamma_bw_rad_s or 0.0) if kind == "ortega" else wc


STEADY_AC_DEG = 10.0  # an estimate whose theta~ wanders more than this about its mean slips


def _sens_observers(mc: CardValues, kind: str, lists) -> dict:
    """One encoder run's shadow observers for `kind`: nominal, each R^/L^/lambda^ error and
    (not emf, which has no cut-off) each cut-off."""
    rs, ls, lams, cuts, _ = lists
    base = {"variant": SENS_RUN.get(kind, kind), "voltage_source": "measured"}
    obs = {f"{kind}_nom": base}
    for f in rs:
        obs[f"{kind}_r{round(100 * f):03d}"] = {**base, "r_hat_ohm": mc.r * f}
    for f in ls:
        obs[f"{kind}_l{round(100 * f):03d}"] = {**base, "l_hat_h": mc.l * f}
    for f in lams:
        obs[f"{kind}_lam{round(100 * f):03d}"] = {**base, "lambda_hat_vs": mc.lam * f}
    if kind != "emf":
        for f in cuts:
            obs[f"{kind}_fc{round(10 * f):04d}"] = {**base, **_cut(kind, f)}
    return obs


def _sens_control_observers(cuts) -> dict:
    """The magnitude-forcing observers' cut-off sweep (up to 20 Hz) for the control runs."""
    return {
        f"{kind}_fc{round(10 * f):04d}": {"variant": SENS_RUN.get(kind, kind), **_cut(kind, f)}
        for kind in ("hinkkanen_luomi", "ortega")
        for f in cuts
        if f <= 20
    }


def _sens_jobs(ctx, speed: float, load: float, lists) -> list:
    """Build: one encoder run per variant, one per current offset (every variant nominal),
    then the two controls (ideal inverter; ideal sensors with the 2 us deadtime)."""
    offs, cuts = lists[4], lists[3]
    jobs = [
        (
            ctx.encoder_run(
                speed, load, observers=_sens_observers(ctx.cv, kind, lists), name=f"sens_{kind}"
            ),
            _x_sens,
            None,
        )
        for kind in SENS_VARIANTS
    ]
    nominal = {
        f"{kind}_nom": {"variant": SENS_RUN.get(kind, kind), "voltage_source": "measured"}
        for kind in SENS_VARIANTS
    }
    for o in offs:
        run = ctx.encoder_run(
            speed,
            load,
            observers=nominal,
            name="sens_offset",
            faults={"current_offset_pu": [0.0, o, 0.0]},
        )
        jobs.append((run, _x_sens, None))
    # control: the magnitude-forcing observers' cut-off sweep with an ideal inverter
    obs = _sens_control_observers(cuts)
    no_dt = ctx.encoder_run(
        speed, load, observers=obs, name="sens_no_deadtime", plant={"deadtime_s": 0.0}
    )
    jobs.append((no_dt, _x_sens, None))
    # and with ideal sensors (no noise, 24-bit ADCs and capture) but the 2 us deadtime
    ideal_kw = {
        "current_noise_a": 0.0,
        "current_adc_bits": 24,
        "capture_bits": 24,
        "dc_bus_adc_bits": 24,
    }
    ideal = ctx.encoder_run(
        speed, load, observers=obs, name="sens_ideal_sensors", machine_kw=ideal_kw
    )
    jobs.append((ideal, _x_sens, None))
    return jobs


def _sens_row(mc: CardValues, kind: str, w: float, iq: float, obs_row: dict, **x) -> dict:
    """One measured row next to the fundamental model's angle and magnitude."""
    est = fundamental_estimate(mc, kind, w, iq, **x)
    return {
        **obs_row,
        "steady": obs_row["ac_rms_deg"] < STEADY_AC_DEG,
        "pred_deg": None if est is None else math.degrees(np.angle(est)),
        "pred_mag": None if est is None else abs(est),
    }


def _sens_kind_table(ctx, kind: str, o: dict, w: float, iq: float, lists, off_res) -> dict:
    """Analyse one variant: every error row against the model, every offset row against the
    first-order prediction."""
    mc = ctx.cv
    rs, ls, lams, cuts, offs = lists
    wc, k = _default_k(ctx.card, kind)
    dk = {"wc": wc, "k": k}
    t = {"nom": _sens_row(mc, kind, w, iq, o[f"{kind}_nom"], **dk)}
    for f in rs:
        x = o[f"{kind}_r{round(100 * f):03d}"]
        t[f"r{f}"] = _sens_row(mc, kind, w, iq, x, **dk, r_err=mc.r * (1 - f))
    for f in ls:
        x = o[f"{kind}_l{round(100 * f):03d}"]
        t[f"l{f}"] = _sens_row(mc, kind, w, iq, x, **dk, l_err=mc.l * (1 - f))
    for f in lams:
        x = o[f"{kind}_lam{round(100 * f):03d}"]
        t[f"lam{f}"] = _sens_row(mc, kind, w, iq, x, **dk, lam_hat=mc.lam * f)
    if kind != "emf":
        for f in cuts:
            kk = 2 * math.pi * f
            x = o[f"{kind}_fc{round(10 * f):04d}"]
            t[f"fc{f}"] = {**_sens_row(mc, kind, w, iq, x, wc=kk, k=kk), "k": kk}
    for o_pu, rr in zip(offs, off_res, strict=True):
        d_ab = o_pu * mc.i_rated * math.sqrt(1 / 9 + 1 / 3)
        x = rr["obs"][f"{kind}_nom"]
        t[f"off{o_pu}"] = {
            **x,
            "steady": x["ac_rms_deg"] < STEADY_AC_DEG + x["h1_deg"],
            "pred_h1_deg": offset_h1_pred_deg(mc, kind, w, d_ab, wc=wc, k=k),
        }
    return t


def _sens_fc_means(r: dict, cuts) -> dict:
    """A control run's mean theta~ per magnitude-forcing observer and cut-off."""
    return {
        f"{kind}_fc{f}": r["obs"][f"{kind}_fc{round(10 * f):04d}"]["mean_deg"]
        for kind in ("hinkkanen_luomi", "ortega")
        for f in cuts
        if f <= 20
    }


def sensitivity(ctx):
    """Every variant under parameter errors, offsets and cut-offs against its steady-state
    fundamental model: build -> run -> analyse -> judge -> plot."""
    mc = ctx.cv  # the card's values (see CardValues)
    lists = _sens_lists(ctx.quick)
    rs, ls, lams, cuts, offs = lists
    speed, load = ctx.rpm(0.02), 1.5
    res = ctx.run(_sens_jobs(ctx, speed, load, lists))
    nv = len(SENS_VARIANTS)
    per = dict(zip(SENS_VARIANTS, res[:nv], strict=True))
    off_res = res[nv : nv + len(offs)]
    w, iq = per["paper"]["we"], per["paper"]["iq"]
    tab = {
        kind: _sens_kind_table(ctx, kind, per[kind]["obs"], w, iq, lists, off_res)
        for kind in SENS_VARIANTS
    }
    nd, ids = _sens_fc_means(res[-2], cuts), _sens_fc_means(res[-1], cuts)
    claims = _sens_claims(mc, tab, lists, w, nd, ids, speed, ctx.card)
    figs = [_plot_sens(ctx, tab, rs, ls, lams, cuts, offs, w, iq)]
    return {
        "claims": claims,
        "figures": figs,
        "data": {
            "table": tab,
            "no_deadtime_mean_deg": nd,
            "ideal_sensors_mean_deg": ids,
            "we_rad_s": w,
            "iq_a": iq,
            "speed_rpm": speed,
            "load_pu": load,
        },
    }


def _wrapdiff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _label(key: str) -> str:
    for pre, lab in (("lam", "λ̂="), ("r", "R̂="), ("l", "L̂="), ("fc", "f_c=")):
        if key.startswith(pre):
            return lab + key[len(pre) :]
    return key


# what the fundamental model says each variant makes of the parameter errors
SENS_DESC = {
    "paper": "R̂: magnitude only, |λ̂| = λ + ΔR i_q/ω (a 180° flip once ΔR i_q < −ωλ); "
    "L̂: angle atan(ΔL i_q/λ); λ̂: nothing",
    "lpf": "a lead atan(ω_c/ω) whatever the parameters (no compensation); parameter "
    "errors add on top as for paper",
    "hinkkanen_luomi": "magnitude errors (R̂, λ̂) become angle errors atan(c/ω), c the "
    "correction that pulls |η| back to λ̂; L̂: as paper",
    "ortega": "as hinkkanen_luomi with the stiffer default loop γλ² = {k:.0f} s⁻¹",
    "emf": "the EMF angle: R̂ (along q) no angle, L̂ atan(ΔL i_q/λ), λ̂ unused",
}


def _sens_sort(t: dict, keys: list[str]) -> tuple[list, list, list, list]:
    """(compared, no model equilibrium, slipping, off the model) among the error rows."""
    used, no_eq, slip, bad = [], [], [], []
    for k in keys:
        x = t[k]
        if x["pred_deg"] is None:
            no_eq.append(k)
        elif not x["steady"]:
            slip.append(k)
        else:
            used.append(k)
            if _wrapdiff(x["mean_deg"], x["pred_deg"]) > 3.0 + 0.1 * abs(x["pred_deg"]):
                bad.append(k)
    return used, no_eq, slip, bad


def _sens_row_txt(x: dict, k: str) -> str:
    pr = "no equilibrium" if x["pred_deg"] is None else f"{x['pred_deg']:.1f}°"
    tag = "" if x["steady"] else ", slips"
    return f"{_label(k)}: {x['mean_deg']:.1f}° (model {pr}{tag})"


def _sens_kind_why(
    kind: str, nom: dict, no_eq: list, slip: list, bad: list, rpm: float, mc: CardValues, w, k
) -> str:
    why = []
    if no_eq:
        why.append(
            f"no stable equilibrium in the model at {', '.join(map(_label, no_eq))} "
            "(the magnitude loop cannot hold |η| at λ̂ with the |x| it is given: "
            "the estimate keeps turning)"
        )
    if slip:
        why.append(
            f"the estimate slips (θ̃ wanders > {STEADY_AC_DEG:.0f}° about its mean) "
            f"at {', '.join(map(_label, slip))}"
        )
    if bad:
        why.append(f"off the model at {', '.join(map(_label, bad))}")
    if kind == "ortega" and not nom["steady"]:
        why.append(
            f"even with exact parameters the default γλ² = {k:.0f} s⁻¹ slips at {rpm:.0f} rpm: "
            f"its angle-error pole ω²/k = {w * w / k:.2g} s⁻¹ barely corrects, and a q-axis EMF "
            f"residue δ gives k δ/(ω²λ) ≈ {_deg_per_mv(mc, k, w):.2g}° per mV (cut-off row)"
        )
    return "; ".join(why)


def _sens_kind_claim(kind: str, t: dict, lists, rpm: float, mc: CardValues, w, k) -> dict:
    """Judge one variant's R^/L^/lambda^ rows against its fundamental model (k: ortega's
    default gamma lambda^2 on the card [rad/s], w the electrical speed [rad/s])."""
    rs, ls, lams = lists
    keys = [f"r{f}" for f in rs] + [f"l{f}" for f in ls] + [f"lam{f}" for f in lams]
    used, no_eq, slip, bad = _sens_sort(t, keys)
    nom = t["nom"]
    return claim(
        f"{kind} (measured voltages, {rpm:.0f} rpm, 150 %): mean θ̃ under R̂ ±30 %, L̂ ±30 %, "
        f"λ̂ ±10 % follows the steady-state fundamental model where the estimate is "
        f"steady — {SENS_DESC[kind].format(k=k)}",
        f"nominal {nom['mean_deg']:.2f}° (RMS {nom['rms_deg']:.2f}°); "
        + "; ".join(_sens_row_txt(t[k], k) for k in keys)
        + f"; compared at {len(used)}/{len(keys)}",
        bool(used) and not bad,
        _sens_kind_why(kind, nom, no_eq, slip, bad, rpm, mc, w, k),
    )


def _sens_offset_claim(tab: dict, offs) -> dict:
    rows, ok = [], True
    for kind, t in tab.items():
        parts = []
        for o in offs:
            x = t[f"off{o}"]
            pr = x["pred_h1_deg"]
            parts.append(
                f"{100 * o:g} %: {x['h1_deg']:.2f}° (model "
                f"{'drift' if pr is None else f'{pr:.2f}°'}"
                f"{'' if x['steady'] else ', slips'})"
            )
            if pr is not None and x["steady"] and kind != "lpf":
                ok = ok and abs(x["h1_deg"] - pr) < 0.35 * pr + 0.3
        rows.append(f"{kind}: " + ", ".join(parts))
    return claim(
        "Current-sensor offset on i_b: first-order θ̃ = the DC EMF error R̂|Δi_αβ| through each "
        "variant's DC gain over its fundamental gain (paper √(1/ω_c² + 1/ω²), emf 1/ω, "
        "hinkkanen_luomi/ortega their linearised magnitude loop r' = −k r + ωλe + Re u, "
        "λe' = −ω r + Im u driven at the rotor frequency)",
        "; ".join(rows),
        ok,
        "paper/emf sit ~15 % under the model (the PLL and the compensation frequency, itself "
        "rippling at the rotor frequency, smooth the first order a little); ortega slips at "
        "its default gain with or without an offset (rows above).  lpf (model: 1/ω_c over "
        "ω/√(ω²+ω_c²)) is 2× above: its uncompensated lead atan(ω_c/ω) also turns the "
        "offset's first-order speed ripple (the encoder drive's torque ripple K_t|Δi|) into "
        "angle, dθ̃/dω = −ω_c/(ω²+ω_c²)",
    )


def _sens_cutoff_claim(tab: dict, cuts, w: float) -> dict:
    lpf_used = [f for f in cuts if tab["lpf"][f"fc{f}"]["steady"]]
    lpf_ok = all(
        _wrapdiff(tab["lpf"][f"fc{f}"]["mean_deg"], tab["lpf"][f"fc{f}"]["pred_deg"]) < 3.0
        for f in lpf_used
    )
    return claim(
        "Cut-off: the uncompensated LPF leads by atan(ω_c/ω); LPF + inverse HPF removes that "
        "(mean ≈ 0 at any ω_c)",
        "; ".join(
            f"{kind}: "
            + ", ".join(
                f"{f:g} Hz {tab[kind][f'fc{f}']['mean_deg']:.1f}° (RMS "
                f"{tab[kind][f'fc{f}']['rms_deg']:.2f}°)"
                for f in cuts
            )
            for kind in ("lpf", "paper")
        ),
        lpf_ok and all(abs(tab["paper"][f"fc{f}"]["mean_deg"]) < 2.0 for f in cuts),
        f"the lpf's |λ̂| = λω/√(ω²+ω_c²) is {w / math.hypot(w, 2 * math.pi * cuts[0]):.2g}λ at "
        f"{cuts[0]:g} Hz and {w / math.hypot(w, 2 * math.pi * cuts[-1]):.2g}λ at {cuts[-1]:g} "
        "Hz, below the 0.3λ validity band for any f_c above ω√(1/0.3² − 1)/2π = "
        f"{w * math.sqrt(1 / 0.09 - 1) / (2 * math.pi):.2g} Hz: a drive could not use it "
        "there; the paper's RMS rises slowly with ω_c "
        "(the inverse HPF gain ω_c/ω amplifies what the LPF lets through)",
    )


def _sens_fit_delta(mc: CardValues, t: dict, cuts, w: float) -> tuple[float, list] | None:
    """The q-axis EMF residue delta [mV] fitted to theta~ = k delta/(w^2 lam) over the
    small-signal regime of the linearisation: from the lowest gain up to the first point that
    slips, leaves |theta~| < 5 deg or changes sign (theta~ keeps the sign of delta while it is
    linear); None below two points."""
    fs: list[float] = []
    for f in cuts:
        mean = t[f"fc{f}"]["mean_deg"]
        if not (t[f"fc{f}"]["steady"] and abs(mean) < 5.0):
            break
        if fs and mean * t[f"fc{fs[-1]}"]["mean_deg"] < 0.0:
            break
        fs.append(f)
    if len(fs) < 2:
        return None
    kk = np.array([2 * math.pi * f for f in fs])
    y = np.radians([t[f"fc{f}"]["mean_deg"] for f in fs])
    # through the origin: e = k delta / (w^2 lam)
    slope = float(np.sum(kk * y) / np.sum(kk * kk))
    return 1e3 * slope * w * w * mc.lam, fs


def _sens_gain_why(mc: CardValues, deltas: dict, slips: dict, w: float) -> str:
    return (
        f"the residue "
        f"({100 * abs(np.mean([v[0] for v in deltas.values()])) / (1e3 * w * mc.lam):.1f}"
        " % of the back-EMF ωλ) comes with the deadtime: it vanishes with an ideal inverter "
        "and stays with ideal sensors, so it is not quantisation or noise; the likely "
        "mechanism is that the valley-sampled current no longer equals the period average "
        "once deadtime distorts the PWM ripple (R × a few mA)."
        + (
            "  Slips at "
            + ", ".join(f"{n}: {v} Hz" for n, v in slips.items() if v)
            + ": the best k is of the order of ω (characteristic s² + k s + ω²), far below "
            "the defaults meant for higher speeds"
            if any(slips.values())
            else ""
        )
    )


def _sens_gain_claim(
    mc: CardValues, tab: dict, cuts, w: float, nd: dict, ids: dict, td_s: float
) -> dict:
    """Judge the magnitude-forcing pair's cut-off sweep: one residue delta for both."""
    pair = (("hinkkanen_luomi", tab["hinkkanen_luomi"]), ("ortega", tab["ortega"]))
    deltas = {}
    for name, t in pair:
        fit = _sens_fit_delta(mc, t, cuts, w)
        if fit is not None:
            deltas[name] = fit
    slips = {name: [f for f in cuts if not t[f"fc{f}"]["steady"]] for name, t in pair}
    ok = (
        len(deltas) == 2
        and abs(deltas["hinkkanen_luomi"][0] - deltas["ortega"][0])
        < 0.3 * max(abs(v[0]) for v in deltas.values())
        and all(abs(v) < 0.3 for v in nd.values())
    )
    return claim(
        "Cut-off (equivalent gain k = 2π f: w_c of hinkkanen_luomi, γλ² of ortega): both turn "
        "a small q-axis EMF residue δ into θ̃ ≈ k δ/(ω²λ) (linearised angle pole ω²/k), so "
        "they show the same δ, and θ̃ grows with k until the estimate slips",
        "; ".join(
            f"{name}: "
            + ", ".join(
                f"{f:g} Hz {t[f'fc{f}']['mean_deg']:.2f}°"
                f"{'' if t[f'fc{f}']['steady'] else ' (slips)'}"
                for f in cuts
            )
            for name, t in pair
        )
        + "; fitted δ (low-gain end, |θ̃| < 5°): "
        + ", ".join(f"{n} {v[0]:.2f} mV" for n, v in deltas.items())
        + "; ideal inverter (no deadtime): "
        + ", ".join(f"{k.replace('_fc', ' ')} Hz {v:.2f}°" for k, v in nd.items())
        + f"; ideal sensors, {1e6 * td_s:g} µs deadtime: "
        + ", ".join(f"{k.replace('_fc', ' ')} Hz {v:.2f}°" for k, v in ids.items()),
        ok,
        _sens_gain_why(mc, deltas, slips, w),
    )


def _sens_claims(mc: CardValues, tab, lists, w, nd, ids, rpm: float, card: MachineCard):
    """Judge: one claim per variant, then the offsets, the cut-off, the magnitude-forcing
    pair's gain sweep."""
    rs, ls, lams, cuts, offs = lists
    k_ortega, td_s = _default_k(card, "ortega")[1], card.deadtime_s
    claims = [
        _sens_kind_claim(kind, t, (rs, ls, lams), rpm, mc, w, k_ortega) for kind, t in tab.items()
    ]
    claims.append(_sens_offset_claim(tab, offs))
    claims.append(_sens_cutoff_claim(tab, cuts, w))
    claims.append(_sens_gain_claim(mc, tab, cuts, w, nd, ids, td_s))
    return claims


def _pts(a, xs, ys, steady, c, label=None):
    """Measured points: filled where the estimate is steady, open where it slips."""
    xs, ys, steady = np.array(xs), np.array(ys, dtype=float), np.array(steady)
    a.plot(xs[steady], ys[steady], "o", color=c, ms=5, label=label)
    a.plot(xs[~steady], ys[~steady], "o", mfc="none", color=c, ms=6)


def _line(a, xs, ys, c, ls="-"):
    """The model, where it has an equilibrium."""
    xy = [(x, y) for x, y in zip(xs, ys, strict=True) if y is not None]
    if xy:
        a.plot(*zip(*xy, strict=True), ls, color=c, lw=1)


def _plot_sens_kind(ax, t: dict, kind: str, c: str, lam: float, rs, ls, lams, cuts, offs):
    """One variant's points and model lines on every panel."""
    for a, keys, xs, ttl in (
        (ax[0, 0], [f"r{f}" for f in rs], [100 * f - 100 for f in rs], "R̂ error [%]"),
        (ax[0, 2], [f"l{f}" for f in ls], [100 * f - 100 for f in ls], "L̂ error [%]"),
        (ax[1, 0], [f"lam{f}" for f in lams], [100 * f - 100 for f in lams], "λ̂ error [%]"),
    ):
        _pts(a, xs, [t[k]["mean_deg"] for k in keys], [t[k]["steady"] for k in keys], c, kind)
        _line(a, xs, [t[k]["pred_deg"] for k in keys], c)
        a.set_xlabel(ttl)
        a.set_ylabel("circular mean θ̃ [deg]")
    xs = [100 * f - 100 for f in rs]
    rows = [t[f"r{f}"] for f in rs]
    _pts(ax[0, 1], xs, [x["mag"] / lam for x in rows], [x["steady"] for x in rows], c, kind)
    pred = [None if x["pred_mag"] is None else x["pred_mag"] / lam for x in rows]
    _line(ax[0, 1], xs, pred, c)
    xs = [100 * o for o in offs]
    rows = [t[f"off{o}"] for o in offs]
    _pts(ax[1, 1], xs, [x["h1_deg"] for x in rows], [x["steady"] for x in rows], c, kind)
    _line(ax[1, 1], xs, [x["pred_h1_deg"] for x in rows], c)
    if kind != "emf":
        rows = [t[f"fc{f}"] for f in cuts]
        _pts(
            ax[1, 2], cuts, [abs(x["mean_deg"]) for x in rows], [x["steady"] for x in rows], c, kind
        )
        ax[1, 2].plot(cuts, [x["rms_deg"] for x in rows], ":", color=c, lw=1)


def _sens_titles(ax) -> None:
    ax[0, 0].set_title("R̂: mean θ̃ (o steady, ○ slips; — model)", fontsize=9)
    ax[0, 1].set_title("R̂: |λ̂|/λ (emf: |ê|/ω̂)", fontsize=9)
    ax[0, 1].set_xlabel("R̂ error [%]")
    ax[0, 1].set_ylabel("|λ̂| / λ")
    ax[0, 1].set_yscale("log")
    ax[0, 2].set_title("L̂: angle atan((L−L̂) i_q/λ) (lpf: on top of its lead)", fontsize=9)
    ax[1, 0].set_title("λ̂: an angle only for the magnitude-forcing observers", fontsize=9)
    ax[1, 1].set_title("phase-b current offset: first-order θ̃", fontsize=9)
    ax[1, 1].set_xlabel("offset [% of rated]")
    ax[1, 1].set_ylabel("θ̃ 1st order [deg]")
    ax[1, 1].set_yscale("log")
    ax[1, 2].set_title(
        "cut-off (ortega: γλ² = 2π f): |mean θ̃| (o), RMS (:), lpf model —", fontsize=9
    )
    ax[1, 2].set_xscale("log")
    ax[1, 2].set_yscale("log")
    ax[1, 2].set_xlabel("cut-off f [Hz]")
    ax[1, 2].set_ylabel("θ̃ [deg]")
    for a in ax.flat:
        a.grid(alpha=0.3, which="both")
    ax[0, 0].legend(fontsize=7)


def _plot_sens(ctx, tab, rs, ls, lams, cuts, offs, w, iq):
    mc = ctx.cv  # the card's values (see CardValues)
    p = plt()
    fig, ax = p.subplots(2, 3, figsize=(14, 7.5))
    col = {k: f"C{i}" for i, k in enumerate(tab)}
    for kind, t in tab.items():
        _plot_sens_kind(ax, t, kind, col[kind], mc.lam, rs, ls, lams, cuts, offs)
    kk = np.geomspace(min(cuts), max(cuts), 50)
    ax[1, 2].plot(kk, np.degrees(np.arctan(2 * np.pi * kk / w)), "-", color=col["lpf"], lw=1)
    _sens_titles(ax)
    rpm = w / mc.p * RAD_S_TO_RPM
    fig.suptitle(
        f"Sensitivity per variant: encoder drive at {rpm:.0f} rpm, 150 % load "
        f"(ω = {w:.1f} rad/s, i_q = {iq:.1f} A), observers in shadow, measured "
        "voltages",
        fontsize=10,
    )
    return ctx.fig(fig, "beyond_sensitivity")


# ======================================================================== speed reversal
def reversal(
    load_pu: float,
    load_type: str,
    *,
    seed: int = 1,
    if_current_pu: float = 1.0,
    speed_rpm: float | None = None,
    reverse_s: float = 1.2,
    name: str = "reversal",
    card: str | Path | None = None,
):
    """Sensorless flux drive (measured voltages): start, +speed_rpm (default 2 % of the rated
    speed of `card`), load ramped in, steady, then a reference ramp to -speed_rpm through zero
    (hand-back to I-f below handback_rpm, handover again past -handover_rpm), steady on the
    other side."""
    speed_rpm = pu_rpm(0.02, card) if speed_rpm is None else speed_rpm
    start = pu_rpm(START_PU, card)
    t_full = 0.6 + max(load_pu / 0.19, 0.5)  # the paper's ramp rate (speed-loop lag ~33 rpm)
    t_rev = t_full + 1.5
    t_neg = t_rev + reverse_s
    dur = t_neg + 2.5
    return build(
        card=card,
        name=name,
        duration_s=round(dur, 4),
        seed=seed,
        speed_rpm=[[0.0, speed_rpm], [t_rev, speed_rpm], [t_neg, -speed_rpm]],
        load_type=load_type,
        load_pu=[[0.0, 0.0], [0.6, 0.0], [t_full, load_pu]],
        steady_window_s=[round(dur - 1.0, 4), round(dur, 4)],
        driving="flux_measured",
        control={
            "if_current_pu": if_current_pu,
            "handover_rpm": start,
            "handback_rpm": 0.5 * start,
        },
        observers={"flux_measured": VARIANTS["flux_measured"]},
        extra={"t_reverse_s": t_rev},
    )


def _x_reversal(r, m):
    t = r.t
    ts = r.scenario.machine.ts_s
    t_rev = float(r.scenario.extra["t_reverse_s"])
    th = r.truth[:, TR_THETA_E]
    err = np.degrees(np.angle(np.exp(1j * (r.estimate("flux_measured")[:, ES_TH] - th))))
    ang = np.degrees(np.angle(np.exp(1j * (r.ctrl[:, CO_TH] - th))))  # what the FOC uses
    mode = r.ctrl[:, CO_MODE]
    rpm = r.truth[:, TR_WM] * RAD_S_TO_RPM
    ref = r.w_ref * RAD_S_TO_RPM
    k_rev = int(t_rev / ts)
    after = np.arange(len(t)) >= k_rev
    k_back = np.nonzero(after & (mode == MODE_IF_RAMP))[0]
    out = {
        "stable": False,
        "fault": FAULT_NAMES.get(m["fault_code"], "?"),
        "handback_s": None,
        "handover_s": None,
        "if_time_s": 0.0,
    }
    pos = slice(k_rev - int(1.0 / ts), k_rev)
    out["rms_pos_deg"] = float(np.sqrt(np.mean(err[pos] ** 2)))
    neg = slice(len(t) - int(1.0 / ts), len(t))
    out["rms_neg_deg"] = float(np.sqrt(np.mean(err[neg] ** 2)))
    out["mean_neg_rpm"] = float(np.mean(rpm[neg]))
    if k_back.size:
        kb = int(k_back[0])
        k_ho = np.nonzero((np.arange(len(t)) > kb) & (mode == MODE_CLOSED_LOOP))[0]
        out["handback_s"] = float(t[kb])
        out["handback_ref_rpm"] = float(ref[kb])
        out["if_time_s"] = float(np.sum(after & (mode == MODE_IF_RAMP)) * ts)
        k_end = int(k_ho[0]) if k_ho.size else len(t)
        in_if = slice(kb, k_end)
        out["if_load_angle_max_deg"] = float(np.max(np.abs(ang[in_if])))
        out["if_slip_max_rpm"] = float(np.max(np.abs(rpm[in_if] - ref[in_if])))
        pre = slice(max(kb - int(0.3 / ts), 0), kb)
        out["peak_before_handback_deg"] = float(np.max(np.abs(err[pre])))
        if k_ho.size:
            kh = int(k_ho[0])
            out["handover_s"] = float(t[kh])
            out["handover_ref_rpm"] = float(ref[kh])
            post = slice(kh, min(kh + int(0.5 / ts), len(t)))
            out["peak_after_handover_deg"] = float(np.max(np.abs(err[post])))
            out["err_at_handover_deg"] = float(err[kh])
        out["stable"] = bool(
            m["stable"]
            and k_ho.size
            and out["if_load_angle_max_deg"] < 90.0
            and mode[-1] == MODE_CLOSED_LOOP
        )
    sl = slice(max(k_rev - int(0.5 / ts), 0), min(k_rev + int(3.0 / ts), len(t)), 20)
    out["series"] = {
        "t": t[sl],
        "rpm": rpm[sl],
        "ref": ref[sl],
        "est_rpm": (
            r.estimate("flux_measured")[sl, ES_W] * RAD_S_TO_RPM / r.scenario.machine.pole_pairs
        ),
        "err": err[sl],
        "ang": ang[sl],
        "iq": r.ctrl[sl, CO_IQ],
        "id": r.ctrl[sl, CO_ID],
        "mode": mode[sl],
    }
    return out


def _reversal_jobs(ctx, cases) -> tuple[list, list]:
    jobs, keys = [], []
    for lt, lp, seeds in cases:
        for seed in seeds:
            sc = reversal(lp, lt, seed=seed, name=f"rev_{lt}", card=ctx.machine)
            jobs.append((sc, _x_reversal, None))
            keys.append((lt, lp, seed))
    return jobs, keys


def _reversal_summary(rr: list[dict], lp: float, i_if: float) -> str:
    def agg(k, f=max):
        v = [x[k] for x in rr if x.get(k) is not None]
        return f(v) if v else float("nan")

    ld = math.degrees(math.asin(lp / i_if)) if lp < i_if else float("nan")
    return (
        f"stable {sum(x['stable'] for x in rr)}/{len(rr)} seeds; I-f {agg('if_time_s', min):.2f}-"
        f"{agg('if_time_s'):.2f} s (hand-back at ref {agg('handback_ref_rpm'):.0f} rpm, "
        f"handover at {agg('handover_ref_rpm', min):.0f} rpm); θ̃ RMS +side "
        f"{agg('rms_pos_deg'):.2f}°, −side {agg('rms_neg_deg'):.2f}°; peak θ̃ "
        f"{agg('peak_before_handback_deg'):.1f}° before hand-back, "
        f"{agg('peak_after_handover_deg'):.1f}° in the 0.5 s after handover; I-f load "
        f"angle ≤ {agg('if_load_angle_max_deg'):.0f}° (asin({lp:g}/{i_if:g}) = {ld:.0f}°)"
        f", slip ≤ {agg('if_slip_max_rpm'):.0f} rpm; faults {sorted({x['fault'] for x in rr})}"
    )


def _reversal_held_claim(ctx, lt: str, lp: float, i_if: float, rr: list[dict]) -> dict:
    card, n_ok = ctx.card, sum(x["stable"] for x in rr)
    start = ctx.rpm(START_PU)
    kt = 1.5 * card.pole_pairs * card.flux_linkage_vs
    delta = math.asin(lp / i_if)
    swing = math.sqrt(
        card.pole_pairs * kt * i_if * card.rated_current_a * math.cos(delta) / card.inertia_kgm2
    ) / (2 * math.pi)
    why = (
        "the brake (the paper's hysteresis dyno) opposes the motion, so its torque flips sign "
        "near zero speed: the I-f load angle swings from +asin(T/K_tI) to −asin(T/K_tI) while "
        "the speed passes zero; an active load (a hoist) keeps its sign, so the drive motors on "
        "one side and brakes (regenerates) on the other, and the I-f vector must hold the load "
        "at standstill.  In I-f the rotor swings about the vector at √(p K_t I_if cos δ/J) ≈ "
        f"{swing:.0f} Hz, undamped by the current loop (the speed ripple in the figure)"
    )
    return claim(
        f"Sensorless reversal +{ctx.rpm(0.02):.0f} → −{ctx.rpm(0.02):.0f} rpm through zero "
        f"under {lt} load ({lp:g} pu, I-f current {i_if:g} pu): no loss of synchronism, "
        f"hand-back to I-f below {0.5 * start:.0f} rpm and handover again past −{start:.0f} rpm",
        _reversal_summary(rr, lp, i_if),
        n_ok == len(rr),
        why if n_ok == len(rr) else "see the figure",
    )


def _reversal_limit_claim(lp: float, i_if: float, rr: list[dict]) -> dict:
    x0, n_ok = rr[0], sum(x["stable"] for x in rr)
    ours = (
        f"stable {n_ok}/{len(rr)}: hand-back at ref "
        f"{x0.get('handback_ref_rpm', float('nan')):.0f} rpm, then pulled out of "
        f"step (load angle up to {x0.get('if_load_angle_max_deg', float('nan')):.0f}°,"
        f" slip up to {x0.get('if_slip_max_rpm', float('nan')):.0f} rpm), fault "
        f"{x0['fault']}; θ̃ RMS on the + side {x0['rms_pos_deg']:.2f}°"
    )
    return claim(
        f"Limit: an active load above what the I-f current carries ({lp:g} pu > "
        f"K_t I_if = {i_if:g} pu) cannot be taken through zero open-loop",
        ours,
        n_ok == 0,
        "the I-f vector holds at most K_t I_if (load angle 90°); the hand-back places it at "
        f"asin(0.9) = {math.degrees(math.asin(0.9)):.0f}° and the load pulls the rotor out of "
        "step: I-f through zero needs I_if above the load, or a sensorless method that sees "
        "standstill (signal injection)",
    )


def speed_reversal(ctx):
    """Sensorless reversal through zero under brake and active loads: build -> run ->
    judge -> plot."""
    if ctx.quick:
        cases = [("brake", 0.4, [1])]
    else:
        cases = [("brake", 0.4, [1, 2, 3]), ("active", 0.4, [1, 2, 3]), ("active", 1.2, [1])]
    jobs, keys = _reversal_jobs(ctx, cases)
    res = ctx.run(jobs)
    rows: dict = {}
    for (lt, lp, seed), x in zip(keys, res, strict=True):
        rows.setdefault(f"{lt} {lp:g} pu", []).append(
            {"seed": seed, **{k: v for k, v in x.items() if k != "series"}}
        )
    i_if = 1.0  # reversal()'s I-f current [pu]
    claims = [
        _reversal_held_claim(ctx, lt, lp, i_if, rows[f"{lt} {lp:g} pu"])
        if lp < i_if
        else _reversal_limit_claim(lp, i_if, rows[f"{lt} {lp:g} pu"])
        for lt, lp, _ in cases
    ]
    figs = [_plot_reversal(ctx, cases, keys, res)]
    return {"claims": claims, "figures": figs, "data": {"runs": rows}}


def _plot_reversal(ctx, cases, keys, res):
    p = plt()
    fig, ax = p.subplots(4, len(cases), figsize=(5.5 * len(cases), 9), sharex="col", squeeze=False)
    for c, (lt, lp, _) in enumerate(cases):
        x = next(r for (a, b, _), r in zip(keys, res, strict=True) if (a, b) == (lt, lp))
        s = x["series"]
        ax[0, c].plot(s["t"], s["rpm"], lw=0.8, label="rotor")
        ax[0, c].plot(s["t"], s["est_rpm"], lw=0.6, alpha=0.7, label="estimate")
        ax[0, c].plot(s["t"], s["ref"], "k--", lw=0.7, label="reference")
        ax[0, c].set_ylim(-150, 150)
        ax[0, c].set_title(f"{lt} load {lp:g} pu, I-f 1 pu (seed 1)", fontsize=9)
        ax[1, c].plot(s["t"], s["err"], lw=0.5, label="θ̃ flux observer")
        ax[1, c].plot(s["t"], s["ang"], lw=0.8, label="FOC angle − θ (I-f: load angle)")
        ax[1, c].set_ylim(-185, 185)
        ax[2, c].plot(s["t"], s["id"], lw=0.6, label="i_d")
        ax[2, c].plot(s["t"], s["iq"], lw=0.6, label="i_q")
        ax[3, c].plot(s["t"], s["mode"], lw=0.9)
        ax[3, c].set_yticks([2, 3, 4])
        ax[3, c].set_yticklabels(["I-f", "closed", "fault"])
        ax[3, c].set_xlabel("time [s]")
    ax[0, 0].set_ylabel("speed [rpm]")
    ax[1, 0].set_ylabel("angle error [deg]")
    ax[2, 0].set_ylabel("current (FOC frame) [A]")
    ax[3, 0].set_ylabel("mode")
    for a in ax[:3, 0]:
        a.legend(fontsize=7)
    for a in ax.flat:
        a.grid(alpha=0.3)
    fig.suptitle(
        "Sensorless speed reversal through zero (flux observer, measured voltages)", fontsize=10
    )
    return ctx.fig(fig, "beyond_speed_reversal")


# ======================================================================== peers fail
def run_switched(sc, t_switch_s: float):
    """The runner's loop with the position source switched from the encoder to the driving
    observer at t_switch_s: the loop is *closed* on the observer at a chosen operating point
    (speed, load) with the observer already converged in shadow.  In-process only (the node
    graph has no mid-run source switch).  Returns a SimResult-like record."""
    from fluxdrive.drive.control import CP_SRC, SRC_ENCODER
    from fluxdrive.drive.sim import DriveSetup, LoopRun

    run = LoopRun(DriveSetup(sc))
    cp_observer = run.cp.copy()
    run.cp[CP_SRC] = SRC_ENCODER  # same gains (designed for the observer), encoder angle
    run.advance(min(run.n, int(round(t_switch_s / run.ds.ts))))
    run.cp[:] = cp_observer
    run.advance(run.n)
    return run.result()


PEERS = [
    "flux_measured",
    "emf_commanded",
    "ortega_commanded",
    "flux_commanded",
    "emf_measured",
    "ortega_measured",
]


def _switch_scenario(ctx, driving: str, seed: int, **extra):
    """2 % speed, rated brake load ramped in at the paper's 0.19 pu/s on the encoder, the loop
    closed on `driving` at t_switch, 2.5 s later a 1.5 s window."""
    t_full = 0.3 + 1.0 / 0.19
    t_sw = t_full + 1.0
    return ctx.build(
        name=f"peers_{driving}",
        duration_s=round(t_sw + 4.0, 4),
        seed=seed,
        speed_rpm=ctx.rpm(0.02),
        load_type="brake",
        load_pu=[[0.0, 0.0], [0.3, 0.0], [round(t_full, 4), 1.0]],
        steady_window_s=[round(t_sw + 2.5, 4), round(t_sw + 4.0, 4)],
        driving=driving,
        control={},
        observers={driving: variant_spec(driving, ctx.cv)},
        extra={"t_switch_s": round(t_sw, 4)},
        **extra,
    )


def _switch_job(args):
    sc = args
    t_sw = float(sc.extra["t_switch_s"])
    r = run_switched(sc, t_sw)
    m = compute(r)
    d = r.driving
    err = np.degrees(np.angle(np.exp(1j * (r.est[0, :, ES_TH] - r.truth[:, TR_THETA_E]))))
    ks = int(t_sw / sc.machine.ts_s)
    pre = err[ks - int(1.0 / sc.machine.ts_s) : ks]
    cm = float(np.degrees(np.angle(np.mean(np.exp(1j * np.radians(pre))))))
    after = np.abs(err[ks:]) > 60.0
    k_lost = int(np.argmax(after)) if after.any() else None
    dec = slice(max(ks - int(0.5 / sc.machine.ts_s), 0), None, 20)
    zoom = slice(max(ks - int(0.02 / sc.machine.ts_s), 0), ks + int(0.06 / sc.machine.ts_s))
    return {
        "stable": m["stable"],
        "fault": FAULT_NAMES.get(m["fault_code"], "?"),
        "rms_deg": m["observers"][d]["theta_err_rms_deg"],
        "mean_rpm": m["speed"]["mean_rpm"],
        "pre_mean_deg": cm,
        "pre_rms_deg": float(np.sqrt(np.mean(pre**2))),
        "lost_after_s": None if k_lost is None else k_lost * sc.machine.ts_s,
        "series": {
            "t": r.t[dec] - t_sw,
            "rpm": r.truth[dec, TR_WM] * RAD_S_TO_RPM,
            "err": err[dec],
            "tz": r.t[zoom] - t_sw,
            "rpmz": r.truth[zoom, TR_WM] * RAD_S_TO_RPM,
            "errz": err[zoom],
        },
    }


def _peers_switch_jobs(ctx, seeds: list[int], drivers: list[str]) -> list:
    """Build the loop-closing runs: (scenario, (driver, seed, deadtime tag)); in full runs
    also the causal check, an ideal inverter with the same observers."""
    sw_jobs = [(_switch_scenario(ctx, d, s), (d, s, "2us")) for d in drivers for s in seeds]
    if not ctx.quick:
        sw_jobs += [
            (_switch_scenario(ctx, d, s, plant={"deadtime_s": 0.0}), (d, s, "0"))
            for d in PEERS[1:4]
            for s in seeds[:2]
        ]
    return sw_jobs


def _peers_jobs(ctx) -> list:
    """Build the shadow run (every variant on the encoder drive at the same point, for the
    mechanism) and, in full runs, the same drivers closing the loop at 16 % speed and descending
    under load."""
    shadow_obs = {v: variant_spec(v, ctx.cv) for v in PEERS}
    shadow_obs["hl_commanded"] = {"variant": "hinkkanen_luomi", "voltage_source": "commanded"}
    shadow = ctx.encoder_run(ctx.rpm(0.02), 1.0, observers=shadow_obs, name="peers_shadow")
    jobs = [(shadow, _x_sens, None)]
    if not ctx.quick:
        jobs += [
            (
                descent(ctx.rpm(0.02), 1.0, driving=d, name=f"peers_descent_{d}", card=ctx.machine),
                _x_hold,
                None,
            )
            for d in PEERS
        ]
    return jobs


def _peers_rows(sw_jobs: list, sw_res: list) -> dict:
    """Analyse the switched runs: "driver@deadtime" -> one row per seed (no series)."""
    rows: dict = {}
    for (_, (d, s, dt)), x in zip(sw_jobs, sw_res, strict=True):
        rows.setdefault(f"{d}@{dt}", []).append(
            {"seed": s, **{k: v for k, v in x.items() if k != "series"}}
        )
    return rows


def _peers_pred(ctx, w: float, iq: float) -> dict:
    """The fundamental model's shadow predictions under the deadtime fundamental along q."""
    mc = ctx.cv
    k_ortega = _default_k(ctx.card, "ortega")[1]
    k_hl = _default_k(ctx.card, "hinkkanen_luomi")[1]
    return _peers_loop_numbers(ctx) | {
        "k_ortega": k_ortega,
        "ortega_commanded_deg": predicted_angle_deg(
            mc, "ortega", w, iq, k=k_ortega, v_err_q=mc.v1_dt
        ),
        "hl_commanded_deg": predicted_angle_deg(
            mc, "hinkkanen_luomi", w, iq, k=k_hl, v_err_q=mc.v1_dt
        ),
        "flux_commanded_mag_vs": mc.lam + mc.v1_dt / w,
    }


def _peers_summ(rows: dict, key: str) -> tuple[str, int, int]:
    """(summary text, runs held, runs) of one driver@deadtime."""
    rr = rows.get(key, [])
    n_ok = sum(x["stable"] for x in rr)
    rms = [x["rms_deg"] for x in rr if x["stable"]]
    lost = [x["lost_after_s"] for x in rr if x["lost_after_s"] is not None]
    faults = sorted({x["fault"] for x in rr if x["fault"] != "none"})
    pre = (
        (
            f" (θ̃ before closing: mean {np.mean([x['pre_mean_deg'] for x in rr]):.1f}°, "
            f"RMS {np.mean([x['pre_rms_deg'] for x in rr]):.1f}°)"
        )
        if rr
        else ""
    )
    return (
        (
            f"{n_ok}/{len(rr)} held{pre}"
            + (f", θ̃ RMS {np.mean(rms):.2f}°" if rms else "")
            + (f", |θ̃| > 60° {min(lost):.2f}-{max(lost):.2f} s after closing" if lost else "")
            + (f", trips: {', '.join(faults)}" if faults else "")
        ),
        n_ok,
        len(rr),
    )


def _peers_headline_claim(rows: dict, n_seeds: int, speed_rpm: float, td_s: float) -> dict:
    """Judge: commanded reduced-order observers lose the rotor, flux_measured holds it."""
    s_fm, n_fm, t_fm = _peers_summ(rows, "flux_measured@2us")
    s_ec, n_ec, _ = _peers_summ(rows, "emf_commanded@2us")
    s_oc, n_oc, _ = _peers_summ(rows, "ortega_commanded@2us")
    ok = n_fm == t_fm and n_ec == 0 and n_oc == 0
    return claim(
        f"{speed_rpm:.0f} rpm, rated load, {1e6 * td_s:g} µs deadtime uncompensated: closing "
        "the loop on a "
        "reduced-order "
        "observer driven by commanded voltages loses the rotor; the paper's flux observer on "
        "measured voltages holds it",
        f"flux_measured: {s_fm}; emf_commanded: {s_ec}; ortega_commanded: {s_oc} "
        f"(loop closed at {speed_rpm:.0f} rpm with the rated load carried, {n_seeds} seeds)",
        ok,
        "" if ok else "see the figure",
    )


def _peers_loop_numbers(ctx) -> dict[str, float]:
    """The card's numbers the mechanism text quotes: the deceleration of a 5 % torque deficit
    under the rated brake (5 % of 1.5 p lambda I_rated over J) [rad/s^2], the time it takes to
    lose the 2 % speed [s], the speed loop's target and the flux observer PLL's bandwidth [Hz]."""
    mc = ctx.cv
    decel = 0.05 * 1.5 * mc.p * mc.lam * mc.i_rated / mc.j
    return {
        "decel_rad_s2": decel,
        "t_lost_s": ctx.rpm(0.02) * RPM / decel,
        "speed_bw_hz": SPEED_OF_CURRENT_BW * card_current_bandwidth_hz(ctx.card),
        "pll_hz": float(observer_config("paper_robust", ctx.card).pll_bandwidth_hz or 0.0),
    }


def _peers_mechanism_why(mc: CardValues, w: float, rpm: float, pred: dict) -> str:
    x_over_lam = pred["flux_commanded_mag_vs"] / mc.lam
    return (
        f"ortega forces |η| = λ̂: the correction c that shrinks |x|/ω ≈ {x_over_lam:.1f}λ back "
        "to λ rotates the estimate by atan(c/ω) = acos(ωλ/|x|), so closing the loop on it puts "
        f"the current ~{pred['ortega_commanded_deg']:.0f}° off the q axis and the torque "
        "collapses at once.  The EMF and paper observers keep the mean angle but carry the "
        f"deadtime's 6th-order ripple (Fig. 14a; its RMS above).  What makes that fatal is "
        f"the operating point: the card's {mc.j:.3g} kg·m² rotor under the rated brake "
        f"decelerates at ΔT/J ≈ {pred['decel_rad_s2']:.0f} rad/s² for a 5 % torque deficit, "
        f"so {rpm:.0f} rpm is gone in ~{1e3 * pred['t_lost_s']:.0f} ms, against the speed "
        f"loop's {pred['speed_bw_hz']:.0f} Hz target and the {pred['pll_hz']:.0f} Hz "
        "observer PLL (slower speed loops fail too).  As the rotor slows, (4/π)V_dt/(ωλ) "
        f"({mc.v1_dt / (w * mc.lam):.1f} at {rpm:.0f} rpm) grows and "
        "with it the error, and once the current follows θ̂ the deadtime error turns with the "
        "estimate (the EMF observer then sees only ωλ/(ωλ+(4/π)V_dt) = "
        f"{w * mc.lam / (w * mc.lam + mc.v1_dt):.2f} of its own angle error): a runaway that "
        "ends at standstill, where no back-EMF observer sees the rotor.  The paper's observer "
        f"on commanded voltages has |λ̂| ≈ {x_over_lam:.1f}λ, "
        + (
            "outside the 3λ validity band: it trips on loss of lock (next row) -- the measured "
            "voltages are what make it work"
            if x_over_lam > 3.0
            else "inside the 3λ validity band here"
        )
    )


def _peers_mechanism_claim(mc: CardValues, so: dict, w: float, pred: dict, rpm) -> dict:
    """Judge the shadow run against the model: what each observer makes of the deadtime."""
    pred_ortega, pred_hl = pred["ortega_commanded_deg"], pred["hl_commanded_deg"]
    pred_mag = pred["flux_commanded_mag_vs"]
    o_c, h_c, f_c, e_c = (
        so["ortega_commanded"],
        so["hl_commanded"],
        so["flux_commanded"],
        so["emf_commanded"],
    )
    vdt_txt = (
        f"V_dt = Vdc·td/Ts = {mc.vdt:.2f} V per leg, fundamental (4/π)V_dt = "
        f"{mc.v1_dt:.2f} V "
        f"along the current, vs the back-EMF ωλ = {w * mc.lam:.2f} V"
    )
    return claim(
        "Mechanism, in shadow before closing (current on the true q axis): the deadtime error "
        "is a magnitude error of the EMF (along the current = along q); what each observer "
        "makes of it decides",
        f"{vdt_txt}.  ortega_commanded θ̃ {o_c['mean_deg']:.1f}° (model acos(ωλ/(ωλ+(4/π)"
        f"V_dt)) with γλ² = {pred['k_ortega']:.0f}: {pred_ortega:.1f}°); hinkkanen_luomi "
        "commanded "
        f"{h_c['mean_deg']:.1f}° (model {pred_hl:.1f}°); paper commanded |λ̂| "
        f"{1e3 * f_c['mag']:.1f} mV·s (model λ + (4/π)V_dt/ω = {1e3 * pred_mag:.1f}, 3λ "
        f"validity limit {3e3 * mc.lam:.1f}), θ̃ mean {f_c['mean_deg']:.1f}°; emf_commanded θ̃ "
        f"mean {e_c['mean_deg']:.1f}° (RMS {e_c['rms_deg']:.1f}°: the 6th order)",
        bool(
            abs(o_c["mean_deg"] - pred_ortega) < 5.0
            and abs(f_c["mag"] - pred_mag) < 0.1 * pred_mag
            and abs(e_c["mean_deg"]) < 5.0
        ),
        _peers_mechanism_why(mc, w, rpm, pred),
    )


def _peers_control_claim(rows: dict, mc: CardValues, w: float, cr: dict) -> list[dict]:
    """The controls at the same point (unjudged): flux on commanded, emf/ortega on measured."""
    ctrl_rows = []
    for d in PEERS[3:]:
        txt, _, n_all = _peers_summ(rows, f"{d}@2us")
        if n_all:
            ctrl_rows.append(f"{d}: {txt}")
    if not ctrl_rows:
        return []
    em_ok = all(x["stable"] for x in rows.get("emf_measured@2us", []))
    x_over_lam = (mc.lam + mc.v1_dt / w) / mc.lam
    return [
        claim(
            "Controls at the same point: the paper's observer on commanded voltages, and the "
            "EMF / ortega observers on measured voltages",
            "; ".join(ctrl_rows),
            None,
            f"flux_commanded: |λ̂| = λ + (4/π)V_dt/ω ≈ {x_over_lam:.1f}λ "
            + (
                "leaves the 3λ validity band → loss-of-lock trip (the angle itself is fine).  "
                if x_over_lam > 3.0
                else "stays inside the 3λ validity band.  "
            )
            + "emf_measured: no deadtime "
            f"error; its per-sample noise L/Ts·σ_i ≈ {cr['emf_noise_v']:.2g} V against "
            f"{w * mc.lam:.2f} V "
            + (
                "costs accuracy (its θ̃ RMS against flux_measured's, headline row) but it holds "
                "here; it fails lower down (lowest_speed).  "
                if em_ok
                else "can make the estimate slip before or after the loop is closed.  "
            )
            + "ortega_measured: measured voltages remove "
            f"the {mc.v1_dt:.2f} V, but the deadtime residue (sensitivity) times k/(ω²λ) = "
            f"{_deg_per_mv(mc, cr['k_ortega'], w):.2g}° per mV and its "
            f"{w * w / cr['k_ortega']:.2g} s⁻¹ angle pole still lose the rotor at its default "
            "gain: a structural limit at low speed, not the voltage source",
        )
    ]


def _peers_no_deadtime_claim(rows: dict, speed_rpm: float) -> list[dict]:
    """Judge the causal check: without deadtime the commanded observers hold."""
    dt0 = []
    all0 = True
    for d in PEERS[1:4]:
        txt, n_ok, n_all = _peers_summ(rows, f"{d}@0")
        if n_all:
            dt0.append(f"{d}: {txt}")
            all0 = all0 and n_ok == n_all
    if not dt0:
        return []
    return [
        claim(
            "The deadtime is the cause: with an ideal inverter (td = 0) the same commanded-"
            f"voltage observers close the loop at {speed_rpm:.0f} rpm / rated load and hold it",
            "; ".join(dt0),
            all0,
        )
    ]


def _peers_descent_claim(ctx, desc: dict) -> list[dict]:
    """Where each driver loses the rotor on the lowest_speed descent (unjudged)."""
    if not desc:
        return []
    parts = []
    for d, x in desc.items():
        lo = x["lost"]
        parts.append(
            f"{d}: "
            + (
                f"held {ctx.rpm(0.02):.0f} rpm"
                if x["stable"]
                else (
                    f"lost at ref {lo['ref_rpm']:.0f} rpm, load "
                    f"{lo['load_pu']:.2f} pu ({lo['fault']})"
                    if lo
                    else f"not held (mean {x['mean_rpm']:.0f} rpm, θ̃ RMS {x['rms_deg']:.0f}°)"
                )
            )
        )
    return [
        claim(
            f"The same drivers started sensorless at {ctx.rpm(DESCENT_START_PU):.0f} rpm, rated "
            f"load ramped in there, then decelerated to {ctx.rpm(0.02):.0f} rpm (the lowest_speed "
            "protocol): where each loses the rotor",
            "; ".join(parts),
            None,
            "commanded-voltage observers are lost on the way down near their bound (0.2 R I + "
            f"V_dt)/λ ≈ {speed_bound_rpm(ctx.cv, 1.0, True):.0f} rpm (lowest_speed), "
            "ortega_commanded already when it first closes "
            "the loop",
        )
    ]


def _peers_rs_claim() -> dict:
    """The other peer-failure case, measured in rs_adapt."""
    return claim(
        "R̂_s 30 % off at 2 % speed / 150 % load (the other peer-failure case of the issue)",
        "see experiment rs_adapt: fixed R̂ = 1.3 R or 0.7 R loses the rotor, the online R_s "
        "estimate (flux-magnitude law) keeps the flux drive running",
        None,
        "voltage-model observers are most sensitive to R̂ at low speed: |λ̂| = λ + ΔR i_q/ω "
        "(sensitivity / mismatch)",
    )


def peers_fail(ctx):
    """2 % speed, rated load, the card's deadtime: the loop closed on each observer
    (in-process), the mechanism in shadow, the descent: build -> run -> analyse -> judge -> plot."""
    mc = ctx.cv  # the card's values (see CardValues)
    seeds = [1] if ctx.quick else [1, 2, 3]
    drivers = PEERS[:3] if ctx.quick else PEERS
    sw_jobs = _peers_switch_jobs(ctx, seeds, drivers)
    t0 = time.perf_counter()
    scs = [j[0] for j in sw_jobs]
    sw_res = ctx.map(_switch_job, scs)
    ctx.log(f"{len(scs)} switched runs (in-process engine) in {time.perf_counter() - t0:.1f} s")
    res = ctx.run(_peers_jobs(ctx))
    shadow, desc = res[0], dict(zip(PEERS, res[1:], strict=False))
    rows = _peers_rows(sw_jobs, sw_res)
    w, iq = shadow["we"], shadow["iq"]
    so = shadow["obs"]
    pred = _peers_pred(ctx, w, iq)
    speed_rpm = ctx.rpm(0.02)
    claims = [_peers_headline_claim(rows, len(seeds), speed_rpm, ctx.card.deadtime_s)]
    claims += [_peers_mechanism_claim(mc, so, w, pred, speed_rpm)] + _peers_control_claim(
        rows, mc, w, card_rates(ctx)
    )
    claims += _peers_no_deadtime_claim(rows, speed_rpm) + _peers_descent_claim(ctx, desc)
    claims.append(_peers_rs_claim())
    figs = [_plot_peers(ctx, sw_jobs, sw_res, drivers)]
    return {
        "claims": claims,
        "figures": figs,
        "data": {
            "switched": rows,
            "shadow": so,
            "we_rad_s": w,
            "iq_a": iq,
            "pred": pred,
            "descent": desc,
            "vdt_v": mc.vdt,
            "v1_dt_v": mc.v1_dt,
        },
    }


def _plot_peers(ctx, sw_jobs, sw_res, drivers):
    p = plt()
    fig = p.figure(figsize=(12, 7))
    gs = fig.add_gridspec(2, 3)
    ax = [fig.add_subplot(gs[0, :2]), fig.add_subplot(gs[1, :2])]
    az = [fig.add_subplot(gs[0, 2]), fig.add_subplot(gs[1, 2])]
    for i, d in enumerate(drivers):
        x = next(
            r
            for (_, key), r in zip(sw_jobs, sw_res, strict=True)
            if key[0] == d and key[2] == "2us"
        )
        s = x["series"]
        ax[0].plot(s["t"], s["rpm"], lw=0.7, color=f"C{i}", label=d)
        ax[1].plot(s["t"], s["err"], lw=0.5, color=f"C{i}")
        az[0].plot(1e3 * s["tz"], s["rpmz"], lw=0.8, color=f"C{i}")
        az[1].plot(1e3 * s["tz"], s["errz"], lw=0.8, color=f"C{i}")
    for a in ax + az:
        a.axvline(0.0, color="k", lw=0.8, ls=":")
        a.grid(alpha=0.3)
    ax[0].set_ylabel("rotor speed [rpm]")
    ax[0].set_ylim(-30, 120)
    az[0].set_ylim(-30, 120)
    ax[0].legend(fontsize=7, ncol=3)
    ax[1].set_ylabel("θ̃ of the driving observer [deg]")
    ax[1].set_ylim(-185, 185)
    az[1].set_ylim(-185, 185)
    ax[1].set_xlabel("time after closing the loop on the observer [s]")
    az[1].set_xlabel("the first tens of ms [ms]")
    ax[0].set_title(
        f"{ctx.rpm(0.02):.0f} rpm, rated brake load, {1e6 * ctx.card.deadtime_s:g} µs deadtime "
        "uncompensated: encoder until t = 0, then sensorless on each observer (seed 1)",
        fontsize=9,
    )
    az[0].set_title("zoom: the first tens of ms after closing", fontsize=9)
    return ctx.fig(fig, "beyond_peers_fail")


# ======================================================================== hexagon
# the spatial saturation's 5th/7th split: which hexagon Figs. 13(d) and 14(b) allow together
HEX_OBS = ("flux_measured", "emf_measured", "paper_measured")


def _x_hexagon(r, m):
    """Per observer: theta~ 6th order [deg], RMS [deg] and the 6th order of |lambda^| over its
    mean, over the steady window."""
    from fluxdrive.analysis.metrics import steady_window

    w = steady_window(r.t, r.scenario.steady_window_s)
    thu = np.unwrap(r.truth[w.k0 : w.k1, TR_THETA_E])
    ws = whole_periods(thu)
    out = {}
    for i, nm in enumerate(r.names):
        e = r.est[i, w.k0 : w.k1][ws]
        mag = np.hypot(e[:, ES_LA], e[:, ES_LB])
        om = m["observers"][nm]
        out[nm] = {
            "h6_deg": om["theta_err_h6_deg"],
            "rms_deg": om["theta_err_rms_deg"],
            "mag_h6": abs(harmonic(mag, thu[ws], 6)) / float(np.mean(mag)),
        }
    return out


def hexagon_splits(ctx, h6: float) -> dict[str, tuple[float, float]]:
    """(h5, h7) at rated current [pu] of each split tried, each harmonic of size h6/2: none,
    the even split (pure radius: the bench's spatial_saturation_h6_pu), the 5th or the 7th
    alone, opposite signs (pure angle) and, in full runs, the split the paper observer's
    fundamental-frequency gains say moves its estimate's angle not at all: it passes order k
    with G_k = k (j w + w_c)/(j k w + w_c) (k = -5, 7), so h7 = (G5/G7) h5 cancels the q
    part."""
    a = 0.5 * h6
    splits = {
        "none": (0.0, 0.0),
        "even (pure radius)": (a, a),
        "5th only": (a, 0.0),
        "7th only": (0.0, a),
    }
    if not ctx.quick:
        w, wc = card_rates(ctx)["w2"], _default_k(ctx.card, "paper")[0]
        g5, g7 = (k * complex(wc, w) / complex(wc, k * w) for k in (-5, 7))
        splits["opposite (pure angle)"] = (a, -a)
        # rotor frame: G5 h5 e^{-j6th} + G7 h7 e^{j6th} with G5 ~ -|G5|: no q part for
        # h7 = (G5/G7) h5
        ratio = (g5 / g7).real
        splits[f"paper observer's no-angle split (h7 = {ratio:.2f} h5)"] = (a, ratio * a)
    return splits


def _hexagon_row(name: str, h5: float, h7: float, x: float, o: dict) -> tuple[dict, float, list]:
    """One split's row (unjudged), Fig. 14(b)'s ratio and the observers that lost lock."""
    ratio = max(
        o[f"{v}_measured"]["h6_deg"] / o[f"{v}_commanded"]["h6_deg"] for v in ("flux", "emf")
    )
    lost = [v for v in HEX_OBS if o[v]["rms_deg"] > 30.0]
    return (
        claim(
            f"{name}: magnet-flux 5th {h5:.3g} pu, 7th {h7:.3g} pu at rated current; at this "
            f"load the machine's own flux angle ripples by (h7 − h5) x = "
            f"{math.degrees((h7 - h5) * x):.2f}°, its radius by (h5 + h7) x = "
            f"{100 * (h5 + h7) * x:.2f} %",
            "θ̃ 6th order "
            + ", ".join(f"{v} {o[v]['h6_deg']:.2f}°" for v in HEX_OBS)
            + "; |λ̂| 6th order "
            + ", ".join(f"{v} {100 * o[v]['mag_h6']:.1f} %" for v in HEX_OBS)
            + f"; Fig. 14(b)'s ratio (measured over commanded, the larger of flux and EMF) "
            f"{ratio:.2f}" + (f"; lost lock (θ̃ RMS > 30°): {', '.join(lost)}" if lost else ""),
            None,
        ),
        ratio,
        lost,
    )


def _hexagon_allowed(rows: dict, thr14: float, thr13: float) -> dict:
    """Which splits keep Fig. 14(b) (ratio under its registered threshold, no observer lost)
    and show Fig. 13(d)'s hexagon (|lambda^|'s 6th order of flux_measured over the no-saturation
    run's above its registered threshold)."""
    base = rows["none"]["obs"]["flux_measured"]["mag_h6"]
    ok14 = [n for n, r in rows.items() if r["ratio"] < thr14 and not r["lost"]]
    ok13 = [n for n, r in rows.items() if r["obs"]["flux_measured"]["mag_h6"] > thr13 * base]
    both = [n for n in ok14 if n in ok13]
    least = min((n for n in rows if n != "none"), key=lambda n: rows[n]["ratio"])
    return claim(
        "What Figs. 13(d) and 14(b) allow together: a hexagon in |λ̂| under load (> "
        f"{thr13:g}× the no-saturation run's 6th order) while the 6th order of θ̃ with "
        f"measured voltages stays under {thr14:g}× the commanded one's, for one split of the "
        "same size",
        f"Fig. 14(b) kept by: {', '.join(ok14) or 'none'}; Fig. 13(d) shown by: "
        f"{', '.join(ok13) or 'none'}; both: {', '.join(both) or 'none'}.  Smallest θ̃ 6th "
        f"order ratio: {least} ({rows[least]['ratio']:.2f}); without "
        f"saturation θ̃'s 6th order is flux_measured "
        f"{rows['none']['obs']['flux_measured']['h6_deg']:.2f}°, emf_measured "
        f"{rows['none']['obs']['emf_measured']['h6_deg']:.2f}°",
        None,
        "a hexagon of pure radius moves no angle in the machine; the observers' unequal "
        "gains on the 5th and 7th turn part of it into angle.  No split of a hexagon big "
        "enough for Fig. 13(d) brings θ̃'s 6th order back to the no-saturation level: the "
        "splits that move the machine's flux angle (one harmonic alone, opposite signs) "
        "give more, not less",
    )


def hexagon(ctx):
    """The spatial saturation's 5th/7th split at Fig. 14's operating point (sensorless 2 %,
    150 % load, the paper bench): build -> run -> judge against what Figs. 13(d) and 14(b)
    show.  Rows are unjudged: the splits are hypotheses, the registered claims stay in
    fig13/fig14."""
    from fluxdrive.experiments.claims import registered

    base = ctx.build(base="paper_2pct_150load")
    p5, p7 = base.bench.spatial_saturation_h5_h7()
    h6 = (p5 + p7) or 0.005  # the paper bench's size when the bench has none
    splits = hexagon_splits(ctx, h6)
    scs = []
    for h5, h7 in splits.values():
        sc = ctx.build(base="paper_2pct_150load")
        bench = dataclasses.replace(
            sc.bench,
            spatial_saturation_h6_pu=0.0,
            spatial_saturation_h5_pu=h5,
            spatial_saturation_h7_pu=h7,
        )
        scs.append((dataclasses.replace(sc, bench=bench), _x_hexagon, None))
    res = ctx.run(scs)
    load = float(np.max(base.load_profile_pu[:, 1]))
    rows = {}
    for n, o in zip(splits, res, strict=True):
        row, ratio, lost = _hexagon_row(n, *splits[n], load**2, o)
        rows[n] = {"obs": o, "row": row, "ratio": ratio, "lost": lost}
    reg = registered()
    claims = [r["row"] for r in rows.values()]
    claims.append(
        _hexagon_allowed(
            rows,
            float(reg["fig14.measured_6th_gone"]["threshold"]),
            float(reg["fig13.fullload_hexagon"]["threshold"]),
        )
    )
    return {
        "claims": claims,
        "figures": [],
        "data": {
            n: {"h5_h7": splits[n], "fig14b_ratio": r["ratio"], **r["obs"]} for n, r in rows.items()
        },
    }


# ======================================================================== online R_s
def run_adaptive(sc, gain: float | None, chunk: int = 10, r0: float | None = None):
    """The runner's loop in 1 ms chunks; between chunks the driving observer's R^ is
    adapted from its flux magnitude (gain [1/s]; None: no adaptation)."""
    from fluxdrive.drive.sim import DriveSetup, LoopRun

    run = LoopRun(DriveSetup(sc))
    n, est, ctl, op = run.n, run.est, run.ctrl, run.obs_params
    card = sc.machine
    r0 = card.resistance_ohm if r0 is None else r0
    i_min = 0.1 * card.rated_current_a  # adapt only with a current to see R^ through
    o = run.driving
    lam = op[o, OP_LAM]
    r_hist = np.zeros(n)
    dt = chunk * run.ds.ts
    k = 0
    while k < n:
        k1 = min(n, k + chunk)
        run.advance(k1)
        if gain is not None:
            e = est[o, k:k1]
            iq = float(np.mean(ctl[k:k1, CO_IQ]))
            w = float(np.mean(e[:, ES_W]))
            if np.all(ctl[k:k1, CO_MODE] == MODE_IF_RAMP):
                # open-loop I-f: the current sits on d of the ramp angle and the unloaded
                # rotor follows it, so an R^ error shows as a q-component of lambda^ in the
                # ramp frame: lambda^_q' = (R^ - R) i_d / w
                th = ctl[k:k1, CO_TH]
                lq = float(np.mean(-e[:, ES_LA] * np.sin(th) + e[:, ES_LB] * np.cos(th)))
                i_d = float(np.mean(ctl[k:k1, CO_ID]))
                w_if = float(np.mean(ctl[k:k1, CO_W_REF])) * card.pole_pairs
                if abs(i_d) > i_min and abs(w_if) > 2 * math.pi * 1.0:
                    r_new = op[o, OP_R] - gain * dt * lq * w_if / i_d
                    op[o, OP_R] = min(max(r_new, 0.3 * r0), 3.0 * r0)
            elif (
                np.all(ctl[k:k1, CO_MODE] == MODE_CLOSED_LOOP)
                and abs(iq) > i_min
                and abs(w) > 2 * math.pi * 1.0
            ):
                mag = float(np.mean(np.hypot(e[:, ES_LA], e[:, ES_LB])))
                dr = (mag - lam) * abs(w) / abs(iq)
                r_new = op[o, OP_R] + gain * dt * dr
                op[o, OP_R] = min(max(r_new, 0.3 * r0), 3.0 * r0)
        r_hist[k:k1] = op[o, OP_R]
        k = k1
    return run.result(), r_hist


def _adaptive_job(args):
    sc, gain = args
    res, r_hist = run_adaptive(sc, gain)
    m = compute(res)
    d = slice(0, len(res.t), 50)
    return {
        "metrics": m,
        "t": res.t[d],
        "r_hat": r_hist[d],
        "rpm": res.truth[d, TR_WM] * RAD_S_TO_RPM,
        "th_err": np.degrees(
            np.angle(np.exp(1j * (res.est[0, d, ES_TH] - res.truth[d, TR_THETA_E])))
        ),
    }


def rs_adapt(ctx):
    mc = ctx.cv  # the card's values (see CardValues)
    factors = [1.3] if ctx.quick else [1.3, 0.7]
    gain = 5.0
    cases = [(f, g) for f in factors for g in (None, gain)]
    jobs = []
    for f, g in cases:
        # ideal bench: only the R^ error under study (the paper bench adds its own R^ error
        # and a heating winding)
        sc = ctx.build(
            base="paper_2pct_150load",
            bench={},
            observers={"flux_measured": {**OBS4["flux_measured"], "r_hat_ohm": mc.r * f}},
        )
        jobs.append((sc, g))
    t0 = time.perf_counter()
    res = ctx.map(_adaptive_job, jobs)
    ctx.log(f"{len(jobs)} adaptive runs in {time.perf_counter() - t0:.1f} s")
    p = plt()
    fig, ax = p.subplots(3, 1, figsize=(9, 8), sharex=True)
    claims = []
    rows = []
    for (f, g), r in zip(cases, res, strict=True):
        lab = f"R̂0 = {f}R, {'adaptive' if g else 'fixed'}"
        ax[0].plot(r["t"], r["r_hat"], lw=0.8, label=lab)
        ax[1].plot(r["t"], r["rpm"], lw=0.7)
        ax[2].plot(r["t"], r["th_err"], lw=0.5)
        m = r["metrics"]
        win = r["t"] >= m["window_s"][0]
        rows.append(
            {
                "r0_factor": f,
                "adaptive": bool(g),
                "stable": m["stable"],
                "r_hat_end": float(np.mean(r["r_hat"][win])),
                "rms_deg": m["observers"]["flux_measured"]["theta_err_rms_deg"],
            }
        )
    ax[0].axhline(mc.r, color="k", ls=":", lw=0.7)
    ax[0].set_ylabel("R̂ [Ω]")
    ax[0].legend(fontsize=7)
    ax[0].set_title(
        "R̂ 30 % off at 2 % speed, 150 % load ramp: fixed vs flux-magnitude "
        "adaptation (1 kHz, outside the kernels)",
        fontsize=9,
    )
    ax[1].set_ylabel("speed [rpm]")
    ax[2].set_ylabel("θ̃ [deg]")
    ax[2].set_ylim(-180, 180)
    ax[2].set_xlabel("time [s]")
    figs = [ctx.fig(fig, "beyond_rs_adapt")]
    for f in factors:
        fx = next(x for x in rows if x["r0_factor"] == f and not x["adaptive"])
        ad = next(x for x in rows if x["r0_factor"] == f and x["adaptive"])
        claims.append(
            claim(
                f"R̂ = {f}·R at 2 %/150 %: an online R_s estimate (flux-magnitude law) keeps the "
                "flux drive running",
                f"fixed R̂: stable {fx['stable']}; adaptive: stable {ad['stable']}, R̂ → "
                f"{ad['r_hat_end']:.3f} Ω (true {mc.r}), θ̃ RMS {ad['rms_deg']:.2f}°",
                bool(ad["stable"] and abs(ad["r_hat_end"] - mc.r) < 0.05 * mc.r),
                "identifiable only with load (|i_q| > 10 %) and with λ_pm known: a λ_pm error is "
                "indistinguishable from an R error at one operating point (magnet temperature "
                "moves both)",
            )
        )
    return {"claims": claims, "figures": figs, "data": {"runs": rows, "gain_per_s": gain}}


GROUP = "beyond"  # experiments.registry lists this module
EXPERIMENTS = {
    "lowest_speed": (lowest_speed, "lowest sustainable speed per variant at 100 % load"),
    "mismatch": (mismatch, "R̂, L̂, λ̂ mismatch and current offsets at 2 %/150 %"),
    "rs_adapt": (rs_adapt, "online R_s estimate for R̂ 30 % off at 2 %/150 %"),
    "sensitivity": (sensitivity, "θ̃ vs R̂, L̂, λ̂, current offset and cut-off, per variant"),
    "speed_reversal": (
        speed_reversal,
        "sensorless reversal +2 % → −2 % speed under load, I-f through zero",
    ),
    "hexagon": (
        hexagon,
        "spatial saturation's 5th/7th split at 2 %/150 %: what Figs. 13(d) and 14(b) allow",
    ),
    "peers_fail": (
        peers_fail,
        "2 % speed, rated load, the card's deadtime: where reduced-order "
        "observers on commanded voltages lose the rotor",
    ),
}
