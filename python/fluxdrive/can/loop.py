"""Closed loop through the CAN encoding, in-process (no ROS):

  DriveEmulator (plant + C drive core) -> python-can bus -> CanBridge -> observer_step /
  controller_step -> CanBridge -> bus -> DriveEmulator

The emulator runs in a thread in lockstep (it waits for the answer to sample k-D before
the interrupt of period k), the bridge and the kernels in the calling thread, so a run
is deterministic and comparable with :func:`fluxdrive.drive.sim.run_scenario` on the same
scenario. Split mode matches it up to the protocol's quantisation (both keep the timing of
real timers: the drive's duty from sample k applies from t_(k+1)); host mode over CAN has
one period more than in-process host mode (the host's answer to sample k is written by the
drive's interrupt at k+1 and applies from k+2, where in-process the controller's duty
from frame k applies from k+1).

``decimation=D`` (either layout; ``layout="classic"`` runs over the classic-CAN layout on
a non-FD bus, by default with the DBC's D = 8) sends a sample every D PWM periods, so the
observers and the controller run at D*Ts (:func:`decimated_scenario`) while the plant
keeps switching at Ts. Control at D*Ts needs its own tuning: the scenario
``config/scenarios/can_2pct_decimated.yaml`` carries one for D = 4..8.

Before arming (both modes) the bridge writes the drive's parameters of the scenario's
design as DRIVE_PARAMs, each acknowledged, and reads each back (``drive_params_of``;
arming is refused on a refusal or a mismatch), then calibrates the current offsets of a drive
that requires it (the drive's periods at standstill with PWM off, before the run). A scenario
in split mode (``control.mode: split``, its ``control.decimation`` D) runs split over the bus:
the bridge sends ARM_MODE.control_split, the observers and ``host_reference_step`` answer
every sample with a HOST_REF, and the drive's C core closes the current loop every period.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from fluxdrive.can.bridge import (
    HOST_HEARTBEAT_TIMEOUT_S,
    BridgeConfig,
    CanBridge,
    bus_factory_from_params,
)
from fluxdrive.can.canlog import open_writer
from fluxdrive.can.emulator import DriveEmulator
from fluxdrive.drive.control import (
    CO_DA,
    CO_DC,
    CO_EN,
    CO_N,
    RF_EN,
    RF_ID_REF,
    RF_IQ_REF,
    RF_N,
    RF_TH,
    RF_W,
    controller_step,
    drive_param_values,
    host_reference_step,
)
from fluxdrive.drive.observers import ES_N, observer_step
from fluxdrive.drive.plant import FR_N, FR_SEQ
from fluxdrive.drive.sim import DriveSetup

__all__ = [
    "CanLoopResult",
    "HostLoop",
    "decimated_scenario",
    "drive_params_of",
    "new_virtual_channel",
    "run_can_loop",
]

_counter = itertools.count()


def new_virtual_channel(prefix: str = "fluxdrive") -> str:
    """A python-can virtual channel name no other test in this process uses."""
    return f"{prefix}-{next(_counter)}-{time.monotonic_ns()}"


def decimated_scenario(sc: Any, decimation: int, **control: Any) -> Any:
    """The control side of a decimated loop (either layout): a copy of scenario ``sc``
    whose machine card runs at ``pwm_hz / decimation`` (observers and controller step once
    per sample, ts = D*Ts), with ``control`` overriding
    :class:`fluxdrive.drive.control.ControllerConfig` fields. A decimated loop needs its own
    tuning (the current-loop bandwidth below a quarter of the sample rate and reachable
    with the 1.5-sample delay; a slower speed loop; a softer I-f start): load it from a
    scenario that carries it, ``config/scenarios/can_2pct_decimated.yaml``, rather than
    passing it here."""
    d = int(decimation)
    out = copy.deepcopy(sc)
    out.machine = dataclasses.replace(sc.machine, pwm_hz=sc.machine.pwm_hz / d)
    if control:
        out.control = dataclasses.replace(out.control, **control)
    return out


@dataclass
class CanLoopResult:
    setup: DriveSetup  # the plant's (emulator's) setup
    frames_sent: np.ndarray  # (N, FR_N) what the emulator's plant sampled (unquantised)
    truth: np.ndarray  # (N, TR_N), per PWM period
    frames_rx: np.ndarray  # (M, FR_N) what the bridge decoded (seq = sample index)
    est: np.ndarray  # (n_obs, M, ES_N)
    ctrl: np.ndarray  # (M, CO_N)
    diagnostics: dict[str, Any]
    emulator_stats: dict[str, Any]
    wall_s: float
    extra: dict[str, Any] = field(default_factory=dict)
    decimation: int = 1  # PWM periods per sample
    control_setup: DriveSetup | None = None  # the observers'/controller's setup (ts = D*Ts)

    @property
    def seq_rx(self) -> np.ndarray:
        return self.frames_rx[:, FR_SEQ].astype(np.int64)

    @property
    def truth_at_samples(self) -> np.ndarray:
        """Plant truth at the received samples' instants (row j: period j*D)."""
        k = self.seq_rx * self.decimation
        return self.truth[k[k < self.truth.shape[0]]]


class _TapLogger(can.Listener):
    """Records bus traffic with the project's capture writer (fluxdrive.can.canlog: python-can's,
    FD frames in .blf as the format defines them); numeric channel (BLF needs one), errors
    kept (a Notifier thread otherwise dies silently)."""

    def __init__(self, path: str) -> None:
        self.writer = open_writer(path)
        self.errors: list[BaseException] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.writer.on_message_received(
            can.Message(
                timestamp=msg.timestamp,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_fd=msg.is_fd,
                bitrate_switch=msg.bitrate_switch,
                data=msg.data,
                channel=1,
            )
        )

    def on_error(self, exc: Exception) -> None:
        self.errors.append(exc)

    def stop(self) -> None:
        self.writer.stop()


def run_can_loop(
    scenario: Any,
    n_periods: int | None = None,
    *,
    channel: str | None = None,
    bridge_config: BridgeConfig | None = None,
    arm: bool = True,
    emulator_kw: dict[str, Any] | None = None,
    frame_hook: Any = None,
    operator: Any = None,
    log_path: str | None = None,
    layout: str = "fd",
    decimation: int | None = None,
    control_scenario: Any = None,
    realtime: bool = False,
) -> CanLoopResult:
    """Run ``scenario`` (a :class:`fluxdrive.drive.scenario.Scenario`) closed loop over a
    virtual CAN bus. ``frame_hook(bridge, k)`` is called before each sample is handled
    (fault injection in tests). ``log_path`` records all bus traffic with python-can's
    Logger (.blf/.log/.asc). ``layout="classic"`` uses a non-FD bus and the classic
    layout. ``decimation``: PWM periods per sample, either layout (default: the DBC's for
    the layout, FD 1, classic 8); with D > 1 the observers and the controller run from
    ``control_scenario`` (default ``decimated_scenario(scenario, D)``, i.e. the
    scenario's own control section at ts = D*Ts). In split mode (the scenario's
    ``control.mode``) D is the scenario's ``control.decimation``. ``operator(bridge, host)``
    is called before each sample is handled, with the host's HostLoop (a fault-injection
    schedule's operator resets and re-arms). A ``frame_hook`` returning
    False leaves that sample unanswered (host silence). ``realtime`` paces the emulator to
    wall time (with ``emulator_kw={"lockstep": False}``: a free-running MCU); the host's
    answer latencies (sample sent -> answer on the bus) are in ``extra["answer_latency_s"]``,
    the host's own time per sample (decoded -> answer sent) in ``extra["host_compute_s"]``."""
    ds = DriveSetup(scenario)
    split = ds.split
    if split:
        decimation = ds.decimation
    n = ds.n if n_periods is None else int(n_periods)
    ch = channel or new_virtual_channel()
    fd = layout == "fd"
    buses = _Buses.open(ch, fd, log_path)
    emu = DriveEmulator(
        ds, buses.emu, record=True, layout=layout, decimation=decimation, **(emulator_kw or {})
    )
    d = emu.decimation
    cfg = _bridge_config(bridge_config, decimation is not None, d, split)
    bridge = CanBridge(bus_factory_from_params("virtual", ch, fd=fd), cfg)
    bridge.connect()
    if arm:  # the drive's parameters written and read back, then armed (both modes)
        bridge.require_params = True
        _configure_drive(emu, bridge, ds)
        ok, why = bridge.arm()
        if not ok:
            raise RuntimeError(f"the drive was not armed: {why}")
    if control_scenario is None:
        control_scenario = decimated_scenario(scenario, d) if d > 1 and not split else scenario
    dsc = DriveSetup(control_scenario) if control_scenario is not scenario else ds
    host = HostLoop(dsc, math.ceil(n / d), split, d)
    host.warm()
    t0 = time.perf_counter()
    emu.start(n, realtime=realtime)
    try:
        _serve(bridge, emu, host, _with_operator(frame_hook, operator, host))
    finally:
        emu.stop()
        bridge.shutdown()
        buses.close()
    return _loop_result(ds, dsc, emu, bridge, host, time.perf_counter() - t0, d)


def _loop_result(ds, dsc, emu, bridge, host, wall_s: float, d: int) -> CanLoopResult:
    """What a CAN loop gave: the drive's recorded frames and truth, the host's rows, both
    sides' counters, the answer latencies and the host's compute time per sample."""
    fs, tr = emu.recorded()
    m = host.m
    return CanLoopResult(
        ds,
        fs,
        tr,
        host.rx_rows[:m],
        host.est_rows[:, :m],
        host.ctrl_rows[:m],
        bridge.diagnostics(),
        emu.stats.as_dict(),
        wall_s,
        extra={
            "answer_latency_s": np.array(emu.answer_latency_s),
            "host_compute_s": np.array(host.host_s),
        },
        decimation=d,
        control_setup=dsc,
    )


def _bridge_config(
    given: BridgeConfig | None, decimated: bool, decimation: int, split: bool
) -> BridgeConfig:
    """The bridge's settings: those given (default: a 1 s stale timeout), with the
    emulator's decimation when one was asked for, and split mode when the scenario's."""
    cfg = given or BridgeConfig(stale_timeout_s=1.0)
    if decimated and not cfg.decimation:
        cfg = dataclasses.replace(cfg, decimation=decimation)
    if split:
        cfg = dataclasses.replace(cfg, control_split=True)
    return cfg


@dataclass
class _Buses:
    """The emulator's end of the virtual bus and, with a log path, a tap recording it."""

    emu: can.BusABC
    tap: can.BusABC | None = None
    notifier: can.Notifier | None = None

    @classmethod
    def open(cls, ch: str, fd: bool, log_path: str | None) -> _Buses:
        emu = can.Bus(interface="virtual", channel=ch, fd=fd, receive_own_messages=False)
        if not log_path:
            return cls(emu)
        tap = can.Bus(interface="virtual", channel=ch, fd=True)
        return cls(emu, tap, can.Notifier(tap, [_TapLogger(log_path)], timeout=0.05))

    def close(self) -> None:
        self.emu.shutdown()
        if self.notifier is not None:
            time.sleep(0.05)
            self.notifier.stop()  # also stops (closes) the logger
        if self.tap is not None:
            self.tap.shutdown()


def drive_params_of(ds: DriveSetup) -> dict[str, float]:
    """The drive parameters a host writes for this scenario's design (both modes): the
    drive-side controller row's (`drive_param_values`) and the host heartbeat timeout."""
    return {**drive_param_values(ds.cp), "HEARTBEAT_TIMEOUT_S": HOST_HEARTBEAT_TIMEOUT_S}


def _configure_drive(emu: DriveEmulator, bridge: CanBridge, ds: DriveSetup) -> None:
    """The drive's parameters of this scenario's design, each acknowledged and read back,
    and its offset calibration if it requires one, all before the run's first period (a
    run does not depend on when)."""
    configured = threading.Event()
    server = threading.Thread(target=emu.serve, args=(configured,), daemon=True)
    server.start()
    try:
        # generous: a cold numba cache compiles the emulator's kernels meanwhile
        ok, why = bridge.write_drive_params(drive_params_of(ds), timeout_s=60.0)
        if not ok:
            raise RuntimeError(why)
        # a drive that refuses to arm uncalibrated (the board image; the C core when asked)
        # is calibrated first, as the bench bridge node does (the drive's periods at
        # standstill, PWM off, before the run: DriveEmulator.serve); the C core's SIL
        # build otherwise keeps the nominal offsets, so its samples are the plant's ADC
        # readings exactly
        if emu.requires_calibration:
            ok, why = bridge.calibrate(timeout_s=60.0, status_wait_s=60.0)
            if not ok:
                raise RuntimeError(why)
    finally:
        configured.set()
        server.join()


class HostLoop:
    """The host's side of the loop -- the bridge's hot path after the decode: the observers
    and the controller (split: the host's reference step) over the received samples, their
    rows, and the answer to each. ``n_rows`` rows are kept (sample m in row m % n_rows: a
    long paced run keeps only the newest)."""

    def __init__(self, dsc: DriveSetup, n_rows: int, split: bool, decimation: int) -> None:
        self.dsc = dsc
        self.split = split
        self.cs = dsc.new_controller()
        self.obs = dsc.new_observer_states()
        self.n_obs = self.obs.shape[0]
        self.n_rows = max(int(n_rows), 1)
        self.est_rows = np.zeros((self.n_obs, self.n_rows, ES_N))
        self.ctrl_rows = np.zeros((self.n_rows, CO_N))
        self.rx_rows = np.zeros((self.n_rows, FR_N))
        self.no_est = np.zeros(ES_N)
        self.ctrl = np.zeros(CO_N)
        self.ref = np.zeros(RF_N)
        # split: the host's rows step at D*Ts, the profiles are per PWM period
        self.k_of_sample = decimation if split else 1
        self.m = 0  # samples handled
        self.host_s: list[float] = []  # per sample: frame decoded -> answer sent [s]

    def warm(self) -> None:
        """Compile (or load) the host's kernels before the drive runs: in lockstep it
        waits only lockstep_wait_s for each answer."""
        dsc, no_est = self.dsc, self.no_est
        scratch_fr = np.zeros(FR_N)
        scratch_est = np.zeros(ES_N)
        for o in range(self.n_obs):
            observer_step(dsc.new_observer_states()[o], dsc.obs_params[o], scratch_fr, scratch_est)
        cs = dsc.new_controller()
        if self.split:
            host_reference_step(cs, dsc.cp_host, scratch_fr, no_est, 0.0, 0.0, self.ctrl, self.ref)
        else:
            controller_step(cs, dsc.cp, scratch_fr, no_est, 0.0, 0.0, self.ctrl)

    def step(self, fr: np.ndarray, kk: int) -> None:
        """Sample `kk` through the observers and the controller, rows kept."""
        dsc, m = self.dsc, self.m % self.n_rows
        self.rx_rows[m] = fr
        for o in range(self.n_obs):
            observer_step(self.obs[o], dsc.obs_params[o], fr, self.est_rows[o, m])
        ki = min(max(kk * self.k_of_sample, 0), dsc.n - 1)
        est = self.est_rows[dsc.driving_index, m] if dsc.driving_index >= 0 else self.no_est
        w_ref, inj = dsc.w_ref[ki], dsc.id_inj[ki]
        if self.split:
            host_reference_step(self.cs, dsc.cp_host, fr, est, w_ref, inj, self.ctrl, self.ref)
        else:
            controller_step(self.cs, dsc.cp, fr, est, w_ref, inj, self.ctrl)
        self.ctrl_rows[m] = self.ctrl
        self.m += 1

    def answer(self, bridge: CanBridge, kk: int) -> None:
        """The duty command (split: the HOST_REF) answering sample `kk`."""
        ref, ctrl = self.ref, self.ctrl
        if self.split:
            bridge.send_reference(
                kk, ref[RF_ID_REF], ref[RF_IQ_REF], ref[RF_TH], ref[RF_W], ref[RF_EN] > 0.5
            )
        else:
            bridge.send_duty(kk, ctrl[CO_DA : CO_DC + 1], ctrl[CO_EN] > 0.5)


def _with_operator(frame_hook: Any, operator: Any, host: HostLoop) -> Any:
    """`frame_hook` with `operator(bridge, host)` called first (either may be None)."""
    if operator is None:
        return frame_hook

    def hook(bridge: CanBridge, kk: int) -> Any:
        operator(bridge, host)
        return True if frame_hook is None else frame_hook(bridge, kk)

    return hook


def _serve(bridge: CanBridge, emu: DriveEmulator, host: HostLoop, frame_hook: Any) -> None:
    """Handle and answer every sample the bridge decodes, until the emulator has finished
    and the bus has been quiet for 0.3 s."""
    n_smp = host.rx_rows.shape[0]
    idle_since = None
    while True:
        frames = bridge.poll(timeout=0.2)
        if frames.shape[0] == 0:
            if emu._thread is None or not emu._thread.is_alive():
                idle_since = idle_since or time.perf_counter()
                if time.perf_counter() - idle_since > 0.3:
                    break
            continue
        for fr in frames:
            t_in = time.perf_counter()
            kk = int(fr[FR_SEQ])
            answer = True
            if frame_hook is not None:
                answer = frame_hook(bridge, kk) is not False
            if host.m >= n_smp:
                break
            host.step(fr, kk)
            if not answer:
                continue
            host.answer(bridge, kk)
            host.host_s.append(time.perf_counter() - t_in)
