"""The speed-loop bandwidth a sensorless drive gets where noise limits it, not its loop design.

Fig. 18's bandwidth rows rest on the loop-design rule (control.design_loops: the target unless
the closed loop peaks by more than 3 dB), so the flux drive's bandwidth is by design and the
EMF drive's 7 Hz is calibrated (its PLL and speed LPF chosen for it).  Here the bandwidth is
designed to stated noise limits instead.  The speed PI turns the speed estimate's noise (the
observer's θ̃ noise through its PLL and speed LPF) into i_q* noise, K_p·ω̂_noise, and K_p grows
with the speed-loop bandwidth: an i_q* noise limit is a ceiling on the bandwidth.  The shaft's
own speed noise falls as the loop holds the speed tighter: a speed-noise limit is a floor.
Each drive (Fig. 18's, at its operating point: 10 % speed, 30 % brake load, measured voltages,
from a sensorless start) runs steady with the speed loop designed for each bandwidth of a
sweep; the broadband parts of i_q* and of the shaft speed (what the joint fit of orders 0..20
against the rotor angle leaves: noise, not the deadtime's harmonics) are measured per setting
and seed.  Per drive: the highest bandwidth its design grants, the highest whose i_q* noise
stays within IQ_NOISE_LIMIT_PU of rated current, and the lowest from which its shaft speed
noise stays within SPEED_NOISE_LIMIT_RPM (both interpolated on the sweep; nan: never).
No claim rows: the numbers are in report.json (`data`) beside Fig. 18's rows.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fluxdrive.analysis.metrics import fit_orders, steady_window, whole_periods
from fluxdrive.core.machine import card_current_bandwidth_hz
from fluxdrive.drive.control import CO_IQ_REF
from fluxdrive.drive.plant import TR_THETA_E, TR_WM
from fluxdrive.experiments.claims import MIN_SEEDS
from fluxdrive.experiments.common import START_PU, plt

DRIVES = ("encoder", "flux_measured", "emf_measured")
# the speed-loop designs swept, in per unit of Fig. 18's target (the current loop's hundredth)
BW_PU = (0.4, 0.55, 0.7, 0.85, 1.0, 1.4, 2.0)
BW_PU_QUICK = (0.5, 1.0)
# the stated limits: broadband i_q* noise (RMS, per unit of rated current: a torque ripple of
# 1 %) and broadband shaft-speed noise (RMS: 1 rpm, the resolution Fig. 19's speed traces read)
IQ_NOISE_LIMIT_PU = 0.01
SPEED_NOISE_LIMIT_RPM = 1.0
SPEED_PU, LOAD_PU = 0.1, 0.3  # Fig. 18's operating point (paper._fr_scenario)
EMF_HANDOVER_PU = 0.04  # an EMF drive's handover (paper.EMF_HANDOVER_PU)
BENCH = "../benches/paper_lab.yaml"


def _scenario(ctx, drive: str, bw_hz: float, seed: int):
    obs = {} if drive == "encoder" else {drive: _obs(drive)}
    start = ctx.rpm(START_PU)
    ctrl = {
        "if_current_pu": 0.6,
        "handover_rpm": ctx.rpm(EMF_HANDOVER_PU) if drive.startswith("emf") else start,
        "handback_rpm": 0.5 * start,
        "speed_bandwidth_hz": round(bw_hz, 6),
    }
    return ctx.build(
        name=f"bw_noise_{drive}",
        duration_s=5.0,
        seed=seed,
        speed_rpm=[[0.0, start], [0.8, start], [1.8, ctx.rpm(SPEED_PU)]],
        load_type="brake",
        load_pu=[[0.0, 0.0], [2.0, 0.0], [3.0, LOAD_PU]],
        steady_window_s=[3.5, 5.0],
        driving=drive,
        control=ctrl,
        observers=obs,
        bench=BENCH,
    )


def _obs(drive: str) -> dict[str, Any]:
    from fluxdrive.experiments.common import OBS4

    return dict(OBS4[drive])


def _x_noise(r, m) -> dict[str, Any]:
    """Broadband i_q* noise and speed noise (true shaft) over the steady window, and the
    loop design the drive ran."""
    w = steady_window(r.t, r.scenario.steady_window_s)
    th = np.unwrap(r.truth[w.k0 : w.k1, TR_THETA_E])
    sl = whole_periods(th)
    iq = r.ctrl[w.k0 : w.k1, CO_IQ_REF][sl]
    wm = r.truth[w.k0 : w.k1, TR_WM][sl]
    f = fit_orders(np.column_stack([iq, wm]), th[sl])
    noise = np.asarray(f.noise_rms)
    d = r.scenario.control.design(r.scenario.machine)
    return {
        "stable": bool(m["stable"]),
        "iq_noise_a": float(noise[0]),
        "iq_total_a": float(np.std(iq)),
        "speed_noise_rpm": float(noise[1]) * 60 / (2 * math.pi),
        "granted_hz": float(d.speed_bandwidth_hz),
        "limited": bool(d.speed_limited),
        "kp": float(d.kp_w),
    }


def noise_limited_bandwidth(bws: list[float], noise: list[float], limit: float) -> float:
    """The largest bandwidth of a sweep (granted bandwidths, rising) whose noise is within
    `limit`, interpolated in log-log between the last setting within it and the first past
    it; nan if even the lowest setting that ran is past it, the highest setting within it if
    none is past it (a lost setting -- nan noise -- past the first that ran ends the sweep
    there; settings lost below it, too slow a loop for the start, are skipped)."""
    first = next((k for k, x in enumerate(noise) if math.isfinite(x)), None)
    if first is None or not noise[first] <= limit:
        return math.nan
    for k in range(first + 1, len(bws)):
        if not math.isfinite(noise[k]):
            return bws[k - 1]
        if noise[k] > limit and bws[k] > bws[k - 1]:
            x0, x1 = math.log(bws[k - 1]), math.log(bws[k])
            y0, y1 = math.log(max(noise[k - 1], 1e-12)), math.log(noise[k])
            return math.exp(x0 + (math.log(limit) - y0) * (x1 - x0) / (y1 - y0))
    return bws[-1]


def lowest_bandwidth_within(bws: list[float], noise: list[float], limit: float) -> float:
    """The lowest bandwidth of a sweep (granted bandwidths, rising) from which on the noise
    stays within `limit` (a noise that falls as the loop gets faster: the shaft's speed
    noise), interpolated in log-log between the last setting past it and the first within
    it; nan if the highest setting that ran is still past it.  Lost settings are skipped."""
    ok = [(b, x) for b, x in zip(bws, noise, strict=True) if math.isfinite(x)]
    if not ok or ok[-1][1] > limit:
        return math.nan
    k = len(ok) - 1
    while k > 0 and ok[k - 1][1] <= limit:
        k -= 1
    if k == 0 or ok[k][0] <= ok[k - 1][0]:
        return ok[k][0]
    (b0, y0), (b1, y1) = ok[k - 1], ok[k]
    t = (math.log(limit) - math.log(y0)) / (math.log(max(y1, 1e-12)) - math.log(y0))
    return math.exp(math.log(b0) + t * (math.log(b1) - math.log(b0)))


def _per_seed(bws, rs, limits) -> dict[str, float]:
    """One drive's sweep on one seed: the highest granted bandwidth that ran stable, and the
    noise-limited bandwidth under each stated limit (nan noise where a setting was lost)."""
    granted = [o["granted_hz"] for o in rs]
    out = {
        "design_max_hz": max(
            (g for g, o in zip(granted, rs, strict=True) if o["stable"]), default=math.nan
        )
    }
    for key, limit in limits.items():
        noise = [o[key] if o["stable"] else math.nan for o in rs]
        # i_q* noise grows with the loop's gain: a ceiling; the shaft's speed noise falls as
        # the loop holds the speed tighter: a floor
        find = noise_limited_bandwidth if key == "iq_noise_a" else lowest_bandwidth_within
        out[key] = find(granted, noise, limit)
    return out


def bandwidth_noise(ctx) -> dict[str, Any]:
    """The sweep per drive and seed (one in --quick): build -> run -> analyse -> plot."""
    seeds = (1,) if ctx.quick else tuple(range(1, 1 + MIN_SEEDS))
    target = 0.01 * card_current_bandwidth_hz(ctx.card)
    bws = [round(p * target, 6) for p in (BW_PU_QUICK if ctx.quick else BW_PU)]
    keys = [(d, bw, s) for d in DRIVES for bw in bws for s in seeds]
    res = ctx.run([(_scenario(ctx, d, bw, s), _x_noise, None) for d, bw, s in keys])
    limits = {
        "iq_noise_a": IQ_NOISE_LIMIT_PU * ctx.card.rated_current_a,
        "speed_noise_rpm": SPEED_NOISE_LIMIT_RPM,
    }
    out: dict[str, Any] = {}
    for d in DRIVES:
        per_seed = [
            _per_seed(
                bws,
                [o for (dd, _, ss), o in zip(keys, res, strict=True) if dd == d and ss == s],
                limits,
            )
            for s in seeds
        ]
        rows = [
            [o for (dd, bw, _), o in zip(keys, res, strict=True) if dd == d and bw == b]
            for b in bws
        ]
        out[d] = {
            **{k: _mean([p[k] for p in per_seed]) for k in ("design_max_hz", *limits)},
            "per_seed": per_seed,
            "sweep": [
                {
                    "design_hz": b,
                    "granted_hz": rr[0]["granted_hz"],
                    "limited": rr[0]["limited"],
                    "iq_noise_a": _mean([o["iq_noise_a"] for o in rr if o["stable"]]),
                    "iq_total_a": _mean([o["iq_total_a"] for o in rr if o["stable"]]),
                    "speed_noise_rpm": _mean([o["speed_noise_rpm"] for o in rr if o["stable"]]),
                    "stable_seeds": sum(o["stable"] for o in rr),
                }
                for b, rr in zip(bws, rows, strict=True)
            ],
        }
        top = [row for row in out[d]["sweep"] if row["stable_seeds"]]
        out[d]["at_design_max"] = top[-1] if top else None
    data = {
        "limits": limits,
        "iq_limit_pu": IQ_NOISE_LIMIT_PU,
        "target_hz": target,
        "seeds": list(seeds),
        "drives": out,
    }
    return {"claims": [], "figures": [_plot(ctx, data)], "data": data}


def _mean(xs: list[float]) -> float:
    a = np.asarray([x for x in xs if math.isfinite(x)], dtype=float)
    return float(np.mean(a)) if a.size else math.nan


def _plot(ctx, data: dict[str, Any]) -> str:
    p = plt()
    fig, ax = p.subplots(1, 2, figsize=(10, 3.8))
    for k, (d, v) in enumerate(data["drives"].items()):
        g = [row["granted_hz"] for row in v["sweep"]]
        ax[0].loglog(g, [row["iq_noise_a"] for row in v["sweep"]], "o-", color=f"C{k}", label=d)
        ax[1].loglog(g, [row["speed_noise_rpm"] for row in v["sweep"]], "o-", color=f"C{k}")
    ax[0].axhline(data["limits"]["iq_noise_a"], color="0.4", ls="--", lw=0.8, label="stated limit")
    ax[1].axhline(data["limits"]["speed_noise_rpm"], color="0.4", ls="--", lw=0.8)
    ax[0].set_ylabel("i_q* broadband noise, RMS [A]")
    ax[1].set_ylabel("shaft speed broadband noise, RMS [rpm]")
    ax[1].set_title("the i_q* limit: a ceiling; the speed limit: a floor", fontsize=8)
    for a in ax:
        a.set_xlabel("speed-loop bandwidth granted by the design [Hz]")
        a.grid(alpha=0.3, which="both")
    ax[0].legend(fontsize=7)
    ax[0].set_title("10 % speed, 30 % load, measured voltages (mean over seeds)", fontsize=8)
    return ctx.fig(fig, "bandwidth_noise")


GROUP = "beyond"  # experiments.registry lists this module
EXPERIMENTS = {
    "bandwidth_noise": (
        bandwidth_noise,
        "the speed-loop bandwidth each drive gets at a stated i_q* noise limit",
    ),
}
