"""`benchmark firmware`'s board part: the board image in closed loop on the virtual board
(fluxdrive.can.vboard), measured; results/firmware/board.json."""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxdrive.core.paths import ROOT

BOARD_RESULTS_PATH = ROOT / "results" / "firmware" / "board.json"


def _bench_scenario(mode: str, duration_s: float) -> Any:
    """The paper's 2 % case, unloaded, ideal bench (test_split_can / test_bench_bridge):
    split mode at D = 4 or host mode at D = 1, the paper flux observer with measured
    voltages driving."""
    from fluxdrive.core import yamlio
    from fluxdrive.drive.scenario import load_scenario, scenario_path

    path = scenario_path("paper_2pct_150load")
    raw = yamlio.load_file(path)
    over: dict[str, Any] = {
        "duration_s": duration_s,
        "steady_window_s": [duration_s - 0.5, duration_s],
        "load_pu": 0.0,
        "bench": {},
        "observers": {"flux_measured": raw["observers"]["flux_measured"]},
    }
    if mode == "split":
        over["control"] = {**raw["control"], "mode": "split", "decimation": 4}
    return load_scenario(path, overrides=over)


def board_benchmark(duration_s: float = 1.5) -> dict[str, Any]:
    """The board image in closed loop on the virtual board (in-process, through the bridge
    and the engine's host side): the period interrupt's executed instructions (every
    period), the main stack's high-water mark, flash and RAM; split mode at D = 4 and host
    mode at D = 1 on the 2 % case. Written to results/firmware/board.json."""
    import json
    import time

    from fluxdrive.can import emulator as emu_mod
    from fluxdrive.can.firmware_target import CPU_HZ, PWM_HZ, target_sizes
    from fluxdrive.can.loop import run_can_loop

    boards: list[Any] = []
    rec: dict[str, Any] = {
        "board": "NUCLEO-G474RE + EVALSTDRIVE101 + CAN FD transceiver (firmware/board)",
        "emulator": "Unicorn " + __import__("unicorn").__version__ + " (Cortex-M4, FPU)",
        "budget_instructions_per_period": int(CPU_HZ / PWM_HZ),
    }
    orig = emu_mod.DriveEmulator._new_firmware
    for mode, d in (("split", 4), ("host", 1)):
        sc = _bench_scenario(mode, duration_s)
        boards.clear()

        def keep(self: Any) -> Any:  # the emulator's MCU, kept for its measurements
            boards.append(orig(self))
            return boards[-1]

        emu_mod.DriveEmulator._new_firmware = keep  # type: ignore[method-assign]
        t0 = time.perf_counter()
        try:
            r = run_can_loop(
                sc, emulator_kw={"mcu": "pil"}, decimation=None if mode == "split" else 1
            )
        finally:
            emu_mod.DriveEmulator._new_firmware = orig  # type: ignore[method-assign]
        vb = boards[-1]
        n = np.array(vb.isr_instructions)
        rec[f"{mode}_mode"] = {
            "decimation": d,
            "periods": int(n.size),
            "isr_instructions_max": int(n.max()),
            "isr_instructions_median": int(np.median(n)),
            "isr_instructions_min": int(n.min()),
            "percent_of_period_at_1_cycle_per_instruction": round(
                100.0 * float(n.max()) / (CPU_HZ / PWM_HZ), 2
            ),
            "stack_high_water_bytes": vb.stack_high_water(),
            "faults": int(r.emulator_stats["faults"]),
            "iwdg_resets": vb.iwdg_resets,
            "wall_s": round(time.perf_counter() - t0, 1),
        }
        rec["size"] = target_sizes(vb.elf)
    rec["method"] = (
        "the board image (fd_board_d4.elf, fd_board_d1.elf) on the virtual board in closed "
        f"loop with the plant, {duration_s:g} s of the 2 % case per mode; instructions of "
        "ADC1_2_IRQHandler (the period interrupt) counted per translated block; exception "
        "entry/exit modelled, not executed (not in the count, its 104-byte frame in the stack "
        "mark); stack mark from the painted main stack"
    )
    rec["never_run_on_hardware"] = True
    BOARD_RESULTS_PATH.parent.mkdir(parents=True, exist_ok=True)
    BOARD_RESULTS_PATH.write_text(json.dumps(rec, indent=2) + "\n")
    return rec
