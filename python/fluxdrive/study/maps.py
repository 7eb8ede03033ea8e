"""Robustness maps from a study table: P(stable) with Wilson intervals and theta~ statistics
over speed x load per variant, PNG heat maps, report.md, and the lowest speed at which each
variant holds the rated load with the spec's probability."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.study.spec import PERTURBATIONS, StudySpec, axis_override_text

Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion k/n (coverage near nominal even at
    p = 0 or 1, where the normal interval collapses to a point)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    den = 1.0 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def cells(table, spec: StudySpec) -> dict[str, Any]:
    """Per variant: the map axes' values and per cell n, k (stable), p, Wilson lo/hi and
    theta~ statistics (over the stable runs: median and 95th percentile of the RMS, the
    largest peak)."""
    ax, ay = spec.map_axes
    d = table.to_pydict()
    xs = sorted({float(v) for v in d[ax]}) if ax in d else [0.0]
    ys = sorted({float(v) for v in d[ay]}) if ay in d else [0.0]
    out: dict[str, Any] = {"x_axis": ax, "y_axis": ay, "x": xs, "y": ys, "variants": {}}
    n_rows = len(d["task_id"])
    for v in spec.variants:
        grid = {}
        for j, yv in enumerate(ys):
            for i, xv in enumerate(xs):
                rows = [
                    r
                    for r in range(n_rows)
                    if d["variant"][r] == v
                    and (ax not in d or d[ax][r] == xv)
                    and (ay not in d or d[ay][r] == yv)
                ]
                st = [bool(d["stable"][r]) for r in rows]
                rms = np.array([d["theta_err_rms_deg"][r] for r in rows if d["stable"][r]])
                peak = [d["theta_err_peak_deg"][r] for r in rows if d["stable"][r]]
                k, n = sum(st), len(st)
                lo, hi = wilson(k, n)
                grid[(i, j)] = {
                    "n": n,
                    "k": k,
                    "p": k / n if n else math.nan,
                    "lo": lo,
                    "hi": hi,
                    "rms_med": float(np.median(rms)) if rms.size else math.nan,
                    "rms_p95": float(np.percentile(rms, 95)) if rms.size else math.nan,
                    "peak_max": float(max(peak)) if peak else math.nan,
                }
        out["variants"][v] = grid
    return out


def lowest_speed(c: dict[str, Any], spec: StudySpec) -> dict[str, dict[str, Any]]:
    """Per variant at the rated load: the lowest speed from which every tested speed upwards
    has P^(stable) >= the spec's probability ('point'), and the same with the Wilson lower
    bound >= it ('confident': needs enough draws -- n >= 59 even with no loss)."""
    res: dict[str, Any] = {}
    if c["x_axis"] != "speed_rpm" or c["y_axis"] != "load_pu":
        return res
    ys = c["y"]
    if not ys:
        return res
    j = int(np.argmin([abs(y - spec.rated_load_pu) for y in ys]))
    q = spec.probability
    for v, grid in c["variants"].items():
        row = [grid[(i, j)] for i in range(len(c["x"]))]

        def lowest(ok, row=row):
            low = None
            for i in range(len(row) - 1, -1, -1):
                if row[i]["n"] and ok(row[i]):
                    low = c["x"][i]
                else:
                    break
            return low

        pt = lowest(lambda cell: cell["p"] >= q)
        cf = lowest(lambda cell: cell["lo"] >= q)
        at = row[c["x"].index(pt)] if pt is not None else None
        res[v] = {
            "load_pu": ys[j],
            "point_rpm": pt,
            "confident_rpm": cf,
            "at": None if at is None else {k: at[k] for k in ("n", "k", "p", "lo", "hi")},
        }
    return res


def plot_maps(c: dict[str, Any], spec: StudySpec, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(c["variants"])
    nx, ny = len(c["x"]), len(c["y"])
    cols = min(2, len(names))
    rows = math.ceil(len(names) / cols)
    files = []
    for what, title, cmap, vmax in (
        ("p", "P(stable)", "RdYlGn", 1.0),
        ("rms_med", "median θ̃ RMS of the stable runs [°el]", "viridis", None),
    ):
        fig, axs = plt.subplots(
            rows,
            cols,
            figsize=(0.9 * nx * cols + 2.5, 0.75 * ny * rows + 1.6),
            squeeze=False,
            layout="constrained",
        )
        vals_all = [
            cell[what]
            for g in c["variants"].values()
            for cell in g.values()
            if not math.isnan(cell[what])
        ]
        top = vmax if vmax is not None else (max(vals_all) if vals_all else 1.0)
        im = None
        for k, ax in enumerate(axs.flat):
            if k >= len(names):
                ax.axis("off")
                continue
            v = names[k]
            z = np.full((ny, nx), np.nan)
            for (i, j), cell in c["variants"][v].items():
                z[j, i] = cell[what]
            im = ax.imshow(z, origin="lower", cmap=cmap, vmin=0.0, vmax=top, aspect="auto")
            for (i, j), cell in c["variants"][v].items():
                if cell["n"] == 0:
                    continue
                if what == "p":
                    txt = f"{cell['p']:.2f}\n[{cell['lo']:.2f},{cell['hi']:.2f}]"
                else:
                    txt = "—" if math.isnan(cell[what]) else f"{cell[what]:.2f}"
                ax.text(i, j, txt, ha="center", va="center", fontsize=6.5)
            ax.set_xticks(range(nx))
            ax.set_xticklabels([f"{x:g}" for x in c["x"]], fontsize=8)
            ax.set_yticks(range(ny))
            ax.set_yticklabels([f"{y:g}" for y in c["y"]], fontsize=8)
            ax.set_xlabel(_label(c["x_axis"]), fontsize=8)
            ax.set_ylabel(_label(c["y_axis"]), fontsize=8)
            ax.set_title(v, fontsize=9)
        fig.suptitle(
            f"{spec.name}: {title}  ({spec.draws} draws per cell"
            + ("; 95 % Wilson interval" if what == "p" else "")
            + ")",
            fontsize=9,
        )
        if im is not None:
            fig.colorbar(im, ax=axs.ravel().tolist(), shrink=0.8)
        name = f"{'p_stable' if what == 'p' else 'theta_rms'}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        files.append(name)
    return files


def _cpu(table) -> float:
    if "cpu_s" not in table.column_names:
        return math.nan
    return float(sum(x for x in table.column("cpu_s").to_pylist() if x is not None))


def _label(axis: str) -> str:
    return {"speed_rpm": "speed [rpm]", "load_pu": "load [pu of rated torque]"}.get(axis, axis)


def _dist(d: dict[str, Any]) -> str:
    if d["dist"] == "uniform":
        return f"uniform [{d['low']:g}, {d['high']:g}]"
    if d["dist"] == "normal":
        return f"normal(mean {d['mean']:g}, std {d['std']:g})"
    return f"one of {d['values']}"


def grid_lines(spec: StudySpec) -> list[str]:
    """Report lines: what every grid axis sets (a level scaling the scenario's profile, a
    value replacing the file's, an observer or controller setting, an uncertainty)."""
    lines = ["## What the grid sets", "", "| axis | values | what it sets |", "|---|---|---|"]
    for axis, values in spec.grid.items():
        vals = ", ".join(f"{x:g}" if isinstance(x, (int, float)) else str(x) for x in values)
        lines.append(f"| {axis} | {vals} | {axis_override_text(spec, axis)} |")
    for a in spec.map_axes:
        if a not in spec.grid:
            lines.append(f"| {a} (map axis) | — | not varied: the map has one row/column |")
    return [*lines, ""]


def unstable_reasons(table, spec: StudySpec) -> list[str]:
    """Report lines: every grid point with runs that were not stable, and why (the latched
    fault, or what the stability verdict found without one), counted over the draws."""
    from fluxdrive.drive.control import FAULT_NAMES

    d = table.to_pydict()
    axes = [a for a in spec.grid if a in d]
    why: dict[tuple[str, str], dict[str, int]] = {}
    for r in range(len(d["task_id"])):
        if d["stable"][r]:
            continue
        code = int(d["fault_code"][r] or 0)
        text = (
            FAULT_NAMES.get(code, f"fault {code}")
            if code
            else "no fault, but the speed missed its reference by over 20 % or the loop did "
            "not stay closed on the observer"
        )
        at = ", ".join(f"{a} = {d[a][r]:g}" for a in axes) or "—"
        cell = why.setdefault((d["variant"][r], at), {})
        cell[text] = cell.get(text, 0) + 1
    if not why:
        return []
    out = ["## Runs that were not stable, and why", "", "| variant | grid point | why (runs) |"]
    out.append("|---|---|---|")
    for (v, at), reasons in why.items():
        out.append(f"| {v} | {at} | " + "; ".join(f"{t} ({n})" for t, n in reasons.items()) + " |")
    return [*out, ""]


def write_report(
    table, spec: StudySpec, out: Path, failures: list[dict[str, Any]], info: dict[str, Any]
) -> dict[str, Any]:
    c = cells(table, spec)
    figs = plot_maps(c, spec, out)
    low = lowest_speed(c, spec)
    q = int(round(spec.probability * 100))
    lines = [
        f"# Study {spec.name}",
        "",
        spec.description.strip(),
        "",
        f"{len(spec.variants)} variants × {math.prod(len(v) for v in spec.grid.values())} "
        f"grid points × {spec.draws} draws = {info.get('tasks', '?')} tasks; "
        f"{table.num_rows} rows, {len(failures)} failed; "
        f"{info.get('runner', '')}, {info.get('elapsed_s', 0):.0f} s wall, "
        f"{_cpu(table):.0f} s of task CPU time; fluxdrive {info.get('commit', '?')}.",
        "",
        "## Uncertainties (one draw per machine, shared by every variant and grid point)",
        "",
        "| axis | distribution | what it sets |",
        "|---|---|---|",
    ]
    for a, d in spec.random.items():
        lines.append(f"| {a} | {_dist(d)} | {PERTURBATIONS[a][1]} |")
    lines += ["", *grid_lines(spec)]
    if low:
        lines += [
            f"## Lowest speed holding {low[next(iter(low))]['load_pu']:g} pu load with "
            f"{q} % probability",
            "",
            f"point: the lowest tested speed from which every speed upwards has "
            f"P̂(stable) ≥ {spec.probability:g}; confident: the same with the 95 % Wilson "
            f"lower bound ≥ {spec.probability:g}.",
            "",
            "| variant | point [rpm] | stable/draws there | 95 % interval | confident [rpm] |",
            "|---|---|---|---|---|",
        ]
        for v, r in low.items():
            at = r["at"]
            pt = "none" if r["point_rpm"] is None else f"{r['point_rpm']:g}"
            cf = "none" if r["confident_rpm"] is None else f"{r['confident_rpm']:g}"
            kn = "—" if at is None else f"{at['k']}/{at['n']}"
            ci = "—" if at is None else f"[{at['lo']:.2f}, {at['hi']:.2f}]"
            lines.append(f"| {v} | {pt} | {kn} | {ci} | {cf} |")
        lines.append("")
    lines += ["## Maps", ""] + [f"![{f}]({f})" for f in figs] + [""]
    lines += ["## P(stable) per cell", ""]
    for v, grid in c["variants"].items():
        lines += [
            f"### {v}",
            "",
            f"| {c['y_axis']} \\ {c['x_axis']} | " + " | ".join(f"{x:g}" for x in c["x"]) + " |",
            "|---|" + "---|" * len(c["x"]),
        ]
        for j, yv in enumerate(c["y"]):
            lines.append(
                f"| {yv:g} | "
                + " | ".join(
                    f"{grid[(i, j)]['k']}/{grid[(i, j)]['n']} ({grid[(i, j)]['rms_med']:.2f}°)"
                    if grid[(i, j)]["n"]
                    else "—"
                    for i in range(len(c["x"]))
                )
                + " |"
            )
        lines.append("")
    lines += ["Cells: stable runs / runs (median θ̃ RMS of the stable runs, electrical).", ""]
    lines += unstable_reasons(table, spec)
    if failures:
        lines += ["## Failed tasks (after one retry)", "", "| task | error |", "|---|---|"]
        for f in failures:
            lines.append(f"| {f['task_id']} | {str(f['error']).splitlines()[0][:160]} |")
        lines.append("")
    (out / "report.md").write_text("\n".join(lines))
    return {"lowest": low, "figures": figs}
