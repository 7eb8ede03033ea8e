"""The config blocks a user writes (a scenario's `control:`, ...), each a dataclass declared
with `fluxdrive.core.schema`, and the parameter tables of docs/configuration.md generated
from them.

A table sits in the page between two markers naming its block::

    <!-- params control -->
    | key | default | unit | ... |
    <!-- /params -->

`fill(text)` rewrites every table from the schema, `stale_tables()` lists the blocks whose
table differs (the docs test fails on any); ``./fluxdrive docs params [--check]`` rewrites
(or checks) the page.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from fluxdrive.core import schema
from fluxdrive.core.bench import SECTIONS, BenchConfig, parse_bench, per_phase
from fluxdrive.core.machine import MachineCard, load_machine
from fluxdrive.core.paths import ROOT
from fluxdrive.drive.control.config import ControllerConfig, DriveParams
from fluxdrive.drive.observers import ObserverConfig
from fluxdrive.drive.scenario import ScenarioSettings, load_scenario

DOC_PAGE = ROOT / "docs" / "configuration.md"
TABLE_RE = re.compile(r"(<!-- params (?P<key>\S+) -->\n)(?P<table>.*?)(<!-- /params -->)", re.S)


@dataclass(frozen=True)
class Block:
    """One config block: its dataclass, how a value set in it is checked (as a scenario
    would give it), and the fields that are not settings (free: no schema; free_text: a
    string without a fixed list of choices)."""

    cls: type
    check: Callable[[dict[str, Any]], Any]
    free: frozenset[str] = frozenset()
    free_text: frozenset[str] = frozenset()
    on_card: bool = False  # `check` holds the fields to their ranges on the default card


@functools.cache
def default_card() -> MachineCard:
    return load_machine(ROOT / "config" / "machines" / "default_spm.yaml")


def _bench_check(section: str | None) -> Callable[[dict[str, Any]], Any]:
    """Check values as a scenario's `bench:` (or `bench.<section>:`) on the default card; a
    per-phase field given one number gets it for every phase."""
    cls = BenchConfig if section is None else SECTIONS[section]

    def check(kw: dict[str, Any]) -> Any:
        raw = {
            k: [v] * 3 if per_phase(cls, k) and not isinstance(v, list) else v
            for k, v in kw.items()
        }
        return parse_bench(
            "bench check", raw if section is None else {section: raw}, default_card()
        )

    return check


def _scenario_check(kw: dict[str, Any]) -> Any:
    """Check values as a scenario's top-level keys (the demo scenario with them set; its
    steady window shrunk to fit a shorter duration)."""
    d = kw.get("duration_s")
    fit = {"steady_window_s": [0.0, d]} if isinstance(d, float) and 0 < d < 11.0 else {}
    path = ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml"
    return load_scenario(path, overrides={**fit, **kw})


BLOCKS: dict[str, Block] = {
    "scenario": Block(ScenarioSettings, _scenario_check),
    "control": Block(ControllerConfig, lambda kw: replace(ControllerConfig(), **kw).validate()),
    "observer": Block(
        ObserverConfig,
        lambda kw: replace(ObserverConfig(), **kw).validate(),
        free=frozenset({"extra"}),  # a user variant's constructor keywords, its own
        free_text=frozenset({"variant"}),  # a built-in name, module:Class or an entry point
    ),
    # on a card where the deadtime rule (below 20 % of the PWM period) does not bind
    "machine": Block(
        MachineCard,
        lambda kw: replace(MachineCard(deadtime_s=0.0, pwm_hz=100.0), **kw).validate("machine"),
        free_text=frozenset({"name"}),
    ),
    "drive": Block(
        DriveParams, lambda kw: schema.check_fields(replace(DriveParams(), **kw), "drive")
    ),
    "bench": Block(BenchConfig, _bench_check(None), free=frozenset(SECTIONS), on_card=True),
    **{
        f"bench.{key}": Block(cls, _bench_check(key), on_card=True) for key, cls in SECTIONS.items()
    },
}


def docs_tables() -> dict[str, str]:
    """{block key: its Markdown table} as the schema says it."""
    return {key: schema.markdown_table(b.cls) + "\n" for key, b in BLOCKS.items()}


def fill(text: str, tables: dict[str, str] | None = None, page: Path = DOC_PAGE) -> str:
    """`text` with every params table rewritten from `tables` (default: the blocks'; an
    unknown key: ValueError)."""
    tables = docs_tables() if tables is None else tables

    def sub(m: re.Match) -> str:
        key = m["key"]
        if key not in tables:
            raise ValueError(f"{page.name}: no config block '{key}' (known: {sorted(tables)})")
        return m.group(1) + tables[key] + m.group(4)

    return TABLE_RE.sub(sub, text)


def stale_tables(tables: dict[str, str] | None = None, page: Path = DOC_PAGE) -> list[str]:
    """The blocks whose table in the docs page is missing or differs from the schema."""
    text = page.read_text()
    present = {m["key"]: m["table"] for m in TABLE_RE.finditer(text)}
    tables = docs_tables() if tables is None else tables
    return [k for k, t in tables.items() if present.get(k) != t]
