"""The claims, registered before the runs and frozen by version: the paper's
(config/claims.yaml) and ours past the paper (config/claims_beyond.yaml, class `beyond`, a
second table of the same form with its own version and history), one id space (`table`).

An experiment measures a number per claim and hands it to `judge`; the verdict comes from the
table's test and threshold, never from the experiment's code, and the table's class decides
how it counts: only a passing *reproduction* is "held"; a failing row is a genuine
disagreement or a modelling gap (the row's `if_fails` says which, the explanation says why),
whatever its class; a claim a model number was fitted to (`calibrated`) or a setting was
chosen for or that is true by construction (`by_design`) is reported with its number and,
when it passes, counted apart: never as held; a claim past the paper (`beyond`) is held when it
passes and counted apart from the paper's.

Frozen: the table carries a version and the SHA-256 of its claim definitions
(`content_hash`), and config/claims_history.yaml keeps every version's hash; a claim changed
without a new version no longer matches its registered hash (`frozen_problems`, checked by
tests/test_experiments.py, printed in the report).  A row whose test changed before it was
first registered keeps the earlier test (`original`): the report shows both verdicts.

Statistics: an experiment hands the per-seed values (`samples`); the row's value is their
mean with a 95 % Student-t confidence interval, and the verdict needs the whole interval on
one side of the threshold.  A comparison registers an equivalence `margin`: the interval
inside threshold ± margin is "no difference", wholly past threshold ∓ margin "better" or
"worse", anything else "undecided" (more seeds needed); only "better" holds.  A row without a
margin is a test, not a comparison: the interval passes, fails or leaves it undecided.
An experiment that runs one seed is run once per seed by the registry (`over_seeds` judges
its rows on the per-seed values).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import operator
from pathlib import Path
from typing import Any

from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.scenario import CONFIG_DIR

CLAIMS_FILE = CONFIG_DIR / "claims.yaml"
HISTORY_FILE = CONFIG_DIR / "claims_history.yaml"
# the claims of the experiments past the paper: a second table of the same form (rows of class
# `beyond` only), frozen by its own version and history, read by the same loader; `table()`
# is both, one id space
BEYOND_FILE = CONFIG_DIR / "claims_beyond.yaml"
BEYOND_HISTORY_FILE = CONFIG_DIR / "claims_beyond_history.yaml"
# (table, its history): the registries the judge reads, the paper's first
REGISTRIES = ((CLAIMS_FILE, HISTORY_FILE), (BEYOND_FILE, BEYOND_HISTORY_FILE))
# `beyond`: a claim of ours past the paper, judged like a reproduction (held / its if_fails /
# undecided) and counted apart from the paper's claims (BEYOND)
CLASSES = ("reproduction", "calibrated", "by_design", "beyond")
JUDGED = ("reproduction", "beyond")  # the classes a passing test makes "held"
BEYOND = "beyond"
FAILURES = ("disagreement", "modelling_gap")
# the six counts of the report, in its order
VERDICTS = ("held", "disagreement", "modelling_gap", "undecided", "calibrated", "by_design")
VERDICT_TEXT = {
    "held": "held",
    "disagreement": "genuine disagreement",
    "modelling_gap": "modelling gap",
    "undecided": "undecided",
    "calibrated": "calibrated",
    "by_design": "by design",
}
TESTS = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge}
_KEYS = {"id", "experiment", "claim", "source", "operating_point", "quantity", "metric"}
_KEYS |= {"unit", "test", "threshold", "class"}
_OPTIONAL = {"variants", "calibration", "design", "sources", "margin", "original", "observer"}
_KEYS.add("if_fails")
# the flux observers a row judges (a row's `variants`, or its `observer`)
OBSERVERS = ("paper_robust", "paper (literal)")
MIN_SEEDS = 8  # a verdict from fewer seeds says so
# two-sided 95 % Student-t quantiles by degrees of freedom (beyond 30: the normal's)
_T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306}
_T95 |= {9: 2.262, 10: 2.228, 11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131}
_T95 |= {16: 2.120, 17: 2.110, 18: 2.101, 19: 2.093, 20: 2.086, 25: 2.060, 30: 2.042}


def content_hash(rows: list[dict[str, Any]]) -> str:
    """SHA-256 of the claim definitions: the `claims` list as canonical JSON (keys sorted,
    no whitespace, UTF-8), so any change to any row -- test, threshold, class, text, margin --
    changes it, and reformatting the YAML does not."""
    text = json.dumps(rows, sort_keys=True, ensure_ascii=False, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _load(path: Path, key: str) -> Any:
    try:
        return yamlio.load_file(path)[key]
    except (OSError, KeyError, TypeError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read `{key}`: {exc}") from exc


def registry_info(path: Path = CLAIMS_FILE, history: Path = HISTORY_FILE) -> dict[str, Any]:
    """The table's declared version and hash, the hash recomputed from its rows, the
    history's versions, and what does not agree (`problems`: empty when frozen)."""
    doc = yamlio.load_file(path) if path.exists() else {}
    rows = _load(path, "claims")
    computed = content_hash(rows)
    version, declared = doc.get("version"), doc.get("sha256")
    versions = _load(history, "versions") if history.exists() else []
    by_version = {v.get("version"): v for v in versions if isinstance(v, dict)}
    problems = []
    if declared != computed:
        problems.append(
            f"{path}: sha256 {str(declared)[:12]}... is not the claims' own {computed[:12]}... "
            "(a claim changed: register a new version)"
        )
    reg = by_version.get(version)
    if reg is None:
        problems.append(f"{history}: version {version} is not registered")
    elif reg.get("sha256") != computed:
        problems.append(
            f"{history}: version {version} was registered as {str(reg.get('sha256'))[:12]}..., "
            f"the claims hash to {computed[:12]}... (changed without a new version)"
        )
    nums = [v.get("version") for v in versions if isinstance(v, dict)]
    if nums != list(range(1, len(nums) + 1)) or (nums and version != nums[-1]):
        problems.append(f"{history}: versions must be 1, 2, ... with the table at the last")
    return {
        "version": version,
        "sha256": computed,
        "registered": not problems,
        "problems": problems,
        "history": [{k: v.get(k) for k in ("version", "sha256", "date", "what")} for v in versions],
    }


@functools.cache
def registered(path: Path = CLAIMS_FILE) -> dict[str, dict[str, Any]]:
    """The table, by id; a malformed row is one line naming the file and the row."""
    rows = _load(path, "claims")
    out: dict[str, dict[str, Any]] = {}
    for i, row in enumerate(rows):
        where = f"{path}: claims[{i}]"
        if not isinstance(row, dict) or not _KEYS <= set(row) or set(row) - _KEYS - _OPTIONAL:
            raise ConfigError(f"{where}: needs exactly the keys {sorted(_KEYS)} (+ optional)")
        if row["class"] not in CLASSES or row["test"] not in TESTS:
            raise ConfigError(f"{where}: class in {CLASSES}, test in {sorted(TESTS)}")
        if row.get("if_fails") not in FAILURES:
            raise ConfigError(f"{where}: names if_fails in {FAILURES}")
        if row.get("observer", OBSERVERS[0]) not in OBSERVERS or (
            "observer" in row and "variants" in row
        ):
            raise ConfigError(
                f"{where}: observer is one of {OBSERVERS}, for a row without variants"
            )
        if row["id"] in out:
            raise ConfigError(f"{where}: duplicate id {row['id']}")
        if "margin" in row and not (isinstance(row["margin"], float) and row["margin"] >= 0):
            raise ConfigError(f"{where}: margin is a number >= 0 in the metric's unit")
        orig = row.get("original")
        if orig is not None and not (
            isinstance(orig, dict)
            and {"commit", "why", "tests"} == set(orig)
            and all(
                isinstance(t, dict)
                and {"metric", "test", "threshold"} == set(t)
                and t["test"] in TESTS
                for t in orig["tests"]
            )
        ):
            raise ConfigError(
                f"{where}: original needs commit, why and tests (metric, test, threshold)"
            )
        if path == BEYOND_FILE and row["class"] != "beyond":
            raise ConfigError(f"{where}: a claim past the paper has class beyond")
        out[row["id"]] = row
    return out


@functools.cache
def table() -> dict[str, dict[str, Any]]:
    """Every registered claim by id: the paper's table and the one past the paper (one id
    space: an id in both is refused, naming it)."""
    out: dict[str, dict[str, Any]] = {}
    for path, _ in REGISTRIES:
        rows = registered(path)
        twice = sorted(set(rows) & set(out))
        if twice:
            raise ConfigError(f"{path}: ids registered in another claims table too: {twice}")
        out.update(rows)
    return out


def interval(samples: list[float]) -> dict[str, Any]:
    """Mean of the per-seed values and its 95 % Student-t confidence interval (a non-finite
    seed -- a run that stopped -- makes the interval unbounded)."""
    n = len(samples)
    if n == 0:
        return {"n": 0, "mean": math.nan, "ci95": [math.nan, math.nan]}
    if n > 1 and all(x == samples[0] for x in samples):  # inf on every seed too: bounded
        return {"n": n, "mean": samples[0], "ci95": [samples[0], samples[0]]}
    finite = all(math.isfinite(x) for x in samples)
    mean = sum(samples) / n if finite else math.nan
    if not finite or n < 2:  # one seed bounds nothing
        return {"n": n, "mean": mean, "ci95": [-math.inf, math.inf]}
    sd = math.sqrt(sum((x - mean) ** 2 for x in samples) / (n - 1))
    dof = n - 1
    t = _T95[max(k for k in _T95 if k <= dof)] if dof <= 30 else 1.960  # conservative
    half = t * sd / math.sqrt(n)
    return {"n": n, "mean": mean, "ci95": [mean - half, mean + half]}


def compare(test: str, threshold: float, margin: float, ci: list[float]) -> str:
    """A comparison's outcome from its interval: "better" (wholly past threshold − margin on
    the side the test asks for), "worse" (wholly past threshold + margin the other way), "no
    difference" (wholly inside threshold ± margin), else "undecided"."""
    lo, hi = ci
    if test in ("<", "<="):
        if TESTS[test](hi, threshold - margin):
            return "better"
        if lo > threshold + margin:
            return "worse"
    else:
        if TESTS[test](lo, threshold + margin):
            return "better"
        if hi < threshold - margin:
            return "worse"
    if threshold - margin <= lo and hi <= threshold + margin:
        return "no difference"
    return "undecided"


def _passes(test: str, threshold: float, value: float) -> bool:
    return not math.isnan(value) and bool(TESTS[test](value, float(threshold)))


def judge(
    cid: str,
    ours: str,
    value: float,
    why: str = "",
    variant: str | None = None,
    samples: list[float] | None = None,
    also: dict[str, float] | None = None,
) -> dict:
    """One claim's row of the report: the registered claim `cid` (for `variant`, if the row
    has variants) judged on the measured `value` (nan: not measured -> does not pass), or on
    the per-seed `samples` (the value: their mean, with a 95 % interval); `also`: the values
    of other metrics an `original` test of the row needs."""
    row = table()[cid]
    cls = row["class"]
    value, passes, verdict, stats = _decide(row, value, samples)
    tag = f"[{variant}] " if variant else ""
    out = {
        "id": cid + (f"[{variant}]" if variant else ""),
        "claim": tag + row["claim"],
        "source": row["source"],
        "operating_point": row["operating_point"],
        "test": f"{row['quantity']} {row['test']} {row['threshold']:g}",
        "value": value,
        "ours": ours,
        "class": cls,
        "passes": passes,
        "holds": passes if cls in JUDGED else None,  # only a reproduction (or beyond) holds
        "verdict": verdict,
    }
    if stats is not None:
        out["stats"] = stats
    obs = row.get("observer") or next((o for o in OBSERVERS if variant and o in variant), None)
    if obs:
        out["observer"] = obs
    if "original" in row:
        out["original"] = _original(row, value, also or {})
    reason = row.get("calibration") or row.get("design")
    why = "; ".join(x for x in (reason, why) if x)
    if why:
        out["why" if verdict in FAILURES else "note"] = why
    return out


def _decide(
    row: dict[str, Any], value: float, samples: list[float] | None
) -> tuple[float, bool, str, dict[str, Any] | None]:
    """(value, passes, verdict, stats) of registered `row` on `value` or the per-seed
    `samples`: a passing row is held (a reproduction) or its class; a failing one its
    `if_fails`, whatever its class; an interval that decides nothing is undecided."""
    thr = float(row["threshold"])
    stats = None
    if samples is not None:
        stats = interval([float(x) for x in samples])
        value = stats["mean"]
    value = float(value)
    passes = _passes(row["test"], thr, value)
    decided = True
    if stats is not None:
        stats["seeds_short"] = stats["n"] < MIN_SEEDS
        margin = float(row.get("margin", 0.0))
        stats["margin"] = margin
        outcome = compare(row["test"], thr, margin, stats["ci95"])
        if "margin" not in row:  # a test, not a comparison: passes / fails / undecided
            outcome = {"better": "passes", "undecided": "undecided"}.get(outcome, "fails")
        stats["outcome"] = outcome
        passes = outcome in ("better", "passes")
        decided = outcome != "undecided"
    if not decided:
        verdict = "undecided"
    elif not passes:
        verdict = row["if_fails"]
    else:
        verdict = "held" if row["class"] in JUDGED else row["class"]
    return value, passes, verdict, stats


def over_seeds(per_seed: list[list[dict]]) -> list[dict]:
    """The rows of an experiment run once per seed (`per_seed[k]`: seed k's rows, the same
    rows in every seed), each registered row judged on its per-seed values (mean, 95 %
    interval, outcome); its text is the first seed's with every seed's value appended.
    Observations (rows without a verdict) are the first seed's."""
    first = per_seed[0]
    out = []
    for i, c in enumerate(first):
        if "verdict" not in c:
            out.append(c)
            continue
        vals = [float(s[i]["value"]) for s in per_seed]
        if any(s[i]["id"] != c["id"] for s in per_seed):
            raise ValueError(f"{c['id']}: the seeds' rows differ")
        row = table()[c["id"].split("[", 1)[0]]
        value, passes, verdict, stats = _decide(row, math.nan, vals)
        d = dict(c)
        d.update(value=value, passes=passes, verdict=verdict, stats=stats)
        d["holds"] = passes if row["class"] in JUDGED else None
        d["per_seed"] = vals
        d["ours"] = f"{c['ours']} (seed 1; per seed: {', '.join(f'{v:.4g}' for v in vals)})"
        if "original" in c and {x["metric"] for x in row["original"]["tests"]} <= {row["metric"]}:
            d["original"] = _original(row, value, {})
        note = d.pop("why", None) or d.pop("note", None)
        if note:
            d["why" if verdict in FAILURES else "note"] = note
        out.append(d)
    return out


def _original(row: dict[str, Any], value: float, also: dict[str, float]) -> dict[str, Any]:
    """The verdict under the row's test before it was changed (every test must pass; the
    row's own metric is `value`, the others come from `also`)."""
    orig = row["original"]
    vals = {row["metric"]: value, **also}
    parts, ok = [], True
    for t in orig["tests"]:
        v = float(vals.get(t["metric"], math.nan))
        ok = ok and _passes(t["test"], t["threshold"], v)
        parts.append(f"{t['metric']} {t['test']} {t['threshold']:g} ({v:.4g})")
    if not ok:
        verdict = row["if_fails"]
    else:
        verdict = "held" if row["class"] in JUDGED else row["class"]
    return {
        "test": " and ".join(parts),
        "passes": ok,
        "verdict": verdict,
        "commit": orig["commit"],
        "why": orig["why"],
    }


def count(claims: list[dict]) -> dict[str, int]:
    """The six counts over judged claims (rows without a verdict -- observations -- are
    not counted)."""
    n = dict.fromkeys(VERDICTS, 0)
    for c in claims:
        if c.get("verdict") in n:
            n[c["verdict"]] += 1
    return n


def counts_line(n: dict[str, int]) -> str:
    return ", ".join(f"{VERDICT_TEXT[v]} {n[v]}" for v in VERDICTS)
