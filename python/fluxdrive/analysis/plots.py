"""PNG plots of a run: theta error vs time, flux loci, speed and currents."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluxdrive.analysis.metrics import RAD_S_TO_RPM, steady_window, wrap
from fluxdrive.drive.control import CO_ID, CO_IQ, CO_IQ_REF
from fluxdrive.drive.observers import ES_LA, ES_LB, ES_TH
from fluxdrive.drive.plant import TR_THETA_E, TR_WM


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _decimate(n: int, max_points: int = 20000) -> slice:
    return slice(0, n, max(1, n // max_points))


def plot_run(result, out_dir: Path) -> list[Path]:
    plt = _plt()
    out_dir.mkdir(parents=True, exist_ok=True)
    t = result.t
    th = result.truth[:, TR_THETA_E]
    d = _decimate(len(t))
    paths = []
    # --- theta error vs time
    fig, ax = plt.subplots(figsize=(10, 4.5))
    for i, nm in enumerate(result.names):
        e = np.degrees(wrap(result.est[i, :, ES_TH] - th))
        ax.plot(t[d], e[d], lw=0.7, label=nm + (" (driving)" if nm == result.driving else ""))
    w0, w1 = result.scenario.steady_window_s
    ax.axvspan(w0, w1, color="0.9", zorder=-1, label="metrics window")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("θ̃ = θ̂ − θ [el. deg]")
    ax.set_ylim(-45, 45)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=3)
    ax.set_title(f"{result.scenario.name}: position error")
    p = out_dir / "theta_error.png"
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    # --- flux loci over the steady window
    win = steady_window(t, result.scenario.steady_window_s)
    sl = slice(win.k0, win.k1)
    n = len(result.names)
    cols = min(n, 4)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.4 * rows), squeeze=False)
    lam = result.scenario.machine.flux_linkage_vs
    circ = np.linspace(0, 2 * np.pi, 200)
    for i, nm in enumerate(result.names):
        ax = axes[i // cols][i % cols]
        la = result.est[i, sl, ES_LA]
        lb = result.est[i, sl, ES_LB]
        dd = _decimate(len(la), 8000)
        ax.plot(la[dd] * 1e3, lb[dd] * 1e3, lw=0.5)
        ax.plot(lam * 1e3 * np.cos(circ), lam * 1e3 * np.sin(circ), "k--", lw=0.6)
        ax.set_aspect("equal")
        ax.set_title(nm, fontsize=9)
        ax.set_xlabel("λ̂α [mV·s]")
        ax.set_ylabel("λ̂β [mV·s]")
        mag = np.hypot(la, lb)
        lim = max(1.3 * lam, 1.1 * float(np.percentile(mag, 99)) if mag.size else 0.0) * 1e3
        lim = max(lim, 1e-6)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].axis("off")
    fig.suptitle("estimated magnet-flux loci (dashed: true |λpm|)")
    fig.tight_layout()
    p = out_dir / "flux_locus.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    # --- speed and currents
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    a1.plot(t[d], result.truth[d, TR_WM] * RAD_S_TO_RPM, lw=0.8, label="speed (true)")
    a1.plot(t[d], result.w_ref[d] * RAD_S_TO_RPM, "k--", lw=0.8, label="reference")
    a1.set_ylabel("speed [rpm]")
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    a2.plot(t[d], result.ctrl[d, CO_IQ], lw=0.6, label="i_q")
    a2.plot(t[d], result.ctrl[d, CO_IQ_REF], lw=0.8, label="i_q*")
    a2.plot(t[d], result.ctrl[d, CO_ID], lw=0.6, label="i_d")
    a2.set_ylabel("current [A]")
    a2.set_xlabel("time [s]")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    fig.tight_layout()
    p = out_dir / "speed_currents.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths
