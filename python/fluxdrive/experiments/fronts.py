"""Flux vs EMF independent of tuning: Pareto fronts of θ̃ against the speed-loop bandwidth each
observer's speed path allows.

One tuning compares a 25 Hz PLL (flux) with a 15 Hz PLL plus a 20 Hz speed LPF (EMF): the
narrower EMF path filters more.  Here every observer's PLL bandwidth is swept, and the EMF
path's speed LPF separately, off included: the LPF filters only the speed the observer reports
(observers.py: the angle path never reads it), so θ̃ is the same with and without it and each
PLL setting is placed once per LPF setting at the bandwidth that speed path allows.  Each
setting sits at the speed-loop bandwidth the project's one loop-design rule
(control.design_loops, 3 dB peaking) grants a drive fed by that speed path; its θ̃ (total RMS,
|mean|, 6th order, broadband noise: each its own front) is measured in shadow on an
encoder-driven run at each operating point, on every seed.  A setting whose θ̃ passes
SLIP_DEG on a run has slipped: it is drawn (marked) but never on a front.  The paper's SNR and
position-error claims are then judged at matched allowed bandwidth, per seed, for the project's
flux observer and the literal one: build -> run -> analyse -> plot -> judge.  The `fronts`
experiment runs on the paper bench (the paper's figures' bench: capture chain, model errors,
saturation); `run_fronts` on any bench file or the ideal one.
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
from fluxdrive.experiments.claims import MIN_SEEDS, judge
from fluxdrive.experiments.common import PAPER_BENCH, plt
from fluxdrive.replay.lab import parse_variant

# multiples of each variant's card-derived PLL bandwidth (and EMF speed LPF) swept
FACTORS = (0.4, 0.6, 0.8, 1.0, 1.4, 2.0)
FACTORS_QUICK = (0.6, 1.0, 1.6)
# multiples of the card-derived flux cutoff w_c swept at the card's PLL (variants with a w_c)
CUTOFF_FACTORS = (0.5, 2.0)
CUTOFF_FACTORS_QUICK = (0.5,)
# multiples of the card's EMF speed-LPF rule each PLL setting is placed at (0: off)
LPF_FACTORS = (0.0, 0.5, 1.0, 2.0)
FAMILIES = {"flux": "paper_robust", "literal": "paper", "emf": "emf"}
# the flux families judged against EMF, with the claims' variant names
JUDGED = {"flux": "paper_robust", "literal": "paper (literal)"}
# the fronts drawn and compared: θ̃ total RMS, |mean|, 6th order, broadband noise
QUANTITIES = ("rms", "mean", "h6", "noise")
SLIP_DEG = 30.0  # a setting whose |θ̃| passes this anywhere in the window has slipped
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
    if base.speed_lpf_hz:  # off in the run: placed at each LPF setting afterwards (_placed)
        cfg["speed_lpf_hz"] = 0.0
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
            "mean_deg": abs(o["theta_err_mean_deg"]),
            "h6_deg": o["theta_err_h6_deg"],
            "noise_deg": o["theta_err_noise_deg"],
            "slipped": bool(o["theta_err_peak_deg"] > SLIP_DEG),
        }
    return {"obs": out}


def _lpf_rule_hz(variant: str, card: MachineCard) -> float:
    """The card's speed-LPF rule of a variant (0: it has none, or a plugin)."""
    target = parse_variant(variant).target
    if ":" in target:
        return 0.0
    return float(observer_config(target, card).speed_lpf_hz or 0.0)


def _placed(
    card, cfg: dict[str, Any], lpf_rule_hz: float, memo: dict[tuple[float, float], float]
) -> list[tuple[float, float]]:
    """(allowed bandwidth, speed LPF) of one run observer: once (no LPF), or once per
    LPF_FACTORS multiple of its rule (the same θ̃: the LPF filters only the reported speed).
    `memo`: bandwidths by (PLL, LPF), the loop design being the slow part."""
    lpfs = [round(f * lpf_rule_hz, 6) for f in LPF_FACTORS] if lpf_rule_hz else [0.0]
    out = []
    for lpf in lpfs:
        key = (float(cfg["pll_bandwidth_hz"]), lpf)
        if key not in memo:
            memo[key] = allowed_bandwidth_hz(card, {**cfg, "speed_lpf_hz": lpf})
        out.append((memo[key], lpf))
    return out


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
    points,
    observers,
    res,
    card,
    families=None,
    sources: tuple[str, ...] = SOURCES,
    place: dict[str, list[tuple[float, float]]] | None = None,
) -> dict[str, Any]:
    """Per operating point and voltage source: each family's points (settings that slipped
    apart) and its four fronts, and each judged flux family's θ̃ over EMF's at matched
    allowed bandwidth over their overlap (`matched`; the paper_robust noise ratio also as
    `noise_ratio_flux_emf`)."""
    fams = families or FAMILIES
    if place is None:
        place = _placements(card, observers, fams, sources)
    out: dict[str, Any] = {}
    for (speed, load), r in zip(points, res, strict=True):
        for src in sources:
            key = f"{100 * speed:g}pct_{100 * load:g}load_{src}"
            cell: dict[str, Any] = {}
            for fam in fams:
                names = [n for n in observers if n.startswith(f"{fam}_{src}_")]
                ok = [n for n in names if not r["obs"][n].get("slipped", False)]
                bad = [n for n in names if r["obs"][n].get("slipped", False)]

                def pts(ns: list[str], q: str, r=r) -> list[tuple[float, float]]:
                    return [(bw, r["obs"][n][f"{q}_deg"]) for n in ns for bw, _ in place[n]]

                cell[fam] = {
                    "points": {q: pts(ok, q) for q in QUANTITIES},
                    "slipped_points": {q: pts(bad, q) for q in QUANTITIES},
                    **{f"front_{q}": pareto(pts(ok, q)) for q in QUANTITIES},
                    "settings": [
                        {**observers[n], "speed_lpf_hz": lpf} if lpf else observers[n]
                        for n in names
                        for _, lpf in place[n]
                    ],
                }
            if "emf" in cell:
                cell.update(_matched(cell))
            out[key] = cell
    return out


def _placements(card, observers, fams, sources) -> dict[str, list[tuple[float, float]]]:
    """Each run observer's (allowed bandwidth, speed LPF) placements."""
    out: dict[str, list[tuple[float, float]]] = {}
    memo: dict[tuple[float, float], float] = {}
    for nm, cfg in observers.items():
        fam = next(f for f in fams if any(nm.startswith(f"{f}_{s}_") for s in sources))
        out[nm] = _placed(card, cfg, _lpf_rule_hz(fams[fam], card), memo)
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
    """Each judged flux family over EMF on every front, over the overlap of their allowed
    bandwidths; the paper_robust noise ratio under its former keys too."""
    matched = {
        fam: {q: matched_ratio(cell, fam, "emf", f"front_{q}") for q in QUANTITIES}
        for fam in JUDGED
        if fam in cell
    }
    out: dict[str, Any] = {"matched": matched}
    if "flux" in matched:
        m = matched["flux"]["noise"]
        out |= {
            "matched_bw_hz": m["matched_bw_hz"],
            "noise_ratio_flux_emf": m["ratios"],
            "held_below_hz": m["held_below_hz"],
        }
    return out


def plot(ctx, fronts: dict[str, Any], families=None, name: str = "fronts_flux_vs_emf") -> str:
    """One row per operating point and voltage source, one column per quantity (θ̃ RMS,
    |mean|, 6th order, noise): every family's settings as dots, its front as a line, settings
    that slipped as crosses (never on a front)."""
    p = plt()
    keys = list(fronts)
    fams = list(families or FAMILIES)
    fig, axes = p.subplots(
        len(keys), len(QUANTITIES), figsize=(3.2 * len(QUANTITIES), 2.4 * len(keys)), squeeze=False
    )
    for row, key in zip(axes, keys, strict=True):
        for ax, q in zip(row, QUANTITIES, strict=True):
            for k, fam in enumerate(fams):
                color = f"C{(0, 1, 3, 2, 4, 5, 6)[k % 7]}"
                c = fronts[key][fam]
                if c["points"][q]:
                    xs, ys = zip(*c["points"][q], strict=True)
                    ax.plot(xs, ys, ".", color=color, ms=3, alpha=0.6)
                if c[f"front_{q}"]:
                    xs, ys = zip(*c[f"front_{q}"], strict=True)
                    ax.plot(xs, ys, "o-", color=color, lw=1.2, ms=2.5)
                if c["slipped_points"][q]:
                    xs, ys = zip(*c["slipped_points"][q], strict=True)
                    ax.plot(xs, ys, "x", color=color, ms=5)
            ax.set_title(f"{key.replace('_', ' ')}: θ̃ {q}", fontsize=7)
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=6)
        row[0].set_ylabel("θ̃ [el. deg]", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("speed bandwidth allowed [Hz]", fontsize=7)
    from matplotlib.lines import Line2D

    keys_ = [Line2D([], [], color="k", ls="", marker=".", label="a setting")]
    keys_ += [Line2D([], [], color="k", ls="", marker="x", label=f"slipped (> {SLIP_DEG:.0f}°)")]
    keys_ += [
        Line2D([], [], color=f"C{(0, 1, 3, 2, 4, 5, 6)[k % 7]}", label=f"{fam} front")
        for k, fam in enumerate(fams)
    ]
    fig.legend(handles=keys_, loc="upper center", ncol=len(keys_), fontsize=7)
    fig.tight_layout(rect=(0, 0, 1, 0.975))
    return ctx.fig(fig, name)


def _cell_txt(key: str, v: dict[str, Any], fam: str, q: str) -> str:
    """One cell of a verdict: the ratio's range over the matched bandwidths, and which front
    held its first point below where it starts."""
    m = v["matched"][fam][q]
    r = m["ratios"]
    lost = [f for f in (fam, "emf") if not v[f][f"front_{q}"] and v[f]["slipped_points"][q]]
    if lost:
        return f"{key}: not comparable ({' and '.join(lost)} slipped at every setting)"
    if not r:
        return f"{key}: not comparable (no bandwidth both allow)"
    lo, hi = m["matched_bw_hz"]
    held = "".join(
        f" ({f}'s front starts at {x:.1f} Hz)" for f, x in m.get("held_below_hz", {}).items()
    )
    return f"{key}: {min(r):.2f}-{max(r):.2f} over {lo:.1f}-{hi:.1f} Hz{held}"


# registered row -> (front compared, what the text calls it)
FRONT_CLAIMS = {
    "fronts.snr_matched": ("noise", "θ̃ broadband noise"),
    "fronts.position_error_matched": ("rms", "total θ̃ RMS"),
}


def _seed_value(cells: dict[str, Any], fam: str, q: str) -> float:
    """One seed's number for a claim: the largest ratio over every compared cell."""
    r = [x for v in cells.values() for x in v["matched"][fam][q]["ratios"]]
    return max(r) if r else math.nan


# a claim whose quantity has parts with fronts of their own: the parts' ratios shown beside it
FRONT_PARTS = {"fronts.position_error_matched": (("mean", "|mean θ̃|"), ("h6", "6th order"))}


def _parts_txt(cid: str, cells: dict[str, Any], fam: str) -> str:
    """The range over the cells of each part's flux/EMF ratio at matched bandwidth (the
    seeds' mean fronts), for a claim in FRONT_PARTS; empty otherwise."""
    parts = []
    for q, name in FRONT_PARTS.get(cid, ()):
        r = [x for v in cells.values() for x in v["matched"][fam][q]["ratios"]]
        parts.append(f"{name} {min(r):.2f}-{max(r):.2f}" if r else f"{name} not comparable")
    if not parts:
        return ""
    return "; its parts, flux/EMF at matched bandwidth over the cells: " + ", ".join(parts)


def judge_fronts(fronts: dict[str, Any], per_seed: list[dict[str, Any]] | None = None) -> list:
    """Per claim, judged flux family and voltage source: the largest flux/EMF ratio at equal
    allowed bandwidth over every operating point, per seed (`per_seed`: each seed's cells;
    None: the cells given are the one run)."""
    claims = []
    seeds = per_seed if per_seed is not None else [fronts]
    for cid, (q, what) in FRONT_CLAIMS.items():
        for fam, vname in JUDGED.items():
            for src in SOURCES:
                cells = {k: v for k, v in fronts.items() if k.endswith(src) and "matched" in v}
                if not cells or fam not in next(iter(cells.values()))["matched"]:
                    continue
                missing = [k for k, v in cells.items() if not v["matched"][fam][q]["ratios"]]
                ours = "; ".join(
                    _cell_txt(k.rsplit("_", 1)[0], v, fam, q) for k, v in cells.items()
                )
                if missing:  # a verdict on fewer cells says so
                    ours += f" -- without {', '.join(missing)}"
                samples = [
                    _seed_value({k: v for k, v in c.items() if k in cells}, fam, q) for c in seeds
                ]
                c = judge(
                    cid,
                    f"{what}, flux/EMF (mean over seeds) " + ours,
                    math.nan,
                    f"the largest flux/EMF ratio of {what} at equal allowed speed-loop "
                    "bandwidth over every operating point, per seed (fronts_flux_vs_emf.png)",
                    variant=f"{vname}, {src} voltages",
                    samples=samples,
                )
                st = c["stats"]
                c["ours"] += (
                    f" (per-seed largest ratio: mean {st['mean']:.3g}, 95 % CI "
                    f"[{st['ci95'][0]:.3g}, {st['ci95'][1]:.3g}], {st['n']} seeds: "
                    f"{st['outcome']})" + _parts_txt(cid, cells, fam)
                )
                claims.append(c)
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
    seeds: tuple[int, ...] = (1,),
    per_seed: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Build, run and analyse the fronts of `families` (name -> variant) at `points`
    ((speed pu, load pu); None: POINTS) for `sources`, θ̃ measured over `window_s` after
    `settle_s` at the operating point, on the ideal bench or the bench file `bench`, on every
    seed; the cells analysed on the seeds' mean θ̃ (a setting that slipped on any seed
    counts as slipped).  `per_seed`: a list that gets each seed's own cells."""
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
                seed=seed,
                **({"bench": bench} if bench else {}),
            ),
            _x_front,
            None,
        )
        for s, load in points
        for seed in seeds
    ]
    res = ctx.run(jobs)
    n = len(seeds)
    by_point = [res[i * n : (i + 1) * n] for i in range(len(points))]
    place = _placements(card, observers, families or FAMILIES, sources)
    if per_seed is not None:
        for k in range(n):
            rs = [rr[k] for rr in by_point]
            per_seed.append(analyse(points, observers, rs, card, families, sources, place))
    mean = [_mean_run(rr) for rr in by_point]
    return analyse(points, observers, mean, card, families, sources, place)


def _mean_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The seeds' runs at one point as one: each observer's θ̃ numbers averaged, slipped if
    it slipped on any seed."""
    obs = {}
    for nm in runs[0]["obs"]:
        rows = [r["obs"][nm] for r in runs]
        obs[nm] = {k: float(np.mean([x[k] for x in rows])) for k in rows[0] if k != "slipped"}
        obs[nm]["slipped"] = any(x.get("slipped", False) for x in rows)
    return {"obs": obs}


def fronts(ctx) -> dict[str, Any]:
    """The fronts on the paper bench, the bench of the paper's figures (`experiment --bench
    FILE` swaps it like theirs), over MIN_SEEDS seeds (one in --quick)."""
    seeds = (1,) if ctx.quick else tuple(range(1, 1 + MIN_SEEDS))
    per_seed: list[dict[str, Any]] = []
    data = run_fronts(ctx, bench=str(PAPER_BENCH), seeds=seeds, per_seed=per_seed)
    claims = judge_fronts(data, per_seed)
    data = {**data, "seeds": list(seeds)}
    return {"claims": claims, "figures": [plot(ctx, _cells(data))], "data": data}


def _cells(data: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in data.items() if k != "seeds"}


GROUP = "beyond"  # experiments.registry lists this module
EXPERIMENTS = {
    "fronts": (fronts, "flux vs EMF at matched speed-loop bandwidth: Pareto fronts"),
}
