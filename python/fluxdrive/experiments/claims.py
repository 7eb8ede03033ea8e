"""The paper's claims, registered before the runs (config/claims.yaml).

An experiment measures a number per claim and hands it to `judge`; the verdict comes from the
table's test and threshold, never from the experiment's code, and the table's class decides
how it counts: only a passing *reproduction* is "held"; a failing one is a genuine
disagreement or a modelling gap (the row says which, the explanation says why); a claim a
model number was fitted to (`calibrated`) or a setting was chosen for (`by_design`) is
reported with its number but never counted as held.
"""

from __future__ import annotations

import functools
import math
import operator
from pathlib import Path
from typing import Any

from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.scenario import CONFIG_DIR

CLAIMS_FILE = CONFIG_DIR / "claims.yaml"
CLASSES = ("reproduction", "calibrated", "by_design")
FAILURES = ("disagreement", "modelling_gap")
# the five counts of the report, in its order
VERDICTS = ("held", "disagreement", "modelling_gap", "calibrated", "by_design")
VERDICT_TEXT = {
    "held": "held",
    "disagreement": "genuine disagreement",
    "modelling_gap": "modelling gap",
    "calibrated": "calibrated",
    "by_design": "by design",
}
TESTS = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge}
_KEYS = {"id", "experiment", "claim", "source", "operating_point", "quantity", "metric"}
_KEYS |= {"unit", "test", "threshold", "class"}
_OPTIONAL = {"if_fails", "variants", "calibration", "design", "sources"}


@functools.cache
def registered(path: Path = CLAIMS_FILE) -> dict[str, dict[str, Any]]:
    """The table, by id; a malformed row is one line naming the file and the row."""
    try:
        rows = yamlio.load_file(path)["claims"]
    except (OSError, KeyError, TypeError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the claims table: {exc}") from exc
    out: dict[str, dict[str, Any]] = {}
    for i, row in enumerate(rows):
        where = f"{path}: claims[{i}]"
        if not isinstance(row, dict) or not _KEYS <= set(row) or set(row) - _KEYS - _OPTIONAL:
            raise ConfigError(f"{where}: needs exactly the keys {sorted(_KEYS)} (+ optional)")
        if row["class"] not in CLASSES or row["test"] not in TESTS:
            raise ConfigError(f"{where}: class in {CLASSES}, test in {sorted(TESTS)}")
        if (row["class"] == "reproduction") != (row.get("if_fails") in FAILURES):
            raise ConfigError(f"{where}: a reproduction (only) names if_fails in {FAILURES}")
        if row["id"] in out:
            raise ConfigError(f"{where}: duplicate id {row['id']}")
        out[row["id"]] = row
    return out


def judge(cid: str, ours: str, value: float, why: str = "", variant: str | None = None) -> dict:
    """One claim's row of the report: the registered claim `cid` (for `variant`, if the row
    has variants) judged on the measured `value` (nan: not measured -> does not pass)."""
    row = registered()[cid]
    value = float(value)
    passes = not math.isnan(value) and bool(TESTS[row["test"]](value, float(row["threshold"])))
    cls = row["class"]
    if cls == "reproduction":
        verdict = "held" if passes else row["if_fails"]
    else:
        verdict = cls
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
        "holds": passes if cls == "reproduction" else None,  # only a reproduction can hold
        "verdict": verdict,
    }
    reason = row.get("calibration") or row.get("design")
    why = "; ".join(x for x in (reason, why) if x)
    if why:
        out["why" if verdict in FAILURES else "note"] = why
    return out


def count(claims: list[dict]) -> dict[str, int]:
    """The five counts over judged claims (rows without a verdict -- beyond the paper -- are
    not counted)."""
    n = dict.fromkeys(VERDICTS, 0)
    for c in claims:
        if c.get("verdict") in n:
            n[c["verdict"]] += 1
    return n


def counts_line(n: dict[str, int]) -> str:
    return ", ".join(f"{VERDICT_TEXT[v]} {n[v]}" for v in VERDICTS)
