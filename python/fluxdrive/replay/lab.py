"""`./fluxdrive replay BAG... --variant SPEC ...`: recorded frames through observer variants.

Every variant runs over every bag's /drive/frame messages (offline, compiled kernel for the
built-in variants); the same metrics as a live run (fluxdrive.analysis.metrics) are computed against
/drive/truth, or against the encoder when the bag has no truth.  Output: a metric table per
bag on stdout, and in --out: metrics.json, PNG plots per bag, report.md side by side, and
optionally a new bag with the variants' estimates added as topics.

Variant SPEC:
  paper                          a built-in variant with its defaults
  paper:cutoff_hz=50,voltage_source=commanded
  my_pkg.mod:MyObserver[:k=v,...]  a user class (module:Class)
  my_variant[:k=v,...]           an entry point in group "fluxdrive.observers"
  @recorded                      every observer recorded in the bag, with its recorded config
                                 and every live change of it (the bag's parameter markers)
                                 applied from the sample it took effect at
  @NAME                          one recorded observer (e.g. @flux_measured)
  label=SPEC                     give the variant a name of your own

Sweeps: --sweep KEY=START:STOP:N (linspace) or KEY=V1,V2,... over one variant, in parallel
        (the project's dask runner: -j N local workers, or --scheduler tcp://HOST:PORT).
Live:   `--live [--rate R] [--loop] [--start S]` publishes the frames on /drive/frame (ROS).

The command line is fluxdrive.cli.replay; sweeps run in fluxdrive.study.bagsweep.
See docs/replay.md.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.analysis.metrics import (
    RAD_S_TO_RPM,
    harmonic_spectrum,
    steady_window,
    whole_periods,
    wrap,
)
from fluxdrive.core.machine import ConfigError, MachineCard
from fluxdrive.core.schema import Parser
from fluxdrive.drive.control import CO_MODE, CO_N, CO_W_REF, ControllerConfig
from fluxdrive.drive.observers import (
    ES_LA,
    ES_LB,
    ES_N,
    ES_TH,
    ES_W,
    OS_N,
    VARIANT_KINDS,
    KernelObserver,
    Observer,
    ObserverConfig,
    make_observer,
)
from fluxdrive.drive.plant import FR_ENC, FR_N, FR_SEQ, TR_N, TR_T, TR_THETA_E, TR_WM
from fluxdrive.drive.scenario import REPO_ROOT, Scenario
from fluxdrive.io.bagio import (
    RunBag,
    est_topic,
    read_run_bag,
    recorded_observer_model,
    write_run_bag,
)

SAMPLES_DIR = REPO_ROOT / "bags" / "samples"


# ====================================================================== variant specs
@dataclass
class VariantSpec:
    label: str
    target: str  # built-in name, entry point, module:Class, or @recorded-name
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def recorded(self) -> str | None:
        return self.target[1:] if self.target.startswith("@") else None


def _value(s: str) -> Any:
    low = s.strip().lower()
    if low in ("none", "null"):
        return None
    if low in ("true", "false"):
        return low == "true"
    try:
        return float(s)
    except ValueError:
        return s.strip()


def parse_params(text: str, src: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in filter(None, (x.strip() for x in text.split(","))):
        key, eq, val = item.partition("=")
        if not eq or not key.strip():
            raise ConfigError(f"{src}: parameter '{item}' must be key=value")
        out[key.strip()] = _value(val)
    return out


def slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", s).strip("_") or "variant"


def parse_variant(spec: str) -> VariantSpec:
    """'[label=]TARGET[:k=v,...]'; TARGET may itself be module:Class."""
    label = None
    m = re.match(r"^([A-Za-z_][A-Za-z0-9_]*)=(?![^:,]*=)(.+)$", spec)
    if m and "=" not in m.group(2).split(":")[0]:
        label, spec = m.group(1), m.group(2)
    parts = spec.split(":")
    params: dict[str, Any] = {}
    if len(parts) > 1 and "=" in parts[-1]:
        params = parse_params(parts[-1], f"--variant {spec}")
        parts = parts[:-1]
    target = ":".join(parts)
    if not target:
        raise ConfigError(f"--variant '{spec}': no variant name")
    if label is None:
        base = target.split(":")[-1] if ":" in target else target
        label = base.lstrip("@")
        if params:
            label += "_" + "_".join(
                f"{k}_{v:g}" if isinstance(v, float) else f"{k}_{v}" for k, v in params.items()
            )
    return VariantSpec(slug(label), target, params)


def build_observer(
    vs: VariantSpec, bag: RunBag, card: MachineCard, model: dict[str, float] | None = None
) -> Observer:
    """Instantiate a variant for one bag (fresh state; recorded state for @recorded on a
    bag cut out of a longer run).  `model` (R^, L^, lambda^; default: the bag's recorded
    observer model) is what a new variant starts from; its own r_hat_ohm=... wins."""
    rec = vs.recorded
    if rec is None:
        if model is None:
            model = recorded_observer_model(bag.meta)[0]
        obs = make_observer(vs.target, card, name=vs.label, model=model, **vs.params)
        obs.reset()
        return obs
    recorded = recorded_config(bag, rec)
    cfg = recorded.with_overrides(**vs.params) if vs.params else recorded
    obs = KernelObserver(cfg, card, name=vs.label)
    obs.reset()
    st = (bag.meta.get("observer_states") or {}).get(rec)
    # the state layout only grows at its end (new counters): a bag recorded before a new
    # index restores its prefix, the new entries keep their reset values
    if st is not None and len(st) <= OS_N and keeps_recorded(vs, bag, card):
        obs.state[: len(st)] = np.array(st, dtype=np.float64)
    return obs


def recorded_config(bag: RunBag, name: str) -> ObserverConfig:
    """The configuration the bag records for observer `name` (at the bag's first frame)."""
    configs = bag.meta.get("observers") or {}
    if name not in configs:
        raise ConfigError(
            f"{bag.path}: no recorded configuration for observer '{name}' "
            f"(bag records {sorted(configs) or 'none'})"
        )
    known = {f.name for f in fields(ObserverConfig)}
    return ObserverConfig(**{k: v for k, v in configs[name].items() if k in known})


def keeps_recorded(vs: VariantSpec, bag: RunBag, card: MachineCard) -> bool:
    """A @recorded variant whose own settings (a sweep's value included) leave the recorded
    observer's kernel parameters as they were: it replays the recorded estimates exactly
    (recorded state restored, the bag's markers applied), so its difference from them is
    reported."""
    if vs.recorded is None:
        return False
    if not vs.params:
        return True
    recorded = recorded_config(bag, vs.recorded)
    if recorded.is_plugin:
        return False
    mine = recorded.with_overrides(**vs.params)
    return bool(np.array_equal(mine.to_params(card), recorded.to_params(card)))


def expand_variants(specs: list[str], bag: RunBag) -> list[VariantSpec]:
    out: list[VariantSpec] = []
    for s in specs:
        vs = parse_variant(s)
        if vs.target == "@recorded":
            names = sorted(bag.meta.get("observers") or {})
            if not names:
                raise ConfigError(
                    f"{bag.path}: @recorded: the bag records no observer configurations"
                )
            out += [VariantSpec(nm, "@" + nm, dict(vs.params)) for nm in names]
        else:
            out.append(vs)
    labels = [v.label for v in out]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ConfigError(f"variants share the label(s) {dup}; name them: label=SPEC")
    return out


# ====================================================================== a replay
@dataclass
class ReplayResult:
    """Quacks like sim.SimResult, so metrics.compute and plots work on it."""

    scenario: Scenario
    names: list[str]
    driving: str
    t: np.ndarray
    frames: np.ndarray
    truth: np.ndarray
    est: np.ndarray  # (n_var, N, ES_N)
    ctrl: np.ndarray
    w_ref: np.ndarray
    id_inj: np.ndarray
    truth_source: str = "truth"
    recorded_diff: dict[str, float] = field(default_factory=dict)
    wall_s: dict[str, float] = field(default_factory=dict)
    bag: RunBag | None = None
    segments: dict = field(default_factory=dict)
    # the observer model (R^, L^, lambda^) new variants started from, and where it came from
    model: dict[str, float] = field(default_factory=dict)
    model_source: str = ""

    def estimate(self, name: str) -> np.ndarray:
        return self.est[self.names.index(name)]


SETTLE_S = 0.3  # not scored at the start of a bag: observers started fresh converge


def _window(bag: RunBag, window: tuple[float, float] | None) -> tuple[float, float]:
    """The metrics window: --window, else the recorded steady window clipped to the bag and
    starting at least min(SETTLE_S, 20 % of the bag) after its first frame, else the
    bag's second half."""
    t0, t1 = float(bag.t[0]), float(bag.t[-1])
    if window is None:
        w = (bag.meta.get("scenario") or {}).get("steady_window_s")
        if w:
            settle = t0 + min(SETTLE_S, 0.2 * (t1 - t0))
            window = (max(float(w[0]), settle), min(float(w[1]), t1))
            if window[1] - window[0] < 0.05 * (t1 - t0):
                window = None
    if window is None:
        window = (t0 + 0.5 * (t1 - t0), t1)
    return window


def encoder_truth(bag: RunBag, card: MachineCard, offset_deg: float = 0.0) -> np.ndarray:
    """No /drive/truth: electrical angle and speed from the encoder (absolute counts from
    mechanical zero, as the simulated plant counts; offset_deg for a real bench)."""
    cpr = 4.0 * card.encoder_lines
    p = card.pole_pairs
    thm = 2.0 * np.pi * (bag.frames[:, FR_ENC] + 0.5) / cpr
    tr = np.zeros((bag.n, TR_N))
    tr[:, TR_THETA_E] = wrap(p * thm + math.radians(offset_deg))
    if bag.n > 1:
        w = np.gradient(thm, bag.t)
        n_avg = max(1, int(round(2e-3 / max(card.ts_s, 1e-9))))
        if bag.n > n_avg:
            w = np.convolve(w, np.ones(n_avg) / n_avg, mode="same")
        tr[:, TR_WM] = w
    tr[:, TR_T] = bag.t
    return tr


def replay_bag(
    bag: RunBag,
    variants: list[VariantSpec],
    machine: MachineCard | None = None,
    window: tuple[float, float] | None = None,
    encoder_offset_deg: float = 0.0,
    card_model: bool = False,
) -> ReplayResult:
    """Every variant over the bag's frames.  A new variant's observer model (R^, L^,
    lambda^) is the one the bag records (`ReplayResult.model_source` says which), unless
    `card_model` asks for the machine card's values."""
    card = bag.machine(machine)
    n = bag.n
    model, model_source = _observer_model(bag, card, card_model)
    frames = np.ascontiguousarray(bag.frames, dtype=np.float64)
    est, walls, diffs = _run_variants(bag, variants, card, model, frames)
    truth, truth_source = _replay_truth(bag, card, encoder_offset_deg)
    ctrl = bag.ctrl if bag.ctrl is not None else np.zeros((n, CO_N))
    ctrl = np.nan_to_num(ctrl)
    if bag.ctrl is not None and np.any(ctrl[:, CO_W_REF] != 0):
        w_ref = ctrl[:, CO_W_REF].copy()
    else:
        w_ref = truth[:, TR_WM].copy()
    sc = _replay_scenario(bag, card, _window(bag, window))
    # a recorded controller state would make the stability check about the recorded
    # controller mode; for replay the variants drive nothing
    ctrl[:, CO_MODE] = 0.0
    return ReplayResult(
        sc,
        [v.label for v in variants],
        "encoder",
        bag.t.copy(),
        frames,
        truth,
        est,
        ctrl,
        w_ref,
        np.zeros(n),
        truth_source,
        diffs,
        walls,
        bag,
        model=model,
        model_source=model_source,
    )


def _observer_model(
    bag: RunBag, card: MachineCard, card_model: bool
) -> tuple[dict[str, float], str]:
    """The observer model new variants get, and where it comes from: the bag's record,
    else (or with `card_model`) the machine card."""
    recorded, model_source = recorded_observer_model(bag.meta)
    if card_model or recorded is None:
        if card_model:
            model_source = "the machine card (--card-model)"
        return _card_model(card), model_source
    return recorded, model_source


def _run_variants(
    bag: RunBag,
    variants: list[VariantSpec],
    card: MachineCard,
    model: dict[str, float],
    frames: np.ndarray,
) -> tuple[np.ndarray, dict[str, float], dict[str, float]]:
    """Each variant's estimates over the frames (recorded live changes applied), its
    wall time, and its difference from the bag's own estimates where it replays one."""
    n = bag.n
    est = np.zeros((len(variants), n, ES_N))
    walls: dict[str, float] = {}
    diffs: dict[str, float] = {}
    for i, vs in enumerate(variants):
        obs = build_observer(vs, bag, card, model)
        t0 = time.perf_counter()
        changes = live_changes(bag, vs) if isinstance(obs, KernelObserver) else []
        out = run_with_changes(obs, frames, changes)
        walls[vs.label] = time.perf_counter() - t0
        if out.shape != (n, ES_N):
            raise ConfigError(
                f"variant '{vs.label}': run() returned shape {out.shape}, expected ({n}, {ES_N})"
            )
        est[i] = out
        rec_name = vs.recorded or vs.label
        if rec_name in bag.est and (vs.recorded is None or keeps_recorded(vs, bag, card)):
            diffs[vs.label] = estimate_difference(out, bag.est[rec_name])
    return est, walls, diffs


def _replay_truth(bag: RunBag, card: MachineCard, offset_deg: float) -> tuple[np.ndarray, str]:
    """The rotor's truth: the bag's, its gaps filled from the encoder; the encoder's
    alone when the bag has none."""
    if bag.truth is None:
        return encoder_truth(bag, card, offset_deg), "encoder"
    truth = bag.truth.copy()
    bad = ~np.isfinite(truth[:, TR_THETA_E])
    if not bad.any():
        return truth, "truth"
    truth[bad] = encoder_truth(bag, card, offset_deg)[bad]
    return truth, "truth+encoder"


def _replay_scenario(bag: RunBag, card: MachineCard, win: tuple[float, float]) -> Scenario:
    """The scenario the metrics read: the bag's span, seed and load step, no profiles."""
    meta_sc = bag.meta.get("scenario") or {}
    step = meta_sc.get("step_load_time_s")
    if step is not None and not (bag.t[0] <= step < bag.t[-1]):
        step = None
    return Scenario(
        name=f"{bag.path.name}",
        machine=card,
        duration_s=float(bag.t[-1] - bag.t[0]),
        seed=int(meta_sc.get("seed", 0)),
        speed_profile_rpm=np.array([[0.0, 0.0]]),
        load_profile_pu=np.array([[0.0, 0.0]]),
        dyno_pu_per_rpm=0.0,
        brake_band_rpm=0.0,
        control=ControllerConfig(),
        observers={},
        driving="encoder",
        steady_window_s=win,
        step_load_time_s=step,
        description=f"replay of {bag.path}",
        source=str(meta_sc.get("source", "")),
    )


def live_changes(bag: RunBag, vs: VariantSpec) -> list[tuple[int, dict[str, Any]]]:
    """The recorded live changes of a @recorded observer: [(row, {name: value})], row = the
    index of the first frame the change held for, from the markers its node published
    (source "node": exact sample; a change the variant spec overrides is left out)."""
    rec = vs.recorded
    if rec is None or not bag.markers or not bag.n:
        return []
    known = {f.name for f in fields(ObserverConfig)}
    seqs = bag.frames[:, FR_SEQ]
    out: dict[int, dict[str, Any]] = {}
    for m in bag.markers:
        node = m["node"].rstrip("/")
        if not (
            m["successful"]
            and m["source"] == "node"
            and node.endswith(f"/obs/{rec}")
            and m["name"] in known
            and m["name"] not in vs.params
        ):
            continue
        try:
            value = json.loads(m["value"])
        except ValueError:
            raise ConfigError(
                f"{bag.path}: parameter marker {node} {m['name']} = {m['value']!r} is not a value"
            ) from None
        row = int(np.searchsorted(seqs, m["seq"]))
        out.setdefault(row, {})[m["name"]] = value
    return sorted(out.items())


def sweep_marker_note(bag: RunBag, vs: VariantSpec, key: str) -> str:
    """What a sweep of `key` over the variant does with the bag's parameter markers, in one
    line ("" when the bag has none): applied in every run at their samples (a @recorded
    variant), except those of `key` itself, which the swept value replaces."""
    if not bag.markers:
        return ""
    if vs.recorded is None:
        return (
            f"the bag's {len(bag.markers)} parameter marker(s) change recorded observers, "
            f"not the new variant {vs.target}: not applied"
        )
    base = VariantSpec(vs.label, vs.target, {k: v for k, v in vs.params.items() if k != key})
    changes = live_changes(bag, base)
    swept = sum(key in ch for _, ch in changes)
    applied = sum(len(ch) for _, ch in changes) - swept
    note = (
        f"{vs.target}: the bag's live parameter changes of it applied in every run at the "
        f"sample they took effect: {applied}"
    )
    if swept:
        note += f"; {swept} change(s) of {key} replaced by the swept value"
    return note


def run_with_changes(
    obs: Observer, frames: np.ndarray, changes: list[tuple[int, dict[str, Any]]]
) -> np.ndarray:
    """obs.run over the frames, its parameters updated (state kept) at the given rows, as
    the node did when the change came (fluxdrive_ros.params)."""
    if not changes:
        return np.asarray(obs.run(frames), dtype=np.float64)
    if not isinstance(obs, KernelObserver):  # only the built-in kernels take live changes
        raise ConfigError(f"{obs.name}: the bag's parameter changes need a built-in variant")
    out = np.zeros((len(frames), ES_N))
    start = 0
    for row, ch in changes:
        row = min(row, len(frames))
        if row > start:
            out[start:row] = obs.run(frames[start:row])
            start = row
        obs.update(**ch)  # KernelObserver: config re-validated, state kept
    if start < len(frames):
        out[start:] = obs.run(frames[start:])
    return out


def _card_model(card: MachineCard) -> dict[str, float]:
    return {
        "r_hat_ohm": card.resistance_ohm,
        "l_hat_h": card.inductance_h,
        "lambda_hat_vs": card.flux_linkage_vs,
    }


def estimate_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Largest difference between two estimate arrays (angles wrapped), over rows present
    in both."""
    ok = np.all(np.isfinite(b), axis=1) & np.all(np.isfinite(a), axis=1)
    if not ok.any():
        return float("nan")
    d = np.abs(a[ok] - b[ok])
    d[:, ES_TH] = np.abs(wrap(a[ok, ES_TH] - b[ok, ES_TH]))
    return float(d.max())


# ====================================================================== plots and report
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_replay(res: ReplayResult, out_dir: Path, orders: int = 12) -> dict[str, Path]:
    """The replay's figures in `out_dir`: θ̃ over time, its harmonic orders, the flux
    loci and the speed estimates; name -> path."""
    plt = _plt()
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = {
        "theta_error": _plot_theta_error(plt, res),
        "theta_harmonics": _plot_theta_harmonics(plt, res, orders),
        "flux_locus": _plot_flux_loci(plt, res),
        "speed": _plot_speed(plt, res),
    }
    paths: dict[str, Path] = {}
    for name, fig in figures.items():
        paths[name] = out_dir / f"{name}.png"
        fig.tight_layout()
        fig.savefig(paths[name], dpi=100)
        plt.close(fig)
    return paths


def _reference(res: ReplayResult) -> str:
    return "true" if res.truth_source.startswith("truth") else "encoder"


def _decimated(res: ReplayResult) -> slice:
    """At most ~20 000 points per line."""
    return slice(0, len(res.t), max(1, len(res.t) // 20000))


def _metrics_window(res: ReplayResult) -> slice:
    win = steady_window(res.t, res.scenario.steady_window_s)
    return slice(win.k0, win.k1)


def _finish(ax) -> None:
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=3)


def _plot_theta_error(plt, res: ReplayResult):
    t, th, dec = res.t, res.truth[:, TR_THETA_E], _decimated(res)
    fig, ax = plt.subplots(figsize=(9, 4))
    for i, nm in enumerate(res.names):
        ax.plot(t[dec], np.degrees(wrap(res.est[i, dec, ES_TH] - th[dec])), lw=0.7, label=nm)
    ax.axvspan(*res.scenario.steady_window_s, color="0.9", zorder=-1, label="metrics window")
    ax.set_ylim(-45, 45)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"θ̃ = θ̂ − θ({_reference(res)}) [el. deg]")
    _finish(ax)
    return fig


def _plot_theta_harmonics(plt, res: ReplayResult, orders: int):
    """Harmonic orders of θ̃ against the rotor angle, over the metrics window."""
    sl = _metrics_window(res)
    th = res.truth[:, TR_THETA_E]
    unw = np.unwrap(th[sl])
    wp = whole_periods(unw)
    fig, ax = plt.subplots(figsize=(9, 3.8))
    nv = max(1, len(res.names))
    width = 0.8 / nv
    ords = np.arange(1, orders + 1)
    for i, nm in enumerate(res.names):
        e = wrap(res.est[i, sl, ES_TH] - th[sl])[wp]
        spec = harmonic_spectrum(e, unw[wp], range(1, orders + 1))
        ax.bar(
            ords + (i - (nv - 1) / 2) * width,
            [np.degrees(spec[o]) for o in range(1, orders + 1)],
            width,
            label=nm,
        )
    ax.set_xticks(ords)
    ax.set_xlabel("order of θ̃ against the electrical angle")
    ax.set_ylabel("amplitude [el. deg]")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, ncol=3)
    return fig


def _plot_flux_loci(plt, res: ReplayResult):
    """Each variant's flux estimate over the metrics window against the card's |λ|."""
    sl = _metrics_window(res)
    nv = max(1, len(res.names))
    cols = min(nv, 4)
    rows = (nv + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * rows), squeeze=False)
    lam = res.scenario.machine.flux_linkage_vs
    circ = np.linspace(0, 2 * np.pi, 200)
    for i, nm in enumerate(res.names):
        ax = axes[i // cols][i % cols]
        la, lb = res.est[i, sl, ES_LA], res.est[i, sl, ES_LB]
        d = slice(0, len(la), max(1, len(la) // 8000))
        ax.plot(la[d] * 1e3, lb[d] * 1e3, lw=0.5)
        ax.plot(lam * 1e3 * np.cos(circ), lam * 1e3 * np.sin(circ), "k--", lw=0.6)
        lim = 1.6 * lam * 1e3
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.set_title(nm, fontsize=8)
        ax.set_xlabel("λ̂α [mV·s]", fontsize=8)
        ax.set_ylabel("λ̂β [mV·s]", fontsize=8)
    for j in range(nv, rows * cols):
        axes[j // cols][j % cols].axis("off")
    return fig


def _plot_speed(plt, res: ReplayResult):
    """Speed estimates against the encoder's / the true speed."""
    t, dec = res.t, _decimated(res)
    p = res.scenario.machine.pole_pairs
    fig, ax = plt.subplots(figsize=(9, 4))
    ref = _reference(res)
    ax.plot(t[dec], res.truth[dec, TR_WM] * RAD_S_TO_RPM, "k", lw=1.0, label=f"{ref} speed")
    for i, nm in enumerate(res.names):
        ax.plot(t[dec], res.est[i, dec, ES_W] / p * RAD_S_TO_RPM, lw=0.7, label=nm)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("mechanical speed [rpm]")
    _finish(ax)
    return fig


MD_COLS = [
    ("theta_err_rms_deg", "θ̃ rms °"),
    ("theta_err_peak_deg", "θ̃ peak °"),
    ("theta_err_mean_deg", "θ̃ mean °"),
    ("theta_err_h1_deg", "h1 °"),
    ("theta_err_h6_deg", "h6 °"),
    ("theta_err_noise_deg", "θ̃ noise °"),
    ("flux_radius_spread", "spread"),
    ("thd_flux_alpha", "THD λα"),
    ("thd_emf_alpha", "THD eα"),
    ("thdn_flux_alpha", "THD+N λα"),
    ("thdn_emf_alpha", "THD+N eα"),
    ("valid_fraction", "valid"),
]


def markdown_section(
    res: ReplayResult, m: dict[str, Any], plots: dict[str, Path], out_dir: Path
) -> str:
    bag = res.bag
    if bag is None:
        raise ValueError("a report section needs the replayed bag (ReplayResult.bag)")
    w0, w1 = res.scenario.steady_window_s
    lines = [
        f"## {bag.path.name}",
        "",
        f"- bag: `{bag.path}` — {bag.n} frames, {res.t[0]:.3f}–{res.t[-1]:.3f} s; "
        f"reference angle: {res.truth_source}; metrics window {w0:.3f}–{w1:.3f} s",
    ]
    sc = bag.meta.get("scenario") or {}
    if sc:
        lines.append(f"- recorded from scenario `{sc.get('name')}` (seed {sc.get('seed')})")
    for pr in bag.problems:
        lines.append(f"- **partial bag**: {pr}")
    lines += [
        "",
        "| variant | " + " | ".join(h for _, h in MD_COLS) + " | replay s | vs recorded |",
        "|---" * (len(MD_COLS) + 3) + "|",
    ]
    for nm, om in m["observers"].items():
        cells = []
        for key, _ in MD_COLS:
            v = om.get(key)
            cells.append(
                "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"
            )
        d = res.recorded_diff.get(nm)
        lines.append(
            f"| {nm} | "
            + " | ".join(cells)
            + f" | {res.wall_s.get(nm, 0):.3f} | "
            + ("—" if d is None else f"{d:.2e}")
            + " |"
        )
    lines.append("")
    rel = {k: os.path.relpath(p, out_dir) for k, p in plots.items()}
    lines += [
        "| position error | harmonic orders of θ̃ |",
        "|---|---|",
        f"| ![θ̃]({rel['theta_error']}) | ![orders]({rel['theta_harmonics']}) |",
        "| **flux locus** | **speed estimate** |",
        f"| ![locus]({rel['flux_locus']}) | ![speed]({rel['speed']}) |",
        "",
    ]
    return "\n".join(lines)


# ====================================================================== sweeps
def parse_sweep(text: str) -> tuple[str, list[float]]:
    key, eq, rng = text.partition("=")
    if not eq:
        raise ConfigError(f"--sweep '{text}': expected KEY=START:STOP:N or KEY=V1,V2,...")
    try:
        if ":" in rng:
            a, b, n = rng.split(":")
            vals = np.linspace(float(a), float(b), int(n)).tolist()
        else:
            vals = [float(x) for x in rng.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--sweep '{text}': expected KEY=START:STOP:N or KEY=V1,V2,...") from None
    if not vals:
        raise ConfigError(f"--sweep '{text}': no values")
    return key.strip(), vals


SWEEP_METRICS = [
    "theta_err_rms_deg",
    "theta_err_peak_deg",
    "theta_err_mean_deg",
    "theta_err_h1_deg",
    "theta_err_h6_deg",
    "flux_radius_spread",
    "thd_flux_alpha",
    "thd_emf_alpha",
    "valid_fraction",
]


def plot_sweep(rows: list[dict[str, Any]], key: str, title: str, path: Path) -> Path:
    plt = _plt()
    x = [r[key] for r in rows]
    fig, axes = plt.subplots(3, 3, figsize=(11, 8), sharex=True)
    for ax, mk in zip(axes.flat, SWEEP_METRICS, strict=True):
        ax.plot(x, [r[mk] for r in rows], "o-", ms=3)
        ax.set_title(mk, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel(key)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def format_sweep(rows: list[dict[str, Any]], key: str) -> str:
    cols = [
        "theta_err_rms_deg",
        "theta_err_peak_deg",
        "theta_err_mean_deg",
        "theta_err_h6_deg",
        "flux_radius_spread",
        "thd_flux_alpha",
        "valid_fraction",
    ]
    head = f"{key:>12s}" + "".join(f"{c.replace('theta_err_', 'θ̃_')[:12]:>13s}" for c in cols)
    return "\n".join(
        [head] + [f"{r[key]:12.4g}" + "".join(f"{r[c]:13.4f}" for c in cols) for r in rows]
    )


def write_augmented_bag(res: ReplayResult, bag: RunBag, path: Path) -> Path:
    """The bag's frames, truth, controller state and recorded estimates, plus the replayed
    variants' estimates (topic /obs/<label>/estimate)."""
    names = list(bag.est)
    est = [bag.est[nm] for nm in names]
    for i, nm in enumerate(res.names):
        if nm in bag.est:
            nm = nm + "_replay"
        names.append(nm)
        est.append(res.est[i])
    sc = res.scenario
    sc.observers = {}
    obj = ReplayResult(
        sc,
        names,
        "encoder",
        res.t,
        res.frames,
        bag.truth if bag.truth is not None else np.zeros((bag.n, TR_N)),
        np.array(est) if est else np.zeros((0, bag.n, ES_N)),
        bag.ctrl if bag.ctrl is not None else np.zeros((bag.n, CO_N)),
        res.w_ref,
        res.id_inj,
    )
    meta = dict(bag.meta)
    meta["replayed_variants"] = res.names
    return write_run_bag(
        obj,
        path,
        truth=bag.truth is not None,
        ctrl=bag.ctrl is not None,
        duty=False,
        extra_meta=meta,
    )


# ====================================================================== benchmark
def bench_replay(argv: list[str]) -> dict[str, Any]:
    """Samples/s of each built-in variant over a sample bag's frames, one core."""

    ap = Parser(prog="fluxdrive benchmark replay")
    ap.add_argument("bag", nargs="?", type=Path)
    ap.add_argument("--samples", type=int, default=2_000_000)
    ap.add_argument("--variant", action="append")
    args = ap.parse_args(argv)
    bag_path = args.bag or next(iter(sorted(SAMPLES_DIR.glob("*/metadata.yaml"))), None)
    if bag_path is None:
        raise ConfigError(f"no bag given and no sample bags in {SAMPLES_DIR}")
    bag_path = bag_path.parent if bag_path.name == "metadata.yaml" else bag_path
    t0 = time.perf_counter()
    bag = read_run_bag(bag_path)
    t_read = time.perf_counter() - t0
    msgs = sum(bag.counts.values())
    print(
        f"[bench] read {bag_path.name}: {bag.n} frames, {msgs} messages in {t_read:.2f} s",
        file=sys.stderr,
    )
    card = bag.machine()
    reps = max(1, args.samples // bag.n)
    frames = np.ascontiguousarray(np.tile(bag.frames, (reps, 1)))
    # one continuous recording: without renumbering, every tile after the first would be
    # "backwards" to the input policy and skipped (measuring the reject path, not the work)
    frames[:, FR_SEQ] = np.arange(len(frames), dtype=float)
    out: dict[str, float] = {}
    for v in args.variant or list(VARIANT_KINDS):
        obs = make_observer(v, card)
        obs.reset()
        obs.run(frames[:16])  # compile / load from cache
        best = 0.0
        for _ in range(3):
            obs.reset()
            t1 = time.perf_counter()
            obs.run(frames)
            best = max(best, len(frames) / (time.perf_counter() - t1))
        out[v] = round(best)
        print(
            f"[bench] {v:18s} {best / 1e6:6.2f} M samples/s ({best * card.ts_s:.0f}x real time)",
            file=sys.stderr,
            flush=True,
        )
    return {
        "samples_per_s": out,
        "samples": len(frames),
        "bag": bag_path.name,
        "bag_read_msgs_per_s": round(msgs / t_read) if t_read > 0 else None,
        "goal_paper_samples_per_s": 2_000_000,
    }


__all__ = [
    "bench_replay",
    "replay_bag",
    "parse_variant",
    "expand_variants",
    "read_run_bag",
    "write_run_bag",
    "est_topic",
    "FR_N",
]
