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

import can

from fluxdrive.can.bridge import HOST_HEARTBEAT_TIMEOUT_S, BridgeConfig, BusFactory, CanBridge
from fluxdrive.can.protocol import PROTOCOL_VERSION, get_protocol
from fluxdrive.core.protocol_constants import PA_OK

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


def _choice(message: Any, signal: str, name: str) -> int:
    """The value of `name` in a signal's value table (the DBC's)."""
    sig = message.get_signal_by_name(signal)
    return next(int(k) for k, v in (sig.choices or {}).items() if str(v) == name)


class _Calibration:
    """One offset calibration on an open bus (see :func:`calibrate`)."""

    def __init__(self, bridge: CanBridge, cfg: BridgeConfig, where: str) -> None:
        from fluxdrive.can.protocol import ARM_KEY

        proto = get_protocol()
        self.bus, self.cfg, self.where = bridge.bus, cfg, where
        self.arm, self.status, self.fault, self.prm, self.ack = (
            proto.message(n)
            for n in ("ARM_MODE", "STATUS", "FAULT", "DRIVE_PARAM", "DRIVE_PARAM_ACK")
        )
        self.cal_id = bridge.param_ids.get(CAL_DONE)  # None: the DBC does not name it
        self.fields = {
            "arm": 1, "arm_key": ARM_KEY, "mode": _choice(self.arm, "mode", "CALIBRATE_ADC"),
            "reset_fault": 0, "sample_layout": int(bridge.layout == "classic"),
            "control_split": int(cfg.control_split), "cmd_timeout": 0.0,
            "decimation": bridge.decimation, "arm_counter": 0,
        }  # fmt: skip
        self.states: list[str] = []
        self.cal_done: list[float] = []  # CAL_DONE as read, oldest first
        self.t_first: float | None = None  # first STATUS

    def send(self, message: Any, fields: dict[str, Any]) -> None:
        data = message.encode(fields, strict=False)
        assert self.bus is not None
        self.bus.send(can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False))

    def request(self) -> None:
        """CALIBRATE_ADC (held: it must repeat while the drive calibrates)."""
        self.fields["arm_counter"] = (self.fields["arm_counter"] + 1) % 256
        self.send(self.arm, self.fields)

    def read_cal_done(self) -> None:
        if self.cal_id is not None:
            self.send(
                self.prm, {"prm_id": self.cal_id, "prm_seq": 0, "prm_write": 0, "prm_value": 0.0}
            )

    def handle(self, msg: can.Message) -> str | None:
        """One frame: a line when the calibration ended (ok or not), else None."""
        from fluxdrive.drive.control import FAULT_NAMES

        data = bytes(msg.data)
        if msg.arbitration_id == self.fault.frame_id:
            f = self.fault.decode(data, decode_choices=False)
            if f["fault_code"] and f["fault_latched"]:
                name = FAULT_NAMES.get(int(f["fault_code"]), str(f["fault_code"]))
                return (
                    f"!the offset calibration failed: drive fault {f['fault_code']} {name} "
                    f"(detail {f['fault_detail']}); nothing stored"
                )
        elif msg.arbitration_id == self.ack.frame_id and self.cal_id is not None:
            a = self.ack.decode(data, decode_choices=False)
            if a["pa_id"] == self.cal_id and a["pa_status"] == PA_OK:
                self.cal_done.append(float(a["pa_value"]))
        elif msg.arbitration_id == self.status.frame_id:
            st = self.status.decode(data, decode_choices=False)
            self.states.append(_state_names().get(int(st["st_state"]), str(st["st_state"])))
            if self.t_first is None:
                self.t_first = time.monotonic()
            if self.states[-1] != "CALIBRATING":
                return self._finished()
        return None

    def _finished(self) -> str | None:
        """After a STATUS that is not CALIBRATING: done if a CALIBRATING one came before it,
        or CAL_DONE went from 0 to 1 (a STATUS may fall outside the short calibration)."""
        if "CALIBRATING" in self.states or (self.cal_done[:1] == [0.0] and 1.0 in self.cal_done):
            return f"offsets calibrated on {self.where} (drive {self.states[-1]})"
        self.read_cal_done()
        return None

    def run(self, timeout_s: float, status_wait_s: float) -> PreflightResult:
        self.read_cal_done()  # before: a 0 that turns 1 is this calibration's
        t0 = next_send = time.monotonic()
        while True:
            now = time.monotonic()
            limit = t0 + status_wait_s if self.t_first is None else self.t_first + timeout_s
            if now > limit:
                break
            if now >= next_send and (self.cal_done or now - t0 > 0.5 or self.cal_id is None):
                next_send = now + self.cfg.heartbeat_period_s
                self.request()
            assert self.bus is not None
            msg = self.bus.recv(0.01)
            line = self.handle(msg) if msg is not None else None
            if line is not None:
                return PreflightResult(not line.startswith("!"), line.lstrip("!"))
        if self.t_first is None:
            return PreflightResult(
                False,
                f"no drive answers on {self.where}: no STATUS frame within {status_wait_s:g} s",
            )
        return PreflightResult(
            False,
            f"the drive on {self.where} did not calibrate within {timeout_s:g} s "
            f"(its states: {' -> '.join(dict.fromkeys(self.states))})",
        )


def calibrate(
    factory: BusFactory, cfg: BridgeConfig, timeout_s: float = 5.0, status_wait_s: float = 1.0
) -> PreflightResult:
    """The drive's offset calibration, motor at standstill: ARM_MODE mode CALIBRATE_ADC with
    the arm key, repeated every heartbeat period while it runs (any other ARM_MODE ends a
    calibration unfinished), until STATUS leaves CALIBRATING or the drive's CAL_DONE turns
    from 0 to 1 (done), or a FAULT frame says why it failed (ADC_FAULT: an offset out of
    range); `timeout_s` counts from the drive's first STATUS.  The drive stays disarmed,
    PWM off, throughout; the disarm at the end ends a calibration still running."""
    bridge, why = _open(factory, cfg)  # the bus opened as the pre-flight opens it
    if bridge is None:
        return PreflightResult(False, why)
    try:
        return _Calibration(bridge, cfg, f"{factory.interface} channel {factory.channel}").run(
            timeout_s, status_wait_s
        )
    finally:
        bridge.shutdown()
