"""Sweeps over a recorded bag: one observer variant, one setting stepped over values, each
value a task of the project's one parallel runner (fluxdrive.study.runner) running the study's
replay task (fluxdrive.study.tasks). `./fluxdrive replay BAG --sweep KEY=...` comes here."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from fluxdrive.core.machine import ConfigError
from fluxdrive.io.bagio import RunBag
from fluxdrive.replay.lab import VariantSpec, plot_sweep
from fluxdrive.study.runner import runner_from_args
from fluxdrive.study.tasks import cache_bag, clear_bag_cache, run_task


def sweep_bag(
    bag: RunBag,
    vs: VariantSpec,
    key: str,
    values: list[float],
    jobs: int,
    out_dir: Path | None,
    machine: str | None = None,
    window: tuple[float, float] | None = None,
    encoder_offset_deg: float = 0.0,
    scheduler: str | None = None,
) -> list[dict[str, Any]]:
    """Each value is a task of the project's one runner (fluxdrive.study.runner): the
    study's replay task, on a dask LocalCluster of `jobs` workers (each reads the bag once),
    on an existing cluster, or in-process for -j 1."""
    scen: dict[str, Any] = {
        "bag": str(Path(bag.path).resolve()),
        "window_s": list(window) if window else None,
        "encoder_offset_deg": encoder_offset_deg,
    }
    if machine:
        scen["machine"] = str(Path(machine).resolve())
    payloads = [
        {
            "task_id": f"{vs.label}|{key}={val:g}",
            "variant": vs.label,
            "variant_cfg": {"variant": vs.target, **vs.params},
            "grid": {key: val},
            "random": {},
            "draw": 0,
            "seed": 0,
            "scenario": scen,
        }
        for val in values
    ]
    rows: list[dict[str, Any]] = [None] * len(values)  # type: ignore[list-item]
    jobs = max(1, min(jobs, len(values)))
    t0 = time.perf_counter()
    cache_bag(scen["bag"], bag)  # in-process runs reuse the bag already read
    try:
        with runner_from_args(scheduler, jobs) as runner:
            items = enumerate(payloads)
            for done, o in enumerate(runner.run_unordered(run_task, items), 1):
                if not o.ok:
                    raise ConfigError(
                        f"sweep {key}={values[o.key]:g} failed twice: {o.error.splitlines()[0]}"
                    )
                m = o.value["metrics"]
                rows[o.key] = {key: values[o.key], **m, "replay_s": o.value["replay_s"]}
                for extra in ("markers_applied", "recorded_max_abs_diff"):
                    if extra in o.value:
                        rows[o.key][extra] = o.value[extra]
                _progress(done, len(values), key, values[o.key], m, t0)
    finally:
        clear_bag_cache()
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "sweep.json").write_text(
            json.dumps(
                {
                    "bag": str(bag.path),
                    "variant": vs.target,
                    "params": vs.params,
                    "key": key,
                    "rows": rows,
                },
                indent=2,
                default=float,
            )
        )
        plot_sweep(rows, key, f"{vs.target} over {bag.path.name}", out_dir / "sweep.png")
    return rows


def _progress(done: int, total: int, key: str, val: float, m: dict, t0: float) -> None:
    print(
        f"[sweep] {done}/{total} {key}={val:g}: θ̃ rms {m['theta_err_rms_deg']:.3f}°, "
        f"spread {m['flux_radius_spread']:.3f} ({time.perf_counter() - t0:.1f} s)",
        file=sys.stderr,
        flush=True,
    )
