"""Studies on dask: serial == LocalCluster bit for bit, a real `dask scheduler` + two
`dask worker` processes with one killed mid-study, resume, retry-then-report, the maps'
statistics, uncertainty physics, bad specs."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml
from fluxdrive.cli import main as cli
from fluxdrive.drive.scenario import RPM
from fluxdrive.study import store
from fluxdrive.study.cli import run_study
from fluxdrive.study.maps import wilson
from fluxdrive.study.runner import Runner
from fluxdrive.study.spec import load_spec
from fluxdrive.study.tasks import ALPHA_CU_PER_K, ALPHA_NDFEB_PER_K, build_task_scenario

SCENARIO = {  # encoder-driven, 0.25 s: the variants run in shadow on a loaded drive
    "name": "tiny",
    "machine": str(
        Path(__file__).resolve().parents[1] / "config" / "machines" / "default_spm.yaml"
    ),
    "duration_s": 0.25,
    "seed": 1,
    "speed_rpm": 300.0,
    "load_type": "active",
    "load_pu": [[0.0, 0.0], [0.05, 0.5]],
    "steady_window_s": [0.15, 0.25],
    "driving": "encoder",
    "observers": {"x": {"variant": "paper"}},
}


def _spec(tmp_path: Path, **over) -> Path:
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(SCENARIO))
    spec = {
        "name": "t",
        "seed": 11,
        "draws": 3,
        "scenario": {"file": "tiny.yaml"},
        "variants": {
            "flux": {"variant": "paper", "voltage_source": "measured"},
            "emf": {"variant": "emf", "voltage_source": "commanded"},
        },
        "grid": {"speed_rpm": [150.0, 300.0], "load_pu": [0.5]},
        "random": {
            "r_hat_err": {"dist": "uniform", "low": -0.2, "high": 0.2},
            "current_offset_pu": {"dist": "normal", "mean": 0.0, "std": 0.005},
            "temperature_c": {"dist": "uniform", "low": 20, "high": 100},
            "deadtime_s": {"dist": "choice", "values": [1.5e-6, 2e-6, 2.5e-6]},
        },
    }
    spec.update(over)
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(spec, sort_keys=False))
    return p


def _computed(t):
    """What the tasks computed, as opposed to how they ran (wall time, worker, attempts)."""
    cols = [c for c in t.column_names if c not in store.RUN_COLUMNS + store.TIMING_COLUMNS]
    return t.select(cols)


@pytest.fixture(scope="module")
def serial_study(tmp_path_factory):
    """The 16-task study (4 draws) run in this process, in order: the reference both
    cluster tests compare with, run once.  (spec, summary, results table)"""
    tmp = tmp_path_factory.mktemp("serial_study")
    spec = load_spec(_spec(tmp, draws=4))
    with Runner("serial") as r:
        summary = run_study(spec, tmp / "serial", r, echo=False)
    return spec, summary, pq.read_table(tmp / "serial" / "results.parquet")


@pytest.mark.serial  # a dask cluster of two worker processes: the two cores to itself
def test_local_cluster_two_workers_equals_serial_bit_for_bit(tmp_path, serial_study):
    spec, s1, a = serial_study
    with Runner("local", workers=2) as r:
        s2 = run_study(spec, tmp_path / "local", r, echo=False)
    assert s1["rows"] == s2["rows"] == 2 * 2 * 4 and s1["failed"] == s2["failed"] == 0
    b = pq.read_table(tmp_path / "local" / "results.parquet")
    assert _computed(a).equals(_computed(b))  # every float identical, same task order
    assert len(set(b.column("worker").to_pylist())) == 2  # both workers did work
    assert all(w.startswith("local:") for w in a.column("worker").to_pylist())
    # the draws are shared by variants and grid points (common random numbers)
    d = a.to_pydict()
    for i in (i for i in range(a.num_rows) if d["variant"][i] == "flux"):
        j = d["task_id"].index(d["task_id"][i].replace("flux|", "emf|"))
        assert d["r_hat_err"][i] == d["r_hat_err"][j] and d["seed"][i] == d["seed"][j]
    assert len(set(d["seed"])) == 4 and len(set(d["r_hat_err"])) == 4
    assert (tmp_path / "local" / "p_stable.png").stat().st_size > 5000
    assert "P(stable) per cell" in (tmp_path / "local" / "report.md").read_text()


def test_resumed_study_skips_completed_tasks(tmp_path):
    spec = load_spec(_spec(tmp_path, draws=2))
    seen = []

    def stop_after_5(o):
        seen.append(o.key)
        if len(seen) == 5:
            raise KeyboardInterrupt

    with Runner("serial") as r, pytest.raises(KeyboardInterrupt):
        run_study(spec, tmp_path / "s", r, echo=False, on_result=stop_after_5, flush_s=0.0)
    part = store.read_table(tmp_path / "s")
    assert part.num_rows == 5
    ran = []
    with Runner("serial") as r:
        s = run_study(spec, tmp_path / "s", r, echo=False, on_result=lambda o: ran.append(o.key))
    assert s["skipped"] == 5 and s["ran"] == 8 - 5 and s["rows"] == 8
    assert not set(ran) & set(seen)
    with Runner("serial") as r:
        full = run_study(spec, tmp_path / "full", r, echo=False)
    assert full["rows"] == 8
    assert _computed(pq.read_table(tmp_path / "s" / "results.parquet")).equals(
        _computed(pq.read_table(tmp_path / "full" / "results.parquet"))
    )
    assert not list((tmp_path / "s" / "parts").glob("*.parquet"))
    # an extended spec (one more draw) runs only the new tasks and keeps the old rows
    with Runner("serial") as r:
        s3 = run_study(load_spec(_spec(tmp_path, draws=3)), tmp_path / "s", r, echo=False)
    assert s3["skipped"] == 8 and s3["ran"] == 4 and s3["rows"] == 12
    # a changed spec is refused on the same folder (its rows would not be this study's)
    other = load_spec(_spec(tmp_path, seed=12))
    with Runner("serial") as r, pytest.raises(ValueError, match="other inputs"):
        run_study(other, tmp_path / "s", r, echo=False)


def test_failed_task_retried_once_then_reported_with_inputs(tmp_path):
    # -400 degC: the plant's resistance would be negative -> the machine card refuses it
    spec = load_spec(_spec(tmp_path, draws=1, random={}, grid={"temperature_c": [20.0, -400.0]}))
    with Runner("serial") as r:
        s = run_study(spec, tmp_path / "f", r, echo=False)
    assert s["rows"] == 2 and s["failed"] == 2
    fails = [json.loads(x) for x in (tmp_path / "f" / "failures.jsonl").read_text().splitlines()]
    assert {f["task_id"] for f in fails} == {
        "flux|temperature_c=-400|draw=0",
        "emf|temperature_c=-400|draw=0",
    }
    assert all(
        f["attempts"] == 2
        and f["inputs"]["grid"] == {"temperature_c": -400.0}
        and "resistance_ohm" in f["error"]
        for f in fails
    )
    assert "Failed tasks" in (tmp_path / "f" / "report.md").read_text()
    # the runner: a transient failure is retried and succeeds; a persistent one is reported
    calls = {"n": 0}

    def flaky(x):
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("transient")
        return x * 2

    with Runner("serial") as r:
        out = list(r.run_unordered(flaky, [(0, 21)]))
    assert out[0].ok and out[0].value == 42 and out[0].attempts == 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.serial  # a worker killed mid-study: timed against the others' progress
def test_dask_scheduler_and_two_workers_one_killed_mid_study(tmp_path, serial_study):
    dask = str(Path(sys.executable).with_name("dask"))
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(
            [str(Path(__file__).resolve().parents[1] / "python"), os.environ.get("PYTHONPATH", "")]
        ),
    )
    procs = [
        subprocess.Popen(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
    ]
    try:
        for i in range(2):
            procs.append(
                subprocess.Popen(
                    [
                        dask,
                        "worker",
                        addr,
                        "--nthreads",
                        "1",
                        "--no-nanny",
                        "--no-dashboard",
                        "--host",
                        "127.0.0.1",
                        "--name",
                        f"w{i}",
                    ],
                    env=env,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    start_new_session=True,
                )
            )
        spec, _, serial = serial_study  # 16 tasks
        r = Runner(addr)
        r.client.wait_for_workers(2, timeout=60)
        killed = {}

        def kill_one_busy_worker(o):
            if killed:
                return
            busy = {w: ks for w, ks in r.client.processing().items() if ks}
            if not busy:
                return
            victim = sorted(busy)[0]
            pid = r.client.run(os.getpid, workers=[victim])[victim]
            os.kill(pid, signal.SIGKILL)
            killed.update(addr=victim, pid=pid, n_done=1)

        with r:
            s = run_study(spec, tmp_path / "c", r, echo=False, on_result=kill_one_busy_worker)
        assert killed, "no worker was busy after the first result"
        assert s["rows"] == 16 and s["failed"] == 0
        t = pq.read_table(tmp_path / "c" / "results.parquet")
        assert sorted(t.column("task_id").to_pylist()) == sorted(x["task_id"] for x in spec.tasks())
        workers = t.column("worker").to_pylist()
        survivor = [w for w in set(workers) if w != killed["addr"]]
        assert len(survivor) == 1 and workers.count(survivor[0]) >= 16 - 2
        # the same numbers as in-process
        assert _computed(t).equals(_computed(serial))
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


def test_wilson_interval_limits():
    z2 = 1.959963984540054**2
    lo, hi = wilson(0, 10)
    assert lo == 0.0 and hi == pytest.approx(z2 / (10 + z2), rel=1e-12)
    lo, hi = wilson(10, 10)
    assert lo == pytest.approx(10 / (10 + z2), rel=1e-12) and hi == pytest.approx(1.0)
    lo, hi = wilson(50, 100)
    assert 0.5 - lo == pytest.approx(hi - 0.5) and lo == pytest.approx(0.4038, abs=1e-4)


def test_temperature_and_model_errors_move_plant_and_belief(tmp_path):
    spec = load_spec(_spec(tmp_path, draws=1))
    p = next(t for t in spec.tasks() if t["variant"] == "flux")
    p["random"] = {"temperature_c": 95.0, "r_hat_err": 0.1, "current_offset_pu": [0.01, 0, 0]}
    sc = build_task_scenario(p)
    r0, lam0 = 0.40, 0.0235  # the card: the 20 degC datasheet values
    assert sc.machine.resistance_ohm == pytest.approx(r0 * (1 + ALPHA_CU_PER_K * 75.0))
    assert sc.machine.flux_linkage_vs == pytest.approx(lam0 * (1 + ALPHA_NDFEB_PER_K * 75.0))
    obs = sc.observers["flux"]
    assert obs.r_hat_ohm == pytest.approx(1.1 * r0) and obs.lambda_hat_vs == lam0
    assert sc.control.r_hat_ohm == r0 and sc.control.lambda_hat_vs == lam0
    # the brake torque in N m is the same on the hot motor
    _, y = sc.load_breakpoints_nm()
    assert y[-1] == pytest.approx(0.5 * 1.5 * 4 * lam0 * 9.0)
    assert sc.current_offset_a == pytest.approx((0.09, 0.0, 0.0))
    assert sc.speed_profile_rpm[0, 1] * RPM == pytest.approx(150.0 * RPM)


def test_bad_spec_one_line_nonzero(tmp_path, capsys):
    p = _spec(tmp_path, random={"r_hat_eror": {"dist": "uniform", "low": 0, "high": 1}})
    rc = cli.main(["study", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "Traceback" not in err and len(err.splitlines()) == 1
    assert "random.r_hat_eror" in err and str(p) in err


def test_a_load_axis_scales_the_scenarios_own_profile_and_the_report_says_so(tmp_path):
    """A grid level on a key the scenario file holds as a profile scales that profile (the
    load still ramps in after the start, as in the file) instead of replacing it with a
    constant from t = 0; the report names what every axis sets and why runs were lost."""
    import pyarrow as pa
    from fluxdrive.study.maps import unstable_reasons
    from fluxdrive.study.spec import axis_override_text, scenario_axis_value

    spec = load_spec(_spec(tmp_path, draws=1, grid={"speed_rpm": [300.0], "load_pu": [1.5]}))
    p = next(t for t in spec.tasks() if t["variant"] == "flux")
    sc = build_task_scenario(p)
    t_s, y_nm = sc.load_breakpoints_nm()
    kt_nm_per_a = 1.5 * 4 * 0.0235
    assert list(t_s) == [0.0, 0.05]  # the file's timing
    assert y_nm[0] == 0.0 and y_nm[-1] == pytest.approx(1.5 * kt_nm_per_a * 9.0)
    text = axis_override_text(spec, "load_pu")
    assert "scales the scenario file's load_pu profile" in text, text
    assert "replaces the scenario file's speed_rpm" in axis_override_text(spec, "speed_rpm")
    # a profile as the grid value replaces; a key the file lacks is set
    assert scenario_axis_value({"load_pu": [[0, 0], [1, 2]]}, "load_pu", [[0, 1]])[0] == [[0, 1]]
    assert scenario_axis_value({}, "seed", 3) == (
        3,
        "sets seed (the scenario file leaves it unset)",
    )
    rows = pa.table(
        {
            "task_id": ["a", "b", "c"],
            "variant": ["flux", "flux", "emf"],
            "speed_rpm": [300.0, 300.0, 300.0],
            "load_pu": [1.5, 1.5, 1.5],
            "stable": [False, True, False],
            "fault_code": [11, 0, 0],
        }
    )
    lines = "\n".join(unstable_reasons(rows, spec))
    assert "| flux | speed_rpm = 300, load_pu = 1.5 | start-up failed (1) |" in lines, lines
    assert "| emf | speed_rpm = 300, load_pu = 1.5 | no fault, but the speed missed" in lines
