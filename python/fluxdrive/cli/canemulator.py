"""`./fluxdrive can-emulator [SCENARIO] ...`: the drive emulator (fluxdrive.can.emulator: the
plant and the C drive core) as a process of its own on a python-can bus."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from fluxdrive.can.bridge import widen_receive_buffer
from fluxdrive.can.emulator import DriveEmulator
from fluxdrive.can.protocol import LinkOptions
from fluxdrive.core.schema import Parser, option, param
from fluxdrive.drive.scenario import ScenarioSettings


@dataclass
class EmulatorOptions:
    """can-emulator's waits, ranged once (a NaN wait spun at 100 % CPU, deaf to SIGTERM)."""

    lockstep_wait_s: float = param(
        0.5,
        unit="s",
        doc="lockstep: wall time to wait for the duty of the previous sample",
        range=(1e-4, 3600.0),
    )
    wait_for_host_s: float = param(
        0.0,
        unit="s",
        doc="wait up to this long for the host's first HOST_HEARTBEAT",
        range=(0.0, 3600.0),
    )


def main(argv: list[str] | None = None) -> int:
    """`./fluxdrive can-emulator [SCENARIO] --interface I --channel C ...`: the drive
    emulator as a process of its own, on any python-can bus (``udp_multicast`` reaches
    other processes on this host). Runs ``--periods`` PWM periods (default: the
    scenario's) or until SIGINT/SIGTERM; the last stdout line is a JSON object with the
    MCU's final state and counters."""
    import signal

    a = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    sc = _scenario(a.scenario, a.duration)
    opened = _open(a, sc)
    if isinstance(opened, int):
        return opened
    emu, bus = opened
    if a.mcu == "pil":
        print(f"[can-emulator] board parameters: {emu.core.storage_note()}", file=sys.stderr)
    signal.signal(signal.SIGTERM, lambda *_: emu._stop.set())
    signal.signal(signal.SIGINT, lambda *_: emu._stop.set())
    n = sc.n_periods if a.periods is None else a.periods
    print(
        f"[can-emulator] {sc.name}: {a.layout} layout (D={emu.decimation}) on "
        f"{a.interface}:{a.channel}, {n} periods, "
        f"{'free-running' if a.free_running else 'lockstep'}",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        rc = 0 if _wait_for_host(emu, a.wait_for_host) and _wait_armed(emu, a.wait_armed) else 1
        if rc == 0:
            emu.run(n, realtime=a.free_running)
            emu._drain(0.05)  # a disarm sent while we stopped
    finally:
        bus.shutdown()
        if a.flash is not None:  # what a save wrote stays for the next run (a power cycle)
            a.flash.write_bytes(emu.core.flash_image())
    _report(emu, a.record_out, time.perf_counter() - t0)
    return rc


def _open(a, sc) -> tuple[DriveEmulator, can.BusABC] | int:
    """The bus and the drive emulator on it, from the options; an exit code (said on
    stderr) when an option or the bus refuses."""
    from fluxdrive.drive.sim import DriveSetup

    inject = None
    if a.inject:
        from fluxdrive.can.faultcases import parse_injections

        try:
            inject = parse_injections(a.inject, sc.machine.ts_s)
        except ValueError as exc:
            print(f"can-emulator: {exc}", file=sys.stderr)
            return 2
    flash = None
    if a.flash is not None:
        if a.mcu != "pil":
            print("can-emulator: --flash goes with --mcu pil", file=sys.stderr)
            return 2
        flash = a.flash.read_bytes() if a.flash.is_file() else None
    try:
        bus = can.Bus(**_bus_kwargs(a))
        widen_receive_buffer(bus)  # a burst of other frames must not push duties out
    except (can.CanError, OSError, ImportError, ValueError) as exc:
        print(
            f"can-emulator: cannot open the {a.interface} bus on {a.channel}: {exc}",
            file=sys.stderr,
        )
        return 2
    try:
        emu = DriveEmulator(
            DriveSetup(sc),
            bus,
            lockstep=not a.free_running,
            lockstep_wait_s=a.lockstep_wait,
            layout=a.layout,
            decimation=a.decimation,
            mcu=a.mcu,
            record=a.record_out is not None,
            inject=inject,
            require_calibration=not a.no_require_calibration,
            bootstrap=True,  # the board's 1 ms charge after arming, before the first switching
            flash_image=flash,
        )
    except ValueError as exc:  # a flash image of another size
        bus.shutdown()
        print(f"can-emulator: --flash {a.flash}: {exc}", file=sys.stderr)
        return 2
    return emu, bus


def _report(emu: DriveEmulator, record_out: str | None, wall_s: float) -> None:
    """The plant's true state (``--record-out``) and the final JSON line."""
    import json

    if record_out is not None and emu.rec_truth:
        import numpy as np

        np.save(record_out, np.vstack(emu.rec_truth))
    out = {
        "periods": emu.k,
        "armed": emu.armed,
        "pwm_enabled": emu.pwm_enabled,
        "fault_latched": emu.fault_latched,
        "fault_code": emu.fault_code,
        "layout": emu.layout,
        "decimation": emu.decimation,
        "wall_s": round(wall_s, 3),
        **emu.stats.as_dict(),
    }
    print(json.dumps(out), flush=True)


def _parser():
    ap = Parser(prog="fluxdrive can-emulator", description=main.__doc__)
    ap.add_argument(
        "scenario",
        nargs="?",
        default="paper_2pct_150load",
        help="scenario YAML or name under config/scenarios (the plant side)",
    )
    ap.add_argument("--interface", default="udp_multicast", help="python-can interface")
    ap.add_argument(
        "--channel",
        default="239.255.74.68",
        help="python-can channel (udp_multicast: the IPv4/IPv6 multicast group)",
    )
    ap.add_argument("--port", type=int, default=None, help="udp_multicast: UDP port")
    ap.add_argument(
        "--hop-limit",
        type=int,
        default=0,
        help="udp_multicast: IP TTL / hop limit (0: never leaves this host)",
    )
    ap.add_argument("--layout", choices=("fd", "classic"), default="fd")
    option(
        ap,
        "--decimation",
        LinkOptions,
        default=None,
        help="PWM periods per sample, either layout (default: the DBC's, FD 1, "
        "classic 8; a real 1/5 Mbit/s FD bus needs 4)",
    )
    ap.add_argument("--periods", type=int, default=None, help="PWM periods to run")
    option(ap, "--duration", ScenarioSettings, "duration_s", default=None)
    ap.add_argument(
        "--free-running",
        action="store_true",
        help="pace periods to wall time and never wait for duties (a real MCU)",
    )
    option(ap, "--lockstep-wait", EmulatorOptions, "lockstep_wait_s")
    option(ap, "--wait-for-host", EmulatorOptions, "wait_for_host_s")
    ap.add_argument(
        "--wait-armed",
        type=float,
        default=0.0,
        help="answer the bus without running periods until the host arms the drive (or the "
        "drive refuses the arming with a fault), up to this long [s] (a lockstep run then "
        "starts armed and configured)",
    )
    _drive_options(ap)
    return ap


def _drive_options(ap) -> None:
    """The drive side's options: MCU, injected faults, calibration, flash, truth record."""
    ap.add_argument(
        "--mcu",
        choices=("c", "pil"),
        default="c",
        help="the drive's MCU: the C firmware core (c, software in the loop) or the board "
        "image on the virtual board (pil)",
    )
    ap.add_argument(
        "--inject",
        default=None,
        metavar="CASE@T[,CASE...]",
        help="inject a protection's condition at T s of drive time (fluxdrive.can.faultcases: "
        "overcurrent, gate_driver, heartbeat, ref_lost, ...), each next case once the host "
        "has reset and re-armed the drive; the run ends after the last; the final JSON says "
        "each reaction",
    )
    ap.add_argument(
        "--no-require-calibration",
        action="store_true",
        help="--mcu c: arm without an offset calibration since boot (by default the drive "
        "refuses, FAULT NOT_CALIBRATED, as the board image does; the bench bridge calibrates "
        "before arming)",
    )
    ap.add_argument(
        "--flash",
        type=Path,
        default=None,
        metavar="FILE",
        help="--mcu pil: the board's flash image, booted from FILE if it exists and written "
        "back at the end: a parameter set saved (DRIVE_PARAM PARAM_SAVE) is there at the next "
        "run, as after a power cycle",
    )
    ap.add_argument(
        "--record-out",
        default=None,
        help="write the plant's true state per PWM period (TR_* rows) to this .npy file",
    )


def _scenario(name: str, duration_s: float | None):
    """The plant's scenario; `--duration` overrides its length (a steady window beyond
    the end becomes the second half of the run)."""
    from fluxdrive.drive.scenario import load_scenario, scenario_path

    overrides: dict[str, Any] | None = None
    if duration_s:
        overrides = {"duration_s": duration_s}
        if load_scenario(scenario_path(name)).steady_window_s[1] > duration_s + 1e-9:
            overrides["steady_window_s"] = [0.5 * duration_s, duration_s]
    return load_scenario(scenario_path(name), overrides=overrides)


def _bus_kwargs(a) -> dict[str, Any]:
    kw: dict[str, Any] = {"interface": a.interface, "channel": a.channel, "fd": a.layout == "fd"}
    if a.interface == "udp_multicast":
        kw["hop_limit"] = a.hop_limit
    if a.port is not None:
        kw["port"] = a.port
    return kw


def _wait_for_host(emu: DriveEmulator, wait_s: float) -> bool:
    """Up to `wait_s` for the host's first HOST_HEARTBEAT (0: do not wait); False (said
    on stderr) when none came."""
    if wait_s <= 0:
        return True
    deadline = time.monotonic() + wait_s
    while emu.host_heard_s is None and not emu._stop.is_set():
        if time.monotonic() > deadline:
            print(f"can-emulator: no host heartbeat within {wait_s:g} s", file=sys.stderr)
            return False
        emu._drain(0.05)
    return True


def _wait_armed(emu: DriveEmulator, wait_s: float) -> bool:
    """Answer the bus without running periods until the host arms the drive, up to
    `wait_s` (0: do not wait); False (said on stderr) when it did not."""
    if wait_s <= 0:
        return True
    import threading

    give_up = threading.Event()
    timer = threading.Timer(wait_s, give_up.set)
    timer.start()
    emu.serve(give_up, until_armed=True)
    timer.cancel()
    if give_up.is_set():
        print(f"can-emulator: not armed within {wait_s:g} s", file=sys.stderr)
        return False
    return True


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
