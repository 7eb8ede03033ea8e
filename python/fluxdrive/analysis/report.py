"""A run's report: metric table on stdout, metrics.json, plots and time series in a folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fluxdrive.analysis.metrics import compute, format_table, write_json
from fluxdrive.analysis.plots import plot_run


def report(
    result, out_dir: Path | None, save_series: bool = True, plots: bool = True, echo: bool = True
) -> dict[str, Any]:
    m = compute(result)
    if echo:
        print(format_table(m))
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        write_json(m, out_dir / "metrics.json")
        if save_series:
            result.save_npz(out_dir / "series.npz")
        if plots:
            plot_run(result, out_dir)
        if echo:
            print(
                f"saved: {out_dir}/metrics.json, series.npz, theta_error.png, flux_locus.png, "
                f"speed_currents.png"
            )
    return m
