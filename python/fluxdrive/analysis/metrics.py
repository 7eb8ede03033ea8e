"""The one metrics module (definitions: docs/engine.md, metrics), shared by the in-process
runner, the graph run, replay and the experiments.

All angle metrics use the true electrical angle at the sample instant.  Harmonic orders are
taken against the rotor's electrical angle by one joint least-squares fit of orders 0..20
(fit_orders) over a whole number of electrical periods, so they stay exact when the speed
moves; what the fit leaves is the broadband noise (noise_rms).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.drive.control import (
    CO_FAULT,
    CO_ID,
    CO_IQ,
    CO_MODE,
    CO_W_FB,
    FAULT_NAMES,
    FAULT_NONE,
    MODE_CLOSED_LOOP,
    describe_trip,
    trip_message,
)
from fluxdrive.drive.observers import ES_EA, ES_LA, ES_LB, ES_TH, ES_VALID
from fluxdrive.drive.plant import TR_THETA_E, TR_WM

RAD_S_TO_RPM = 60.0 / (2.0 * math.pi)
THD_ORDERS = range(2, 21)


def wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def theta_error_deg(result, name: str) -> np.ndarray:
    """θ̃ = θ̂ − θ of observer `name` over a run, wrapped to (−180, 180] electrical degrees."""
    est = result.estimate(name)
    return np.degrees(np.angle(np.exp(1j * (est[:, ES_TH] - result.truth[:, TR_THETA_E]))))


def handover(result) -> dict[str, Any]:
    """The sensorless start's I-f -> observer handover of a run: its time, the rotor's mean
    speed over the 0.1 s before it (the I-f ramp's), the driving observer and the criterion's
    low-pass (0: per sample); handover_s None when the drive never reached closed loop on an
    estimate (an encoder drive, or a start that failed)."""
    from fluxdrive.drive.control import CO_MODE, MODE_CLOSED_LOOP

    sc = result.scenario
    closed = np.flatnonzero(result.ctrl[:, CO_MODE] == MODE_CLOSED_LOOP)
    out: dict[str, Any] = {
        "driving": sc.driving,
        "criterion_lpf_hz": float(sc.control.handover_agree_lpf_hz or 0.0),
        "handover_s": None,
        "rotor_rpm": None,
    }
    if sc.driving == "encoder" or not closed.size:
        return out
    k0 = int(closed[0])
    k_back = max(k0 - int(round(0.1 / sc.machine.ts_s)), 0)
    out["handover_s"] = float(k0 * sc.machine.ts_s)
    out["rotor_rpm"] = float(np.mean(result.truth[k_back : k0 + 1, TR_WM]) * 60.0 / (2 * np.pi))
    return out


def handover_text(h: dict[str, Any]) -> str:
    """`handover` in words, for the rows that rest on it."""
    if h["handover_s"] is None:
        return f"{h['driving']}: no handover"
    how = f"low-passed at {h['criterion_lpf_hz']:g} Hz" if h["criterion_lpf_hz"] else "per sample"
    return (
        f"{h['driving']} from a sensorless start: I-f, handover at {h['handover_s']:.2f} s with "
        f"the rotor at {h['rotor_rpm']:.0f} rpm (criterion {how})"
    )


def whole_periods(theta_unwrapped: np.ndarray) -> slice:
    """Largest leading part of the window spanning a whole number of electrical periods
    (falls back to everything when less than one period elapsed).  Samples that are not
    finite (rows a run never received) are skipped: the span runs between the first and
    the last finite angle."""
    th = np.asarray(theta_unwrapped, dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(th))
    if ok.size < 2:
        return slice(0, len(th))
    first, last = float(th[ok[0]]), float(th[ok[-1]])
    n_per = math.floor(abs(last - first) / (2 * math.pi))
    if n_per < 1:
        return slice(0, len(th))
    target = first + math.copysign(n_per * 2 * math.pi, last - first)
    end = int(ok[np.argmin(np.abs(th[ok] - target))])
    return slice(0, max(end, 2))


# orders fitted jointly: 0 (DC) .. 20; THD's orders and what "broadband noise" leaves out
FIT_ORDERS = 20


@dataclass(frozen=True)
class OrderFit:
    """A joint least-squares fit of orders 0..N of x against the angle theta:
    x ≈ c_0 + Σ_{n=1..N} Re(c_n·e^{jnθ}) (c_0 the real DC part, |c_n| order n's amplitude),
    and what the fit leaves (`residual`: the broadband noise, higher and non-integer orders).
    x may be (samples,) or (samples, signals): then every array has a signals axis last."""

    coef: np.ndarray
    residual: np.ndarray

    def amplitude(self, order: int) -> np.ndarray | float:
        a = np.abs(self.coef[order])
        return float(a) if np.ndim(a) == 0 else a

    @property
    def noise_rms(self) -> np.ndarray | float:
        r = np.sqrt(np.mean(self.residual**2, axis=0)) if len(self.residual) else np.nan
        return float(r) if np.ndim(r) == 0 else r


def fit_orders(x: np.ndarray, theta: np.ndarray, max_order: int = FIT_ORDERS) -> OrderFit:
    """Joint least-squares fit of orders 0..max_order of x against the measured angle theta
    (wrapped or unwrapped; the true rotor angle at each sample).  Why joint: under speed
    ripple (a hunting rotor, the deadtime's 6th-order torque ripple) the samples crowd where
    the rotor is slow, so e^{jnθ} are not orthogonal over the samples; a projection on one
    order at a time then leaks the others into it and leaves harmonic power in the residual,
    which a joint fit does not: it assumes nothing about the speed, only that x is a function
    of θ plus noise.  Non-finite input gives nan coefficients and residual."""
    x = np.asarray(x, dtype=float)
    th = np.asarray(theta, dtype=float)
    y = x[:, None] if x.ndim == 1 else x
    n_col = 2 * max_order + 1
    coef = np.full((max_order + 1, y.shape[1]), np.nan + 0j)
    res = np.full(y.shape, np.nan)
    ok = np.all(np.isfinite(y), axis=0)  # a signal with a non-finite sample: nan
    if len(th) and np.all(np.isfinite(th)) and ok.any():
        e1 = np.exp(1j * th)
        a = np.empty((len(th), n_col))
        a[:, 0] = 1.0
        en = np.ones(len(th), dtype=complex)
        for k in range(1, max_order + 1):
            en = en * e1
            a[:, 2 * k - 1] = en.real
            a[:, 2 * k] = en.imag
        gram = a.T @ a
        if len(th) >= n_col and np.linalg.cond(gram) < 1e10:
            sol = np.linalg.solve(gram, a.T @ y[:, ok])
        else:  # less than a period or a standstill: the minimum-norm fit
            sol = np.linalg.lstsq(a, y[:, ok], rcond=None)[0]
        res[:, ok] = y[:, ok] - a @ sol
        coef[0, ok] = sol[0]
        coef[1:, ok] = sol[1::2] - 1j * sol[2::2]  # a·cos + b·sin = Re((a − jb)·e^{jθ})
    if x.ndim == 1:
        return OrderFit(coef[:, 0], res[:, 0])
    return OrderFit(coef, res)


def harmonic(x: np.ndarray, theta: np.ndarray, order: int) -> complex:
    """Complex amplitude c_n of order `order` of x against the angle theta, from the joint
    fit of orders 0..max(20, order) (fit_orders); order 0: the DC part."""
    return complex(fit_orders(x, theta, max(FIT_ORDERS, order)).coef[order])


def noise_rms(x: np.ndarray, theta_unwrapped: np.ndarray, max_order: int = FIT_ORDERS) -> float:
    """Broadband noise of x: the RMS of what the joint fit of orders 0..max_order against the
    rotor angle leaves, over the largest whole number of electrical periods (the SNR of θ̃
    in the paper's sense)."""
    sl = whole_periods(theta_unwrapped)
    return float(fit_orders(x[sl], theta_unwrapped[sl], max_order).noise_rms)


def _thd_of(c: np.ndarray) -> float:
    h1 = abs(c[1])
    if not h1 > 0:
        return float("nan")
    return float(math.sqrt(float(np.sum(np.abs(c[list(THD_ORDERS)]) ** 2))) / h1)


def _thd_n_of(c: np.ndarray, residual: np.ndarray) -> float:
    h1 = abs(c[1])
    if not h1 > 0:
        return float("nan")
    resid_ms = float(np.mean(residual**2))
    rest_ms = float(np.real(c[0])) ** 2 + float(np.sum(np.abs(c[list(THD_ORDERS)]) ** 2)) / 2
    return float(math.sqrt(rest_ms + resid_ms) / (h1 / math.sqrt(2.0)))


def thd(x: np.ndarray, theta: np.ndarray) -> float:
    """Harmonics 2..20 over the fundamental (Figs. 15, 16), from the joint fit."""
    return _thd_of(fit_orders(x, theta).coef)


def thd_n(x: np.ndarray, theta: np.ndarray) -> float:
    """THD+N: RMS of everything but the fundamental (DC, orders 2.., broadband noise) over the
    fundamental's RMS.  x over a whole number of electrical periods of theta.  From the same
    joint fit as thd(): DC² + the orders 2..20 exactly as thd() counts them + the mean square
    of what the fit leaves (noise, higher and non-integer orders), so THD+N >= THD holds by
    construction."""
    f = fit_orders(x, theta)
    return _thd_n_of(f.coef, f.residual)


def harmonic_spectrum(x: np.ndarray, theta: np.ndarray, orders=range(1, 21)) -> dict[int, float]:
    """|c_n| of the requested orders, from one joint fit of orders 0..max(20, the highest)."""
    orders = list(orders)
    c = fit_orders(x, theta, max([FIT_ORDERS, *orders])).coef
    return {n: float(abs(c[n])) for n in orders}


def thd_spectra(x: np.ndarray, theta: np.ndarray, orders=range(1, 21)) -> list[dict[str, Any]]:
    """Per column of x (samples, signals): {"thd", "thd_n", "spectrum"}, what thd(), thd_n()
    and harmonic_spectrum(orders) give that column, from one joint fit of every column (one
    design matrix and factorisation instead of three per signal)."""
    orders = list(orders)
    f = fit_orders(x, theta, max([FIT_ORDERS, *orders]))
    return [
        {
            "thd": _thd_of(f.coef[:, j]),
            "thd_n": _thd_n_of(f.coef[:, j], f.residual[:, j]),
            "spectrum": {n: float(abs(f.coef[n, j])) for n in orders},
        }
        for j in range(f.coef.shape[1])
    ]


@dataclass
class Window:
    k0: int
    k1: int


def steady_window(t: np.ndarray, window_s: tuple[float, float]) -> Window:
    k0 = int(np.searchsorted(t, window_s[0]))
    k1 = int(np.searchsorted(t, window_s[1], side="right"))
    return Window(k0, max(k1, k0 + 2))


def observer_metrics(
    est: np.ndarray, theta_true: np.ndarray, theta_unwrapped: np.ndarray
) -> dict[str, float]:
    """est: (n, ES_N) over the steady window; theta_true wrapped, theta_unwrapped for orders."""
    err = wrap(est[:, ES_TH] - theta_true)
    sl = whole_periods(theta_unwrapped)
    th = theta_unwrapped[sl]
    # one joint fit of θ̃, λ̂α and êα against the rotor angle (one factorisation)
    fit = fit_orders(np.column_stack([err[sl], est[sl, ES_LA], est[sl, ES_EA]]), th)
    c, res = fit.coef, fit.residual
    flux_mag = np.hypot(est[:, ES_LA], est[:, ES_LB])
    mean_mag = float(np.mean(flux_mag))
    return {
        "theta_err_rms_deg": float(np.degrees(np.sqrt(np.mean(err**2)))),
        "theta_err_peak_deg": float(np.degrees(np.max(np.abs(err)))),
        "theta_err_mean_deg": float(np.degrees(np.mean(err))),
        "theta_err_h1_deg": float(np.degrees(abs(c[1, 0]))),
        "theta_err_h6_deg": float(np.degrees(abs(c[6, 0]))),
        "theta_err_noise_deg": float(np.degrees(np.sqrt(np.mean(res[:, 0] ** 2)))),
        "flux_radius_spread": float((flux_mag.max() - flux_mag.min()) / mean_mag)
        if mean_mag > 0
        else float("nan"),
        "flux_radius_mean_vs": mean_mag,
        "thd_flux_alpha": _thd_of(c[:, 1]),
        "thd_emf_alpha": _thd_of(c[:, 2]),
        "thdn_flux_alpha": _thd_n_of(c[:, 1], res[:, 1]),
        "thdn_emf_alpha": _thd_n_of(c[:, 2], res[:, 2]),
        "valid_fraction": float(np.mean(est[:, ES_VALID] > 0.5)),
    }


def speed_metrics(
    t: np.ndarray, w_true: np.ndarray, w_ref: np.ndarray, win: Window, step_time_s: float | None
) -> dict[str, Any]:
    rpm = w_true * RAD_S_TO_RPM
    ref = w_ref * RAD_S_TO_RPM
    # ripple: peak-to-peak of the speed smoothed over 1 ms (the PWM-rate jitter is not ripple)
    n_avg = max(1, int(round(1e-3 / (t[1] - t[0])))) if len(t) > 1 else 1
    seg = rpm[win.k0 : win.k1]
    sm = np.convolve(seg, np.ones(n_avg) / n_avg, mode="valid") if len(seg) > n_avg else seg
    out: dict[str, Any] = {
        "ripple_rpm": float(sm.max() - sm.min()) if len(sm) else float("nan"),
        "mean_rpm": float(np.mean(seg)),
        "mean_error_rpm": float(np.mean(seg - ref[win.k0 : win.k1])),
        "dip_rpm": None,
        "recovery_s": None,
    }
    if step_time_s is not None and t[0] <= step_time_s < t[-1]:
        ks = int(np.searchsorted(t, step_time_s))
        after = rpm[ks:] - ref[ks:]
        kd = int(np.argmin(after))
        out["dip_rpm"] = float(-after[kd])
        out["min_rpm_after_step"] = float(rpm[ks + kd])
        tol = 0.1 * np.maximum(np.abs(ref[ks:]), 1e-9)
        outside = np.nonzero(np.abs(after) > tol)[0]
        if outside.size == 0:
            out["recovery_s"] = 0.0
        elif outside[-1] + 1 < len(after):
            out["recovery_s"] = float(t[ks + outside[-1] + 1] - t[ks])
        else:
            out["recovery_s"] = None  # never settled within 10 %
    return out


def compute(result) -> dict[str, Any]:
    """Metrics of a run (SimResult or anything with the same fields)."""
    sc = result.scenario
    t = result.t
    win = steady_window(t, sc.steady_window_s)
    theta = result.truth[:, TR_THETA_E]
    theta_unw = np.unwrap(theta)
    sl = slice(win.k0, win.k1)
    # split mode: the host estimates every D periods (the rows between hold the sample's):
    # each estimate against the angle at its own sample instant
    dec = int(getattr(result, "decimation", 1))
    sl_est = sl if dec == 1 else slice(win.k0 + (-win.k0) % dec, win.k1, dec)
    observers = {
        nm: observer_metrics(result.est[i, sl_est], theta[sl_est], theta_unw[sl_est])
        for i, nm in enumerate(result.names)
    }
    trip = trip_info(result)
    # after a trip in or before the window (PWM off, rotor coasting or stopped) an observer's
    # numbers describe a stopped drive: it has valid data only if it flagged some sample
    # valid while the drive still ran.  (Without a trip a never-valid shadow observer keeps
    # its numbers: how wrong it is on a running drive is the point of running it.)
    k_run_end = win.k1 if trip is None else min(max(trip["k"], win.k0), win.k1)
    for i, nm in enumerate(result.names):
        ok = trip is None or bool(np.any(result.est[i, win.k0 : k_run_end, ES_VALID] > 0.5))
        observers[nm]["valid_data"] = ok
    speed = speed_metrics(t, result.truth[:, TR_WM], result.w_ref, win, sc.step_load_time_s)
    faults = result.ctrl[:, CO_FAULT]
    faults = faults[np.isfinite(faults)]  # a sample lost on a bench bus is NaN: no code
    fault_code = int(faults.max()) if faults.size else 0
    ref_rpm = float(np.mean(result.w_ref[sl])) * RAD_S_TO_RPM
    stable = fault_code == FAULT_NONE and abs(speed["mean_error_rpm"]) <= 0.2 * max(
        abs(ref_rpm), 1.0
    )
    if result.driving != "encoder":
        d = observers[result.driving]
        stable = stable and d["theta_err_peak_deg"] < 60.0
        closed = result.ctrl[sl, CO_MODE] == MODE_CLOSED_LOOP
        stable = stable and bool(np.all(closed))
    return {
        "scenario": sc.name,
        "driving": result.driving,
        "stable": bool(stable),
        "fault_code": fault_code,
        "trip": trip,
        "window_s": list(sc.steady_window_s),
        "observers": observers,
        "lowest": lowest_by_metric(observers),
        "speed": speed,
        "currents": {
            "i_q_mean_a": float(np.mean(result.ctrl[sl, CO_IQ])),
            "i_d_mean_a": float(np.mean(result.ctrl[sl, CO_ID])),
        },
    }


# the metrics a run names a winner on (lower is better), with their label and unit
RANKED = (
    ("theta_err_rms_deg", "θ̃ RMS", "°"),
    ("theta_err_peak_deg", "θ̃ peak", "°"),
    ("theta_err_h6_deg", "θ̃ 6th order", "°"),
    ("theta_err_noise_deg", "θ̃ noise", "°"),
    ("thd_flux_alpha", "THD λ̂α", ""),
    ("thdn_flux_alpha", "THD+N λ̂α", ""),
)


def lowest_by_metric(observers: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per ranked metric, the observer with the lowest value (and the value) among those
    with valid data; a metric no observer has is left out."""
    out: dict[str, dict[str, Any]] = {}
    for key, _, _ in RANKED:
        vals = [
            (float(om[key]), nm)
            for nm, om in observers.items()
            if om.get("valid_data", True) and om.get(key) is not None and math.isfinite(om[key])
        ]
        if vals:
            v, nm = min(vals, key=lambda x: x[0])
            out[key] = {"observer": nm, "value": v}
    return out


def _lowest_line(m: dict[str, Any]) -> str | None:
    low = m.get("lowest") or lowest_by_metric(m["observers"])
    if len(m["observers"]) < 2 or not low:
        return None
    parts = [
        f"{label} {low[key]['observer']} ({low[key]['value']:.3g}{unit})"
        for key, label, unit in RANKED
        if key in low
    ]
    return (
        "lowest, each observer at its own tuning: "
        + "; ".join(parts)
        + " (at matched speed-loop bandwidth: ./fluxdrive compare)"
    )


def trip_info(result) -> dict[str, Any] | None:
    """The first latched fault of a run: code, name, time, the values that tripped it and
    the one-line message ('tripped at 0.000 s: DC-bus over-voltage 160.0 V > 95.0 V
    (control.vdc_max_v)'); None if the drive never tripped."""
    faults = result.ctrl[:, CO_FAULT]
    hit = np.nonzero(faults > 0)[0]
    if hit.size == 0:
        return None
    k = int(hit[0])
    code = int(faults[k])
    sc = result.scenario
    detail = FAULT_NAMES.get(code, str(code))
    try:
        cp = sc.control.to_params(sc.machine)
        d = result.names.index(result.driving) if result.driving in result.names else -1
        est = result.est[d, k] if d >= 0 else np.full(8, np.nan)
        w_prev = float(result.ctrl[k - 1, CO_W_FB]) if k > 0 else 0.0
        cs = getattr(result, "controller_state", None)
        detail = describe_trip(code, result.frames[k], est, cp, cs, w_fb_prev_rad_s=w_prev)
    except Exception:  # noqa: BLE001 - a replayed run may lack a controller model: name only
        pass
    t_s = float(result.t[k])
    return {
        "code": code,
        "fault": FAULT_NAMES.get(code, str(code)),
        "k": k,
        "t_s": t_s,
        "detail": detail,
        "message": trip_message(t_s, detail),
    }


def format_table(m: dict[str, Any]) -> str:
    """The metric table printed by sim/run/replay."""
    cols = [
        ("theta_err_rms_deg", "rms°", 7, 3),
        ("theta_err_peak_deg", "peak°", 7, 2),
        ("theta_err_mean_deg", "mean°", 7, 3),
        ("theta_err_h1_deg", "h1°", 6, 3),
        ("theta_err_h6_deg", "h6°", 7, 3),
        ("theta_err_noise_deg", "noise°", 7, 3),
        ("flux_radius_spread", "spread", 7, 3),
        ("thd_flux_alpha", "THDλα", 7, 3),
        ("thd_emf_alpha", "THDeα", 7, 3),
        ("thdn_flux_alpha", "THD+Nλ", 7, 3),
        ("thdn_emf_alpha", "THD+Ne", 7, 3),
        ("valid_fraction", "valid", 6, 2),
    ]
    name_w = max([len(n) for n in m["observers"]] + [10]) + 2
    lines = [
        f"scenario {m['scenario']}: driving={m['driving']} stable={m['stable']} "
        f"window={m['window_s'][0]:.2f}-{m['window_s'][1]:.2f} s",
        "observer".ljust(name_w) + "".join(h.rjust(w + 1) for _, h, w, _ in cols),
    ]
    trip = m.get("trip")
    if trip:
        lines.insert(0, trip["message"])
    for name, om in m["observers"].items():
        tag = "*" if name == m["driving"] else " "
        row = (tag + name).ljust(name_w)
        if not om.get("valid_data", True):
            t_trip_s = trip["t_s"] if trip else float("nan")
            lines.append(
                row + f"  -- no valid data in the window (drive tripped at {t_trip_s:.3f} s)"
            )
            continue
        for key, _, w, p in cols:
            v = om[key]
            row += (
                f"{v:{w}.{p}f}" if v is not None and not math.isnan(v) else "nan".rjust(w)
            ).rjust(w + 1)
        lines.append(row)
    s = m["speed"]
    line = (
        f"speed: mean {s['mean_rpm']:.2f} rpm (error {s['mean_error_rpm']:+.2f}), "
        f"ripple {s['ripple_rpm']:.2f} rpm p-p"
    )
    if s.get("dip_rpm") is not None:
        rec = "not within 10 %" if s["recovery_s"] is None else f"{s['recovery_s']:.3f} s"
        line += f", step-load dip {s['dip_rpm']:.1f} rpm, recovery {rec}"
    lines.append(line)
    lowest = _lowest_line(m)
    if lowest:
        lines.append(lowest)
    lines.append(
        "(* driving; θ̃ = θ̂ − θ in electrical degrees over the window; h1/h6 orders "
        "of θ̃ vs the rotor angle, noise what a joint fit of orders 0..20 leaves; "
        "spread = (max−min)/mean |λ̂|; THD: orders 2..20; "
        "THD+N: all but the fundamental, noise and DC included)"
    )
    return "\n".join(lines)


def write_json(m: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(m, indent=2, default=float))
