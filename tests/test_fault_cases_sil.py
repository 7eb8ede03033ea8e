"""The drive's protections (fluxdrive.can.faultcases) through the SIL graph, `bench --sil
--inject`: the C core behind a python-can bus, the bench_bridge node, the observer, the
controller and the recorder. One run injects every case armed in the normal way, one after
the other (the bench's operator resets the fault through /drive/reset_fault and re-arms
through /drive/arm in between), one run arms a drive that requires calibration. Each case:
PWM off within its bound (the drive's record), a FAULT frame with its code, one DriveFault
from the drive on /drive/fault in the bag and one error line on /rosout naming it, in the
order of the cases; the reactions are docs/firmware.md's."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("msgpack")  # python-can's udp_multicast needs it
# lockstep: the drive waits for each answer (up to 1 s of wall time), so a busy neighbour
# slows the run but changes no number; this passed with the load average at 20-30 on two
# cores, so it runs in the parallel part, where the core the serial part leaves idle
# beside a lockstep graph is used

from fluxdrive.can import faultcases as fc  # noqa: E402
from fluxdrive.cli.faultcases import run_graph  # noqa: E402

DOC = Path(__file__).resolve().parents[1] / "docs" / "firmware.md"


def _bag_faults(bag: Path) -> tuple[list[int], list[int]]:
    """Codes of the drive's latched DriveFaults, and of the error lines on /rosout that
    report a drive fault, in order."""
    from fluxdrive.io.bagio import read_raw, typestore

    ts = typestore()
    events, lines = [], []
    for topic, mtype, _t, raw in read_raw(bag, lambda t: t in ("/drive/fault", "/rosout")):
        m = ts.deserialize_cdr(raw, mtype)
        if topic == "/drive/fault":
            if m.latched and m.source.startswith("drive via"):
                events.append(int(m.code))
        elif m.level >= 40:
            found = re.search(r"drive fault (\d+) ", m.msg)
            if found:
                lines.append(int(found.group(1)))
    return events, lines


def test_every_case_through_the_sil_graph(tmp_path):
    cases = [c for c in fc.CASES if "sil" not in c.not_on]
    results, bags = run_graph(cases, tmp_path, domain_id=domain(68))
    cells = fc.doc_cells(DOC.read_text())
    for c, res in zip(cases, results, strict=True):
        print(c.name, fc.cell(res), res["checks"])
    for c, res in zip(cases, results, strict=True):
        assert res["ok"], (c.name, res)
        assert fc.cell(res) == cells[c.name]["sil"], "./fluxdrive fault-cases --write"
    for run, bag in zip(fc.runs_of(cases), bags, strict=True):
        codes = [c.code for c in run]
        events, lines = _bag_faults(bag)
        assert events == codes  # one DriveFault per case, from the drive, in order
        assert lines == codes  # one log line per case naming it
