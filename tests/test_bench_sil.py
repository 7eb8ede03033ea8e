"""`./fluxdrive bench --sil`: the whole bench path in one command -- the C firmware core as
the drive's MCU with the plant in its process, on a udp_multicast bus (a port of its own,
TTL 0), the bench_bridge node, the observer and controller nodes and the recorder -- in split
mode at D = 4 on the ideal-bench 2 % case the CAN split tests use (test_split_can.py), checked
from the recorded bag against the in-process split run of the same case: θ̃ RMS within
0.05°."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from ros_domains import domain

pytest.importorskip("rclpy")
pytest.importorskip("msgpack")  # python-can's udp_multicast needs it
# the C drive paced against the graph over a CAN bus: wall-clock deadlines, so alone
pytestmark = pytest.mark.serial

from fluxdrive.analysis.metrics import compute  # noqa: E402
from fluxdrive.core import yamlio  # noqa: E402
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario  # noqa: E402
from fluxdrive.drive.sim import run_scenario  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
D = 4
DURATION_S = 1.5  # the graph's I-f start hands over within 1 s; 0.5 s of closed loop after


def _case(path: Path) -> Path:
    """The ideal-bench, unloaded 2 % case in split mode at D = 4 as a scenario file."""
    raw = dict(yamlio.load_file(CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml"))
    raw.update(
        name="sil_2pct_split",
        machine=str((CONFIG_DIR / "machines" / "default_spm.yaml").resolve()),
        duration_s=DURATION_S,
        steady_window_s=[DURATION_S - 0.5, DURATION_S],
        load_pu=0.0,
        bench={},
        control={**raw["control"], "mode": "split", "decimation": D},
        observers={"flux_measured": raw["observers"]["flux_measured"]},
    )
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_bench_sil_split_mode_records_every_sample_and_matches_in_process(tmp_path):
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.io.bagio import read_raw, topic_counts, typestore
    from fluxdrive.io.topics import CURRENT_REF
    from fluxdrive_bringup.measure.sil import result_from_sil_bag

    sp = _case(tmp_path / "sil_2pct_split.yaml")
    bag = tmp_path / "bag"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    p = subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "bench", "--sil", str(sp), "--mode", "split"]
        + ["--decimation", str(D), "--bag", str(bag), "--domain-id", str(domain(42)), "--quiet"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    print(p.stdout[-3000:])
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]

    sc = load_scenario(sp)
    n = int(round(DURATION_S / sc.machine.ts_s)) // D
    counts = topic_counts(bag)
    # every sample delivered, in order: frames, the estimate, the controller's state and its
    # current references, one per sample
    res, arr = result_from_sil_bag(bag, sc, D, Path(str(bag) + "-report") / "truth.npy")
    assert arr["n"] == n
    for topic in ("frame", "estimate/flux_measured", "controller_state"):
        assert arr["missing"][topic] == 0, (topic, arr["missing"])
    assert counts.get(CURRENT_REF, 0) == n
    assert np.array_equal(arr["frames"][:, FR_SEQ], np.arange(n))
    ts = typestore()
    ref_seqs, split_flags = [], set()
    for topic, mtype, _t, raw in read_raw(bag, lambda t: t in (CURRENT_REF, "/diagnostics")):
        msg = ts.deserialize_cdr(raw, mtype)
        if topic == CURRENT_REF:
            ref_seqs.append(int(msg.seq))
        else:
            for st in msg.status:
                split_flags.update(kv.value for kv in st.values if kv.key == "control_split")
    assert ref_seqs == list(range(n))  # in order, none lost
    assert split_flags == {"True"}  # the drive was armed in split mode
    # theta~ RMS of the driving observer: the in-process split run of the same case
    ref = compute(run_scenario(sc, progress=False))
    th_ref = ref["observers"]["flux_measured"]["theta_err_rms_deg"]
    th_sil = compute(res)["observers"]["flux_measured"]["theta_err_rms_deg"]
    print(f"theta~ RMS: SIL graph {th_sil:.3f} deg, in-process split {th_ref:.3f} deg")
    assert ref["stable"]
    # the timing of real timers on both sides (a duty computed at t_k applies from t_(k+1):
    # the SIL's timer model, the in-process split loop): equal up to the protocol's
    # quantisation and the C core's float32
    assert abs(th_sil - th_ref) < 0.05
