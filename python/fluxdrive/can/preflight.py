"""Pre-flight of a real bench: may this host arm the drive on this bus?  Checked before
anything is started or armed (`./fluxdrive bench`, `--check` alone), each failure one line:

1. the python-can interface and channel open (socketcan can0 exists and is up, the PCAN /
   Kvaser library and adapter are there, ...);
2. a drive answers: a STATUS frame within `status_wait_s` (the drive sends one every 0.1 s);
3. it speaks this host's protocol version (STATUS.st_protocol_version);
4. it is ready: not booting or still calibrating its current offsets (STATUS.st_state),
   and its offsets were calibrated since boot (DRIVE_PARAM CAL_DONE, read);
5. no fault is latched on it (STATUS / FAULT, named);
6. it runs the sample layout and decimation D this host reads (STATUS, after this host's
   disarmed ARM_MODE told it);
7. split mode: it acknowledges every drive parameter this host would write before arming
   (DRIVE_PARAM_ACK; a refusal named with the drive's reason).

The checks speak the bridge's own protocol through :class:`fluxdrive.can.bridge.CanBridge`
(disarmed throughout: its ARM_MODE frames carry arm = 0); the bus is closed afterwards
(the bridge's shutdown sends a disarm as well).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

from fluxdrive.can.bridge import HOST_HEARTBEAT_TIMEOUT_S, BridgeConfig, BusFactory, CanBridge
from fluxdrive.can.protocol import PROTOCOL_VERSION, get_protocol

__all__ = [
    "PreflightResult",
    "calibrate",
    "drive_param_name",
    "preflight",
    "scenario_drive_params",
]


def drive_param_name(prm: str) -> str:
    """The bench_bridge node's ROS parameter of a DRIVE_PARAM: drive.<name in lower case>
    (a DriveParams field)."""
    return "drive." + prm.lower()


def scenario_drive_params(scenario: str) -> dict[str, float]:
    """The drive-side parameters (DRIVE_PARAM name -> value) of a scenario's controller
    design, or the default card's without one: what a bench writes before arming."""
    from fluxdrive.core.machine import load_machine
    from fluxdrive.drive.control import ControllerConfig, drive_param_values
    from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario, scenario_path

    if scenario:
        sc = load_scenario(scenario_path(scenario))
        cfg, card = sc.control, sc.machine
    else:
        card = load_machine(CONFIG_DIR / "machines" / "default_spm.yaml")
        cfg = ControllerConfig()
    vals = drive_param_values(cfg.to_params(card))
    vals["HEARTBEAT_TIMEOUT_S"] = HOST_HEARTBEAT_TIMEOUT_S  # the host supervised, both modes
    return vals


@dataclass
class PreflightResult:
    """``ok``, the one line that says why (or that it passed), and what the drive reported."""

    ok: bool
    line: str
    status: dict[str, Any] = field(default_factory=dict)


def _state_names() -> dict[int, str]:
    sig = get_protocol().message("STATUS").get_signal_by_name("st_state")
    return {int(k): str(v) for k, v in (sig.choices or {}).items()}


# the read-only DRIVE_PARAM that says the offsets were calibrated since boot
CAL_DONE = "CAL_DONE"
# STATUS.st_state values in which a drive may be armed (the DBC's value table names them)
READY_STATES = ("IDLE", "ARMED", "RUNNING")


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"


class _Said(logging.Handler):
    """python-can's warnings while a bus opens (e.g. "Kvaser canlib is unavailable."),
    kept for the one line instead of printed beside it."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(" ".join(record.getMessage().split()))


def _open(factory: BusFactory, cfg: BridgeConfig) -> tuple[CanBridge | None, str]:
    where = f"{factory.interface} channel {factory.channel}"
    try:
        bridge = CanBridge(factory, cfg)
    except ValueError as exc:
        return None, f"the bridge settings are not valid: {exc}"
    said = _Said()
    log = logging.getLogger("can")  # python-can's own warnings: into the one line
    log.addHandler(said)
    propagate, log.propagate = log.propagate, False
    try:
        bridge.bus = factory()
    except Exception as exc:  # noqa: BLE001 - any driver error: the interface is not usable
        extra = f"; python-can: {' '.join(said.lines)}" if said.lines else ""
        return None, f"CAN interface {where} cannot be opened ({_one_line(exc)}{extra})"
    finally:
        log.removeHandler(said)
        log.propagate = propagate
    bridge.counters["connects"] += 1
    return bridge, ""


def _wait_status(bridge: CanBridge, wait_s: float, n: int) -> bool:
    """Poll until `n` STATUS frames came (True) or `wait_s` passed (False)."""
    deadline = time.monotonic() + wait_s
    while bridge.counters["status_rx"] < n:
        if time.monotonic() > deadline or bridge.bus is None:
            return False
        bridge.poll(timeout=0.02)
    return True


def _drive_checks(bridge: CanBridge, where: str, status_wait_s: float) -> str:
    """Steps 2-6 (see the module doc) on the bus `where`: '' when they pass, else the line."""
    if not _wait_status(bridge, status_wait_s, 1):
        why = f" ({bridge.last_error})" if bridge.last_error else ""
        return (
            f"no drive answers on {where}: no STATUS frame within {status_wait_s:g} s{why} "
            f"(drive powered? bit rates? termination?)"
        )
    st = bridge.mcu
    if st.get("protocol_version") != PROTOCOL_VERSION:
        return (
            f"the drive speaks protocol version {st.get('protocol_version')}, this host "
            f"{PROTOCOL_VERSION}: flash the firmware built from this checkout"
        )
    state = _state_names().get(int(st.get("state", -1)), f"state {st.get('state')}")
    if st.get("fault_latched") or state == "FAULT":
        _wait_status(bridge, status_wait_s, int(bridge.counters["status_rx"]) + 1)  # its FAULT
        what = bridge.drive_fault_text() or "no FAULT frame seen"
        return f"the drive has a fault latched ({what}): clear its cause, then fault reset"
    if state not in READY_STATES:
        return (
            f"the drive is not ready: state {state} (calibrating its current offsets or "
            f"booting); wait for IDLE"
        )
    why = _calibration_check(bridge)
    if why:
        return why
    # the drive applies the layout and D of this host's ARM_MODE (sent disarmed with the
    # heartbeat) by its next STATUS: judge the one after that
    _wait_status(bridge, 3.0 * bridge.cfg.heartbeat_period_s + status_wait_s, 3)
    if bridge.drive_mismatch:
        return f"{bridge.drive_mismatch} (set fd and decimation to what the drive runs)"
    return ""


def _calibration_check(bridge: CanBridge) -> str:
    """Step 4b: the drive's current offsets calibrated since boot (its read-only
    DRIVE_PARAM CAL_DONE, where the DBC names it); '' or why not."""
    if CAL_DONE not in bridge.param_ids:
        return ""
    ok, why, done = bridge.read_drive_param(CAL_DONE)
    if not ok:
        return f"the drive's calibration state could not be read: {why}"
    if done < 0.5:
        return (
            "the drive's current offsets are not calibrated since boot: run ./fluxdrive bench "
            "--calibrate with the motor at standstill"
        )
    return ""


def _param_checks(bridge: CanBridge, drive_params: dict[str, float]) -> str:
    """Step 7: every drive parameter written and acknowledged; '' or the first refusal."""
    for name, value in drive_params.items():
        ok, why, _ = bridge.set_drive_param(name, float(value))
        if not ok:
            return f"drive parameter not acknowledged: {why}"
    return ""


def preflight(
    factory: BusFactory,
    cfg: BridgeConfig,
    drive_params: dict[str, float] | None = None,
    status_wait_s: float = 1.0,
) -> PreflightResult:
    """Run the pre-flight on the bus `factory` opens with the bridge settings `cfg` (its
    layout, D, split mode); `drive_params` (DRIVE_PARAM name -> value) are written and must
    be acknowledged.  Nothing is armed; the bus is closed again."""
    bridge, why = _open(factory, cfg)
    if bridge is None:
        return PreflightResult(False, why)
    try:
        where = f"{factory.interface} channel {factory.channel}"
        why = _drive_checks(bridge, where, status_wait_s)
        why = why or _param_checks(bridge, drive_params or {})
        status = dict(bridge.mcu)
    finally:
        bridge.shutdown()
    if why:
        return PreflightResult(False, why, status)
    n = len(drive_params or {})
    acks = f", {n} drive parameters acknowledged" if n else ""
    return PreflightResult(
        True,
        f"pre-flight passed: drive on {factory.interface} channel {factory.channel}, "
        f"protocol {PROTOCOL_VERSION}, {bridge.layout} layout at D={bridge.decimation}{acks}",
        status,
    )


def calibrate(
    factory: BusFactory, cfg: BridgeConfig, timeout_s: float = 5.0, status_wait_s: float = 1.0
) -> PreflightResult:
    """The drive's offset calibration, motor at standstill, on a bus of its own: the
    bridge's (:meth:`fluxdrive.can.bridge.CanBridge.calibrate`, the one the bench bridge
    runs before arming). The drive stays disarmed, PWM off, throughout."""
    bridge, why = _open(factory, cfg)  # the bus opened as the pre-flight opens it
    if bridge is None:
        return PreflightResult(False, why)
    where = f"{factory.interface} channel {factory.channel}"
    try:
        ok, line = bridge.calibrate(timeout_s, status_wait_s)
    finally:
        bridge.shutdown()
    if ok:
        return PreflightResult(
            True, line.replace("offsets calibrated", f"offsets calibrated on {where}", 1)
        )
    return PreflightResult(False, f"{line} (drive on {where})")
