"""Past the paper: the lowest sustainable speed per variant.

Sensorless start at 16 % speed, load ramped in, descent under load to the speed; grid +
bisection per variant, 100 % and 150 % load, against the bound (0.2 R I + V_dt)/lambda.
"""

from __future__ import annotations

import math

import numpy as np

from fluxdrive.experiments.beyond_common import (
    DESCENT_DECEL_PU_S,
    DESCENT_START_PU,
    RPM,
    VARIANTS,
    card_rates,
    deg_per_mv,
    descent,
    speed_bound_rpm,
    x_hold,
)
from fluxdrive.experiments.claims import judge
from fluxdrive.experiments.common import (
    observe,
    plt,
)

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
                        x_hold,
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
        return cases, [ctx.rpm(x) for x in (0.08, 0.02, 0.01)], [ctx.seed], 0
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
    # the context's seed: the registry runs the search once per seed and judges the rows over
    # the seeds (a second seed once disagreed only at two bisection points: emf_measured 100 %
    # at 35.7 rpm, hl_measured 150 % at 12.6 rpm)
    grid = [ctx.rpm(x) for x in (0.16, 0.08, 0.04, 0.02, 0.01, 0.005, 0.0025)]
    return cases, grid, [ctx.seed], 2


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
        f"residue δ into an angle error k δ/(ω² λ), ≈ {deg_per_mv(mc, k_or, w2):.2g}° per mV "
        f"at {r2:.0f} rpm and growing as 1/ω² (the deadtime residue: sensitivity "
        f"experiment); its angle pole ω²/k is {w2 * w2 / k_or:.2g} s⁻¹ there",
        "flux_measured_rhat120": "R^ 20 % high: |λ̂| = λ − 0.2 R I/ω, which leaves the 0.3λ "
        "validity band at ω = 0.2 R I/(0.7 λ) = 1.43× the bound and "
        "flips sign at the bound itself",
    }


def _lowest_variant_claims(lowest: dict, start_rpm: float, notes: dict) -> list[dict]:
    """One observation per variant: its lowest speed per load against the bound."""
    claims = []
    for v in lowest:
        keys = list(lowest[v])
        claims.append(
            observe(
                f"{v}: lowest speed holding {' / '.join(keys)} load (sensorless, descent under "
                f"load from {start_rpm:.0f} rpm) vs ω_min ≈ (0.2 R I + V_dt)/λ",
                "; ".join(f"{k}: {_lowest_txt(lowest[v][k])}" for k in keys),
                notes.get(v, ""),
            )
        )
    return claims


def _low(lowest: dict, v: str, key: str) -> float | None:
    d = lowest.get(v, {}).get(key)
    return None if d is None else d["lowest_rpm"]


def _over(x: float | None, b: float, none: float = math.inf) -> float:
    """A speed over its bound (`none` where there is no speed: never held, never lost)."""
    return none if x is None else x / b


def _lowest_flux_claim(lowest: dict, loads: list[str]) -> list[dict]:
    """With measured voltages and R^ = R the flux observer beats the bound."""
    if "flux_measured" not in lowest:
        return []
    fm = [
        (k, _low(lowest, "flux_measured", k), lowest["flux_measured"][k]["bound_rpm"])
        for k in loads
        if k in lowest["flux_measured"]
    ]
    return [
        judge(
            "lowest_speed.flux_below_bound",
            "; ".join(
                f"{k}: {x:g} rpm vs bound {b:.0f}" if x is not None else f"{k}: none"
                for k, x, b in fm
            ),
            max(_over(x, b) for _, x, b in fm),
        )
    ]


def _lowest_rhat_claim(lowest: dict, loads: list[str]) -> list[dict]:
    """The bound's 0.2 R I term as an R^ error of 20 %."""
    v = "flux_measured_rhat120"
    if v not in lowest:
        return []
    rows = [
        (k, _low(lowest, v, k), lowest[v][k]["first_lost_rpm"], lowest[v][k]["bound_rpm"])
        for k in loads
    ]
    ours = "; ".join(
        f"{k}: lost at {lo}, held at {hi} rpm (bound {b:.0f}, 1.43× = {1.43 * b:.0f})"
        for k, hi, lo, b in rows
    )
    why = (
        "the search brackets the loss between two tested speeds; a bracket straddling the "
        "predicted band edge counts"
    )
    return [
        # never lost: no speed below 2x the bound was lost (inf); never held: 0
        judge(
            "lowest_speed.rhat_lost_below_2bound",
            ours,
            max(_over(lo, b) for _, _, lo, b in rows),
            why,
        ),
        judge(
            "lowest_speed.rhat_held_above_bound",
            ours,
            min(_over(hi, b, none=0.0) for _, hi, _, b in rows),
            why,
        ),
    ]


def _lowest_bound_claims(ctx, lowest: dict, loads: list[str]) -> list[dict]:
    """The bound's V_dt term (full runs only) and the paper's SNR argument."""
    claims = []
    com = [v for v in ("flux_commanded", "emf_commanded") if v in lowest]
    if com and not ctx.quick:
        rows = [(v, k, _low(lowest, v, k), lowest[v][k]["bound_rpm"]) for v in com for k in loads]
        claims.append(
            judge(
                "lowest_speed.commanded_near_bound",
                "; ".join(f"{v} {k}: {x} rpm vs {b:.0f}" for v, k, x, b in rows),
                max(abs(math.log2(_over(x, b))) for _, _, x, b in rows),
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
            judge(
                "lowest_speed.flux_lower_than_emf",
                "; ".join(f"{k}: flux {a} vs EMF {b} rpm" for k, a, b in rows2),
                # flux never held: inf; EMF never held (flux did): 0
                max(math.inf if a is None else (0.0 if b is None else a / b) for _, a, b in rows2),
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


GROUP = "beyond"  # experiments.registry lists this module
EXPERIMENTS = {
    "lowest_speed": (lowest_speed, "lowest sustainable speed per variant at 100 % load"),
}
