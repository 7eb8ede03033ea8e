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


def test_summary_ratio_is_the_median_chunk_ratio():
    """Two runs of three steps (set-up + two chunks) per engine, (cpu, wall) each: the
    ratio is the median over the six steps of REF's time over this engine's; `best` is the
    ratio of the best runs' rates (periods over the run's summed time)."""
    ref = [[(2.0, 4.0), (4.0, 8.0), (6.0, 6.0)], [(2.0, 2.0), (4.0, 4.0), (4.0, 4.0)]]
    new = [[(1.0, 4.0), (5.0, 8.0), (6.0, 12.0)], [(2.0, 1.0), (2.0, 4.0), (8.0, 2.0)]]
    steps = {
        "ref": {"paper_bench": ref, "ideal_bench": new},
        "checkout": {"paper_bench": new, "ideal_bench": ref},
    }
    out = _against_summary(steps, {"paper_bench": 120, "ideal_bench": 120})
    # cpu ratios 2, 0.8, 1, 1, 2, 0.5 -> median 1; wall 1, 1, 0.5, 2, 1, 2 -> median 1
    assert out["paper_bench_ratio_per_cpu_s"] == 1.0
    assert out["paper_bench_ratio_per_wall_s"] == 1.0
    # run totals (cpu): REF 12, 10; this 12, 12 -> best 120/10 vs 120/12
    assert out["paper_bench_ref_periods_per_cpu_s"] == 12
    assert out["paper_bench_periods_per_cpu_s"] == 10
    assert out["paper_bench_best_ratio_per_cpu_s"] == round(10 / 12, 4)
    assert out["paper_bench_run_ratios_per_cpu_s"] == [1.0, round(10 / 12, 4)]
    # the other way round: the inverse ratios (cpu: 0.5, 1.25, 1, 1, 0.5, 2 -> median 1)
    assert out["ideal_bench_best_ratio_per_cpu_s"] == round(12 / 10, 4)
