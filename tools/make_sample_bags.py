#!/usr/bin/env python3
"""Make the shipped sample bags in bags/samples/ with the project's own simulator (in-process,
no ROS graph).  Usage: .venv/bin/python tools/make_sample_bags.py [--out bags/samples]

Each bag is a window cut out of a full closed-loop run; its metadata carries the machine card,
the observers' configurations and their states at the first frame, so `./fluxdrive replay BAG`
(variant @recorded) reproduces the recorded estimates exactly.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "python"))

from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario  # noqa: E402
from fluxdrive.drive.sim import run_scenario  # noqa: E402
from fluxdrive.io.bagio import observer_states_at, write_run_bag  # noqa: E402

# name -> (scenario file, window start, window end, observers recorded)
# (paper_measured: the paper's observer as written, so a replayed `paper` -- which takes the
# bag's recorded observer model -- can be checked against the recorded one)
RECORDED = ["flux_measured", "emf_measured", "paper_measured"]
SAMPLES = {
    "paper_2pct_150load": ("paper_2pct_150load.yaml", 9.7, 11.0, RECORDED),
    "paper_6pct_stepload": ("paper_6pct_stepload.yaml", 1.8, 2.8, RECORDED),
}


def make(name: str, out: Path) -> Path:
    fname, t0, t1, obs = SAMPLES[name]
    sc = load_scenario(CONFIG_DIR / "scenarios" / fname)
    res = run_scenario(sc, progress="always")
    k0 = int(round(t0 / sc.machine.ts_s))
    states = {k: v for k, v in observer_states_at(res, k0).items() if k in obs}
    path = out / name
    if path.exists():
        shutil.rmtree(path)
    # bag times on a fixed epoch (2026-01-01T00:00:00Z + sim time): the same bytes each run
    write_run_bag(
        res,
        path,
        start_s=t0,
        end_s=t1,
        observers=obs,
        duty=False,
        epoch_offset_ns=1_767_225_600 * 10**9,
        obs_states=states,
        extra_meta={"made_by": "tools/make_sample_bags.py", "window_s": [t0, t1]},
    )
    size = sum(p.stat().st_size for p in path.iterdir())
    print(f"{path}: {sc.name} seed {sc.seed}, {t0}-{t1} s, {size / 1e6:.2f} MB")
    return path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=ROOT / "bags" / "samples")
    ap.add_argument("names", nargs="*", default=list(SAMPLES))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for nm in args.names:
        make(nm, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
