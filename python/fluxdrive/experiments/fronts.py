"""Flux vs EMF independent of tuning: Pareto fronts of θ̃ against the speed-loop bandwidth each
observer's speed path allows.

One tuning compares a 25 Hz PLL (flux) with a 15 Hz PLL plus a 20 Hz speed LPF (EMF): the
narrower EMF path filters more.  Here every observer's speed-path settings are swept (the PLL
bandwidth, and the EMF path's speed LPF with it) and each setting is placed at the speed-loop
bandwidth the project's one loop-design rule (control.design_loops, 3 dB peaking) grants a
drive fed by that speed path; its θ̃ (RMS, 6th order, broadband noise) is measured in shadow
on an encoder-driven run at each operating point.  The paper's SNR claim is then judged at
matched allowed bandwidth, from the fronts: build -> run -> analyse -> plot -> judge.  The
`fronts` experiment runs on the paper bench (the paper's figures' bench: capture chain, model
errors, saturation); `run_fronts` on any bench file or the ideal one.
For a variant with a flux cutoff (w_c), the cutoff is swept too, at the card's PLL setting.

`./fluxdrive compare VARIANT...` (fluxdrive.cli.compare) makes the same fronts for any set of
variants, a user's `module:Class` included, with these functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxdrive.core.machine import MachineCard
from fluxdrive.core.schema import param
from fluxdrive.drive.control import ControllerConfig, design_loops
from fluxdrive.drive.observers import observer_config
from fluxdrive.experiments.claims import judge
from fluxdrive.experiments.common import PAPER_BENCH, plt
from fluxdrive.replay.lab import parse_variant

# multiples of each variant's card-derived PLL bandwidth (and EMF speed LPF) swept
FACTORS = (0.4, 0.6, 0.8, 1.0, 1.4, 2.0)
FACTORS_QUICK = (0.6, 1.0, 1.6)
# multiples of the card-derived flux cutoff w_c swept at the card's PLL (variants with a w_c)
CUTOFF_FACTORS = (0.5, 2.0)
CUTOFF_FACTORS_QUICK = (0.5,)
FAMILIES = {"flux": "paper_robust", "emf": "emf"}
# a plugin's constructor keywords for the PLL and the flux cutoff (`compare --pll-key` ...)
PLUGIN_KEYS = {"pll": "pll_hz", "cutoff": "cutoff_hz"}
SOURCES = ("measured", "commanded")
# operating points in per unit of the card's rated speed and torque
POINTS = ((0.02, 1.5), (0.02, 0.0), (0.10, 1.5), (0.10, 0.0))


def _name(fam: str, src: str, i: int) -> str:
    return f"{fam}_{src}_{i}"


def _setting(
    variant: str, card: MachineCard, src: str, pll_f: float, wc_f: float, keys: dict[str, str]
):
    """One observer config of a sweep: the variant's card-derived PLL (and EMF speed LPF)
    times pll_f and flux cutoff times wc_f.  A plugin takes them as constructor keywords
    (PLUGIN_KEYS), from the built-in rules' values for the flux observer.  `variant` is a
    replay-style spec, `TARGET[:key=value,...]`: its fixed settings ride along unswept."""
    spec = parse_variant(variant)
    target, fixed = spec.target, dict(spec.params)
    plugin = ":" in target
    base = observer_config("paper_robust" if plugin else target, card)
    pll_hz = round(pll_f * float(base.pll_bandwidth_hz or 0.0), 6)
    wc_hz = round(wc_f * float(base.cutoff_hz or 0.0), 6)
    if plugin:
        extra = {**fixed, keys["pll"]: pll_hz, keys["cutoff"]: wc_hz}
        return {"variant": target, "extra": extra, "pll_bandwidth_hz": pll_hz}
    cfg: dict[str, Any] = {**fixed, "variant": target, "voltage_source": src}
    cfg["pll_bandwidth_hz"] = pll_hz
    if base.speed_lpf_hz:
        cfg["speed_lpf_hz"] = round(pll_f * base.speed_lpf_hz, 6)
    if wc_f != 1.0:
        cfg["cutoff_hz"] = wc_hz
    return cfg


def _has_cutoff(variant: str, card: MachineCard) -> bool:
    target = parse_variant(variant).target
    if ":" in target:
        return True
    return bool(observer_config(target, card).cutoff_hz) and target != "emf"


def build_cases(
    quick: bool,
    card: MachineCard,
    families: dict[str, str] | None = None,
    points: list[tuple[float, float]] | None = None,
    sources: tuple[str, ...] = SOURCES,
    plugin_keys: dict[str, str] = PLUGIN_KEYS,
) -> tuple[list[tuple[float, float]], dict[str, dict[str, Any]]]:
    """The operating points and the observers every run carries in shadow (name -> config):
    per family and voltage source the PLL sweep, then (variants with a w_c) the cutoff sweep."""
    factors = FACTORS_QUICK if quick else FACTORS
    cutoffs = CUTOFF_FACTORS_QUICK if quick else CUTOFF_FACTORS
    observers: dict[str, dict[str, Any]] = {}
    for fam, variant in (families or FAMILIES).items():
        sweep = [(f, 1.0) for f in factors]
        if _has_cutoff(variant, card):
            sweep += [(1.0, f) for f in cutoffs]
        for src in sources:
            for i, (pll_f, wc_f) in enumerate(sweep):
                observers[_name(fam, src, i)] = _setting(
                    variant, card, src, pll_f, wc_f, plugin_keys
                )
    if points is None:
        points = list(POINTS[:2] if quick else POINTS)
    return points, observers


def _x_front(r, m) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for nm in r.names:
        o = m["observers"][nm]
        out[nm] = {
            "rms_deg": o["theta_err_rms_deg"],
            "h6_deg": o["theta_err_h6_deg"],
            "noise_deg": o["theta_err_noise_deg"],
        }
    return {"obs": out}


def allowed_bandwidth_hz(card, cfg: dict[str, Any]) -> float:
    """The speed-loop bandwidth the design rule grants a drive whose speed feedback is this
    observer's speed path (its PLL and speed LPF), asked for the current loop's tenth."""
    current_bw_hz = float(ControllerConfig().resolved(card).current_bandwidth_hz or 0.0)
    d = design_loops(
        card,
        current_bw_hz=current_bw_hz,
        speed_bw_hz=0.1 * current_bw_hz,
        feedback_pll_hz=cfg["pll_bandwidth_hz"],
        feedback_lpf_hz=cfg.get("speed_lpf_hz", 0.0),
    )
    return float(d.speed_bandwidth_hz)


def pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Non-dominated (bandwidth up, θ̃ down) points, by bandwidth."""
    front: list[tuple[float, float]] = []
    for bw, e in sorted(points, key=lambda p: (-p[0], p[1])):
        if not front or e < front[-1][1]:
            front.append((bw, e))
    return sorted(front)


def _at(front: list[tuple[float, float]], bw: float) -> float:
    """The θ̃ a family reaches with an allowed speed-loop bandwidth of `bw`: on its front,
    linear between its points; below the front's lowest bandwidth that point's θ̃ (a speed
    loop can always be tuned slower than its observer allows, and the settings that allow
    less did no better); nan above its highest (no setting allows that much)."""
    xs = [p[0] for p in front]
    if not front or bw > xs[-1] + 1e-9:
        return math.nan
    return float(np.interp(bw, xs, [p[1] for p in front]))


def analyse(
    points, observers, res, card, families=None, sources: tuple[str, ...] = SOURCES
) -> dict[str, Any]:
    """Per operating point and voltage source: each family's points and fronts (RMS and
    noise), and the noise ratio flux/EMF at matched allowed bandwidth over their overlap."""
    bw = {nm: allowed_bandwidth_hz(card, cfg) for nm, cfg in observers.items()}
    out: dict[str, Any] = {}
    for (speed, load), r in zip(points, res, strict=True):
        for src in sources:
            key = f"{100 * speed:g}pct_{100 * load:g}load_{src}"
            cell: dict[str, Any] = {}
            for fam in families or FAMILIES:
                names = [n for n in observers if n.startswith(f"{fam}_{src}_")]
                pts = {
                    q: [(bw[n], r["obs"][n][f"{q}_deg"]) for n in names]
                    for q in ("rms", "noise", "h6")
                }
                cell[fam] = {
                    "points": pts,
                    "front_rms": pareto(pts["rms"]),
                    "front_noise": pareto(pts["noise"]),
                    "front_h6": pareto(pts["h6"]),
                    "settings": [observers[n] for n in names],
                }
            if "flux" in cell and "emf" in cell:
                cell.update(_matched(cell))
            out[key] = cell
    return out


def matched_ratio(cell: dict[str, Any], a: str, b: str, front: str = "front_noise") -> dict:
    """θ̃ of family a over family b on their fronts at equal allowed bandwidth, on a grid from
    the higher of their lowest swept bandwidths (both have settings there) up to the highest
    bandwidth both fronts reach.  A front that starts above the grid's start holds its first
    point's θ̃ below it (`_at`): that family's settings allowing less were measured and did
    no better, so it dominates there; `held_below_hz` names such fronts and where they
    start.  Empty ratios and no range: a family without a front."""
    fronts = {f: cell[f][front] for f in (a, b)}
    if not all(fronts.values()):
        return {"matched_bw_hz": None, "ratios": [], "held_below_hz": {}}
    q = front.removeprefix("front_")
    swept = {f: cell[f].get("points", {}).get(q) or fronts[f] for f in (a, b)}
    lo = max(min(p[0] for p in pts) for pts in swept.values())
    hi = min(max(p[0] for p in fr) for fr in fronts.values())
    if hi < lo:  # one family's settings all allow less than the other's least
        return {"matched_bw_hz": None, "ratios": [], "held_below_hz": {}}
    grid = np.linspace(lo, hi, 9)
    ratios = [_at(fronts[a], x) / _at(fronts[b], x) for x in grid]
    starts = {f: min(p[0] for p in fr) for f, fr in fronts.items()}
    return {
        "matched_bw_hz": [float(lo), float(hi)],
        "ratios": [x for x in ratios if math.isfinite(x)],
        "held_below_hz": {f: x for f, x in starts.items() if x > lo + 1e-9},
    }


def _matched(cell: dict[str, Any]) -> dict[str, Any]:
    """The flux/EMF noise ratio over the overlap of their allowed bandwidths."""
    m = matched_ratio(cell, "flux", "emf")
    return {
        "matched_bw_hz": m["matched_bw_hz"],
        "noise_ratio_flux_emf": m["ratios"],
        "held_below_hz": m["held_below_hz"],
    }


def plot(ctx, fronts: dict[str, Any], families=None, name: str = "fronts_flux_vs_emf") -> str:
    p = plt()
    keys = list(fronts)
    cols = 4
    rows = (len(keys) + cols - 1) // cols
    fig, axes = p.subplots(rows, cols, figsize=(3.4 * cols, 3.0 * rows), squeeze=False)
    for ax, key in zip(axes.flat, keys, strict=False):
        for k, fam in enumerate(families or FAMILIES):
            color = f"C{(0, 3, 2, 1, 4, 5, 6)[k % 7]}"
            c = fronts[key][fam]
            for q, style in (("rms", "o-"), ("noise", "s--")):
                xs, ys = zip(*sorted(c["points"][q]), strict=True)
                ax.plot(xs, ys, style, color=color, ms=3, lw=0.8, label=f"{fam} θ̃ {q}")
        ax.set_title(key.replace("_", " "), fontsize=8)
        ax.set_xlabel("speed bandwidth allowed [Hz]", fontsize=7)
        ax.set_ylabel("θ̃ [el. deg]", fontsize=7)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=6)
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    return ctx.fig(fig, name)


def _cell_txt(key: str, v: dict[str, Any]) -> str:
    """One cell of the verdict: the noise ratio's range over the matched bandwidths, and
    which front held its first point below where it starts."""
    r = v["noise_ratio_flux_emf"]
    if not r:
        return f"{key}: noise flux/EMF not comparable (no bandwidth both allow)"
    lo, hi = v["matched_bw_hz"]
    held = "".join(
        f" ({fam}'s front starts at {x:.1f} Hz: below, its {x:.1f}-Hz setting)"
        for fam, x in v.get("held_below_hz", {}).items()
    )
    return f"{key}: noise flux/EMF {min(r):.2f}-{max(r):.2f} over {lo:.1f}-{hi:.1f} Hz{held}"


def judge_fronts(fronts: dict[str, Any]) -> list[dict]:
    claims = []
    for src in SOURCES:
        cells = {k: v for k, v in fronts.items() if k.endswith(src)}
        ratios = [x for v in cells.values() for x in v["noise_ratio_flux_emf"]]
        missing = [k for k, v in cells.items() if not v["noise_ratio_flux_emf"]]
        ours = "; ".join(_cell_txt(k.rsplit("_", 1)[0], v) for k, v in cells.items())
        if missing:  # a verdict on fewer cells says so
            ours += f" -- judged without {', '.join(missing)}"
        claims.append(
            judge(
                "fronts.snr_matched",
                ours,
                max(ratios) if ratios else math.nan,
                "the largest flux/EMF ratio of θ̃ broadband noise at equal allowed speed-loop "
                "bandwidth, over every operating point (fronts_flux_vs_emf.png)",
                variant=f"{src} voltages",
            )
        )
    return claims


@dataclass(frozen=True)
class FrontWindow:
    """When θ̃ is measured at each operating point (`./fluxdrive compare --settle-s
    --window-s`)."""

    settle_s: float = param(
        0.7, unit="s", doc="settling at the operating point before θ̃ is measured", range=(0.0, 60.0)
    )
    window_s: float = param(1.0, unit="s", doc="θ̃ measured over this long", range=(0.05, 60.0))


def run_fronts(
    ctx,
    families=None,
    points=None,
    sources=SOURCES,
    plugin_keys=PLUGIN_KEYS,
    settle_s: float = FrontWindow.settle_s,
    window_s: float = FrontWindow.window_s,
    bench: str | None = None,
) -> dict[str, Any]:
    """Build, run and analyse the fronts of `families` (name -> variant) at `points`
    ((speed pu, load pu); None: POINTS) for `sources`, θ̃ measured over `window_s` after
    `settle_s` at the operating point, on the ideal bench or the bench file `bench`; the
    analysed cells by point/source."""
    card = ctx.card
    points, observers = build_cases(ctx.quick, card, families, points, sources, plugin_keys)
    jobs = [
        (
            ctx.encoder_run(
                ctx.rpm(s),
                load,
                observers=observers,
                ramp_s=1.5,
                settle_s=settle_s,
                window_s=window_s,
                name="fronts",
                **({"bench": bench} if bench else {}),
            ),
            _x_front,
            None,
        )
        for s, load in points
    ]
    res = ctx.run(jobs)
    return analyse(points, observers, res, card, families, sources)


def fronts(ctx) -> dict[str, Any]:
    """The fronts on the paper bench, the bench of the paper's figures (`experiment --bench
    FILE` swaps it like theirs)."""
    data = run_fronts(ctx, bench=str(PAPER_BENCH))
    return {"claims": judge_fronts(data), "figures": [plot(ctx, data)], "data": data}


EXPERIMENTS = {
    "fronts": (fronts, "flux vs EMF at matched speed-loop bandwidth: Pareto fronts"),
}
