"""The experiments by name, running one in its context, and the report.

Each experiment builds scenarios, runs them through the project's one parallel runner
(fluxdrive.study.runner: a dask LocalCluster on every core, an existing cluster with
--scheduler, or in-process with --workers 1), writes PNGs laid out like the paper's figure,
and one row per claim into report.md / report.json (experiments.claims judges every claim against
its registered row: config/claims.yaml for the paper's, config/claims_beyond.yaml for ours past
the paper; an experiment computes numbers, never a verdict -- `check_rows` refuses a row that
carries one the judge did not give).

Experiments live in the modules of this package, found by listing it (`experiment_modules`:
no hand-kept list): a module with an `EXPERIMENTS` table (name -> (function, title)) and a
`GROUP` ("paper" or "beyond") is one; paper.py (Figs. 2-4, 13-19), and past the paper one module
per experiment (fronts, emf_start, lowest_speed, mismatch, sensitivity, rs_adapt,
speed_reversal, hexagon, peers_fail; what they share is beyond_common.py), and whatever module
is added.  Each one is `fn(ctx) -> dict` with keys claims, figures, data; `ctx` (a
common.Ctx) carries the card, the runner and the output folder, and `ctx.run(jobs)` runs
(scenario, extractor, kwargs) jobs and returns the extractors' outputs, so only small arrays
cross process boundaries.  The command line is fluxdrive.cli.experiment.
"""

from __future__ import annotations

import functools
import importlib
import json
import math
import pkgutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fluxdrive.experiments.claims import (
    BEYOND,
    BEYOND_FILE,
    BEYOND_HISTORY_FILE,
    FAILURES,
    MIN_SEEDS,
    OBSERVERS,
    VERDICT_TEXT,
    count,
    counts_line,
    judge,
    over_seeds,
    registry_info,
    table,
)

# re-exported: study specs, the graph runner and tests name them here
from fluxdrive.experiments.common import (  # noqa: F401
    DEFAULT_MACHINE,
    LITERAL,
    OBS4,
    OBS6,
    CardValues,
    Ctx,
    Turns,
    build,
    encoder_run,
    observe,
    plt,
    sensorless,
)

# ---------------------------------------------------------------- registry
GROUPS = ("paper", "beyond")  # the report's order: the paper's figures, then past the paper


@functools.cache
def experiment_modules() -> tuple[Any, ...]:
    """Every module of this package that holds experiments (an `EXPERIMENTS` table and a
    `GROUP` in GROUPS), found by listing the package: the paper's first, then by name."""
    import fluxdrive.experiments as pkg

    mods = []
    for info in pkgutil.iter_modules(pkg.__path__):
        mod = importlib.import_module(f"{pkg.__name__}.{info.name}")
        if isinstance(getattr(mod, "EXPERIMENTS", None), dict) and getattr(mod, "GROUP", None):
            if mod.GROUP not in GROUPS:
                raise ValueError(f"{mod.__name__}: GROUP must be one of {GROUPS}")
            mods.append(mod)
    return tuple(sorted(mods, key=lambda m: (GROUPS.index(m.GROUP), m.__name__)))


def _registry() -> dict[str, tuple[Callable, str]]:
    out: dict[str, tuple[Callable, str]] = {}
    for mod in experiment_modules():
        for name, entry in mod.EXPERIMENTS.items():
            if name in out:
                raise ValueError(f"{mod.__name__}: experiment {name} is defined twice")
            out[name] = entry
    return out


def experiments() -> dict[str, tuple[Callable, str]]:
    """Every experiment by name: (function of a Ctx, title), in the report's order."""
    return _registry()


def groups() -> dict[str, list[str]]:
    """Names that stand for several experiments: `paper` (the paper's figures), `beyond`
    (past the paper: every module whose GROUP is "beyond") and `all`."""
    out: dict[str, list[str]] = {g: [] for g in GROUPS}
    for mod in experiment_modules():
        out[mod.GROUP] += list(mod.EXPERIMENTS)
    return {**out, "all": list(_registry())}


def expand(names: str) -> list[str]:
    """A comma-separated list of experiment and group names -> experiment names, in order,
    each once (unknown names are kept for the caller to refuse)."""
    grp = groups()
    out: list[str] = []
    for n in (x.strip() for x in names.split(",") if x.strip()):
        for e in grp.get(n, [n]):
            if e not in out:
                out.append(e)
    return out


def run_experiment(
    name: str,
    out: Path,
    quick: bool = False,
    runner=None,
    echo: bool = True,
    machine: Path | None = None,
    graph_run: Callable | None = None,
    bench: Path | None = None,
    seeds: int | None = None,
    turns: Turns | None = None,
    ledger: list[dict] | None = None,
) -> dict:
    """Run one experiment in a context of its own (card `machine`, None: the default card;
    `graph_run`: every scenario through the node graph; `bench`: a bench file that replaces the
    paper bench).  An experiment whose registered rows come from one seed is run again on
    seeds 2..`seeds` (None: MIN_SEEDS, 1 when quick; figures from seed 1) and its rows judged
    over the seeds; one that runs its seeds itself is run once.  `turns`: it runs beside
    other experiments on the runner (`run_experiments`), its seeds beside each other;
    `ledger`: what each run cost is appended to it."""
    fn, title = _registry()[name]
    ctx = Ctx(
        out=Path(out),
        quick=quick,
        runner=runner,
        name=name,
        echo=echo,
        machine=machine,
        graph_run=graph_run,
        bench=bench,
        turns=turns,
        ledger=ledger,
    )
    t0 = time.perf_counter()
    res = fn(ctx)
    check_rows(name, res["claims"])
    n_seeds = seeds if seeds is not None else (1 if quick else MIN_SEEDS)
    if n_seeds > 1 and any("verdict" in c and "stats" not in c for c in res["claims"]):
        res = _over_seeds(fn, ctx, res, n_seeds)
    res["runtime_s"] = round(time.perf_counter() - t0, 2)
    res["title"] = title
    res["quick"] = quick
    return res


# the keys only the judge writes: a row with any of them is a judged claim
_JUDGED_KEYS = ("verdict", "holds", "passes")


def check_rows(name: str, rows: list[dict]) -> None:
    """Refuse a row whose verdict the experiment `name` decided itself: a row is either a
    registered claim as `claims.judge` returned it (its id registered, its verdict the table's
    test on its value) or an observation with no verdict at all (`common.observe`)."""
    reg = table()
    for c in rows:
        if not any(k in c for k in _JUDGED_KEYS):
            continue
        cid = str(c.get("id", "")).split("[", 1)[0]
        if cid not in reg or c.get("class") != reg[cid]["class"]:
            raise ValueError(
                f"experiment {name}: row {c.get('id') or c.get('claim')!r} carries a verdict "
                "but is not a registered claim as the judge returns it"
            )
        if "stats" not in c:
            again = judge(cid, "", float(c["value"]))["verdict"]
            if again != c["verdict"]:
                raise ValueError(
                    f"experiment {name}: row {c['id']} says {c['verdict']}, its registered "
                    f"test on {c['value']!r} says {again}"
                )


def _over_seeds(fn: Callable, ctx: Ctx, first: dict, n_seeds: int) -> dict:
    """`first` (seed 1's result) with its rows judged over seeds 1..n_seeds: the experiment
    run again per seed (its figures not saved; with turns, the seeds at once), the seeds'
    data kept by seed."""
    import dataclasses
    import tempfile

    with tempfile.TemporaryDirectory(prefix="fluxdrive-seed-") as tmp:

        def seed(s: int) -> Callable[[], dict]:
            def run() -> dict:
                again = dataclasses.replace(
                    ctx, out=Path(tmp) / str(s), seed=s, echo=False, figures=False
                )
                res = fn(again)
                ctx.log(f"seed {s} of {n_seeds} done")
                return res

            return run

        later = [seed(s) for s in range(2, n_seeds + 1)]
        if ctx.turns is not None:
            runs = ctx.turns.all(later, holding=True)
        else:
            runs = [run() for run in later]
    res = dict(first)
    res["claims"] = over_seeds([first["claims"]] + [r["claims"] for r in runs])
    res["seeds"] = list(range(1, n_seeds + 1))
    return res


def run_experiments(
    names: list[str],
    out: Path,
    done: Callable[[str, dict], None],
    failed: Callable[[str, Exception], dict],
    runner=None,
    **kw: Any,
) -> None:
    """Run experiments `names` (`run_experiment`'s keywords in `kw`), each result handed to
    `done(name, result)` as it ends (`failed(name, exc)` makes the result of one that raised;
    the others still run).  On a cluster runner all of them run at once, their seeds too
    (`Turns`: the workers see every run from the start, so none waits on one experiment's
    few runs or analysis); in-process (no runner, a serial one, or a graph runner) one after
    the other, in order."""
    turns = Turns() if getattr(runner, "client", None) is not None else None

    def one(n: str) -> Callable[[], None]:
        def run() -> None:
            try:
                res = run_experiment(n, out, runner=runner, turns=turns, **kw)
            except Exception as exc:  # one broken experiment must not lose the others
                res = failed(n, exc)
            done(n, res)

        return run

    if turns is None:
        for n in names:
            one(n)()
    else:
        turns.all([one(n) for n in names])


def fmt_verdict(c: dict) -> str:
    """A registered claim's verdict (bold where a reproduction fails or is undecided), with a
    comparison's outcome over seeds and, where the test changed before registration, the
    verdict under the original test; a claim beyond the paper (no verdict): whether it
    holds."""
    v = c.get("verdict")
    if v is None:  # an observation (no claim), or an experiment that failed to run
        return "**the experiment failed**" if c.get("error") else "no test (measured)"
    text = VERDICT_TEXT[v]
    if v in ("disagreement", "modelling_gap", "undecided"):
        text = f"**{text}**"
    if c.get("class", "reproduction") not in ("reproduction", BEYOND) and v in FAILURES:
        # a calibrated or by-design claim never counts as held; one that fails its own
        # registered test counts as that failure and says which class it is
        text += f" ({c['class'].replace('_', ' ')}, fails its test)"
    st = c.get("stats")
    if st:
        text += f" ({st['outcome']}, {st['n']} seeds)"
    o = c.get("original")
    if o:
        text += f"; original test ({o['commit']}): {VERDICT_TEXT.get(o['verdict'], o['verdict'])}"
    return text


def _fmt_value(c: dict) -> str:
    st = c.get("stats")
    if not st:
        return f"**{c['value']:.4g}**"
    lo, hi = st["ci95"]
    margin = f", margin ±{st['margin']:g}" if st.get("margin") else ""
    return f"**{c['value']:.4g}** [{lo:.4g}, {hi:.4g}]{margin}"


def _claim_rows(claims: list[dict]) -> list[str]:
    lines = [
        "| id | claim (source; operating point) | class | registered test: value [95 % CI] "
        "| ours | verdict | why / note |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in claims:
        why = c.get("why", c.get("note", ""))
        if "verdict" in c:
            what = f"{_md(c['claim'])} ({_md(c['source'])}; {_md(c['operating_point'])})"
            test = f"{_md(c['test'])}: {_fmt_value(c)}"
            o = c.get("original")
            if o:
                test += f"; original: {_md(o['test'])}"
                why = "; ".join(x for x in (why, f"test changed in {o['commit']}: {o['why']}") if x)
            cls = c["class"].replace("_", " ")
        else:
            what, test, cls = _md(c["claim"]), "", "observation"
            why = c.get("error", why)
        lines.append(
            f"| {c.get('id', '')} | {what} | {cls} | {test} | {_md(c['ours'])} | "
            f"{fmt_verdict(c)} | {_md(why)} |"
        )
    return lines


BEYOND_VERDICTS = ("held", "disagreement", "modelling_gap", "undecided")


def counts_by_observer(claims: list[dict]) -> dict[str, dict[str, int]]:
    """The counts of the rows judging each flux observer (the row's variant or its
    registered `observer`), and of the rest (rows that involve neither)."""

    def observer(c: dict) -> str | None:  # rows judged before `observer` was kept: the id's
        return c.get("observer") or next((o for o in OBSERVERS if f"[{o}" in c.get("id", "")), None)

    out = {name: count([c for c in claims if observer(c) == name]) for name in OBSERVERS}
    out["neither"] = count([c for c in claims if observer(c) is None])
    return out


def original_changes(claims: list[dict]) -> list[dict]:
    """The rows whose verdict under the original (pre-registration) test differs."""
    return [
        {"id": c["id"], "current": c["verdict"], "original": c["original"]["verdict"]}
        for c in claims
        if c.get("original") and c["original"]["verdict"] != c["verdict"]
    ]


def _report_head(doc: dict[str, Any]) -> list[str]:
    """The report's head: what it is, the registry's version and hash, the counts overall
    and per flux observer, the verdicts the original tests change."""
    reg, n, changed = doc["registry"], doc["counts"], doc["original_tests_changed"]
    lines = [
        "# fluxdrive experiments: the paper's claims with our numbers",
        "",
        "Chen, Chen, Yang, IEEE Access 2019, reproduced on the switching-level engine "
        "(docs/engine.md).  Every claim of the paper is registered before the runs in "
        "config/claims.yaml: its source, operating point, the quantity measured, the test and "
        "threshold, and a class.  The verdict comes from that table: only a reproduction that "
        "passes is *held*; a failing one is a genuine disagreement or a modelling gap (why: "
        "the mechanism); a claim a model number was fitted to (*calibrated*) or a setting was "
        "chosen for or that is true by construction (*by design*) shows its number and is "
        "counted apart, never as held -- and when it fails its own test it counts as that "
        "failure.  THD is orders 2..20, "
        "THD+N everything but the fundamental; rows that use either show both.",
        "",
        _registry_line("Claims registry", reg, "config/claims_history.yaml"),
        "",
        _registry_line(
            "Past the paper (config/claims_beyond.yaml)",
            doc["registry_beyond"],
            "config/claims_beyond_history.yaml",
        ),
        "",
        "Every row is judged over noise seeds (their number is in the verdict): the mean of "
        "the per-seed values with its 95 % confidence interval; a comparison's outcome "
        "(better / worse / no difference / undecided) comes from the interval against the "
        "registered threshold ± margin.  Rows whose test was "
        "changed before the first registration show the verdict under the original test too.",
        "",
        f"**Claims: {counts_line(n)}.**",
        "",
        "Claims of ours past the paper (class *beyond*: registered in the second table, "
        "judged by the same judge over seeds, counted apart; rows marked *observation* "
        "report a measurement and claim nothing): "
        + ", ".join(f"{VERDICT_TEXT[v]} {doc['counts_beyond'][v]}" for v in BEYOND_VERDICTS)
        + ".",
        "",
        *(f"- {name}: {counts_line(c)}" for name, c in doc["counts_by_observer"].items()),
        "",
    ]
    if changed:
        lines += [
            "Verdicts that differ under the original tests: "
            + "; ".join(
                f"{x['id']} {VERDICT_TEXT[x['current']]} (original: "
                f"{VERDICT_TEXT.get(x['original'], x['original'])})"
                for x in changed
            )
            + ".",
            "",
        ]
    return lines


def _registry_line(what: str, reg: dict[str, Any], history: str) -> str:
    return f"**{what}: version {reg['version']}, sha256 `{reg['sha256'][:16]}`** " + (
        f"(the hash registered for this version in {history})."
        if reg["registered"]
        else "(**not the registered claims**: " + "; ".join(reg["problems"]) + ")."
    )


def write_report(out: Path, results: dict[str, dict]) -> None:
    """Merge into out/report.json and regenerate out/report.md."""
    out.mkdir(parents=True, exist_ok=True)
    jpath = out / "report.json"
    allres: dict[str, Any] = {}
    if jpath.exists():
        try:
            allres = json.loads(jpath.read_text()).get("experiments", {})
        except (ValueError, OSError):
            allres = {}
    allres.update(results)
    order = list(_registry())
    allres = {
        k: allres[k] for k in sorted(allres, key=lambda k: order.index(k) if k in order else 999)
    }
    rows = [c for r in allres.values() for c in r.get("claims", [])]
    judged = [c for c in rows if c.get("class") != BEYOND]  # the paper's claims
    n = count(judged)
    by_obs = counts_by_observer(judged)
    reg = registry_info()
    reg_beyond = registry_info(BEYOND_FILE, BEYOND_HISTORY_FILE)
    changed = original_changes(judged)
    doc = {  # the counts and the registry: for the docs to quote
        "registry": {k: reg[k] for k in ("version", "sha256", "registered", "problems")},
        "registry_beyond": {
            k: reg_beyond[k] for k in ("version", "sha256", "registered", "problems")
        },
        "counts": n,
        "counts_beyond": count([c for c in rows if c.get("class") == BEYOND]),
        "counts_by_observer": by_obs,
        "original_tests_changed": changed,
        "experiments": allres,
    }
    jpath.write_text(json.dumps(doc, indent=1, default=_json_default))
    lines = _report_head(doc)
    for name, r in allres.items():
        lines += [
            f"## {name}: {r.get('title', '')}",
            "",
            f"runtime {r.get('runtime_s', 0):.1f} s{' (quick)' if r.get('quick') else ''}",
            "",
        ]
        lines += _claim_rows(r.get("claims", []))
        lines.append("")
        for f in r.get("figures", []):
            lines.append(f"![{f}]({f})")
        lines.append("")
    (out / "report.md").write_text("\n".join(lines))


def _md(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, float) and math.isnan(o):
        return None
    return str(o)
