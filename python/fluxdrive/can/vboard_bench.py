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


class _Costing:
    """Cycle bounds (the target build's cost model) of every 8th run of a context and of
    every one with more instructions than the 5 most seen so far: the period interrupt
    (ending at the emulated exception return, entry/exit costed) or a pass of the background
    loop (ending at its idle point, no exception entry)."""

    def __init__(self, coster: Any, end_pc: int, entry_exit: bool) -> None:
        self.coster = coster
        self.end_pc = end_pc
        self.entry_exit = entry_exit
        self.costed: list[Any] = []
        self.top: list[int] = []

    def take(self, vb: Any, n: int, seq: list[tuple[int, int]], runs: int) -> None:
        """Run number ``runs`` of ``n`` instructions, its blocks ``seq`` in order."""
        from fluxdrive.can.elf import thumb_pcs

        worst = len(self.top) < 5 or n > min(self.top)
        if not worst and runs % 8:
            return
        if worst:
            if len(self.top) >= 5:
                self.top.remove(min(self.top))
            self.top.append(n)
        pcs = [pc for a, size in seq for pc in thumb_pcs(a, bytes(vb.mu.mem_read(a, size)))]
        self.costed.append(self.coster.cost(pcs, self.end_pc, self.entry_exit))

    def summary(self, counts: list[int], prefix: str) -> dict[str, Any]:
        """Instructions over every run, cycle bounds (worst, median) of the costed ones."""
        from fluxdrive.can.firmware_target import CPU_HZ, PWM_HZ

        n = np.array(counts)
        upper = sorted(b.upper for b in self.costed)
        lower = sorted(b.lower for b in self.costed)
        return {
            f"{prefix}instructions_max": int(n.max()),
            f"{prefix}instructions_median": int(np.median(n)),
            f"{prefix}instructions_min": int(n.min()),
            f"{prefix}costed": len(self.costed),
            f"{prefix}cycles_lower_max": lower[-1],
            f"{prefix}cycles_lower_median": lower[len(lower) // 2],
            f"{prefix}cycles_upper_max": upper[-1],
            f"{prefix}cycles_upper_median": upper[len(upper) // 2],
            f"{prefix}percent_of_period_upper": round(100.0 * upper[-1] * PWM_HZ / CPU_HZ, 2),
        }


def _mode_record(
    vb: Any, isr: _Costing, bg: _Costing, d: int, r: Any, wall_s: float
) -> dict[str, Any]:
    """One mode's figures: the period interrupt's and the background loop's instructions
    over every run, the cycle bounds of the costed ones, the stack mark, faults."""
    from fluxdrive.can.firmware_target import CPU_HZ, PWM_HZ

    n_max = max(vb.isr_instructions)
    isr_rec = {k.removeprefix("isr_"): v for k, v in isr.summary(vb.isr_instructions, "").items()}
    return {
        "decimation": d,
        "periods": len(vb.isr_instructions),
        "isr_instructions_max": isr_rec.pop("instructions_max"),
        "isr_instructions_median": isr_rec.pop("instructions_median"),
        "isr_instructions_min": isr_rec.pop("instructions_min"),
        "percent_of_period_at_1_cycle_per_instruction": round(100.0 * n_max * PWM_HZ / CPU_HZ, 2),
        "costed_periods": isr_rec.pop("costed"),
        **isr_rec,
        "background_passes": len(vb.bg_instructions),
        **bg.summary(vb.bg_instructions, "background_"),
        "stack_high_water_bytes": vb.stack_high_water(),
        "faults": int(r.emulator_stats["faults"]),
        "iwdg_resets": vb.iwdg_resets,
        "wall_s": round(wall_s, 1),
    }


def board_benchmark(duration_s: float = 1.5) -> dict[str, Any]:
    """The board image in closed loop on the virtual board (in-process, through the bridge
    and the engine's host side): the period interrupt's executed instructions (every
    period), the main stack's high-water mark, flash and RAM; split mode at D = 4 and host
    mode at D = 1 on the 2 % case. Written to results/firmware/board.json."""
    import json
    import time

    from fluxdrive.can import emulator as emu_mod
    from fluxdrive.can.firmware_cycles import TraceCoster, placement
    from fluxdrive.can.firmware_target import CPU_HZ, PWM_HZ, target_sizes
    from fluxdrive.can.loop import run_can_loop
    from fluxdrive.can.vboard import _RETURN, build_board

    boards: list[Any] = []
    rec: dict[str, Any] = {
        "board": "NUCLEO-G474RE + EVALSTDRIVE101 + CAN FD transceiver (firmware/board)",
        "emulator": "Unicorn " + __import__("unicorn").__version__ + " (Cortex-M4, FPU)",
        "budget_instructions_per_period": int(CPU_HZ / PWM_HZ),
    }
    orig = emu_mod.DriveEmulator._new_firmware
    bdir = build_board()
    for mode, d in (("split", 4), ("host", 1)):
        sc = _bench_scenario(mode, duration_s)
        boards.clear()
        elf = bdir / f"fd_board_d{d}.elf"
        coster = TraceCoster(elf, placement(elf))
        isr = _Costing(coster, _RETURN, entry_exit=True)
        bgs: list[_Costing] = []

        def keep(
            self: Any, isr: _Costing = isr, bgs: list[_Costing] = bgs, coster: Any = coster
        ) -> Any:
            vb = orig(self)  # kept for its measurements
            boards.append(vb)
            bg = _Costing(coster, vb.syms["fd_board_wait"][0] & ~1, entry_exit=False)
            bgs.append(bg)
            vb.on_isr = lambda n, seq, vb=vb: isr.take(vb, n, seq, len(vb.isr_instructions))
            vb.on_background = lambda n, seq, vb=vb, bg=bg: bg.take(
                vb, n, seq, len(vb.bg_instructions)
            )
            return vb

        emu_mod.DriveEmulator._new_firmware = keep  # type: ignore[method-assign]
        t0 = time.perf_counter()
        try:
            r = run_can_loop(
                sc, emulator_kw={"mcu": "pil"}, decimation=None if mode == "split" else 1
            )
        finally:
            emu_mod.DriveEmulator._new_firmware = orig  # type: ignore[method-assign]
        vb = boards[-1]
        rec[f"{mode}_mode"] = _mode_record(vb, isr, bgs[-1], d, r, time.perf_counter() - t0)
        rec["size"] = target_sizes(vb.elf)
    rec["method"] = (
        "the board image (fd_board_d4.elf, fd_board_d1.elf) on the virtual board in closed "
        f"loop with the plant, {duration_s:g} s of the 2 % case per mode; instructions of "
        "ADC1_2_IRQHandler (the period interrupt) counted per translated block; cycle bounds "
        "from fluxdrive.can.firmware_cycles (the target build's cost model, entry/exit "
        "included, code placement from the board image) for every 8th interrupt and every "
        "one among the most instructions seen; exception entry/exit modelled, not executed "
        "(its 104-byte frame in the stack mark); the background loop (CAN frames received "
        "handed to the core, outside the interrupt) counted and costed the same way per pass "
        "from its idle point (fd_board_wait) round to it again, no exception entry; stack "
        "mark from the painted main stack"
    )
    rec["never_run_on_hardware"] = True
    BOARD_RESULTS_PATH.parent.mkdir(parents=True, exist_ok=True)
    BOARD_RESULTS_PATH.write_text(json.dumps(rec, indent=2) + "\n")
    return rec
