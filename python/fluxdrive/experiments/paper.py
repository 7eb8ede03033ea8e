"""The paper's figures (Chen, Chen, Yang 2019): Figs. 2-4, 13, 14, 15/16, 17, 18, 19.

Every experiment returns {"claims": [...], "figures": [...], "data": {...}}; see
experiments.py for the framework and the claim format.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from fluxdrive.analysis.freqresp import analyse
from fluxdrive.analysis.metrics import (
    RAD_S_TO_RPM,
    handover,
    handover_text,
    harmonic,
    harmonic_spectrum,
    steady_window,
    thd_spectra,
    whole_periods,
    wrap,
)
from fluxdrive.core.machine import MachineCard, card_current_bandwidth_hz
from fluxdrive.core.transforms import clarke
from fluxdrive.drive.control import (
    CO_ID,
    CO_ID_REF,
    CO_IQ,
    CO_MODE,
    CO_W_FB,
    MODE_CLOSED_LOOP,
    ControllerConfig,
)
from fluxdrive.drive.observers import (
    ES_EA,
    ES_EB,
    ES_LA,
    ES_LB,
    ES_TH,
    ES_VALID,
    KernelObserver,
    observer_config,
)
from fluxdrive.drive.plant import TR_IA, TR_IB, TR_IC, TR_THETA_E, TR_WM
from fluxdrive.experiments.claims import MIN_SEEDS, judge, registered
from fluxdrive.experiments.common import (
    LITERAL,
    OBS4,
    OBS6,
    PAPER_BENCH,
    START_PU,
    Ctx,
    plt,
)

RPM = 2 * math.pi / 60
# the non-ideal bench of the paper scenarios, for the experiments that build their own runs
# (Figs. 13, 15-18 and paper_robust; Figs. 2-4 are the paper's own idealised simulations)
BENCH = str(PAPER_BENCH)


def _win(r):
    w = steady_window(r.t, r.scenario.steady_window_s)
    return slice(w.k0, w.k1)


def theta_err(r, name):
    return wrap(r.estimate(name)[:, ES_TH] - r.truth[:, TR_THETA_E])


def _dec(x, n=3000):
    return x[:: max(1, len(x) // n)]


# ======================================================================== Fig. 14
def op_point(r) -> dict:
    """The run's operating point over its steady window and every observer's speed path and
    cut-off: what verdict texts quote instead of typed numbers."""
    sl = _win(r)
    mc = r.scenario.machine
    rpm = float(np.mean(r.truth[sl, TR_WM])) * RAD_S_TO_RPM
    lp = r.scenario.load_profile_pu
    return {
        "rpm": rpm,
        "speed_pu": rpm / mc.rated_speed_rpm,
        "fe_hz": abs(rpm) / 60.0 * mc.pole_pairs,
        "load_pu": float(lp[-1, 1]),
        "obs": {
            nm: {
                "cutoff_hz": float(o.cutoff_hz or 0.0),
                "pll_hz": float(o.pll_bandwidth_hz or 0.0),
                "lpf_hz": float(o.speed_lpf_hz or 0.0),
            }
            for nm, o in r.scenario.observers.items()
        },
    }


def _x_fig14(r, m, show_s=0.5):
    sl = _win(r)
    th = r.truth[sl, TR_THETA_E]
    cap = r.scenario.bench.voltage_capture
    out = {"metrics": m, "noise": {}, "op": op_point(r)}
    out["capture"] = (
        None
        if cap is None
        else {"delay_diff_s": cap.delay_rise_s - cap.delay_fall_s, "min_pulse_s": cap.min_pulse_s}
    )
    n_show = int(show_s / r.scenario.machine.ts_s)
    series = {"t": _dec(r.t[sl][-n_show:]), "theta": _dec(th[-n_show:])}
    for nm in r.names:
        e = theta_err(r, nm)[sl]
        out["noise"][nm] = m["observers"][nm]["theta_err_noise_deg"]
        series[nm] = _dec(np.degrees(e[-n_show:]))
        series[nm + "_th"] = _dec(r.estimate(nm)[sl, ES_TH][-n_show:])
    out["series"] = series
    return out


def per_seed(vals: list[float], fmt: str = "{:.2f}", rel: float = 0.5) -> str:
    """One number when the seeds agree (within `rel` of their median), else every seed's."""
    v = np.asarray(vals, dtype=float)
    med = float(np.median(v))
    if len(v) == 1 or np.all(np.abs(v - med) <= rel * max(abs(med), 1e-9)):
        return fmt.format(float(np.mean(v)))
    return "[" + ", ".join(fmt.format(x) for x in v) + " per seed]"


VARIANTS = (("paper_robust", "flux"), ("paper (literal)", "paper"))
SLIP_DEG = 30.0  # a seed whose |θ̃| passes this anywhere in the window has slipped


def _fig14_jobs(ctx, seeds: list[int]) -> list:
    return [(ctx.build(base="paper_2pct_150load", seed=s), _x_fig14, None) for s in seeds]


def _fig14_analyse(res: list[dict]) -> dict:
    """Per observer, per seed: θ̃ RMS, mean, 6th order, broadband noise, peak; stability;
    slips."""
    names = list(OBS6)

    def per(key: str) -> dict[str, list[float]]:
        return {n: [r["metrics"]["observers"][n][key] for r in res] for n in names}

    peak = per("theta_err_peak_deg")
    return {
        "rms": per("theta_err_rms_deg"),
        "mean": per("theta_err_mean_deg"),
        "h6": per("theta_err_h6_deg"),
        "noise": {n: [r["noise"][n] for r in res] for n in names},
        "peak": peak,
        "stable": [r["metrics"]["stable"] for r in res],
        "slipped": {n: [p > SLIP_DEG for p in peak[n]] for n in names},
        "op": res[0]["op"],
        "capture": res[0]["capture"],
    }


def _fig14_plot(ctx, a: dict, s: dict, seed: int) -> str:
    p = plt()
    op = a["op"]
    fig, ax = p.subplots(4, 2, figsize=(11, 9), sharex=True)
    for c, src in enumerate(("commanded", "measured")):
        ax[0, c].plot(s["t"], np.degrees(wrap(s["theta"])), lw=0.8, label="θe (encoder)")
        ax[0, c].plot(s["t"], np.degrees(s[f"flux_{src}_th"]), lw=0.8, label="θ̂ flux")
        ax[0, c].set_ylabel("angle [deg]")
        ax[0, c].legend(fontsize=7)
        ax[0, c].set_title(
            f"({'ab'[c]}) {src} voltages, {op['rpm']:.0f} rpm ({100 * op['speed_pu']:.0f} %), "
            f"{100 * op['load_pu']:.0f} % load (seed {seed})"
        )
        for rr, (kind, lab) in enumerate(
            (("emf", "emf"), ("flux", "flux robust"), ("paper", "flux literal")), 1
        ):
            nm = f"{kind}_{src}"
            ax[rr, c].plot(s["t"], s[nm], lw=0.6)
            ax[rr, c].set_ylim(-40, 40)
            ax[rr, c].set_ylabel(f"θ̃ {lab} [deg]", fontsize=8)
            ax[rr, c].grid(alpha=0.3)
            ax[rr, c].text(
                0.01,
                0.85,
                f"RMS {per_seed(a['rms'][nm])}°, 6th {per_seed(a['h6'][nm])}°, "
                f"noise {per_seed(a['noise'][nm])}°",
                transform=ax[rr, c].transAxes,
                fontsize=7,
            )
        ax[3, c].set_xlabel("time [s]")
    return ctx.fig(fig, "fig14_theta_error")


def div(a: float, b: float) -> float:
    """a / b, nan where b is zero (a run that stopped: no speed, no band)."""
    return a / b if b else math.nan


def _med(d: dict, n: str) -> float:
    return float(np.median(d[n]))


def _fig14_commanded_snr_why(a: dict, fc: str) -> str:
    """Why the commanded-voltage θ̃ RMS is the deadtime 6th order's, numbers from the run."""
    op, noise = a["op"], a["noise"]
    flux, emf = op["obs"][fc], op["obs"]["emf_commanded"]
    fe, wc = op["fe_hz"], flux["cutoff_hz"]
    lpf = f" plus a {emf['lpf_hz']:.0f} Hz speed LPF" if emf["lpf_hz"] else ""
    return (
        f"the total RMS is the deadtime 6th order's: at {100 * op['speed_pu']:.0f} % speed the "
        f"5th/7th ({5 * fe:.0f}-{7 * fe:.0f} Hz) lie at up to {7 * fe / wc:.2f} of the "
        f"{wc:.0f} Hz cut-off, where LPF + inverse HPF has about the EMF's 1/(jω) gain, and the "
        f"EMF path's {emf['pll_hz']:.0f} Hz PLL{lpf} filters the {6 * fe:.0f} Hz θ̃ ripple "
        f"more than the flux path's {flux['pll_hz']:.0f} Hz one.  The broadband part passes "
        "each PLL in proportion to √(its bandwidth): per √Hz of PLL bandwidth flux "
        f"{_med(noise, fc) / math.sqrt(flux['pll_hz']):.3f}° vs emf "
        f"{_med(noise, 'emf_commanded') / math.sqrt(emf['pll_hz']):.3f}°"
    )


def _fig14_capture_why(a: dict) -> str:
    cap = a["capture"]
    if cap is None:
        return "the bench has no voltage capture model: the measured voltages are exact"
    return (
        "the bench's capture chain (comparator threshold and edge ramp, a "
        f"{1e9 * abs(cap['delay_diff_s']):.0f} ns rise/fall delay difference, a "
        f"{1e9 * cap['min_pulse_s']:.0f} ns minimum pulse) mis-measures short line pulses, so "
        "a deadtime-like residue of the 6th order stays"
    )


def _fig14_measured_snr_why(a: dict, k: str) -> str:
    why = (
        "verdict on the SNR, i.e. the broadband noise; the total RMS also carries the "
        "6th-order residue of the capture chain (previous row), which the EMF path's "
        "lower-bandwidth PLL filters more"
    )
    if k != "paper":
        return why
    op = a["op"]
    return why + (
        "; the literal observer compensates at the PLL's own ω̂e: its θ̃ ripple moves ω̂e, "
        "which moves the compensation angle atan(ωc/ω̂e) -- a loop that amplifies "
        f"low-frequency θ̃ noise at {100 * op['speed_pu']:.0f} % speed (ωc/ωe = "
        f"{div(op['obs']['paper_measured']['cutoff_hz'], op['fe_hz']):.0f}), and a seed can "
        "slip"
    )


def _ratio(d: dict, a: str, b: str) -> list[float]:
    """Per seed: d[a] over d[b] (the same seed's runs: a paired comparison)."""
    return [div(x, y) for x, y in zip(d[a], d[b], strict=True)]


def _ci(c: dict, fmt: str = "{:.3g}") -> str:
    """' (mean M, 95 % CI [lo, hi], N seeds: outcome)' of a row judged over seeds."""
    st = c.get("stats")
    if not st:
        return ""
    lo, hi = (fmt.format(x) for x in st["ci95"])
    return (
        f" (mean {fmt.format(st['mean'])}, 95 % CI [{lo}, {hi}], {st['n']} seeds: {st['outcome']})"
    )


def _with_ci(c: dict) -> dict:
    c["ours"] += _ci(c)
    return c


def _fig14_variant_claims(a: dict, vname: str, k: str) -> list[dict]:
    """The four per-variant rows: 6th order and SNR on commanded and measured voltages, each
    over the seeds (per-seed values, paired flux/EMF on the same seed)."""
    rms, h6, noise, sl = a["rms"], a["h6"], a["noise"], a["slipped"]
    fc, fm = f"{k}_commanded", f"{k}_measured"
    ec, em = "emf_commanded", "emf_measured"

    def q(d, n):
        return per_seed(d[n])

    slips = (
        f"; seeds with a slip (|θ̃| > {SLIP_DEG:.0f}°): flux {sum(sl[fm])}, emf {sum(sl[em])}"
        if any(sl[fm] + sl[em])
        else ""
    )
    gone = [
        max(div(x_em, x_ec), div(x_fm, x_fc))
        for x_em, x_ec, x_fm, x_fc in zip(h6[em], h6[ec], h6[fm], h6[fc], strict=True)
    ]
    rows = [
        judge(
            "fig14.commanded_6th",
            f"6th order: emf {q(h6, ec)}°, flux {q(h6, fc)}° (RMS {q(rms, ec)}° / {q(rms, fc)}°)",
            math.nan,
            variant=vname,
            samples=[min(x, y) for x, y in zip(h6[ec], h6[fc], strict=True)],
        ),
        judge(
            "fig14.commanded_snr",
            f"broadband noise (θ̃ minus the joint fit of orders 0-20): flux {q(noise, fc)}° vs "
            f"emf {q(noise, ec)}°; total RMS {q(rms, fc)}° vs {q(rms, ec)}°",
            math.nan,
            _fig14_commanded_snr_why(a, fc),
            variant=vname,
            samples=_ratio(noise, fc, ec),
        ),
        judge(
            "fig14.measured_6th_gone",
            f"6th order: emf {q(h6, em)}°, flux {q(h6, fm)}° (commanded: {q(h6, ec)}° / "
            f"{q(h6, fc)}°)",
            math.nan,
            _fig14_capture_why(a),
            variant=vname,
            samples=gone,
        ),
        judge(
            "fig14.measured_snr",
            f"noise flux {q(noise, fm)}° vs emf {q(noise, em)}°; RMS {q(rms, fm)}° vs "
            f"{q(rms, em)}°" + slips,
            math.nan,
            _fig14_measured_snr_why(a, k),
            variant=vname,
            samples=_ratio(noise, fm, em),
            also={"theta_rms_ratio": float(np.mean(_ratio(rms, fm, em)))},
        ),
    ]
    return [_with_ci(c) for c in rows]


def _fig14_position_claims(a: dict, vname: str, k: str) -> list[dict]:
    """The paper's position-error claim, per voltage source: total θ̃ RMS and its mean and
    6th-order parts, flux over (or minus) EMF, per seed."""
    rms, h6, mean = a["rms"], a["h6"], a["mean"]
    rows = []
    for src in ("commanded", "measured"):
        f, e = f"{k}_{src}", f"emf_{src}"
        tag = f"{vname}, {src}"
        absd = [abs(x) - abs(y) for x, y in zip(mean[f], mean[e], strict=True)]
        rows += [
            judge(
                "fig14.position_error_rms",
                f"θ̃ RMS flux {per_seed(rms[f])}° vs emf {per_seed(rms[e])}°",
                math.nan,
                variant=tag,
                samples=_ratio(rms, f, e),
            ),
            judge(
                "fig14.position_error_mean",
                f"mean θ̃ flux {per_seed(mean[f])}° vs emf {per_seed(mean[e])}°",
                math.nan,
                variant=tag,
                samples=absd,
            ),
            judge(
                "fig14.position_error_h6",
                f"6th order of θ̃ flux {per_seed(h6[f])}° vs emf {per_seed(h6[e])}°",
                math.nan,
                variant=tag,
                samples=_ratio(h6, f, e),
            ),
        ]
    return [_with_ci(c) for c in rows]


def _fig14_judge(a: dict) -> list[dict]:
    claims = [c for vname, k in VARIANTS for c in _fig14_variant_claims(a, vname, k)]
    claims += [c for vname, k in VARIANTS for c in _fig14_position_claims(a, vname, k)]
    st = a["stable"]
    claims.append(
        judge(
            "fig14.stable",
            f"paper_robust driving: stable on {sum(st)}/{len(st)} seeds (the literal observer as "
            "the driving one: see the paper_robust experiment)",
            math.nan,
            samples=[float(bool(x)) for x in st],
        )
    )
    return claims


def fig14(ctx):
    """Fig. 14: θ̃ of every observer on commanded and measured voltages at the 2 % / 150 %
    point, per seed: build -> run -> analyse -> plot -> judge."""
    seeds = [1] if ctx.quick else list(range(1, 1 + MIN_SEEDS))
    res = ctx.run(_fig14_jobs(ctx, seeds))
    a = _fig14_analyse(res)
    figs = [_fig14_plot(ctx, a, res[0]["series"], seeds[0])]
    data = {"seeds": seeds, "rms_deg": a["rms"], "h6_deg": a["h6"], "noise_deg": a["noise"]}
    data["mean_deg"] = a["mean"]
    data["peak_deg"] = a["peak"]
    return {"claims": _fig14_judge(a), "figures": figs, "data": data}


# ======================================================================== Fig. 13
def _bench_effects(bench) -> str:
    """The effects a run's bench has on, with their numbers (for the texts)."""
    on = []
    if bench.voltage_capture is not None:
        on.append("voltage capture")
    if bench.current_sample_skew_s and any(bench.current_sample_skew_s):
        on.append("current-sampling skew")
    om = bench.observer_model
    if om is not None:
        on.append(f"observer model R̂ {om.r_pu:g}, L̂ {om.l_pu:g}, λ̂ {om.lambda_pu:g} of the card")
    if bench.thermal is not None:
        on.append("winding heating")
    h5, h7 = bench.spatial_saturation_h5_h7()
    if h5 or h7:
        on.append(
            f"spatial saturation (magnet-flux 5th {h5:.3g} pu, 7th {h7:.3g} pu at I_rated: "
            f"{abs(h5 + h7):.3g} pu of radius, {abs(h7 - h5):.3g} rad of angle)"
        )
    return ", ".join(on) if on else "the ideal bench"


def _radius_h6(radius: np.ndarray, thu: np.ndarray) -> float:
    """6th order of a locus radius over its mean: how hexagonal the locus is (nan for a
    locus that is a point: a run that stopped)."""
    mean = float(radius.mean()) if radius.size else 0.0
    if mean <= 0.0 or radius.size < 2:
        return math.nan
    return float(abs(harmonic(radius - mean, thu, 6)) / mean)


def _x_locus(r, m):
    sl = _win(r)
    mc = r.scenario.machine
    we = float(np.mean(r.truth[sl, TR_WM])) * mc.pole_pairs
    emf = r.estimate("emf_measured")[sl]
    flx = r.estimate("flux_measured")[sl]
    e_a, e_b = emf[:, ES_EA], emf[:, ES_EB]
    n_av = max(1, round(1e-3 / mc.ts_s))  # 1 ms moving average (what a scope would show)
    k = np.ones(n_av) / n_av
    ea_f, eb_f = np.convolve(e_a, k, "valid"), np.convolve(e_b, k, "valid")
    re, ref = np.hypot(e_a, e_b), np.hypot(ea_f, eb_f)
    rf = np.hypot(flx[:, ES_LA], flx[:, ES_LB]) * we
    thu = np.unwrap(r.truth[sl, TR_THETA_E])

    def rng(x):
        return [float(np.percentile(x, 0.5)), float(np.percentile(x, 99.5))]

    kc = np.nonzero(r.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP)[0]
    i_if = r.scenario.control.if_current_pu * mc.rated_current_a
    kt = 1.5 * mc.pole_pairs * mc.flux_linkage_vs
    return {
        "metrics": m,
        "we": we,
        "ripple_rpm": m["speed"]["ripple_rpm"],
        "handover_s": float(r.t[kc[0]]) if kc.size else float("nan"),
        "handover_lpf_hz": float(r.scenario.control.handover_agree_lpf_hz or 0.0),
        "window_s": float(r.scenario.steady_window_s[0]),
        "if_swing_hz": math.sqrt(mc.pole_pairs * kt * i_if / mc.inertia_kgm2) / (2 * math.pi),
        "n_av": n_av,
        "bench": _bench_effects(r.scenario.bench),
        "emf_raw": rng(re),
        "emf_1ms": rng(ref),
        "emf_h6_rel": _radius_h6(ref, thu[n_av - 1 :]),
        "flux_v": rng(rf),
        "flux_mean_v": float(rf.mean()),
        "flux_h6_rel": _radius_h6(rf, thu),
        "emf_series": (_dec(ea_f, 4000), _dec(eb_f, 4000)),
        "emf_raw_series": (_dec(e_a, 4000), _dec(e_b, 4000)),
        "flux_series": (_dec(flx[:, ES_LA] * we, 4000), _dec(flx[:, ES_LB] * we, 4000)),
    }


def _fig13_cases(ctx) -> list[tuple[str, float, dict]]:
    """(label, load, scenario keys): no load and full load on the paper bench; the full run
    adds full load on the ideal bench and the no-load start with the per-sample handover."""
    cases: list[tuple[str, float, dict[str, Any]]] = [
        ("no load", 0.0, {"bench": BENCH}),
        ("full load", 1.0, {"bench": BENCH}),
    ]
    if not ctx.quick:
        cases.append(("full load, ideal bench", 1.0, {}))
        ctrl = {"handover_agree_lpf_hz": 0.0}
        cases.append(("no load, per-sample handover", 0.0, {"bench": BENCH, "control": ctrl}))
    return cases


def _fig13_jobs(ctx, cases) -> list:
    obs = {k: OBS4[k] for k in ("flux_measured", "emf_measured")}
    speed = ctx.rpm(0.02)
    return [
        (ctx.sensorless(speed, ld, observers=obs, name="fig13", **kw), _x_locus, None)
        for _, ld, kw in cases
    ]


def _fig13_plot(ctx, cases, res) -> str:
    p = plt()
    n_plot = min(len(cases), 3)
    lim = 1.2 * max(max(r["emf_raw"][1], r["flux_v"][1]) for r in res[:n_plot])
    fig, ax = p.subplots(2, n_plot, figsize=(3.6 * n_plot, 7.2), squeeze=False)
    for c, ((lab, _, _), r) in enumerate(zip(cases[:n_plot], res[:n_plot], strict=True)):
        for row, (key, what) in enumerate((("emf", "ê"), ("flux", "ω·λ̂pm"))):
            a = ax[row, c]
            if key == "emf":
                a.plot(*r["emf_raw_series"], lw=0.3, color="0.75", label="per sample")
                a.plot(*r["emf_series"], lw=0.5, label=f"{r['n_av']}-sample average")
                a.legend(fontsize=6, loc="lower right")
                rr = r["emf_raw"]
            else:
                a.plot(*r["flux_series"], lw=0.5)
                rr = r["flux_v"]
            a.set_aspect("equal")
            a.set_xlim(-lim, lim)
            a.set_ylim(-lim, lim)
            a.set_title(
                f"({'abcdef'[row * n_plot + c]}) {what}, {lab}\nradius {rr[0]:.2f}-{rr[1]:.2f} V",
                fontsize=8,
            )
            a.set_xlabel("α [V]")
            a.set_ylabel("β [V]")
    return ctx.fig(fig, "fig13_loci")


def _band(x: list[float]) -> float:
    return x[1] - x[0]


def _fig13_emf_claims(ctx, nl: dict, fl: dict, ideal: dict | None, r_nl: float) -> list[dict]:
    mc, card = ctx.cv, ctx.card
    ratio = _band(fl["emf_1ms"]) / _band(nl["emf_1ms"])
    ideal_txt = (
        f"; on the ideal bench {100 * ideal['emf_h6_rel']:.1f} %" if ideal is not None else ""
    )
    shows = (
        f"panel (b): over {fl['n_av']} samples the full-load ê radius spans "
        f"{_band(fl['emf_1ms']):.2f} V against {_band(nl['emf_1ms']):.2f} V at no load "
        f"({ratio:.2f}×), and its 6th order is {100 * fl['emf_h6_rel']:.1f} % of the mean radius "
        f"({100 * nl['emf_h6_rel']:.1f} % at no load{ideal_txt}): the locus "
        + ("turns hexagonal" if fl["emf_h6_rel"] > 2 * nl["emf_h6_rel"] else "keeps its shape")
        + f" under load on this bench ({fl['bench']})"
    )
    return [
        judge(
            "fig13.noload_emf_noisy",
            f"ê radius {nl['emf_raw'][0]:.2f}-{nl['emf_raw'][1]:.2f} V per sample, "
            f"{nl['emf_1ms'][0]:.2f}-{nl['emf_1ms'][1]:.2f} V over {nl['n_av']} samples "
            f"(ω·λ = {r_nl:.2f} V)",
            _band(nl["emf_1ms"]) / r_nl,
            f"per-sample band: the current sensor's {1e3 * card.current_noise_a:.0f} mA RMS noise "
            f"({card.current_adc_bits}-bit ADC) times L/Ts = {mc.l / mc.ts:.1f} Ω; the "
            f"{1e3 * nl['n_av'] * mc.ts:.0f} ms average is closer to a scope view",
        ),
        judge(
            "fig13.fullload_emf_distorts",
            f"ê radius {fl['emf_raw'][0]:.2f}-{fl['emf_raw'][1]:.2f} V per sample, "
            f"{fl['emf_1ms'][0]:.2f}-{fl['emf_1ms'][1]:.2f} V over {fl['n_av']} samples",
            ratio,
            shows,
        ),
    ]


def _fig13_handover_txt(nl: dict, ps: dict | None) -> str:
    """The no-load start as run (filtered handover), and the per-sample one for comparison."""
    txt = (
        f"run: sensorless start on the paper bench ({nl['bench']}), handover on the estimate's "
        f"agreement with the I-f ramp low-passed at {nl['handover_lpf_hz']:g} Hz at "
        f"{nl['handover_s']:.2f} s, window from {nl['window_s']:.2f} s, speed ripple "
        f"{nl['ripple_rpm']:.0f} rpm p-p; the radius is |λ̂| times the window's mean speed, so "
        "this band is |λ̂|'s own"
    )
    if ps is None:
        return txt
    return txt + (
        f".  With the per-sample handover criterion (control.handover_agree_lpf_hz = 0) the same "
        f"start hands over at {ps['handover_s']:.2f} s (window from {ps['window_s']:.2f} s): the "
        "unloaded rotor swings about the I-f vector (undamped, sqrt(p K_t I_if/J)/2π = "
        f"{ps['if_swing_hz']:.0f} Hz), which resets a per-sample check; ω·|λ̂| then spans "
        f"{ps['flux_v'][0]:.3f}-{ps['flux_v'][1]:.3f} V with {ps['ripple_rpm']:.0f} rpm p-p of "
        "speed ripple"
    )


def _fig13_flux_claims(nl, fl, ideal, ps, r_nl) -> list[dict]:
    claims = [
        judge(
            "fig13.noload_flux_circle",
            f"ω·|λ̂| {nl['flux_v'][0]:.3f}-{nl['flux_v'][1]:.3f} V, mean "
            f"{nl['flux_mean_v']:.3f} V (speed ripple {nl['ripple_rpm']:.1f} rpm p-p at "
            f"no load; full load {fl['flux_v'][0]:.3f}-{fl['flux_v'][1]:.3f} V)",
            _band(nl["flux_v"]) / r_nl,
            _fig13_handover_txt(nl, ps),
        ),
        judge(
            "fig13.fullload_flux_tighter",
            f"flux band {_band(fl['flux_v']):.3f} V vs EMF band {_band(fl['emf_1ms']):.3f} V "
            f"({fl['n_av']}-sample average), {_band(fl['emf_raw']):.2f} V (per sample)",
            _band(fl["flux_v"]) / _band(fl["emf_1ms"]),
        ),
    ]
    if ideal is not None:
        claims.append(
            judge(
                "fig13.fullload_hexagon",
                f"6th order of |λ̂| at full load: {100 * fl['flux_h6_rel']:.2f} % on the "
                f"non-ideal bench vs {100 * ideal['flux_h6_rel']:.2f} % on the ideal bench; no "
                f"load {100 * nl['flux_h6_rel']:.2f} %",
                fl["flux_h6_rel"] / ideal["flux_h6_rel"],
                "the bench's spatial saturation gives the magnet flux 5th/7th orders growing "
                "with (i/I_rated)²: a 6th order in |λ̂| under load only; which 5th/7th split "
                "Figs. 13(d) and 14(b) allow together: experiment hexagon",
            )
        )
    return claims


def fig13(ctx):
    """Fig. 13: EMF and flux loci at 2 % speed, no load and full load: build -> run -> plot ->
    judge (the extractor analyses each run)."""
    cases = _fig13_cases(ctx)
    res = ctx.run(_fig13_jobs(ctx, cases))
    mc = ctx.cv  # the card's values
    r_nl = ctx.rpm(0.02) * RPM * mc.p * mc.lam  # |e| = w lambda at 2 % speed [V]
    figs = [_fig13_plot(ctx, cases, res)]
    nl, fl = res[0], res[1]
    ideal = res[2] if len(res) > 2 else None
    ps = res[3] if len(res) > 3 else None
    claims = _fig13_emf_claims(ctx, nl, fl, ideal, r_nl) + _fig13_flux_claims(
        nl, fl, ideal, ps, r_nl
    )
    data = {
        lab: {k: v for k, v in r.items() if not k.endswith("series") and k != "metrics"}
        for (lab, _, _), r in zip(cases, res, strict=True)
    }
    return {"claims": claims, "figures": figs, "data": data}


# ======================================================================== Figs. 2-4
def _x_frames(r, m):
    return {
        "metrics": m,
        "frames": r.frames,
        "theta": r.truth[:, TR_THETA_E],
        "t": r.t,
        "iq": r.ctrl[:, CO_IQ],
        "wm": r.truth[:, TR_WM],
        "win": r.scenario.steady_window_s,
    }


def _replay(card, frames, variant, src, **kw):
    obs = KernelObserver(observer_config(variant, voltage_source=src, **kw), card)
    return obs.run(frames)


OFFSET_PU = 0.05  # Fig. 3's current-sensor offset on i_b, of the rated current


def _fig2_4_jobs(ctx) -> list:
    pure = {"pure_integrator": {"variant": "pure_integrator", "voltage_source": "measured"}}
    card_kw = {"inertia_kgm2": 100 * ctx.card.inertia_kgm2}  # isolate the estimator
    low = ctx.rpm(0.02)
    jobs = [
        # Fig. 2 and 4: encoder drive at 2 % (and 10 %) speed, full load, no sensor offsets
        (ctx.encoder_run(low, 1.0, observers=pure, window_s=1.0), _x_frames, None),
        # Fig. 3: an offset on i_b, 2 % speed, no load
        (
            ctx.build(
                machine_kw=card_kw,
                duration_s=2.0,
                speed_rpm=low,
                steady_window_s=[1.0, 2.0],
                faults={"current_offset_pu": [0.0, OFFSET_PU, 0.0]},
                observers={"pure": {"variant": "pure_integrator"}, "paper": {"variant": "paper"}},
            ),
            _x_frames,
            None,
        ),
    ]
    if not ctx.quick:
        jobs.append(
            (ctx.encoder_run(ctx.rpm(0.1), 1.0, observers=pure, window_s=1.0), _x_frames, None)
        )
    return jobs


def _fig2_analyse(ctx, r) -> dict:
    """Pure integration started where θ = 45°: the locus centre against eq. (6)'s."""
    mc = ctx.cv
    th = r["theta"]
    k_start = int(np.searchsorted(r["t"], r["win"][0]))
    n_search = int(round(0.3 / mc.ts))  # look for 45° within 0.3 s of the window's start
    near = np.abs(wrap(th[k_start : k_start + n_search] - math.radians(45)))
    k0 = k_start + int(np.argmin(near))
    est = _replay(ctx.card, r["frames"][k0:], "pure_integrator", "measured")
    n_per = int(round(2 * math.pi / (np.mean(r["wm"][k0:]) * mc.p) / mc.ts))
    seg = est[1 : 1 + 2 * n_per]
    centre = complex(seg[:, ES_LA].mean(), seg[:, ES_LB].mean())
    # the observer integrates the EMF v - R i - L di/dt from zero, so it misses
    # lambda_pm(t0): centre -|lambda| e^{j theta0} (eq. 6), whatever the current
    pred = -mc.lam * np.exp(1j * th[k0])
    e2 = wrap(seg[:, ES_TH] - th[k0 + 1 : k0 + 1 + 2 * n_per])
    h1 = abs(harmonic(e2, np.unwrap(th[k0 + 1 : k0 + 1 + 2 * n_per]), 1))
    rpm = float(np.mean(r["wm"][k0:])) * RAD_S_TO_RPM
    return {"seg": seg, "centre": centre, "pred": pred, "h1": h1, "rpm": rpm}


def _fig2_plot(ctx, f2: dict) -> str:
    p = plt()
    seg, centre, pred = f2["seg"], f2["centre"], f2["pred"]
    fig, ax = p.subplots(1, 2, figsize=(10, 4))
    tt = np.arange(len(seg)) * ctx.cv.ts
    ax[0].plot(tt, seg[:, ES_LA] * 1e3, label="λ̂α")
    ax[0].plot(tt, seg[:, ES_LB] * 1e3, label="λ̂β")
    ax[0].axhline(centre.real * 1e3, color="C0", ls="--", lw=0.7)
    ax[0].axhline(centre.imag * 1e3, color="C1", ls="--", lw=0.7)
    ax[0].set_xlabel("time since integration start [s]")
    ax[0].set_ylabel("flux [mV·s]")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"Fig. 2: pure integration from θ0 = 45° ({f2['rpm']:.0f} rpm)", fontsize=9)
    ax[1].plot(seg[:, ES_LA] * 1e3, seg[:, ES_LB] * 1e3, lw=0.6)
    ax[1].plot(pred.real * 1e3, pred.imag * 1e3, "rx", label="eq. 6 centre")
    ax[1].set_aspect("equal")
    ax[1].legend(fontsize=8)
    ax[1].set_xlabel("λ̂α [mV·s]")
    ax[1].set_ylabel("λ̂β [mV·s]")
    return ctx.fig(fig, "fig2_integration_offset")


def _fig2_claim(f2: dict) -> dict:
    centre, pred = f2["centre"], f2["pred"]
    return judge(
        "fig2.offset",
        f"locus centre {1e3 * abs(centre):.2f} mV·s at {math.degrees(np.angle(centre)):.0f}° "
        f"(eq. 6: {1e3 * abs(pred):.2f} mV·s at {math.degrees(np.angle(pred)):.0f}°); θ̃ 1st "
        f"order {math.degrees(f2['h1']):.0f}°",
        abs(centre - pred) / abs(pred),
    )


def _fig3_analyse(ctx, r) -> dict:
    """The pure integrator's drift under an i_b offset, and the bounded LPF + inverse HPF."""
    mc, ts = ctx.cv, ctx.cv.ts
    est_p = _replay(ctx.card, r["frames"], "pure_integrator", "measured")
    est_q = _replay(ctx.card, r["frames"], "paper", "measured")
    est_r = _replay(ctx.card, r["frames"], "paper_robust", "measured")
    we = ctx.rpm(0.02) * RPM * mc.p  # the run's speed (_fig2_4_jobs)
    n_per = int(round(2 * math.pi / we / ts))  # one electrical period
    ks = list(range(int(round(0.2 / ts)), len(est_p) - n_per, n_per))
    cen = np.array(
        [
            complex(est_p[k : k + n_per, ES_LA].mean(), est_p[k : k + n_per, ES_LB].mean())
            for k in ks
        ]
    )
    tk = np.array(ks) * ts
    rate = np.polyfit(tk, cen.real, 1)[0] + 1j * np.polyfit(tk, cen.imag, 1)[0]
    dab = complex(*clarke(0.0, OFFSET_PU * mc.i_rated, 0.0))
    wc = 2 * math.pi * float(observer_config("paper", ctx.card).cutoff_hz or 0.0)
    # the LPF leaves R*Delta/w_c, the inverse HPF multiplies it by |1 - j w_c/w|
    off_pred = mc.r * abs(dab) / wc * abs(1 - 1j * wc / we)
    sl = slice(int(round(1.0 / ts)), None)  # after the filters have settled
    thq = r["theta"][sl]
    err = {
        v: wrap(e[sl, ES_TH] - thq)
        for v, e in (("paper_robust", est_r), ("paper (literal)", est_q))
    }
    h1 = {v: abs(harmonic(e, np.unwrap(thq), 1)) for v, e in err.items()}
    return {
        "est_p": est_p,
        "est_q": est_q,
        "rate": rate,
        "pred_rate": -mc.r * dab,  # x = v - R i_meas: the offset enters as -R*Delta
        "err": err,
        "h1": h1,
        "h1_pred": math.asin(min(off_pred / mc.lam, 1.0)),
        "hpf_gain": abs(1 - 1j * wc / we),
        "rpm": we / mc.p * RAD_S_TO_RPM,
        "settle_k": sl.start,
    }


def _fig3_plot(ctx, r, f3: dict) -> str:
    p = plt()
    est_p, est_q, k1 = f3["est_p"], f3["est_q"], f3["settle_k"]
    fig, ax = p.subplots(1, 2, figsize=(10, 4))
    step = max(1, int(round(2e-3 / ctx.cv.ts)))  # plot every 2 ms
    dd = slice(0, len(est_p), step)
    ax[0].plot(r["t"][dd], est_p[dd, ES_LA] * 1e3, lw=0.6, label="λ̂α pure integrator")
    ax[0].plot(r["t"][dd], est_p[dd, ES_LB] * 1e3, lw=0.6, label="λ̂β pure integrator")
    ax[0].plot(r["t"][dd], est_q[dd, ES_LA] * 1e3, lw=0.6, label="λ̂α proposed")
    ax[0].set_xlabel("time [s]")
    ax[0].set_ylabel("flux [mV·s]")
    ax[0].legend(fontsize=7)
    ax[0].set_title(
        f"Fig. 3: {100 * OFFSET_PU:.0f} % offset on i_b ({f3['rpm']:.0f} rpm)", fontsize=9
    )
    ax[1].plot(est_p[dd, ES_LA] * 1e3, est_p[dd, ES_LB] * 1e3, lw=0.5, label="pure")
    q = slice(k1, None, step)
    ax[1].plot(est_q[q, ES_LA] * 1e3, est_q[q, ES_LB] * 1e3, lw=0.5, label="proposed")
    ax[1].set_aspect("equal")
    ax[1].legend(fontsize=7)
    return ctx.fig(fig, "fig3_offset_drift")


def _fig3_claims(f3: dict) -> list[dict]:
    rate, pred_rate = f3["rate"], f3["pred_rate"]
    claims = [
        judge(
            "fig3.drift",
            f"locus centre drifts at {1e3 * abs(rate):.3f} mV·s/s (predicted R̂·|Δi_αβ| = "
            f"{1e3 * abs(pred_rate):.3f}), direction {math.degrees(np.angle(rate)):.0f}° "
            f"(pred. {math.degrees(np.angle(pred_rate)):.0f}°)",
            abs(rate - pred_rate) / abs(pred_rate),
        )
    ]
    literal = (
        "; the literal observer compensates at the PLL's ω̂e, which that 1st-order ripple "
        "modulates, and with L̂·i filtered at ω̂e (eq. 5) it can be kicked through ω̂e = 0 into "
        "a 180° false lock"
    )
    for vname, e_ in f3["err"].items():
        pk = float(np.degrees(np.max(np.abs(e_))))
        claims.append(
            judge(
                "fig3.bounded",
                f"θ̃ peak {pk:.1f}°; the DC residual R̂Δi/ωc is re-amplified by |1 - jωc/ω| at "
                f"{f3['rpm']:.0f} rpm: θ̃ 1st order {math.degrees(f3['h1'][vname]):.1f}° "
                f"(predicted {math.degrees(f3['h1_pred']):.1f}°)",
                pk if bool(np.all(np.isfinite(e_))) else math.nan,
                f"bounded but not harmless: at {f3['rpm']:.0f} rpm the inverse HPF gain "
                f"|1 - jωc/ω| = {f3['hpf_gain']:.0f} turns the offset into a 1st-order position "
                "error" + ("" if vname == "paper_robust" else literal),
                variant=vname,
            )
        )
    return claims


def _fig4_one(ctx, r) -> tuple[dict, list[np.ndarray]]:
    """Deadtime on commanded voltages: |λ̂|, its d part, the 5th/7th of λ̂ and ê, per variant."""
    mc = ctx.cv
    k0 = int(np.searchsorted(r["t"], r["win"][0]))
    th = r["theta"][k0:]
    thu = np.unwrap(th)
    sl = whole_periods(thu)
    w_e = float(np.mean(r["wm"][k0:])) * mc.p
    iq = float(np.mean(r["iq"][k0:]))

    def h57(x):
        h = harmonic_spectrum(x[sl], thu[sl], (1, 5, 7))
        return float(math.hypot(h[5], h[7]) / h[1])

    out: dict = {}
    shown = []
    for var in ("pure_integrator", "paper"):
        e = _replay(ctx.card, r["frames"], var, "commanded")[k0:]
        la, lb = e[:, ES_LA], e[:, ES_LB]
        if var == "pure_integrator":
            la, lb = la - la.mean(), lb - lb.mean()
        lam_c = (la + 1j * lb) * np.exp(-1j * th)  # rotor frame
        mag, d = float(np.mean(np.abs(la + 1j * lb))), float(np.mean(lam_c.real))
        out[var] = {"mag": mag, "d": d, "h57": h57(la)}
        if var == "paper":
            out["emf"] = {"h57": h57(e[:, ES_EA])}
        shown.append(la[: min(len(la), int(2 * 2 * math.pi / w_e / mc.ts))])
    wc = 2 * math.pi * float(observer_config("paper", ctx.card).cutoff_hz or 0.0)
    out["pred_d_mag"] = mc.lam + (4 / math.pi) * mc.vdt / w_e * (1 if iq > 0 else -1)
    out["rpm"] = w_e / mc.p / RPM
    out["paper_rel_attenuation_pred"] = abs(1j * w_e + wc) / abs(1j * 6 * w_e + wc)
    return out, shown


def _fig4_plot(ctx, f4: dict, shown: list) -> str:
    p = plt()
    mc = ctx.cv
    fig, ax = p.subplots(1, len(f4), figsize=(10, 4), squeeze=False)
    for c, (o, la_s) in enumerate(zip(f4.values(), shown, strict=True)):
        for var, la in zip(("pure_integrator", "paper"), la_s, strict=True):
            ax[0, c].plot(np.arange(len(la)) * mc.ts, la * 1e3, lw=0.7, label=f"λ̂α {var}")
        ax[0, c].axhline(mc.lam * 1e3, color="k", ls=":", lw=0.6)
        ax[0, c].axhline(-mc.lam * 1e3, color="k", ls=":", lw=0.6)
        ax[0, c].set_title(
            f"Fig. 4: commanded voltages, {1e6 * ctx.card.deadtime_s:g} µs deadtime, "
            f"{o['rpm']:.0f} rpm, full load",
            fontsize=8,
        )
        ax[0, c].set_xlabel("time [s]")
        ax[0, c].set_ylabel("flux [mV·s]")
        ax[0, c].legend(fontsize=7)
    return ctx.fig(fig, "fig4_deadtime")


def _fig4_claims(ctx, f4: dict) -> list[dict]:
    mc = ctx.cv
    o = f4[min(f4, key=lambda k: float(k[:-3]))]
    wc_hz = float(observer_config("paper", ctx.card).cutoff_hz or 0.0)
    fe = o["rpm"] / 60 * mc.p
    # below this speed the deadtime's flux error (4/pi) V_dt / w exceeds lambda itself
    cross_pct = 100 * mc.v1_dt / mc.lam / mc.p * RAD_S_TO_RPM / ctx.card.rated_speed_rpm
    txt = "; ".join(
        f"{k}: emf {100 * v['emf']['h57']:.1f} %, pure ∫ {100 * v['pure_integrator']['h57']:.1f} "
        f"%, LPF+inverse HPF {100 * v['paper']['h57']:.1f} %"
        for k, v in f4.items()
    )
    return [
        judge(
            "fig4.magnitude",
            f"{o['rpm']:.0f} rpm, full load, commanded voltages: |λ̂| = "
            f"{1e3 * o['pure_integrator']['mag']:.1f} mV·s vs λpm {1e3 * mc.lam:.1f} (d-axis "
            f"{1e3 * o['pure_integrator']['d']:.1f}; predicted λ + (4/π)Vdt/ω = "
            f"{1e3 * o['pred_d_mag']:.1f})",
            abs(o["pure_integrator"]["mag"] - mc.lam) / mc.lam,
            f"the deadtime fundamental (4/π)·{mc.vdt:.2f} V lies along the current (q), so it "
            "integrates into a d-axis (magnitude) error, larger than λpm itself below "
            f"~{cross_pct:.0f} % speed",
        ),
        judge(
            "fig4.integration_reduces",
            "5th+7th relative to the fundamental: " + txt,
            max(v["pure_integrator"]["h57"] / v["emf"]["h57"] for v in f4.values()),
            "a pure integral divides the n-th order by n",
        ),
        judge(
            "fig4.proposed_reduces",
            "see the previous row (LPF+inverse HPF column)",
            max(v["paper"]["h57"] / v["emf"]["h57"] for v in f4.values()),
            f"LPF({wc_hz:.0f} Hz) + inverse HPF at ω attenuates order n only by "
            "|jω+ωc|/|jnω+ωc|, ≈1 when nω << ωc (at "
            f"{o['rpm']:.0f} rpm the 5th/7th lie at {5 * fe:.0f}-{7 * fe:.0f} Hz): at low speed "
            "the proposed observer keeps the EMF's relative 5th/7th; the reduction returns as "
            "nω approaches ωc",
        ),
    ]


def fig2_4(ctx):
    """Figs. 2-4: the integration offset, a current-sensor offset's drift, the deadtime's
    magnitude error and harmonics: build -> run -> analyse -> plot -> judge."""
    res = ctx.run(_fig2_4_jobs(ctx))
    f2 = _fig2_analyse(ctx, res[0])
    f3 = _fig3_analyse(ctx, res[1])
    f4, shown = {}, []
    for r in [res[0]] + res[2:]:
        o, la = _fig4_one(ctx, r)
        f4[f"{o['rpm']:.0f}rpm"] = o
        shown.append(la)
    figs = [_fig2_plot(ctx, f2), _fig3_plot(ctx, res[1], f3), _fig4_plot(ctx, f4, shown)]
    claims = [_fig2_claim(f2)] + _fig3_claims(f3) + _fig4_claims(ctx, f4)
    data = {
        "fig2": {
            "centre_mvs": [1e3 * f2["centre"].real, 1e3 * f2["centre"].imag],
            "pred_mvs": [1e3 * f2["pred"].real, 1e3 * f2["pred"].imag],
        },
        "fig3": {
            "drift_mvs_per_s": abs(f3["rate"]) * 1e3,
            "pred": abs(f3["pred_rate"]) * 1e3,
            "paper_h1_deg": math.degrees(f3["h1"]["paper (literal)"]),
            "robust_h1_deg": math.degrees(f3["h1"]["paper_robust"]),
            "paper_h1_pred_deg": math.degrees(f3["h1_pred"]),
        },
        "fig4": f4,
    }
    return {"claims": claims, "figures": figs, "data": data}


# ======================================================================== Fig. 17
# injection frequencies in per unit of the card's current-loop design bandwidth (the paper's
# 1 kHz loop: 5 Hz .. 4 kHz)
FR17_FULL_PU = [
    0.005,
    0.01,
    0.02,
    0.05,
    0.1,
    0.2,
    0.3,
    0.5,
    0.7,
    0.85,
    1.0,
    1.2,
    1.5,
    2.0,
    3.0,
    4.0,
]
FR17_QUICK_PU = [0.02, 0.1, 0.3, 0.7, 1.0, 1.5, 3.0]
FR17_LEAK_SHOWN_PU = (0.02, 0.05, 0.1, 0.3, 1.0)
ID_INJECTION_PU = 0.2  # d-current injection amplitude, of the rated current
PAPER_EMF_CURRENT_BW_HZ = 100.0  # the paper's EMF drive (Fig. 17), on its machine


def _x_fr_current(r, m):
    sc = r.scenario
    segs = r.segments["current_d"]
    ts = sc.machine.ts_s
    # controller frame (what the drive itself measures) and the true rotor frame
    ta, tb = clarke(r.truth[:, TR_IA], r.truth[:, TR_IB], r.truth[:, TR_IC])
    th = r.truth[:, TR_THETA_E]
    id_true = ta * np.cos(th) + tb * np.sin(th)
    ctl = analyse(r.ctrl[:, CO_ID], r.ctrl[:, CO_ID_REF], segs, ts)
    tru = analyse(id_true, r.ctrl[:, CO_ID_REF], segs, ts)
    k0 = segs[0].k_start
    closed = bool(np.all(r.ctrl[k0:, CO_MODE] == MODE_CLOSED_LOOP))
    # theta~ at each injection frequency (amplitude, deg) for every flux observer
    leak = {}
    for nm in r.names:
        if nm.startswith(("flux", "paper")):
            e = theta_err(r, nm)
            leak[nm] = [_amplitude_deg(e, sg, ts) for sg in segs]
    om = sc.bench.observer_model
    return {
        "metrics": m,
        "ctrl": ctl,
        "true": tru,
        "closed_loop": closed,
        "start": handover(r),
        "leak": leak,
        "freqs": [sg.frequency_hz for sg in segs],
        "l_hat_pu": om.l_pu if om is not None else 1.0,
    }


def _amplitude_deg(e: np.ndarray, sg, ts: float) -> float:
    """Amplitude [deg] of e at a stepped-sine segment's frequency, over that segment."""
    kk = np.arange(sg.k_start, sg.k_end)
    return float(
        np.degrees(2 * abs(np.mean(e[kk] * np.exp(-2j * math.pi * sg.frequency_hz * kk * ts))))
    )


def _fr_injection(kind: str, freqs, ctx, t_inj: float) -> tuple[dict, int]:
    """The stepped-sine injection of a sweep and its length in samples."""
    from fluxdrive.analysis.freqresp import stepped_sine

    cycles, settle = (10, 4) if kind == "current" else (6, 3)
    key, amp = (
        ("id_injection", ID_INJECTION_PU)
        if kind == "current"
        else ("speed_injection", ctx.rpm(0.02))
    )
    inj = {"frequencies_hz": freqs, "amplitude": amp, "start_s": t_inj, "cycles": cycles}
    inj["settle_cycles"] = settle
    _, _, n = stepped_sine(freqs, 1.0, ctx.cv.ts, t_inj, cycles, settle)
    return {key: inj}, n


def _fr_scenario(driving, freqs, kind, seed: int | None = None, ctx: Ctx | None = None):
    """Fig. 17's (kind "current") or Fig. 18's ("speed") stepped-sine sweep at 10 % speed
    with `driving` closing the loop, on the context's card (None: the default card)."""
    ctx = ctx or Ctx()
    start, speed_rpm = ctx.rpm(START_PU), ctx.rpm(0.1)
    machine_kw = {"deadtime_s": 0.0} if driving == "encoder_ideal" else None
    no_load = driving == "encoder_noload"
    driving = "encoder" if driving in ("encoder_ideal", "encoder_noload") else driving
    obs = {driving: OBS4[driving]} if driving != "encoder" else {}
    if driving == "flux_measured" and kind == "current":
        # the literal observer in shadow: what a d-axis sweep does to eq. (5)'s order
        obs["paper_measured"] = LITERAL["paper_measured"]
    # current: half load keeps the d sweep off zero current (the deadtime's small-signal
    # resistance); ramped over 1.4 s: over 1 s the EMF drive's speed loop (granted less than
    # the target by the peaking rule) lets the speed collapse to standstill before the sweep.
    # An EMF drive gets 3.4 s (the sweep 2 s later): at 1.4 s the ramp's lag rate/(K_t K_i)
    # with its integral gain is about 270 rpm of the 300, and on some seeds the rotor stalls
    late = 2.0 if kind == "current" and driving.startswith("emf") else 0.0
    inj, n = _fr_injection(kind, freqs, ctx, 3.5 + late)
    load_end = (3.4 + late, 0.0 if no_load else 0.5) if kind == "current" else (3.0, 0.3)
    # the paper's Fig. 18 drives are 10 Hz speed loops on its 1 kHz current loop: that ratio
    # is the target here; every drive gets its own loops from the one design rule
    # (design_loops: target bandwidth unless the closed loop would peak by more than 3 dB)
    ctrl = {
        "if_current_pu": 0.6,
        # an EMF drive hands over on the ramp to the sweep's speed, at >= EMF_HANDOVER_PU: at
        # 4/3 % its slower speed loop lets the handover's torque kick swing the unloaded rotor
        # out of the estimate (docs/engine.md, "The EMF drive's start")
        "handover_rpm": ctx.rpm(EMF_HANDOVER_PU) if driving.startswith("emf") else start,
        "handback_rpm": 0.5 * start,
        "speed_bandwidth_hz": round(0.01 * card_current_bandwidth_hz(ctx.card), 6),
    }
    bench = {} if machine_kw else {"bench": BENCH}  # encoder_ideal: the ideal inverter/bench
    return ctx.build(
        machine_kw=machine_kw,
        name=f"fr_{kind}_{driving}",
        duration_s=round(n * ctx.cv.ts + 0.01, 4),
        seed=ctx.seed if seed is None else seed,
        speed_rpm=[[0.0, start], [0.8, start], [1.8, speed_rpm]],
        load_type="brake",
        load_pu=[[0.0, 0.0], [2.0, 0.0], list(load_end)],
        steady_window_s=[3.0 + late, 3.4 + late],
        driving=driving,
        control=ctrl,
        observers=obs,
        **bench,
        **inj,
    )


DRIVES = ["encoder", "flux_measured", "emf_measured", "emf_commanded"]
# where an EMF drive's sensorless start hands over (config/scenarios/emf_2pct_150load.yaml's
# handover_pu): 4 % of rated speed, 120 rpm on the default card
EMF_HANDOVER_PU = 0.04


def feedback_lpf_bandwidth_hz(lpf_hz: float, delay_s: float, peak_db: float = 3.0) -> float:
    """-3 dB bandwidth of i/i* for a current loop whose feedback passes a first-order low-pass
    at lpf_hz (the filter an EMF estimator puts on the current before L di/dt, if the drive
    also regulates that filtered current), the PI cancelling the RL pole (open loop
    w_b e^{-s delay}/s) and w_b the largest the peaking limit allows (the design rule)."""
    f = np.logspace(0, 4, 1500)
    s = 2j * np.pi * f
    h = 2 * np.pi * lpf_hz / (s + 2 * np.pi * lpf_hz)
    best = float("nan")
    for fb in np.logspace(0.5, 3.5, 300):
        lo = 2 * np.pi * fb / s * np.exp(-s * delay_s)
        g = 20 * np.log10(np.abs(lo / (1 + lo * h)))
        if g.max() > peak_db:
            break
        below = np.nonzero(g < -3.0)[0]
        best = float(f[below[0]]) if below.size else best
    return best


def feedback_lpf_for_bandwidth(target_hz: float, delay_s: float) -> float:
    """The feedback low-pass cut-off [Hz] at which feedback_lpf_bandwidth_hz = target_hz."""
    lo, hi = 1.0, 10_000.0
    for _ in range(30):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if feedback_lpf_bandwidth_hz(mid, delay_s) < target_hz else (lo, mid)
    return math.sqrt(lo * hi)


def _bode(ctx, res, labels, key, title, fname, target_db=-3.0):
    p = plt()
    fig, ax = p.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    for lab, r in zip(labels, res, strict=True):
        fr = r[key]
        bw = fr["bandwidth_hz"]
        ax[0].semilogx(
            fr["frequency_hz"],
            fr["gain_db"],
            "o-",
            ms=3,
            label=f"{lab} (-3 dB: {bw:.0f} Hz)" if bw == bw else f"{lab}",
        )
        ax[1].semilogx(fr["frequency_hz"], fr["phase_deg"], "o-", ms=3)
    ax[0].axhline(target_db, color="k", ls=":", lw=0.7)
    ax[0].set_ylabel("gain [dB]")
    ax[0].set_ylim(-25, 8)
    ax[0].legend(fontsize=8)
    ax[0].grid(alpha=0.3, which="both")
    ax[1].set_ylabel("phase [deg]")
    ax[1].set_xlabel("frequency [Hz]")
    ax[1].grid(alpha=0.3, which="both")
    ax[0].set_title(title, fontsize=9)
    return ctx.fig(fig, fname)


def _fig17_emf_why(ctx, a: dict) -> str:
    """Why the EMF drive keeps its current loop, and what would give the paper's number."""
    mc, bw = ctx.cv, a["bw"]
    i_inj = ID_INJECTION_PU * mc.i_rated
    emf = ctx.rpm(0.1) * RPM * mc.p * mc.lam
    why = (
        "our EMF drive is not changed to match: the d-axis injection enters its estimate "
        "only through L̂ di/dt (cancelled up to the bench's "
        f"{100 * abs(a['l_hat_pu'] - 1):.0f} % L̂ error), and its low-bandwidth PLL and speed "
        "LPF sit in the speed loop, not the current loop, so it keeps the designed current "
        "loop (on commanded voltages it loses the estimate before the sweep: the deadtime's "
        f"{mc.v1_dt:.2f} V against ωλ = {emf:.2f} V at {ctx.rpm(0.1):.0f} rpm, as in fig18).  "
        f"What would give the paper's {PAPER_EMF_CURRENT_BW_HZ:.0f} Hz: regulating a current "
        f"low-passed at {a['f_lpf']:.0f} Hz (the filter an EMF estimator needs before di/dt) "
        "under the same 3 dB peaking rule grants "
        f"{feedback_lpf_bandwidth_hz(a['f_lpf'], a['delay']):.0f} Hz (no filter: the "
        f"{a['bw_design']:.0f} Hz design).  The paper does not describe its EMF current path, "
        "and such a filter leaves the gain near 0 dB up to the bandwidth, so it would not also "
        "reproduce the paper's -20 dB dip: the paper's number stays unexplained by its text."
    )
    if "encoder_noload" not in bw:
        return why
    return why + (
        "  A low reading appears on every drive at no load (encoder drive: "
        f"{bw['encoder_noload']:.0f} Hz): the {i_inj:.1f} A sweep then crosses zero current, "
        f"where the deadtime's (4/π)V_dt = {mc.v1_dt:.2f} V acts as ≈"
        f"{mc.v1_dt / i_inj:.1f} Ω in series with R = {mc.r:g} Ω -- a bench effect, not an "
        "EMF one"
    )


def _fig17_analyse(ctx, drives, res) -> dict:
    delay = ControllerConfig().angle_advance_periods * ctx.cv.ts  # 1.5 PWM periods
    f_lpf = feedback_lpf_for_bandwidth(PAPER_EMF_CURRENT_BW_HZ, delay)
    z = list(zip(drives, res, strict=True))
    return {
        "bw": {d: r["ctrl"]["bandwidth_hz"] for d, r in z},
        "bw_true": {d: r["true"]["bandwidth_hz"] for d, r in z},
        "closed": {d: r["closed_loop"] for d, r in z},
        "start": {d: r["start"] for d, r in z},
        "delay": delay,
        "f_lpf": f_lpf,
        "bw_design": card_current_bandwidth_hz(ctx.card),
        "l_hat_pu": res[0]["l_hat_pu"],
        "flux": res[drives.index("flux_measured")],
    }


def _fig17_leak_claim(a: dict) -> list[dict]:
    fx = a["flux"]
    lk, fq = fx["leak"], fx["freqs"]
    if "paper_measured" not in lk:
        return []
    i50 = int(np.argmin(np.abs(np.array(fq) - 0.05 * a["bw_design"])))
    shown = {round(p * a["bw_design"], 6) for p in FR17_LEAK_SHOWN_PU}
    rows = zip(fq, lk["paper_measured"], lk["flux_measured"], strict=True)
    return [
        judge(
            "fig17.eq5_leak",
            "θ̃ at the injection frequency, literal paper (shadow) vs paper_robust (driving): "
            + ", ".join(
                f"{f:g} Hz: {x:.2f}° / {y:.2f}°" for f, x, y in rows if round(f, 6) in shown
            ),
            lk["paper_measured"][i50],
            "eq. (5) integrates v - R̂i and subtracts L̂i afterwards; the LPF + inverse HPF is "
            "exact only at ω̂e, so L̂·i at the injection frequency comes out of the filter "
            "with the wrong gain and phase while L̂·i is subtracted exactly: the difference "
            "enters λ̂pm and θ̂.  paper_robust removes L̂ di/dt before the filter "
            "(inductance_term = before_filter): only the rotor-frequency EMF is filtered",
        )
    ]


def _fig17_judge(ctx, drives, a: dict) -> list[dict]:
    bw, bw_true, closed = a["bw"], a["bw_true"], a["closed"]

    def rel_to(d: str, ref: float) -> float:
        return abs(bw[d] - ref) / ref if closed.get(d, True) else math.inf

    ideal = f": {bw['encoder_ideal']:.0f} Hz here)" if "encoder_ideal" in bw else ")"
    emf = [d for d in drives if d.startswith("emf")]
    return [
        judge(
            "fig17.encoder",
            f"{bw['encoder']:.0f} Hz (true-frame i_d: {bw_true['encoder']:.0f} Hz; design "
            f"{a['bw_design']:.0f} Hz)",
            rel_to("encoder", a["bw_design"]),
            f"the {1e6 * ctx.card.deadtime_s:g} µs deadtime acts as an extra small-signal "
            f"resistance and lowers it below the {a['bw_design']:.0f} Hz design (met exactly "
            "with an ideal inverter" + ideal,
        ),
        judge(
            "fig17.flux",
            f"{bw['flux_measured']:.0f} Hz (true frame {bw_true['flux_measured']:.0f} Hz), "
            f"stayed in closed loop: {closed['flux_measured']}",
            rel_to("flux_measured", bw["encoder"]),
        ),
        judge(
            "fig17.emf",
            "; ".join(
                f"{d}: {bw[d]:.0f} Hz (true frame {bw_true[d]:.0f} Hz), closed loop {closed[d]}"
                for d in emf
            )
            + "; rests on "
            + "; ".join(handover_text(a["start"][d]) for d in emf),
            max(bw[d] for d in emf) / a["bw_design"],
            _fig17_emf_why(ctx, a),
        ),
    ] + _fig17_leak_claim(a)


def fig17(ctx):
    """Fig. 17: the current loop's d-axis response at 10 % speed per drive: build -> run ->
    analyse -> plot -> judge."""
    bw0 = card_current_bandwidth_hz(ctx.card)
    freqs = [round(p * bw0, 6) for p in (FR17_QUICK_PU if ctx.quick else FR17_FULL_PU)]
    drives = DRIVES[:3] if ctx.quick else DRIVES + ["encoder_ideal", "encoder_noload"]
    res = ctx.run(
        [(_fr_scenario(d, freqs, "current", ctx=ctx), _x_fr_current, None) for d in drives]
    )
    title = (
        f"Fig. 17: i_d/i_d* (controller frame) at 10 % speed ({ctx.rpm(0.1):.0f} rpm), half "
        f"load, {100 * ID_INJECTION_PU:.0f} % rated injection"
    )
    figs = [_bode(ctx, res, drives, "ctrl", title, "fig17_current_fr")]
    a = _fig17_analyse(ctx, drives, res)
    data = {
        d: {"ctrl": r["ctrl"], "true": r["true"], "leak": r["leak"]}
        for d, r in zip(drives, res, strict=True)
    }
    return {"claims": _fig17_judge(ctx, drives, a), "figures": figs, "data": data}


# ======================================================================== Fig. 18
# injection frequencies in per unit of the speed-loop target (the paper's 10 Hz)
FR18_FULL_PU = [0.05, 0.1, 0.2, 0.4, 0.6, 0.8, 1.0, 1.3, 1.6, 2.0, 3.0, 5.0, 10.0, 30.0]
FR18_QUICK_PU = [0.1, 0.4, 0.8, 1.2, 2.0, 5.0]


def _x_fr_speed(r, m):
    segs = r.segments["speed"]
    ts = r.scenario.machine.ts_s
    # the true shaft speed (what the paper's encoder measures; the verdicts use it) and the
    # drive's own speed estimate (what its speed PI sees)
    fr = analyse(r.truth[:, TR_WM], r.w_ref, segs, ts)
    fr_est = analyse(r.ctrl[:, CO_W_FB], r.w_ref, segs, ts)
    k0 = segs[0].k_start
    closed = bool(np.all(r.ctrl[k0:, CO_MODE] == MODE_CLOSED_LOOP))
    d = r.scenario.control.design(r.scenario.machine)
    return {
        "metrics": m,
        "speed": fr,
        "speed_est": fr_est,
        "closed_loop": closed,
        "start": handover(r),
        "op": op_point(r),
        "design": {
            "bandwidth_hz": d.speed_bandwidth_hz,
            "peak_db": d.speed_peak_db,
            "est_bandwidth_hz": d.speed_est_bandwidth_hz,
            "est_peak_db": d.speed_est_peak_db,
            "limited": d.speed_limited,
            "kp": d.kp_w,
            "ki": d.ki_w,
        },
    }


def _fig18_analyse(drives, res) -> dict:
    z = list(zip(drives, res, strict=True))
    return {
        "bw": {d: r["speed"]["bandwidth_hz"] for d, r in z},
        "bw_est": {d: r["speed_est"]["bandwidth_hz"] for d, r in z},
        "closed": {d: r["closed_loop"] for d, r in z},
        "start": {d: r["start"] for d, r in z},
        "peak": {d: float(np.nanmax(r["speed"]["gain_db"])) for d, r in z},
        "peak_est": {d: float(np.nanmax(r["speed_est"]["gain_db"])) for d, r in z},
        "des": {d: r["design"] for d, r in z},
        "obs": {d: r["op"]["obs"].get(d) for d, r in z},
    }


def _fig18_row(a: dict, d: str) -> str:
    des = a["des"][d]
    if not a["closed"][d]:
        return f"{d}: lost the estimate during the sweep"
    return (
        f"{d}: true {a['bw'][d]:.1f} Hz / estimated {a['bw_est'][d]:.1f} Hz, peak "
        f"{a['peak'][d]:+.1f} / {a['peak_est'][d]:+.1f} dB (design {des['bandwidth_hz']:.1f} "
        f"Hz, {des['peak_db']:+.1f} dB{', peaking-limited' if des['limited'] else ''}"
        f"), closed loop {a['closed'][d]}"
    )


def _fig18_emf_why(ctx, a: dict) -> str:
    mc = ctx.cv
    emf = a["obs"].get("emf_measured") or {"pll_hz": 0.0, "lpf_hz": 0.0}
    low = ctx.rpm(0.08)  # the sweep's lowest speed: 10 % minus the 2 % amplitude
    return (
        f"the EMF path's low-bandwidth PLL ({emf['pll_hz']:.0f} Hz) and speed LPF "
        f"({emf['lpf_hz']:.0f} Hz) sit inside the speed loop: with the 3 dB peaking limit the "
        f"design can only grant {a['des']['emf_measured']['bandwidth_hz']:.1f} Hz.  The two "
        "values are not in the paper; they are the pair that reproduces its ratio under our "
        "design rule, so this row checks the measurement against the design, not the paper's "
        f"numbers.  With commanded voltages the sweep takes the speed down to {low:.0f} rpm, "
        f"where the deadtime error (4/π)V_dt = {mc.v1_dt:.2f} V stands against an EMF of "
        f"{low * RPM * mc.p * mc.lam:.2f} V"
        + (": the EMF estimate is lost" if not a["closed"].get("emf_commanded", True) else "")
    )


def _fig18_judge(ctx, drives, a: dict) -> list[dict]:
    bw, closed, peak, peak_est = a["bw"], a["closed"], a["peak"], a["peak_est"]
    lost = [d for d in drives if not closed[d]]
    flux = a["obs"].get("flux_measured") or {"pll_hz": 0.0}

    def rel(d: str, ref: float) -> float:
        return abs(bw[d] - ref) / ref if closed[d] else math.inf

    worst = max(max(peak[d], peak_est[d]) for d in drives if closed[d])
    return [
        judge(
            "fig18.encoder",
            _fig18_row(a, "encoder"),
            rel("encoder", a["des"]["encoder"]["bandwidth_hz"]),
        ),
        judge(
            "fig18.flux",
            _fig18_row(a, "flux_measured"),
            rel("flux_measured", bw["encoder"]),
            f"the speed PI is designed with the observer's speed path ({flux['pll_hz']:.0f} Hz "
            "PLL) in the loop model; the 3 dB peaking limit does not bind for it",
        ),
        judge(
            "fig18.emf",
            "; ".join(_fig18_row(a, d) for d in drives if d.startswith("emf"))
            + "; rests on "
            + "; ".join(handover_text(a["start"][d]) for d in drives if d.startswith("emf")),
            bw["emf_measured"] / bw["encoder"] if closed["emf_measured"] else math.inf,
            _fig18_emf_why(ctx, a),
        ),
        judge(
            "fig18.peaking",
            ", ".join(f"{d}: {max(peak[d], peak_est[d]):+.1f} dB" for d in drives if closed[d])
            + (f" ({', '.join(lost)}: lost the estimate)" if lost else ""),
            worst,
        ),
    ]


def fig18(ctx):
    """Fig. 18: the speed loop's response at 10 % speed per drive: build -> run -> analyse
    -> plot -> judge."""
    target = 0.01 * card_current_bandwidth_hz(ctx.card)  # the speed-loop target (_fr_scenario)
    freqs = [round(p * target, 6) for p in (FR18_QUICK_PU if ctx.quick else FR18_FULL_PU)]
    drives = DRIVES[:3] if ctx.quick else DRIVES
    res = ctx.run([(_fr_scenario(d, freqs, "speed", ctx=ctx), _x_fr_speed, None) for d in drives])
    title = (
        f"Fig. 18: true ω/ω* at {ctx.rpm(0.1):.0f} rpm, ±{ctx.rpm(0.02):.0f} rpm injection "
        f"(loops designed for {target:.0f} Hz, ≤ 3 dB peaking)"
    )
    figs = [_bode(ctx, res, drives, "speed", title, "fig18_speed_fr")]
    a = _fig18_analyse(drives, res)
    data = {
        d: {"true": r["speed"], "estimated": r["speed_est"], "design": r["design"]}
        | {"verdict_uses": "true"}
        for d, r in zip(drives, res, strict=True)
    }
    return {"claims": _fig18_judge(ctx, drives, a), "figures": figs, "data": data}


# ======================================================================== Fig. 19
def _x_step(r, m, t_step=2.0):
    k = int(np.searchsorted(r.t, t_step - 0.3))
    ks = int(np.searchsorted(r.t, t_step))
    k_pre = int(np.searchsorted(r.t, t_step - 0.1))
    sl = slice(k, None, 5)
    return {
        "metrics": m,
        "t_step": t_step,
        "pre_step_rpm": float(np.mean(r.truth[k_pre:ks, TR_WM])) * RAD_S_TO_RPM,
        "step_ref_rpm": float(r.w_ref[ks]) * RAD_S_TO_RPM,
        "t": r.t[sl],
        "rpm": r.truth[sl, TR_WM] * RAD_S_TO_RPM,
        "ref": r.w_ref[sl] * RAD_S_TO_RPM,
        "iq": r.ctrl[sl, CO_IQ],
        "th_err": np.degrees(theta_err(r, r.driving)[sl]) if r.driving != "encoder" else None,
    }


STEP_BASE = "paper_6pct_stepload"
# the registered floor of Fig. 19's dip (80 rpm of the paper's 3000 rpm machine), per unit
DIP_FLOOR_PU = 0.08 / 3.0
REACHED = 0.9  # the speed before the step must be within 10 % of the command


def _fig19_step_job(ctx, rig, s: float):
    """The step on the rig card with its inertia times s.  The I-f acceleration falls as 1/s
    (the I-f current's torque accelerates J s at 1/s the rate) and the step comes later by the
    longer spin-up, so every inertia runs at the step speed when the load steps in."""
    base = ctx.build(base=STEP_BASE)
    t0 = float(base.step_load_time_s or 0.0)
    accel = float(base.control.resolved(rig).if_accel_rpm_s or 0.0)
    kt = 1.5 * rig.pole_pairs * rig.flux_linkage_vs
    step_rpm = float(base.speed_profile_rpm[-1, 1])
    # spin-up of the nominal rig: the I-f ramp to the handover, then the rated torque's
    # acceleration to the step speed; J s takes s times as long for both
    spin = float(base.control.resolved(rig).handover_rpm or 0.0) / accel
    spin += rig.inertia_kgm2 * step_rpm * RPM / (kt * rig.rated_current_a)
    t_step = round(t0 + 4.0 * (s - 1.0) * spin, 4)
    tail = base.duration_s - t0
    load = [[0.0, 0.0], [t_step, 0.0], [t_step + 1e-4, 1.0]]
    sc = ctx.build(
        base=STEP_BASE,
        duration_s=round(t_step + (tail - 0.5 if ctx.quick else tail), 4),
        steady_window_s=[round(t_step + tail - 1.4 + (0.0 if ctx.quick else 0.5), 4)]
        + [round(t_step + (tail - 0.5 if ctx.quick else tail), 4)],
        load_pu=load,
        step_load_time_s=t_step,
        control={"if_accel_rpm_s": round(accel / s, 6)},
    )
    sc.machine = dataclasses.replace(sc.machine, inertia_kgm2=rig.inertia_kgm2 * s).validate()
    return (sc, _x_step, {"t_step": t_step})


def _fig19_rows(j_scales, steps, floor_rpm: float, max_s: float) -> list[dict]:
    rows = []
    for s, r in zip(j_scales, steps, strict=True):
        sp = r["metrics"]["speed"]
        reached = r["pre_step_rpm"] >= REACHED * r["step_ref_rpm"]
        rec = sp.get("recovery_s")
        min_rpm = sp.get("min_rpm_after_step")
        stable = bool(r["metrics"]["stable"])
        rows.append(
            {
                "J_scale": s,
                "stable": stable,
                "reached_step_speed": reached,
                "pre_step_rpm": r["pre_step_rpm"],
                "min_rpm": min_rpm,
                "dip_rpm": sp.get("dip_rpm"),
                "recovery_s": rec,
                "stalled": not stable or (min_rpm is not None and min_rpm <= 0.0),
                "meets": bool(
                    stable
                    and reached
                    and min_rpm is not None
                    and min_rpm >= floor_rpm
                    and rec is not None
                    and rec <= max_s
                ),
            }
        )
    return rows


def _fig19_plot_step(ctx, j_scales, steps, floor_rpm: float, step_rpm: float) -> str:
    p = plt()
    fig, ax = p.subplots(3, 1, figsize=(9, 8), sharex=True)
    for s, r in zip(j_scales, steps, strict=True):
        t = r["t"] - r["t_step"]  # every inertia's step at 0
        ax[0].plot(t, r["rpm"], lw=0.7, label=f"J×{s:g}")
        ax[1].plot(t, r["iq"], lw=0.6)
        if r["th_err"] is not None:
            ax[2].plot(t, r["th_err"], lw=0.6)
    ax[0].plot(steps[0]["t"] - steps[0]["t_step"], steps[0]["ref"], "k--", lw=0.7)
    ax[0].axhline(floor_rpm, color="0.5", ls=":", lw=0.7)
    ax[0].set_ylabel("speed [rpm]")
    ax[0].legend(fontsize=7, ncol=3)
    ax[0].set_title(
        f"Fig. 19: 100 % step load at {step_rpm:.0f} rpm, flux drive, measured voltages "
        f"(dotted: the registered floor {floor_rpm:.0f} rpm)",
        fontsize=9,
    )
    ax[1].set_ylabel("i_q [A]")
    ax[2].set_ylabel("θ̃ [deg]")
    ax[2].set_ylim(-60, 60)
    ax[2].set_xlabel("time since the step [s]")
    return ctx.fig(fig, "fig19_step_load")


def _fig19_plot_full(ctx, full4) -> str:
    p = plt()
    fig, ax = p.subplots(2, 1, figsize=(9, 5), sharex=True)
    ax[0].plot(full4["t"], full4["rpm"], lw=0.7)
    ax[0].set_ylabel("speed [rpm]")
    ax[0].set_title(
        f"Fig. 19: full load at {full4['metrics']['speed']['mean_rpm']:.0f} rpm", fontsize=9
    )
    ax[1].plot(full4["t"], full4["th_err"], lw=0.6)
    ax[1].set_ylabel("θ̃ [deg]")
    ax[1].set_xlabel("time [s]")
    return ctx.fig(fig, "fig19_full_load_4pct")


def _fig19_row_txt(r: dict) -> str:
    if not r["reached_step_speed"]:
        return f"J×{r['J_scale']:g}: {r['pre_step_rpm']:.0f} rpm at the step (not up to speed)"
    rec = "no recovery" if r["recovery_s"] is None else f"recovery {r['recovery_s']:.2f} s"
    return f"J×{r['J_scale']:g}: min {r['min_rpm']:.0f} rpm, {rec}" + (
        ", stalls" if r["stalled"] else ""
    )


def _fig19_step_claim(rows, rig, model: dict, floor_rpm: float) -> dict:
    r1 = rows[0]
    ok = ", ".join(f"{r['J_scale']:g}" for r in rows if r["meets"])
    rec = "none" if r1["recovery_s"] is None else f"{r1['recovery_s']:.3f} s"
    ours = (
        f"J = {rig.inertia_kgm2:.3g} kg·m² (card {rig.name}): min speed {r1['min_rpm']:.0f} rpm, "
        f"recovery {rec}, stable {r1['stable']}; "
        + (
            f"the registered test met at J×{ok}"
            if ok
            else f"the registered test met at no inertia up to J×{rows[-1]['J_scale']:g}"
        )
        + " (same loop design rule, gains scale with J)"
    )
    why = (
        (
            f"paper_rig.yaml infers J = {rig.inertia_kgm2:.3g} kg·m² from the paper's dip for a "
            "ζ = 1 PI loop of 10 Hz; "
            if rig.name.endswith("+paper_rig")  # the scenario's rig file (config/rigs)
            else ""
        )
        + "our design rule gives this drive K_p = "
        f"{model['kp']:.3g} A·s/rad, so the P-term alone needs {model['dw_p_rpm']:.0f} rpm of "
        f"error for the rated {rig.rated_torque_nm:.2f} N·m, and the step decelerates the "
        f"rotor at {model['decel']:.0f} rad/s² at first.  "
        + ("; ".join(_fig19_row_txt(r) for r in rows))
        + f" (registered floor {floor_rpm:.0f} rpm)"
    )
    # the registered quantity: the recovery time, inf when not stable, not recovered, not up
    # to speed at the step or dipping below the floor
    fails = not (r1["stable"] and r1["reached_step_speed"]) or r1["recovery_s"] is None
    fails = fails or r1["min_rpm"] is None or r1["min_rpm"] < floor_rpm
    value = math.inf if fails else r1["recovery_s"]
    return judge("fig19.step_dip", ours, value, why)


def fig19(ctx):
    """Fig. 19: the 100 % step at 6 % speed over inertias (spin-up scaled with J), and full
    load at 4 % speed: build -> run -> analyse -> plot -> judge."""
    j_scales = [1.0, 3.0] if ctx.quick else [1.0, 2.0, 3.0, 6.0, 10.0]
    rig = ctx.build(base=STEP_BASE).machine  # the card the runs use
    jobs = [_fig19_step_job(ctx, rig, s) for s in j_scales]
    jobs.append((ctx.build(base="paper_4pct_fullload"), _x_step, {"t_step": 6.3}))
    res = ctx.run(jobs)
    steps, full4 = res[:-1], res[-1]
    floor_rpm = DIP_FLOOR_PU * rig.rated_speed_rpm
    max_s = float(registered()["fig19.step_dip"]["threshold"])
    rows = _fig19_rows(j_scales, steps, floor_rpm, max_s)
    step_rpm = steps[0]["step_ref_rpm"]
    figs = [
        _fig19_plot_step(ctx, j_scales, steps, floor_rpm, step_rpm),
        _fig19_plot_full(ctx, full4),
    ]
    sc6 = ctx.build(base=STEP_BASE)  # the step-load drive's own loop design
    kp = sc6.control.design(sc6.machine).kp_w
    model = {
        "kp": kp,
        "dw_p_rpm": rig.rated_torque_nm / (rig.torque_constant_nm_per_a * kp) * RAD_S_TO_RPM,
        "decel": rig.rated_torque_nm / rig.inertia_kgm2,
    }
    m4 = full4["metrics"]
    claims = [
        _fig19_step_claim(rows, rig, model, floor_rpm),
        judge(
            "fig19.fullload_4pct",
            f"stable {m4['stable']}, mean {m4['speed']['mean_rpm']:.1f} rpm, θ̃ RMS "
            f"{m4['observers']['flux_measured']['theta_err_rms_deg']:.2f}°",
            float(bool(m4["stable"])),
        ),
    ]
    data = {"step_vs_inertia": rows, "p_term_error_rpm": model["dw_p_rpm"]}
    data["initial_decel_rad_s2"] = model["decel"]
    data["fullload_4pct"] = {"stable": m4["stable"], "speed": m4["speed"]}
    return {"claims": claims, "figures": figs, "data": data}


# ======================================================================== Figs. 15/16
def _x_thd(r, m):
    sl = _win(r)
    thu = np.unwrap(r.truth[sl, TR_THETA_E])
    ws = whole_periods(thu)
    out: dict[str, Any] = {"metrics": m}
    srcs, sigs = ("commanded", "measured"), ("emf", "flux", "paper")
    cols = []
    for src in srcs:
        e = r.estimate(f"flux_{src}")[sl]
        cols += [e[ws, ES_EA], e[ws, ES_LA], r.estimate(f"paper_{src}")[sl][ws, ES_LA]]
    # THD, THD+N and the spectrum of all six signals from one joint fit
    fit = iter(thd_spectra(np.column_stack(cols), thu[ws]))
    for src in srcs:
        f = {k: next(fit) for k in sigs}
        out[src] = {f"thd_{k}": f[k]["thd"] for k in sigs}
        out[src] |= {f"thdn_{k}": f[k]["thd_n"] for k in sigs}
        out[src] |= {f"spec_{k}": f[k]["spectrum"] for k in sigs}
    return out


# current-loop bandwidths in per unit of the card's design (the paper's 250-1500 Hz on 1 kHz)
FIG15_BW_PU = (0.25, 0.5, 1.0, 1.5)
THD_KEYS = ("thd_emf", "thd_flux", "thd_paper", "thdn_emf", "thdn_flux", "thdn_paper")


def _fig15_jobs(ctx, grid) -> list:
    obs = {
        k: OBS6[k] for k in ("flux_commanded", "flux_measured", "paper_commanded", "paper_measured")
    }
    return [
        (
            ctx.encoder_run(
                ctx.rpm(s / 100),
                1.0,
                observers=obs,
                bench=BENCH,
                control={"current_bandwidth_hz": float(b)},
                window_s=1.0 if s >= 4 else 1.5,
            ),
            _x_thd,
            None,
        )
        for s, b in grid
    ]


def _fig15_plot(ctx, tab, speeds, bws) -> str:
    p = plt()
    fig, ax = p.subplots(2, 3, figsize=(14, 7), sharey=True)
    panels = [
        ("a", "commanded", "emf", "EMF ê_α, commanded"),
        ("b", "measured", "emf", "EMF ê_α, measured"),
        ("c", "commanded", "flux", "flux λ̂_α (robust), commanded"),
        ("d", "measured", "flux", "flux λ̂_α (robust), measured"),
        ("c'", "commanded", "paper", "flux λ̂_α (literal), commanded"),
        ("d'", "measured", "paper", "flux λ̂_α (literal), measured"),
    ]
    axes = [ax[0, 0], ax[1, 0], ax[0, 1], ax[1, 1], ax[0, 2], ax[1, 2]]
    for (lt, src, key, title), a in zip(panels, axes, strict=True):
        for i, b in enumerate(bws):
            for q, style, lab in (("thd", "o-", "THD"), ("thdn", "x--", "THD+N")):
                ys = [100 * tab[(s, b)][src][f"{q}_{key}"] for s in speeds]
                a.plot(speeds, ys, style, ms=3, color=f"C{i}", label=f"{b:.0f} Hz {lab}")
        a.set_title(f"({lt}) {title} (full load)", fontsize=9)
        a.set_xlabel("speed [% rated]")
        a.set_ylabel("THD, THD+N [%]")
        a.set_yscale("log")
        a.grid(alpha=0.3, which="both")
        a.legend(fontsize=6, title="current bw", title_fontsize=6, ncol=2)
    return ctx.fig(fig, "fig15_thd")


def _fig16_plot(ctx, tab, speeds, b0: float) -> str:
    p = plt()
    fig, ax = p.subplots(1, 3, figsize=(15, 4), sharey=True)
    orders = np.arange(2, 21)
    wdt = 0.8 / len(speeds)
    for i, (key, lab) in enumerate(
        (("emf", "ê_α"), ("flux", "λ̂_α robust"), ("paper", "λ̂_α literal"))
    ):
        for j, s in enumerate(speeds):
            sp = tab[(s, b0)]["commanded"][f"spec_{key}"]
            tn = 100 * tab[(s, b0)]["commanded"][f"thdn_{key}"]
            ax[i].bar(
                orders + (j - len(speeds) / 2) * wdt,
                [100 * sp[n] / sp[1] for n in orders],
                width=wdt,
                label=f"{s} % (THD+N {tn:.1f} %)",
            )
        ax[i].set_xticks(orders)
        ax[i].set_xlabel("harmonic order")
        ax[i].set_title(f"({'abc'[i]}) {lab}: full load, commanded, {b0:.0f} Hz", fontsize=9)
        ax[i].legend(fontsize=7)
    ax[0].set_ylabel("% of fundamental")
    return ctx.fig(fig, "fig16_harmonics")


def _crossover_pct(ctx) -> float:
    """The speed [% rated] below which the 7th order lies under the flux filter's cut-off."""
    fe_rated = ctx.card.rated_speed_rpm / 60.0 * ctx.card.pole_pairs
    wc = float(observer_config("paper_robust", ctx.card).cutoff_hz or 0.0)
    return 100.0 * wc / (7.0 * fe_rated)


def _fig15_emf_claims(t, speeds, bws, b0, grid) -> list[dict]:
    lo, hi, n = speeds[0], speeds[-1], len(grid)
    mono = sum(t(lo, b, "commanded", "thd_emf") > t(hi, b, "commanded", "thd_emf") for b in bws)

    def fewer(q):
        return sum(t(s, b, "measured", q) < t(s, b, "commanded", q) for s, b in grid)

    pts = ", ".join(
        f"{s} %: THD {100 * t(s, b0, 'commanded', 'thd_emf'):.1f} → "
        f"{100 * t(s, b0, 'measured', 'thd_emf'):.1f} %, THD+N "
        f"{100 * t(s, b0, 'commanded', 'thdn_emf'):.1f} → "
        f"{100 * t(s, b0, 'measured', 'thdn_emf'):.1f} %"
        for s in speeds
    )
    return [
        judge(
            "fig15.emf_thd_speed",
            ", ".join(
                f"{s} %: {100 * t(s, b0, 'commanded', 'thd_emf'):.1f} % (THD+N "
                f"{100 * t(s, b0, 'commanded', 'thdn_emf'):.1f} %)"
                for s in speeds
            )
            + f" (at {b0:.0f} Hz)",
            mono / len(bws),
        ),
        judge(
            "fig15.measured_lowers_emf",
            f"THD (orders 2..20, the registered metric): {fewer('thd_emf')}/{n} points lower; "
            f"THD+N: {fewer('thdn_emf')}/{n}; " + pts,
            fewer("thd_emf") / n,
        ),
    ]


def _fig15_variant_claims(ctx, t, speeds, b0, grid, vname: str, k: str) -> list[dict]:
    n = len(grid)

    def better(src, q):
        return sum(t(s, b, src, f"{q}_{k}") < t(s, b, src, f"{q}_emf") for s, b in grid)

    meas = [100 * t(s, b0, "measured", f"thd_{k}") for s in speeds]
    cmd_txt = ", ".join(
        f"{s} %: {100 * t(s, b0, 'commanded', f'thd_{k}'):.1f} vs "
        f"{100 * t(s, b0, 'commanded', 'thd_emf'):.1f} % (THD+N "
        f"{100 * t(s, b0, 'commanded', f'thdn_{k}'):.1f} vs "
        f"{100 * t(s, b0, 'commanded', 'thdn_emf'):.1f} %)"
        for s in speeds
    )
    literal = (
        "; the literal observer adds the PLL's 6th-order ripple fed back through atan(ωc/ω̂e) into λ̂"
        if k == "paper"
        else ""
    )
    return [
        judge(
            "fig15.flux_below_emf_commanded",
            f"THD (orders 2..20, the registered metric): {better('commanded', 'thd')}/{n} "
            f"points, THD+N: {better('commanded', 'thdn')}/{n}; " + cmd_txt,
            better("commanded", "thd") / n,
            f"below ~{_crossover_pct(ctx):.0f} % speed the deadtime 5th/7th lie below the "
            f"{observer_config('paper_robust', ctx.card).cutoff_hz:.0f} Hz cut-off where the "
            "LPF + inverse HPF equals 1/(jω) for every order: the flux has the EMF's relative "
            "harmonics; its advantage grows with speed" + literal,
            variant=vname,
        ),
        judge(
            "fig15.flux_measured_lowest",
            "flux measured < emf measured: THD (orders 2..20, the registered metric) "
            f"{better('measured', 'thd')}/{n}, THD+N {better('measured', 'thdn')}/{n}; "
            + ", ".join(
                f"{s} %: {100 * t(s, b0, 'measured', f'thd_{k}'):.2f} % (THD+N "
                f"{100 * t(s, b0, 'measured', f'thdn_{k}'):.2f} %)"
                for s in speeds
            ),
            better("measured", "thd") / n,
            f"with measured voltages the flux THDs (orders 2..20) are {min(meas):.2f}-"
            f"{max(meas):.2f} % at {b0:.0f} Hz; what separates the paths is noise, which only "
            "THD+N counts",
            variant=vname,
        ),
    ]


def _fig16_claim(tab, speeds, b0) -> dict:
    def h57(s, k):
        sp = tab[(s, b0)]["commanded"][k]
        return math.hypot(sp[5], sp[7]) / sp[1]

    lo, hi = speeds[0], speeds[-1]
    grows = h57(lo, "spec_emf") > h57(hi, "spec_emf")
    return judge(
        "fig16.h57",
        ", ".join(
            f"{s} %: ê {100 * h57(s, 'spec_emf'):.1f} %, λ̂ robust "
            f"{100 * h57(s, 'spec_flux'):.1f} %, literal {100 * h57(s, 'spec_paper'):.1f} %"
            for s in speeds
        ),
        max(h57(s, "spec_flux") / h57(s, "spec_emf") for s in speeds) if grows else 1.0,
        ("the growth with falling speed holds" if grows else "the EMF's 5th/7th do not grow")
        + "; the flux reduction is small at low speed (|jω+ωc|/|jnω+ωc| ≈ 1) and only appears "
        "as nω approaches ωc",
    )


def _fig15_bw_claim(t, speeds, bws) -> list[dict]:
    if len(bws) < 2:
        return []
    lo = speeds[0]
    t0, t1 = t(lo, bws[0], "commanded", "thd_emf"), t(lo, bws[-1], "commanded", "thd_emf")
    n0, n1 = t(lo, bws[0], "commanded", "thdn_emf"), t(lo, bws[-1], "commanded", "thdn_emf")
    each = ", ".join(
        f"{b:.0f} Hz: {100 * t(lo, b, 'commanded', 'thd_emf'):.1f} / "
        f"{100 * t(lo, b, 'commanded', 'thdn_emf'):.1f} %"
        for b in bws
    )
    return [
        judge(
            "fig15.bandwidth_raises_thd",
            f"at {lo} % speed, {bws[0]:.0f} → {bws[-1]:.0f} Hz: THD {100 * t0:.1f} → "
            f"{100 * t1:.1f} %, THD+N {100 * n0:.1f} → {100 * n1:.1f} % ({each})",
            t1 / t0,
            "a rise of more than 10 % of the THD counts; smaller changes are within what a "
            "seed changes.  In our model the 2..20 orders come from the deadtime, which the "
            "current-loop bandwidth does not change; a wider loop passes more current-ADC "
            "noise into the voltages, which THD+N sees",
        )
    ]


def fig15_16(ctx):
    """Figs. 15/16: THD and harmonics of ê and λ̂ over speed and current-loop bandwidth
    (encoder drive, full load): build -> run -> plot -> judge (the extractor analyses)."""
    speeds = [2, 6] if ctx.quick else [2, 4, 6, 10, 20]
    b0 = card_current_bandwidth_hz(ctx.card)
    bws = [b0] if ctx.quick else [round(p * b0, 6) for p in FIG15_BW_PU]
    grid = [(s, b) for b in bws for s in speeds]
    res = ctx.run(_fig15_jobs(ctx, grid))
    tab = {(s, b): r for (s, b), r in zip(grid, res, strict=True)}
    figs = [_fig15_plot(ctx, tab, speeds, bws), _fig16_plot(ctx, tab, speeds, b0)]

    def t(s, b, src, key):
        return tab[(s, b)][src][key]

    claims = _fig15_emf_claims(t, speeds, bws, b0, grid)
    for vname, k in VARIANTS:
        claims += _fig15_variant_claims(ctx, t, speeds, b0, grid, vname, k)
    claims += [_fig16_claim(tab, speeds, b0)] + _fig15_bw_claim(t, speeds, bws)
    data = {
        f"{s}pct_{b:.0f}Hz": {
            src: {k: tab[(s, b)][src][k] for k in THD_KEYS} for src in ("commanded", "measured")
        }
        for s, b in grid
    }
    return {"claims": claims, "figures": figs, "data": data}


# ======================================================================== paper vs robust
# paper_robust's departures from eqs. (5)-(8), one option at a time on the literal observer
DEPARTURES: dict[str, dict[str, Any] | None] = {
    "paper": {},
    "+comp_freq_lpf_hz=2": {"comp_freq_lpf_hz": 2.0},
    "+before_filter": {"inductance_term": "before_filter"},
    "+sin detector": {"phase_detector": "sin"},
    "paper_robust": None,
}


def _dep_obs(src: str) -> dict:
    out = {}
    for lab, kw in DEPARTURES.items():
        base = {"variant": "paper_robust"} if kw is None else {"variant": "paper", **kw}
        out[f"{lab}|{src}"] = {**base, "voltage_source": src}
    return out


def _x_driving(r, m):
    from fluxdrive.drive.control import CO_FAULT

    f = r.ctrl[:, CO_FAULT]
    k = int(np.argmax(f > 0)) if np.any(f > 0) else None
    closed = np.nonzero(r.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP)[0]
    return {
        "metrics": m,
        "stable": m["stable"],
        "fault": int(f.max()),
        "fault_t": None if k is None else float(r.t[k]),
        "handover_t": float(r.t[closed[0]]) if closed.size else None,
    }


def _x_shadow(r, m):
    sl = _win(r)
    thu = np.unwrap(r.truth[sl, TR_THETA_E])
    ws = whole_periods(thu)
    out = {"metrics": m, "leak": {}}
    segs = r.segments.get("current_d")
    for nm in r.names:
        o = m["observers"][nm]
        out[nm] = {
            "rms": o["theta_err_rms_deg"],
            "peak": o["theta_err_peak_deg"],
            "thd": o["thd_flux_alpha"],
            "thdn": o["thdn_flux_alpha"],
        }
        if segs:
            e = theta_err(r, nm)
            sg = segs[0]
            kk = np.arange(sg.k_start, sg.k_end)
            out["leak"][nm] = float(
                np.degrees(
                    2
                    * abs(
                        np.mean(
                            e[kk]
                            * np.exp(-2j * math.pi * sg.frequency_hz * kk * r.scenario.machine.ts_s)
                        )
                    )
                )
            )
    del ws
    return out


# the leak test's d-current amplitude, of the rated current (id_injection's unit)
ROBUST_INJECTION_PU = 1.8
ROBUST_INJECTION_LOAD_PU = 1.0


def _robust_jobs(ctx, f_inj: float) -> list:
    """The literal observer with each departure driving the 2 % / 150 % case, then all of
    them in shadow on an encoder drive, then in shadow under a d-axis current at f_inj."""
    drive_jobs = []
    for kw in DEPARTURES.values():
        spec = {"variant": "paper_robust"} if kw is None else {"variant": "paper", **kw}
        drv = {"drv": {**spec, "voltage_source": "measured"}}
        sc = ctx.build(base="paper_2pct_150load", observers=drv, driving="drv")
        drive_jobs.append((sc, _x_driving, None))
    shadow = {**_dep_obs("commanded"), **_dep_obs("measured")}
    speed = ctx.rpm(0.02)
    inj = {
        "frequencies_hz": [f_inj],
        "amplitude": ROBUST_INJECTION_PU,
        "start_s": 3.5,
        "cycles": 40,
    }
    inj["settle_cycles"] = 5
    return drive_jobs + [
        (
            ctx.encoder_run(speed, 1.5, observers=shadow, window_s=1.0, bench=BENCH),
            _x_shadow,
            None,
        ),
        (
            ctx.encoder_run(
                speed,
                ROBUST_INJECTION_LOAD_PU,
                observers=_dep_obs("measured"),
                window_s=1.0,
                bench=BENCH,
                id_injection=inj,
            ),
            _x_shadow,
            None,
        ),
    ]


def _robust_drive_txt(lab: str, r: dict) -> str:
    if r["stable"]:
        return f"{lab}: stable"
    t = f" at {r['fault_t']:.2f} s" if r["fault_t"] is not None else ""
    return f"{lab}: not stable (fault {r['fault']}{t})"


def _injection_txt(card: MachineCard, f_inj: float) -> str:
    """The leak test's d-current, from the values the run used (amplitude in A and in per
    unit of the card's rated current)."""
    amp_a = ROBUST_INJECTION_PU * card.rated_current_a
    return f"d-axis current {amp_a:.3g} A ({ROBUST_INJECTION_PU:g} × rated) at {f_inj:.3g} Hz"


def _robust_judge(drv, sh, inj, f_inj: float, card: MachineCard) -> list[dict]:
    labs = list(DEPARTURES)
    ok = {lab: r["stable"] for lab, r in zip(labs, drv, strict=True)}
    claims = [
        judge(
            "robust.literal_drives",
            "; ".join(_robust_drive_txt(lab, r) for lab, r in zip(labs, drv, strict=True)),
            float(bool(ok["paper"])),
            "the departure that matters is the L̂ term: in eq. (5)'s order every current "
            "component away from ω̂e (the handover's i_q step, the speed loop's i_q "
            f"ripple) leaks into θ̂ (see the {f_inj:.0f} Hz row), and a kick that carries the "
            "PLL's ω̂e through zero flips the compensation (1 − jωc/ω̂e) by 180°: the estimate "
            "loses lock.  With before_filter alone the literal observer starts and "
            "holds; the compensation frequency and the phase detector do not rescue it",
        ),
    ]
    for src in ("commanded", "measured"):
        row = {lab: sh[f"{lab}|{src}"] for lab in labs}
        claims.append(
            judge(
                "robust.departures_thd",
                "; ".join(
                    f"{lab}: THD {100 * x['thd']:.1f} %, THD+N {100 * x['thdn']:.1f} %, θ̃ RMS "
                    f"{x['rms']:.2f}°"
                    for lab, x in row.items()
                ),
                row["paper_robust"]["thd"] / row["paper"]["thd"],
                "comp_freq_lpf_hz: the PLL's ω̂e carries the θ̃ 6th-order ripple (commanded "
                "voltages); evaluated at ω̂e the compensation angle atan(ωc/ω̂e) and gain "
                "|1 − jωc/ω̂e| ≈ ωc/ω̂e turn it back into flux harmonics; the rotation rate of "
                "the LPF output, low-passed, does not",
                variant=f"{src} voltages",
            )
        )
    claims.append(
        judge(
            "robust.departures_leak",
            f"{_injection_txt(card, f_inj)}: "
            + "; ".join(f"{lab}: {inj['leak'][f'{lab}|measured']:.2f}°" for lab in labs),
            inj["leak"]["paper_robust|measured"] / inj["leak"]["paper|measured"],
            "eq. (5) filters L̂·i with the rest of v − R̂i; the inverse HPF is right only at "
            f"ω̂e, so the {f_inj:.0f} Hz part leaves the filter with the wrong gain and phase "
            "while L̂·i is subtracted exactly; before_filter removes L̂ di/dt first",
        )
    )
    return claims


def paper_robust(ctx):
    """What each of paper_robust's departures does, measured: start-up/lock as the driving
    observer, THD and θ̃ in shadow on commanded and measured voltages, the angle leak of a
    d-axis current at another frequency: build -> run -> judge."""
    f_inj = round(0.05 * card_current_bandwidth_hz(ctx.card), 6)  # 50 Hz on a 1 kHz loop
    res = ctx.run(_robust_jobs(ctx, f_inj))
    drv, sh, inj = res[: len(DEPARTURES)], res[-2], res[-1]
    data = {
        "driving": {
            lab: {k: v for k, v in r.items() if k != "metrics"}
            for lab, r in zip(DEPARTURES, drv, strict=True)
        },
        "shadow": {k: v for k, v in sh.items() if k not in ("metrics", "leak")},
        "leak_50hz_deg": inj["leak"],
        "leak_hz": f_inj,
        "injection_pu": ROBUST_INJECTION_PU,
        "injection_a": ROBUST_INJECTION_PU * ctx.card.rated_current_a,
        "injection_load_pu": ROBUST_INJECTION_LOAD_PU,
    }
    claims = _robust_judge(drv, sh, inj, f_inj, ctx.card)
    return {"claims": claims, "figures": [], "data": data}


GROUP = "paper"  # experiments.registry lists this module
EXPERIMENTS = {
    "fig14": (fig14, "θ̃ with commanded vs measured voltages, 2 % speed / 150 % load"),
    "fig13": (fig13, "EMF vs flux loci at 2 % speed, no load / full load"),
    "fig2_4": (fig2_4, "integration offset, current-offset drift, deadtime (Figs. 2-4)"),
    "fig17": (fig17, "current-loop frequency response at 10 % speed"),
    "fig19": (fig19, "100 % step load at 6 % speed; full load at 4 % speed"),
    "fig15_16": (fig15_16, "THD vs current bandwidth and speed; harmonic distribution"),
    "fig18": (fig18, "speed-loop frequency response at 10 % speed"),
    "paper_robust": (paper_robust, "the literal observer vs paper_robust, one departure at a time"),
}

_ = (ES_VALID,)
