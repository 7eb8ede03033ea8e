"""`./fluxdrive benchmark engine --against REF`: a bad REF is refused in one line before
anything is measured, and the summary's ratios are the checkout's best rate over REF's (the
figures themselves come from the benchmark, not from a test)."""

from __future__ import annotations

import subprocess

import pytest
from fluxdrive.cli.bench import _against_summary, bench_engine
from fluxdrive.core.paths import ROOT


def _first_commit_without_engine() -> str:
    """The parent of the commit that added the in-process runner."""
    added = subprocess.run(
        ["git", "log", "--format=%H", "--diff-filter=A", "--", "python/fluxdrive/drive/sim.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()[-1]
    return f"{added}~1"


@pytest.mark.parametrize(
    "ref, says",
    [
        ("no-such-ref", "no such commit"),
        ("-x", "not a commit name"),
        ("HEAD:README.md", "no such commit"),
    ],
)
def test_bad_ref_is_one_line(ref, says):
    with pytest.raises(SystemExit) as exc:
        bench_engine(["--against", ref] if not ref.startswith("-") else [f"--against={ref}"])
    msg = str(exc.value)
    assert says in msg and ref in msg and "\n" not in msg


def test_ref_without_the_engine_is_one_line():
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    ref = _first_commit_without_engine()
    with pytest.raises(SystemExit) as exc:
        bench_engine(["--against", ref])
    assert "has no python/fluxdrive/drive/sim.py" in str(exc.value)


def test_rounds_and_write_need_against():
    with pytest.raises(SystemExit) as exc:
        bench_engine(["--rounds", "5"])
    assert "--against" in str(exc.value)


def _row(paper_cpu, ideal_cpu, paper_wall, ideal_wall, warm):
    return {
        "periods_per_cpu_s": {"paper_bench": paper_cpu, "ideal_bench": ideal_cpu},
        "periods_per_wall_s": {"paper_bench": paper_wall, "ideal_bench": ideal_wall},
        "warm_s": warm,
    }


def test_summary_ratio_is_best_over_best():
    rows = {
        "ref": [_row(100.0, 200.0, 80.0, 150.0, 30.0), _row(120.0, 190.0, 90.0, 160.0, 2.0)],
        "checkout": [_row(110.0, 210.0, 60.0, 170.0, 40.0), _row(117.0, 230.0, 99.0, 140.0, 3.0)],
    }
    out = _against_summary(rows)
    assert out["paper_bench_ratio_per_cpu_s"] == round(117.0 / 120.0, 4)
    assert out["ideal_bench_ratio_per_cpu_s"] == round(230.0 / 200.0, 4)
    assert out["paper_bench_ratio_per_wall_s"] == round(99.0 / 90.0, 4)
    assert out["ideal_bench_ratio_per_wall_s"] == round(170.0 / 160.0, 4)
    assert out["paper_bench_round_ratios_per_cpu_s"] == [1.1, round(117.0 / 120.0, 4)]
    assert out["warm_s"] == {"ref": [30.0, 2.0], "checkout": [40.0, 3.0]}
