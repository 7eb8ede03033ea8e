"""The drive's protections, one case table (fluxdrive.can.faultcases) run on the targets: the
C core's host build through its ctypes binding and the board image on the virtual board,
each as the MCU of the drive emulator with the plant, in closed loop over a virtual CAN bus
with the bridge and the host in-process (split mode, D = 4), the cases one after the other
in one run (an operator resets and re-arms in between). Each injected condition turns
the PWM off within its stated number of periods and keeps it off, the drive sends a FAULT
frame with the case's code, and the bridge gets exactly one drive fault naming it; the
reactions are those in docs/firmware.md's generated table. No ROS."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fluxdrive.can import faultcases as fc
from fluxdrive.core import protocol_constants as pc

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "firmware.md"


def test_every_protection_of_the_core_is_a_case_or_said_why_not():
    """Every fault code fd_core.c raises is a case of the table, or one of the two the table
    says no condition reaches (the horizon's end behind a shorter reference timeout; a
    non-finite duty from integer inputs); every code is the DBC's (protocol_constants)."""
    src = (fc.FIRMWARE_DIR / "src" / "fd_core.c").read_text()
    raised = {getattr(pc, n) for n in re.findall(r"raise_fault\(c, FD_(FAULT_\w+)", src)}
    covered = {c.code for c in fc.CASES}
    assert raised - covered == set(fc.NOT_INJECTABLE)
    assert all(c.code in pc.FAULT_CHOICES for c in fc.CASES)
    assert len({c.name for c in fc.CASES}) == len(fc.CASES)
    for c in fc.CASES:
        assert set(c.not_on) <= set(fc.TARGETS) and all(c.not_on.values()), c.name


def test_bad_injections_are_one_clear_line():
    with pytest.raises(ValueError, match="unknown fault case 'nope'"):
        fc.parse_injection("nope@0.1", 1e-4)
    with pytest.raises(ValueError, match="not a number"):
        fc.parse_injection("gate_driver@soon", 1e-4)
    inj = fc.parse_injection("gate_driver@0.05", 1e-4)
    assert (inj.case.name, inj.k_at) == ("gate_driver", 500)


@pytest.mark.parametrize("target", ["core", "pil"])
def test_every_case_on_the_target(target):
    """Every case of the table not marked otherwise, on the host core or the virtual board:
    one run injecting them one after the other (reset and re-armed in between) and one for
    the case before arming."""
    cases = [c for c in fc.CASES if target not in c.not_on]
    results = fc.run_in_process(cases, "c" if target == "core" else "pil")
    cells = fc.doc_cells(DOC.read_text())
    for c, res in zip(cases, results, strict=True):
        print(target, c.name, fc.cell(res), res["checks"])
    for c, res in zip(cases, results, strict=True):
        assert res["ok"], (c.name, res["checks"])
        if c.name == "i2t":  # the integral's own time: limit / ((i/I_rated)^2 - 1)
            assert res["bound"] - 0.005 * res["bound"] <= res["reaction"] <= res["bound"]
        assert fc.cell(res) == cells[c.name][target], "./fluxdrive fault-cases --write"


def test_cases_not_run_on_a_target_say_why_in_the_doc():
    cells = fc.doc_cells(DOC.read_text())
    for c in fc.CASES:
        for target, why in c.not_on.items():
            assert cells[c.name][target] == f"n/a: {why}"
