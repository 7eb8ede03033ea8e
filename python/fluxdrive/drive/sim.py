"""In-process closed-loop runner: plant + observers + FOC in one compiled loop.

Per period k (docs/engine.md, timing convention), exactly the order the ROS graph follows:
  1. every observer (driving and shadow) consumes frame k,
  2. the controller turns frame k and the driving estimate into duty(k),
  3. the plant simulates [t_k, t_{k+1}] with duty(k-1) and samples frame k+1,
  4. duty(k) is latched for the next period.
The kernels are the same compiled functions the nodes call one message at a time, so a
graph run of the same scenario and seed reproduces these numbers bit for bit.

Split mode (`control.mode: split`, docs/can.md): the drive side (`split_drive_step`, the
current loops) runs every period on frame k; the host side (observers and
`host_reference_step`) runs every D periods on the decimated sample (line voltages and
duties averaged over the window, as `fluxdrive.can.protocol.decimate_frames`), and its
answer to sample j is taken by the drive at period (j + 1 + host_delay_samples) D.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numba import njit

from fluxdrive.core.blocks import rng_new
from fluxdrive.core.excitation import Segment, stepped_sine
from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.control import (
    CO_DA,
    CO_DC,
    CO_EN,
    CO_N,
    CO_W_FB,
    CO_W_REF,
    CP_TS,
    CS_N,
    DR_N,
    RF_N,
    controller_reset,
    controller_step,
    host_params,
    host_reference_step,
    split_drive_reset,
    split_drive_step,
    split_drive_take_reference,
)
from fluxdrive.drive.observers import (
    ES_N,
    OP_N,
    OP_TS,
    OS_N,
    KernelObserver,
    Observer,
    build_observer,
    observer_reset,
    observer_step,
)
from fluxdrive.drive.plant import (
    FR_DA,
    FR_DC,
    FR_EN,
    FR_FLAGS,
    FR_N,
    FR_SEQ,
    FR_VAB,
    FR_VCA,
    TR_N,
    WORK_N,
    load_config,
    machine_params,
    plant_initial_frame,
    plant_period,
    plant_state,
)
from fluxdrive.drive.scenario import RPM, Scenario

# the duty latched from period k to k+1: the controller row up to its enable flag
LATCH_N = max(CO_DA, CO_DC, CO_EN) + 1


def pwm_off_latch() -> np.ndarray:
    """The latch before the first period: PWM off, duties at 50 %."""
    latch = np.zeros(LATCH_N)
    latch[CO_DA : CO_DC + 1] = 0.5
    latch[CO_EN] = 0.0
    return latch


@njit(cache=True, inline="always")
def _row_into(out, k, row):
    """out[k, :] = row, element by element (a slice assignment builds its indexers each
    period)."""
    for j in range(row.shape[0]):
        out[k, j] = row[j]


@njit(cache=True)
def closed_loop_chunk(
    k0,
    k1,
    pst,
    mp,
    rng,
    load_t,
    load_y,
    load_cfg,
    cs,
    cp,
    w_ref,
    id_inj,
    obs_states,
    obs_params,
    driving,
    frame,
    truth,
    duty_prev,
    out_frames,
    out_truth,
    out_est,
    out_ctrl,
):
    """Run periods k0..k1-1.  `frame`/`truth` hold frame k0 on entry and frame k1 on exit;
    `duty_prev` (the controller row's first LATCH_N fields: duties and enable) the duty
    latched for the next period."""
    n_obs = obs_states.shape[0]
    no_est = np.zeros(ES_N)
    ctrl = np.zeros(CO_N)
    work = np.empty(WORK_N)  # the plant's scratch: the periods allocate nothing
    for k in range(k0, k1):
        _row_into(out_frames, k, frame)
        _row_into(out_truth, k, truth)
        for o in range(n_obs):
            observer_step(obs_states[o], obs_params[o], frame, out_est[o, k])
        est = out_est[driving, k] if driving >= 0 else no_est
        control_and_plant(
            k,
            pst,
            mp,
            rng,
            load_t,
            load_y,
            load_cfg,
            cs,
            cp,
            w_ref,
            id_inj,
            est,
            frame,
            truth,
            duty_prev,
            ctrl,
            work,
        )
        _row_into(out_ctrl, k, ctrl)
    return k1


@njit(cache=True)
def control_and_plant(
    k,
    pst,
    mp,
    rng,
    load_t,
    load_y,
    load_cfg,
    cs,
    cp,
    w_ref,
    id_inj,
    est,
    frame,
    truth,
    duty_prev,
    ctrl,
    work,
):
    """Steps 2-4 of period k (after the observers): the controller turns frame k and the
    driving estimate `est` into duty(k) (in `ctrl`), the plant simulates [t_k, t_{k+1}] with
    the latched duty(k-1) into `frame`/`truth` (`work`: its scratch), and duty(k) is latched
    in `duty_prev`."""
    controller_step(cs, cp, frame, est, w_ref[k], id_inj[k], ctrl)
    plant_period(
        pst,
        mp,
        rng,
        duty_prev[CO_DA : CO_DC + 1],
        duty_prev[CO_EN] > 0.5,
        load_t,
        load_y,
        load_cfg,
        frame,
        truth,
        work,
    )
    for j in range(LATCH_N):
        duty_prev[j] = ctrl[j]


@njit(cache=True)
def kernel_observers_step(obs_states, obs_params, is_kernel, frame, out_est, k):
    """Every built-in (kernel) observer consumes frame k (the plugin rows are skipped)."""
    for o in range(obs_states.shape[0]):
        if is_kernel[o]:
            observer_step(obs_states[o], obs_params[o], frame, out_est[o, k])


# the decimation window's accumulator (split mode): sums of the averaged fields, the
# minimum enable, the OR of the flags, the number of periods
_AVG_FIELDS = (FR_VAB, FR_VAB + 1, FR_VCA, FR_DA, FR_DA + 1, FR_DC)
WIN_N = len(_AVG_FIELDS) + 3


@njit(cache=True)
def window_add(win, frame):
    """Add period `frame` to the decimation window `win` (WIN_N; all zeros when empty)."""
    n = win[WIN_N - 1]
    for j in range(6):
        win[j] += frame[_AVG_FIELDS[j]]
    win[6] = frame[FR_EN] if n == 0.0 else min(win[6], frame[FR_EN])
    win[7] = float(int(win[7]) | int(frame[FR_FLAGS]))
    win[WIN_N - 1] = n + 1.0


@njit(cache=True)
def window_sample(win, frame, out):
    """The decimated sample of the window ending at `frame` (its last period) into `out`:
    currents, bus voltage, encoder, seq of the last period; line voltages and duties the
    window's means; enable only if on in every period; flags OR-ed.  Empties `win`."""
    n = win[WIN_N - 1]
    for j in range(FR_N):
        out[j] = frame[j]
    for j in range(6):
        out[_AVG_FIELDS[j]] = win[j] / n
    out[FR_EN] = win[6]
    out[FR_FLAGS] = win[7]
    for j in range(WIN_N):
        win[j] = 0.0


@njit(cache=True)
def split_loop_chunk(
    k0,
    k1,
    decimation,
    delay,
    pst,
    mp,
    rng,
    load_t,
    load_y,
    load_cfg,
    cs_host,
    cp_host,
    cs_drive,
    cp,
    dr,
    w_ref,
    id_inj,
    obs_states,
    obs_params,
    driving,
    frame,
    truth,
    duty_prev,
    win,
    refs,
    host_row,
    out_frames,
    out_truth,
    out_est,
    out_ctrl,
):
    """Split mode, periods k0..k1-1 (state as in `closed_loop_chunk`, plus the host's and
    the drive's controller states, the drive's reference `dr`, the decimation window `win`
    and the references in flight `refs` (a ring of delay + 2 RF_* rows); `host_row` holds
    the host's newest CO_* row).  The estimate rows between two samples hold the sample's."""
    n_obs = obs_states.shape[0]
    no_est = np.zeros(ES_N)
    fdec = np.zeros(FR_N)
    ref = np.zeros(RF_N)
    ctrl = np.zeros(CO_N)
    work = np.empty(WORK_N)  # the plant's scratch: the periods allocate nothing
    n_ring = refs.shape[0]
    ts = cp[CP_TS]
    for k in range(k0, k1):
        _row_into(out_frames, k, frame)
        _row_into(out_truth, k, truth)
        window_add(win, frame)
        # the drive takes the host's answer to sample j = k/D - 1 - delay at this boundary
        if k % decimation == 0:
            j = k // decimation - 1 - delay
            if j >= 0:
                since_s = (k - j * decimation) * ts
                split_drive_take_reference(cs_drive, dr, refs[j % n_ring], since_s)
        split_drive_step(cs_drive, cp, dr, frame, ctrl)
        if k % decimation == 0:
            # the host: observers and references on the decimated sample k / D
            window_sample(win, frame, fdec)
            fdec[FR_SEQ] = k // decimation  # the host counts samples (as over CAN)
            for o in range(n_obs):
                observer_step(obs_states[o], obs_params[o], fdec, out_est[o, k])
            est = out_est[driving, k] if driving >= 0 else no_est
            host_reference_step(cs_host, cp_host, fdec, est, w_ref[k], id_inj[k], host_row, ref)
            refs[(k // decimation) % n_ring, :] = ref
        else:
            for o in range(n_obs):
                out_est[o, k, :] = out_est[o, k - 1, :]
        ctrl[CO_W_REF] = host_row[CO_W_REF]
        ctrl[CO_W_FB] = host_row[CO_W_FB]
        _row_into(out_ctrl, k, ctrl)
        plant_period(
            pst,
            mp,
            rng,
            duty_prev[CO_DA : CO_DC + 1],
            duty_prev[CO_EN] > 0.5,
            load_t,
            load_y,
            load_cfg,
            frame,
            truth,
            work,
        )
        for j in range(LATCH_N):
            duty_prev[j] = ctrl[j]
    return k1


@dataclass
class SimResult:
    scenario: Scenario
    names: list[str]  # observer names, in est order
    driving: str
    t: np.ndarray
    frames: np.ndarray  # (N, FR_N)
    truth: np.ndarray  # (N, TR_N)
    est: np.ndarray  # (n_obs, N, ES_N)
    ctrl: np.ndarray  # (N, CO_N)
    w_ref: np.ndarray  # (N,) mechanical speed reference incl. injection [rad/s]
    id_inj: np.ndarray
    segments: dict[str, list[Segment]] = field(default_factory=dict)
    wall_s: float = 0.0
    # split mode: the host's samples are every `decimation` periods (the estimate rows
    # between two hold the sample's); 1: every period
    decimation: int = 1
    # the controller's state (CS_*) at the end of the run (split mode: the host's): what
    # a latched trip saw (fluxdrive.drive.control.trips explains it with these values)
    controller_state: np.ndarray | None = None

    def estimate(self, name: str) -> np.ndarray:
        return self.est[self.names.index(name)]

    def save_npz(self, path: Path) -> None:
        np.savez_compressed(
            path,
            t=self.t,
            frames=self.frames,
            truth=self.truth,
            est=self.est,
            ctrl=self.ctrl,
            w_ref=self.w_ref,
            id_inj=self.id_inj,
            names=np.array(self.names),
            driving=self.driving,
        )


class DriveSetup:
    """Everything a run needs, as arrays: built once from a scenario, shared by the
    in-process runner and the ROS nodes (which take the pieces they own)."""

    def __init__(self, sc: Scenario):
        self.sc = sc
        card = sc.machine
        self.card = card
        self.n = sc.n_periods
        self.ts = card.ts_s
        self.mp = machine_params(
            card,
            sc.current_offset_a,
            sc.current_gain,
            deadtime_s=sc.plant_deadtime_s,
            bench=sc.bench,
        )
        self.load_t, self.load_y = sc.load_breakpoints_nm()
        self.load_cfg = load_config(sc.dyno_nm_per_rad_s(), sc.brake_band_rpm * RPM)
        self.cp = sc.control.to_params(card)
        self.names = list(sc.observers)
        self.obs_params = np.zeros((len(self.names), OP_N))
        # user variants (module:Class, entry points) run in Python: their rows stay zero
        self.plugins = [nm for nm in self.names if sc.observers[nm].is_plugin]
        for o, nm in enumerate(self.names):
            if nm not in self.plugins:
                self.obs_params[o] = sc.observers[nm].to_params(card)
        # split mode: the host (observers, speed loop, start-up) steps at D*Ts
        self.split = sc.control.mode == "split"
        if self.split and self.plugins:
            raise ConfigError(
                f"{sc.name}: user variant(s) {self.plugins} in split mode: the in-process "
                f"split loop is compiled and runs built-in variants only"
            )
        self.decimation = int(sc.control.decimation)
        self.host_delay_samples = int(sc.control.host_delay_samples)
        self.cp_host = host_params(self.cp, self.decimation) if self.split else self.cp
        if self.split:
            self.obs_params[:, OP_TS] = self.decimation * self.ts
        self.driving_index = -1 if sc.driving == "encoder" else self.names.index(sc.driving)
        t = np.arange(self.n) * self.ts
        self.w_ref = sc.speed_ref_rad_s(t)
        self.id_inj = np.zeros(self.n)
        self.segments: dict[str, list[Segment]] = {}
        if sc.id_injection:
            sig, segs, _ = _injection(sc.id_injection, self.ts, card.rated_current_a)
            m = min(len(sig), self.n)
            self.id_inj[:m] = sig[:m]
            self.segments["current_d"] = [s for s in segs if s.k_end <= self.n]
        if sc.speed_injection:
            sig, segs, _ = _injection(sc.speed_injection, self.ts, RPM)
            m = min(len(sig), self.n)
            self.w_ref[:m] += sig[:m]
            self.segments["speed"] = [s for s in segs if s.k_end <= self.n]

    # fresh states (a run or a node starts from these)
    def new_plant(self):
        th = self.sc.bench.thermal
        pst = plant_state(
            math.radians(self.sc.initial_angle_deg),
            0.0,
            self.card.pole_pairs,
            winding_c=self.card.resistance_ref_c if th is None else th.initial_winding_c,
        )
        return pst, rng_new(self.sc.seed)

    def new_controller(self):
        cs = np.zeros(CS_N)
        controller_reset(cs)
        return cs

    def new_observer_states(self):
        st = np.zeros((len(self.names), OS_N))
        for o in range(len(self.names)):
            observer_reset(st[o])
        return st

    def kernel_observer(self, name: str) -> KernelObserver:
        return KernelObserver(self.sc.observers[name], self.card, name=name)

    def new_plugin_observers(self) -> dict[int, Observer]:
        """Fresh instances of the user variants, by observer index."""
        return {
            self.names.index(nm): build_observer(self.sc.observers[nm], self.card, name=nm)
            for nm in self.plugins
        }


def _injection(spec: dict, ts: float, unit: float):
    freqs = spec.get("frequencies_hz")
    if freqs is None:
        f0, f1, n = spec.get("f_start_hz", 1.0), spec.get("f_stop_hz", 1000.0), spec.get("n", 20)
        freqs = np.geomspace(f0, f1, int(n)).tolist()
    return stepped_sine(
        freqs,
        float(spec.get("amplitude", 1.0)) * unit,
        ts,
        float(spec.get("start_s", 0.5)),
        int(spec.get("cycles", 6)),
        int(spec.get("settle_cycles", 3)),
    )


class LoopRun:
    """One in-process closed-loop run over a DriveSetup: fresh plant, controller and observer
    states, frame 0 sampled, the PWM-off latch, and output rows for every period.  `advance`
    runs the compiled loop up to a period; between calls a caller may change `cp` or
    `obs_params` (copies of the setup's rows), so experiments that switch a source or adapt
    a parameter mid-run use the very loop `run_scenario` uses.  In split mode `cp` is the
    drive's row and `cp_host` the host's (CP_TS = D*Ts); `cs` is the host's state."""

    def __init__(self, ds: DriveSetup):
        self.ds = ds
        n = self.n = ds.n
        self.pst, self.rng = ds.new_plant()
        self.cs = ds.new_controller()
        self.obs_states = ds.new_observer_states()
        self.cp = ds.cp.copy()
        self.obs_params = ds.obs_params.copy()
        self.driving = ds.driving_index
        self.frame = np.zeros(FR_N)
        self.truth = np.zeros(TR_N)
        plant_initial_frame(self.pst, ds.mp, self.rng, self.frame, self.truth)
        self.latch = pwm_off_latch()
        self.frames = np.zeros((n, FR_N))
        self.truths = np.zeros((n, TR_N))
        self.est = np.zeros((len(ds.names), n, ES_N))
        self.ctrl = np.zeros((n, CO_N))
        self.k = 0
        self.wall_s = 0.0
        self.plugins = ds.new_plugin_observers()
        if ds.split:
            # the host's controller state is `cs`; the drive's, its reference, the
            # decimation window and the references in flight
            self.cp_host = ds.cp_host.copy()
            self.cs_drive = np.zeros(CS_N)
            self.dr = np.zeros(DR_N)
            split_drive_reset(self.cs_drive, self.dr)
            self.win = np.zeros(WIN_N)
            self.refs = np.zeros((ds.host_delay_samples + 2, RF_N))
            self.host_row = np.zeros(CO_N)

    def advance(self, k1: int) -> None:
        """Run periods k..k1-1 (k1 = k compiles, or loads from the cache, and runs nothing)."""
        ds = self.ds
        t0 = time.perf_counter()
        if ds.split:
            self.k = split_loop_chunk(
                self.k,
                k1,
                ds.decimation,
                ds.host_delay_samples,
                self.pst,
                ds.mp,
                self.rng,
                ds.load_t,
                ds.load_y,
                ds.load_cfg,
                self.cs,
                self.cp_host,
                self.cs_drive,
                self.cp,
                self.dr,
                ds.w_ref,
                ds.id_inj,
                self.obs_states,
                self.obs_params,
                self.driving,
                self.frame,
                self.truth,
                self.latch,
                self.win,
                self.refs,
                self.host_row,
                self.frames,
                self.truths,
                self.est,
                self.ctrl,
            )
            self.wall_s += time.perf_counter() - t0
            return
        if self.plugins:
            self._advance_with_plugins(k1)
            self.wall_s += time.perf_counter() - t0
            return
        self.k = closed_loop_chunk(
            self.k,
            k1,
            self.pst,
            ds.mp,
            self.rng,
            ds.load_t,
            ds.load_y,
            ds.load_cfg,
            self.cs,
            self.cp,
            ds.w_ref,
            ds.id_inj,
            self.obs_states,
            self.obs_params,
            self.driving,
            self.frame,
            self.truth,
            self.latch,
            self.frames,
            self.truths,
            self.est,
            self.ctrl,
        )
        self.wall_s += time.perf_counter() - t0

    def _advance_with_plugins(self, k1: int) -> None:
        """The same period as closed_loop_chunk, driven from Python so that user variants
        (Python classes) can drive or shadow: the kernel observers and the controller and
        plant steps are the compiled functions the chunk calls, in the same order."""
        ds = self.ds
        is_kernel = np.array([nm not in ds.plugins for nm in ds.names])
        no_est = np.zeros(ES_N)
        ctrl = np.zeros(CO_N)
        work = np.empty(WORK_N)
        for k in range(self.k, k1):
            self.frames[k, :] = self.frame
            self.truths[k, :] = self.truth
            kernel_observers_step(
                self.obs_states, self.obs_params, is_kernel, self.frame, self.est, k
            )
            for o, obs in self.plugins.items():
                self.est[o, k, :] = obs.step(self.frame.copy())  # a copy: plugins may write
            est = self.est[self.driving, k] if self.driving >= 0 else no_est
            control_and_plant(
                k,
                self.pst,
                ds.mp,
                self.rng,
                ds.load_t,
                ds.load_y,
                ds.load_cfg,
                self.cs,
                self.cp,
                ds.w_ref,
                ds.id_inj,
                est,
                self.frame,
                self.truth,
                self.latch,
                ctrl,
                work,
            )
            self.ctrl[k, :] = ctrl
        self.k = max(self.k, k1)

    def result(self) -> SimResult:
        ds = self.ds
        return SimResult(
            ds.sc,
            ds.names,
            ds.sc.driving,
            np.arange(self.n) * ds.ts,
            self.frames,
            self.truths,
            self.est,
            self.ctrl,
            ds.w_ref,
            ds.id_inj,
            ds.segments,
            self.wall_s,
            ds.decimation if ds.split else 1,
            self.cs.copy(),
        )


def run_scenario(
    sc: Scenario, progress: bool | Literal["always"] = True, chunk_s: float = 0.25
) -> SimResult:
    """Run a scenario headless in-process.  Shows progress on stderr for long runs."""
    run = LoopRun(DriveSetup(sc))
    n, ts = run.n, run.ds.ts
    chunk = max(1, int(chunk_s / ts))
    run.advance(0)  # compile (or load from cache) before timing
    run.wall_s = 0.0
    show = progress == "always" or (progress and sys.stderr.isatty())
    tty = sys.stderr.isatty()
    last_print = time.perf_counter()
    while run.k < n:
        run.advance(min(n, run.k + chunk))
        now = time.perf_counter()
        if show and (tty or now - last_print > 2.0 or run.k == n):
            last_print = now
            msg = (
                f"[sim] {sc.name}: {run.k * ts:6.2f}/{sc.duration_s:.2f} s simulated, "
                f"{run.wall_s:5.1f} s wall"
            )
            sys.stderr.write("\r" + msg if tty else msg + "\n")
            sys.stderr.flush()
    if show and tty:
        sys.stderr.write("\n")
    return run.result()
