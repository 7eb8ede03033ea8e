"""The one harness of the `./fluxdrive bench --sil` / `--pil` tests: the ideal-bench 2 % case
as a scenario file, the bench run as a subprocess, and the checks of its bag (every sample,
in order) and its θ̃ RMS against the in-process run of the same case."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from fluxdrive.analysis.metrics import compute
from fluxdrive.core import yamlio
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
from fluxdrive.drive.sim import run_scenario

REPO = Path(__file__).resolve().parents[1]
D = 4
DURATION_S = 1.5  # the graph's I-f start hands over within 1 s; 0.5 s of closed loop after


def case(
    path: Path,
    *,
    mode: str = "split",
    decimation: int = D,
    duration_s: float = DURATION_S,
    **over: Any,
) -> Path:
    """The ideal-bench 2 % case (unloaded unless ``over`` says otherwise) in ``mode`` at
    ``decimation``, the paper flux observer driving, as a scenario file at ``path``."""
    raw = dict(yamlio.load_file(CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml"))
    raw.update(
        name=path.stem,
        machine=str((CONFIG_DIR / "machines" / "default_spm.yaml").resolve()),
        duration_s=duration_s,
        steady_window_s=[duration_s - 0.5, duration_s],
        load_pu=0.0,
        bench={},
        control={**raw["control"], "mode": mode, "decimation": decimation},
        observers={"flux_measured": raw["observers"]["flux_measured"]},
    )
    raw.update(over)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def paper_case(path: Path, name: str, decimation: int = D) -> Path:
    """Scenario `name` of config/scenarios as it is (its bench, load and duration) in split
    mode at ``decimation``, only its driving observer (one observer node), at ``path``."""
    src = CONFIG_DIR / "scenarios" / f"{name}.yaml"
    raw = dict(yamlio.load_file(src))
    for key in ("machine", "rig", "bench"):  # file references, relative to the scenario
        if isinstance(raw.get(key), str):
            raw[key] = str((src.parent / raw[key]).resolve())
    raw.update(
        name=path.stem,
        control={**raw["control"], "mode": "split", "decimation": decimation},
        observers={raw["driving"]: raw["observers"][raw["driving"]]},
    )
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def drive_report(bag: Path) -> dict[str, Any]:
    """The drive's final report of a bench run (`can-emulator`'s last line JSON: its state,
    faults and fault codes)."""
    import json

    log = Path(str(bag) + "-report") / "logs" / "drive.log"
    lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.startswith("{")]
    return json.loads(lines[-1])


def run_bench(
    kind: str,
    sp: Path,
    bag: Path,
    domain_id: int,
    *,
    mode: str = "split",
    decimation: int = D,
    extra: tuple[str, ...] = (),
    timeout_s: float = 480.0,
) -> subprocess.CompletedProcess[str]:
    """`./fluxdrive bench --sil|--pil SCENARIO` (kind "sil" or "pil"), asserted to pass."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    p = subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "bench", f"--{kind}", str(sp), "--mode", mode]
        + ["--decimation", str(decimation), "--bag", str(bag), "--domain-id", str(domain_id)]
        + ["--quiet", *extra],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    print(p.stdout[-3000:])
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p


def bag_result(bag: Path, sp: Path, decimation: int = D) -> tuple[Any, dict[str, Any], Any]:
    """(SimResult, the bag's arrays, the metrics) of a bench bag, after checking that every
    sample of every topic is in it, in order."""
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive_bringup.measure.sil import result_from_sil_bag

    sc = load_scenario(sp)
    n = int(round(sc.duration_s / sc.machine.ts_s)) // decimation
    res, arr = result_from_sil_bag(bag, sc, decimation, Path(str(bag) + "-report") / "truth.npy")
    assert arr["n"] == n
    for topic in ("frame", "estimate/flux_measured", "controller_state"):
        assert arr["missing"][topic] == 0, (topic, arr["missing"])
    assert np.array_equal(arr["frames"][:, FR_SEQ], np.arange(n))
    return res, arr, compute(res)


def theta_rms_deg(metrics: dict[str, Any]) -> float:
    """θ̃ RMS of the driving observer (flux_measured) over the steady window [deg]."""
    return float(metrics["observers"]["flux_measured"]["theta_err_rms_deg"])


def in_process(sp: Path) -> dict[str, Any]:
    """The in-process run's metrics of the same scenario (asserted stable)."""
    ref = compute(run_scenario(load_scenario(sp), progress=False))
    assert ref["stable"]
    return ref
