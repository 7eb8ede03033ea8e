"""The fault-injection matrix (fluxdrive.drive.faultmatrix): every fault class does what it
should -- protection and sequencing faults latch with one log line and the PWM off,
dropped or lost frames and a controller stall are ridden through -- with every frame
answered or counted, and docs/safety.md holds the table of this very run."""

from __future__ import annotations

from pathlib import Path

from fluxdrive.drive.faultmatrix import BEGIN, END, run_matrix, table

ROOT = Path(__file__).resolve().parents[1]


def test_fault_matrix_outcomes_and_the_documented_table():
    rows = run_matrix()
    bad = [(r["fault"], r["drive"], r["recorded"]) for r in rows if not r["ok"]]
    assert not bad, bad
    assert len(rows) >= 10
    doc = (ROOT / "docs" / "safety.md").read_text()
    got = doc[doc.index(BEGIN) + len(BEGIN) : doc.index(END)].strip()
    new = table(rows).strip()
    diff = [(a, b) for a, b in zip(got.splitlines(), new.splitlines(), strict=False) if a != b]
    assert got == new, (
        f"docs/safety.md is out of date (./fluxdrive fault-matrix --write docs/safety.md): {diff}"
    )
