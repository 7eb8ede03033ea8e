"""The bench in real time: the drive and the host in processes of their own, a busy core
beside them (`./fluxdrive benchmark bench --paced`; no ROS).

* **drive** (a process): the plant and the C drive core (:class:`DriveEmulator`,
  free-running: it never waits for the host) paced by the wall clock at the PWM rate,
  a sample every D periods (split mode, FD layout), on python-can's ``udp_multicast`` bus
  (a group and port of the run's own, TTL 0: the datagrams never leave this host). It
  times every answer (``latency_*``: the HOST_REF's receive timestamp minus the time just
  before its sample went out, one wall clock) and counts the periods it started more than
  one period late (``drive_missed_periods``: an MCU's interrupt would have overrun; the
  emulated MCU shares the PC, which can hold it up). After such a hold-up it catches up,
  its clock its periods (an MCU's timer never stalls);
* **host** (a process): one thread from the sample to its answer -- :class:`CanBridge`
  decodes the sample (as in the bench_bridge node's CAN thread),
  :class:`fluxdrive.can.loop.HostLoop` runs the observers and the host's reference step,
  the bridge sends the HOST_REF -- in a :class:`fluxdrive.can.realtime.HotPath`
  (``SCHED_FIFO``, memory locked, pinned to its core, the garbage collector off the hot
  path), the HotPath the node's CAN thread runs too (on the real-bench graph the observers
  and the controller are nodes of their own, behind ROS topics: not measured here). It
  times its own part (``host_latency_*``: from the bus's receive timestamp of the sample
  -- the oldest of a poll's, for each of them -- to its answer sent) and its work
  (``host_compute_*``: decoded -> answer sent);
* **busy** (``busy_cores`` processes): a loop that never sleeps, at normal priority.

The drive runs the paper's 2 % case unloaded in split mode (its profile held at its end
for a long run); the host writes the drive's parameters, reads them back and arms it,
then the drive runs ``minutes``. What counts: answers later than the drive's reference
timeout -- as the drive saw them (``late_beyond_timeout``: its own hold-ups between a
sample and its sending included) and as the host held them (``host_late_beyond_timeout``)
--, samples never answered, the drive's faults (``drive_faults_at``: when, and how far
behind the wall clock the drive was then: catching up, its periods come faster than the
wall clock's), and the latency p50/p99/max.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import threading
import time
from array import array
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from fluxdrive.core.schema import param

__all__ = ["PacedConfig", "run_paced_bench", "split_bench_scenario"]


@dataclass
class PacedConfig:
    """One paced run (see the module doc)."""

    minutes: float = param(
        10.0, unit="min", doc="wall time the drive runs, paced", range=(0.01, 1440.0)
    )
    decimation: int = param(
        4, unit="", doc="PWM periods per sample (split mode, FD layout)", range=(1, 255)
    )
    busy_cores: int = param(
        1, unit="", doc="busy-loop processes beside the bench (normal priority)", range=(0, 64)
    )
    priority: int = param(
        80,
        unit="",
        doc="SCHED_FIFO priority of the host's hot path (0: normal scheduling, memory not locked)",
        range=(0, 99),
    )
    drive_priority: int = param(
        80,
        unit="",
        doc="SCHED_FIFO priority of the emulated drive (it stands for an MCU of its own; "
        "0: normal scheduling)",
        range=(0, 99),
    )
    drive_cpu: int | None = None  # None: the first core of this process's set
    host_cpu: int | None = None  # None: the last core of this process's set
    group: str = ""  # udp_multicast group ('' : one drawn for the run)
    port: int = 0  # udp_multicast port (0: one drawn for the run)
    progress_s: float = 10.0
    arm_timeout_s: float = 120.0


def split_bench_scenario(duration_s: float, decimation: int) -> Any:
    """The paper's 2 % case unloaded in split mode at D = ``decimation``, the flux observer
    on measured voltages driving, ``duration_s`` long (`benchmark bench`'s split run)."""
    from fluxdrive.core import yamlio
    from fluxdrive.drive.scenario import load_scenario, scenario_path

    paper = scenario_path("paper_2pct_150load")
    raw = yamlio.load_file(paper)
    return load_scenario(
        paper,
        overrides={
            "duration_s": duration_s,
            "steady_window_s": [duration_s / 2, duration_s],
            "load_pu": 0.0,
            "control": {**raw["control"], "mode": "split", "decimation": int(decimation)},
            "observers": {"flux_measured": raw["observers"]["flux_measured"]},
        },
    )


# the drive this far behind the wall clock is no paced run any more (and, at real-time
# priority, a thread that never sleeps): the run stops with an error
_GIVE_UP_S = 1.0

# the scenario's own length: its profile (start, ramp to speed) then held to the run's end
_PROFILE_S = 4.0


def _say(text: str) -> None:
    print(f"[bench paced] {text}", file=sys.stderr, flush=True)


def _cores(cfg: PacedConfig) -> tuple[int | None, int | None]:
    """(drive core, host core): given ones, else the first and the last this process may
    use (one core only: both None, nothing pinned)."""
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < 2:
        return cfg.drive_cpu, cfg.host_cpu
    drive = allowed[0] if cfg.drive_cpu is None else cfg.drive_cpu
    host = allowed[-1] if cfg.host_cpu is None else cfg.host_cpu
    return drive, host


def _bus_kwargs(cfg: PacedConfig) -> dict[str, Any]:
    return {"port": cfg.port, "hop_limit": 0}


def _child() -> None:
    """A child process leaves Ctrl-C to the parent (which stops it)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _busy_main() -> None:  # pragma: no cover - a child process, terminated by the parent
    _child()
    while True:
        pass


def _drive_main(cfg: PacedConfig, cpu: int | None, out: Any) -> None:
    """The drive process: serve the bus until the host armed it, then run paced."""
    _child()
    import can

    from fluxdrive.can.bridge import widen_receive_buffer
    from fluxdrive.can.emulator import DriveEmulator
    from fluxdrive.can.realtime import HotPath
    from fluxdrive.drive.sim import DriveSetup

    try:
        sc = split_bench_scenario(_PROFILE_S, cfg.decimation)
        ds = DriveSetup(sc)
        bus = can.Bus(interface="udp_multicast", channel=cfg.group, fd=True, **_bus_kwargs(cfg))
        widen_receive_buffer(bus)
        emu = DriveEmulator(ds, bus, lockstep=False, time_answers=True, decimation=cfg.decimation)
        emu.schedule_clock = True
        give_up = threading.Event()
        timer = threading.Timer(cfg.arm_timeout_s, give_up.set)
        timer.start()
        emu.serve(give_up, until_armed=True)
        timer.cancel()
        if not emu.armed:
            out.put({"error": f"the drive was not armed within {cfg.arm_timeout_s:g} s"})
            bus.shutdown()
            return
        with HotPath(cfg.drive_priority, cpu) as hot:
            for note in hot.report.notes:
                _say(f"drive: {note}")
            res = _run_paced(emu, int(round(cfg.minutes * 60.0 / emu.ts)), cfg)
        res["drive_realtime"] = hot.report.as_dict()
        bus.shutdown()
        out.put(res)
    except Exception as exc:  # noqa: BLE001 - one line to the parent, not a traceback
        out.put({"error": f"drive process: {type(exc).__name__}: {exc}"})


def _run_paced(emu: Any, n: int, cfg: PacedConfig) -> dict[str, Any]:
    """Periods 0..n-1 of `emu`, each started at t0 + k Ts (sleeping until then; behind,
    at once); progress every cfg.progress_s; then the answers' figures."""
    ts = emu.ts
    d = emu.decimation
    lat = emu.answer_latency_s
    timeout_s = float(emu.setup.sc.control.reference_timeout_s)
    missed = 0
    worst_lag = 0.0
    seen = late = 0  # answers looked at so far, and of them later than the timeout
    worst = worst_step = 0.0
    worst_step_k = 0
    n_faults = emu.stats.faults
    faults_at: list[tuple[float, float, float]] = []
    clock, sleep = time.perf_counter, time.sleep
    t0 = clock()
    next_print = t0 + cfg.progress_s
    for k in range(n):
        t_k = t0 + k * ts
        lag = clock() - t_k
        if lag < 0.0:
            sleep(-lag)
        else:
            if lag > ts:
                missed += 1
                if lag > _GIVE_UP_S:  # a real-time thread that never sleeps: stop it
                    raise RuntimeError(
                        f"the emulated drive fell {lag:.1f} s behind the wall clock at "
                        f"{k * ts:.1f} s: this PC does not run it at the PWM rate"
                    )
            worst_lag = max(worst_lag, lag)
        t_step = clock()
        emu.step()
        step_s = clock() - t_step
        if emu.stats.faults > n_faults:  # when, and how far behind the drive was then
            n_faults = emu.stats.faults
            faults_at.append((round(k * ts, 4), round(lag * 1e6, 1), round(step_s * 1e6, 1)))
        if step_s > worst_step:
            worst_step, worst_step_k = step_s, k
        if k % d:
            continue
        while seen < len(lat):  # the new answers, a few per sample: cheap
            x = lat[seen]
            seen += 1
            late += x > timeout_s
            worst = max(worst, x)
        if clock() >= next_print:
            next_print += cfg.progress_s
            _say(
                f"{(k + 1) * ts:.0f} s of {n * ts:.0f}: {emu.stats.samples_sent} samples, "
                f"{seen} references, {late} later than {timeout_s * 1e3:g} ms, latency max "
                f"{worst * 1e6:.0f} us; drive: {missed} missed periods, faults "
                f"{emu.stats.fault_codes}"
            )
    wall = clock() - t0
    emu._drain(0.05)  # answers still on their way (well within the timeout)
    deadline = clock() + 2 * timeout_s
    while clock() < deadline:
        emu._drain(0.005)
    drive = {
        "missed": missed,
        "worst_lag_s": worst_lag,
        "worst_step_s": worst_step,
        "worst_step_at_s": worst_step_k * ts,
        "faults_at": faults_at,
    }
    return _paced_figures(emu, lat, wall, timeout_s, drive)


def _paced_figures(
    emu: Any, lat: Any, wall: float, timeout_s: float, drive: dict[str, Any]
) -> dict[str, Any]:
    """The record of a paced run: the answers' latencies against the reference timeout and
    the sample period, and the drive's own timing (`drive`, gathered by _run_paced)."""
    st = emu.stats
    a = np.asarray(lat, dtype=float)
    us = a * 1e6
    return {
        "periods": int(st.periods),
        "wall_s": round(wall, 2),
        "samples": int(st.samples_sent),
        "references": int(us.size),
        "unanswered": int(st.samples_sent - us.size),
        "late_beyond_timeout": int(np.sum(a > timeout_s)),
        "reference_timeout_ms": round(timeout_s * 1e3, 3),
        "latency_p50_us": round(float(np.percentile(us, 50)), 1) if us.size else None,
        "latency_p99_us": round(float(np.percentile(us, 99)), 1) if us.size else None,
        "latency_p999_us": round(float(np.percentile(us, 99.9)), 1) if us.size else None,
        "latency_max_us": round(float(us.max()), 1) if us.size else None,
        "over_sample_period": int(np.sum(a > emu.decimation * emu.ts)),
        "drive_missed_periods": drive["missed"],
        "drive_worst_lag_us": round(drive["worst_lag_s"] * 1e6, 1),
        "drive_step_max_us": round(drive["worst_step_s"] * 1e6, 1),
        "drive_step_max_at_s": round(drive["worst_step_at_s"], 4),
        "drive_faults": list(st.fault_codes),
        # per fault: [drive time s, the period's lag behind the wall clock us, its step us]
        "drive_faults_at": drive["faults_at"],
        "refs_applied": int(st.refs_applied),
        "drive_armed_at_end": bool(emu.armed),
    }


def _host_main(cfg: PacedConfig, cpu: int | None, stop: Any, out: Any) -> None:
    """The host process: the bridge's hot path (decode -> observers -> reference step ->
    HOST_REF) in a HotPath until `stop`."""
    _child()
    from fluxdrive.can.bridge import BridgeConfig, CanBridge, bus_factory_from_params
    from fluxdrive.can.loop import HostLoop, drive_params_of
    from fluxdrive.can.realtime import HotPath
    from fluxdrive.drive.plant import FR_SEQ
    from fluxdrive.drive.sim import DriveSetup

    try:
        ds = DriveSetup(split_bench_scenario(_PROFILE_S, cfg.decimation))
        factory = bus_factory_from_params("udp_multicast", cfg.group, fd=True, **_bus_kwargs(cfg))
        bridge = CanBridge(
            factory,
            BridgeConfig(decimation=cfg.decimation, control_split=True, stale_timeout_s=1.0),
        )
        bridge.connect()
        host = HostLoop(ds, 1, True, cfg.decimation)
        host.warm()
        bridge.require_params = True
        compute = array("d")  # per sample: decoded -> answer sent [s]
        held = array("d")  # per sample: on the host's bus -> answer sent [s]
        clock = time.perf_counter
        # real time before arming: locking the memory takes a while, the drive would not wait
        with HotPath(cfg.priority, cpu) as hot:
            _say(f"host: {hot.report.line()}")
            for note in hot.report.notes:
                _say(f"host: {note}")
            ok, why = bridge.write_drive_params(drive_params_of(ds), timeout_s=cfg.arm_timeout_s)
            if ok:
                ok, why = bridge.arm()
            if not ok:
                out.put({"error": f"the drive was not armed: {why}"})
                bridge.shutdown()
                return
            while not stop.is_set():
                frames = bridge.poll(timeout=0.05)
                t_rx = bridge.poll_first_rx_s  # the bus's receive time of the first
                for fr in frames:
                    t_in = clock()
                    kk = int(fr[FR_SEQ])
                    host.step(fr, kk)
                    host.answer(bridge, kk)
                    compute.append(clock() - t_in)
                    if t_rx > 0.0:
                        held.append(time.time() - t_rx)
                hot.after_answer()  # a young collection when one is due
        diag = bridge.diagnostics()
        bridge.shutdown()
        c = np.frombuffer(compute, dtype=float) * 1e6
        h = np.frombuffer(held, dtype=float)
        timeout_s = float(ds.sc.control.reference_timeout_s)
        out.put(
            {
                "host_latency_p50_us": _pct(h, 50),
                "host_latency_p99_us": _pct(h, 99),
                "host_latency_max_us": round(float(h.max()) * 1e6, 1) if h.size else None,
                "host_late_beyond_timeout": int(np.sum(h > timeout_s)),
                "host_realtime": hot.report.as_dict(),
                "host_compute_p50_us": round(float(np.percentile(c, 50)), 1) if c.size else None,
                "host_compute_p99_us": round(float(np.percentile(c, 99)), 1) if c.size else None,
                "host_compute_max_us": round(float(c.max()), 1) if c.size else None,
                "host_samples": int(c.size),
                "host_gc_collections": hot.gc.collections,
                "host_gc_longest_us": round(hot.gc.longest_s * 1e6, 1),
                "host_seq_gaps": int(diag.get("seq_gaps", 0)),
                "host_fault": diag.get("fault", ""),
                "drive_fault_text": bridge.drive_fault_text(),
            }
        )
    except Exception as exc:  # noqa: BLE001 - one line to the parent, not a traceback
        out.put({"error": f"host process: {type(exc).__name__}: {exc}"})


def _pct(x_s: np.ndarray, q: float) -> float | None:
    """Percentile `q` of times [s] in us (None: no times)."""
    return round(float(np.percentile(x_s, q)) * 1e6, 1) if x_s.size else None


def _get(q: Any, proc: Any, what: str, wait_s: float) -> dict[str, Any]:
    """The result `proc` puts on `q`, waiting up to `wait_s` while it lives."""
    import queue

    end = time.monotonic() + wait_s
    while time.monotonic() < end:
        try:
            return dict(q.get(timeout=0.5))
        except queue.Empty:
            if not proc.is_alive():
                try:
                    return dict(q.get(timeout=1.0))
                except queue.Empty:
                    return {"error": f"the {what} process ended without a result"}
    return {"error": f"no result from the {what} process within {wait_s:g} s"}


def run_paced_bench(cfg: PacedConfig) -> dict[str, Any]:
    """One paced run (module doc); the figures of both sides in one record (``error`` says
    in one line what went wrong, if something did)."""
    from fluxdrive.can.bridge import software_bus_endpoint

    group, port = software_bus_endpoint()
    cfg.group = cfg.group or group
    cfg.port = cfg.port or port
    drive_cpu, host_cpu = _cores(cfg)
    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    q_drive, q_host = ctx.Queue(), ctx.Queue()
    busy = [ctx.Process(target=_busy_main, daemon=True) for _ in range(cfg.busy_cores)]
    host = ctx.Process(target=_host_main, args=(cfg, host_cpu, stop, q_host), daemon=True)
    drive = ctx.Process(target=_drive_main, args=(cfg, drive_cpu, q_drive), daemon=True)
    _say(
        f"{cfg.minutes:g} min at D = {cfg.decimation}, split mode, udp_multicast "
        f"{cfg.group}:{cfg.port}; drive on core {drive_cpu}, host on core {host_cpu}, "
        f"{cfg.busy_cores} busy loop(s), priority host {cfg.priority} drive "
        f"{cfg.drive_priority}"
    )
    for p in busy:
        p.start()
    host.start()
    drive.start()
    try:
        res = _get(q_drive, drive, "drive", cfg.arm_timeout_s + cfg.minutes * 60.0 * 3 + 60.0)
        stop.set()
        got = _get(q_host, host, "host", 30.0)
        if "error" in got:
            got["host_error"] = got.pop("error")
        res.update(got)
    finally:
        stop.set()
        for p in (*busy, host, drive):
            if p.is_alive():
                p.terminate()
            p.join(5.0)
    settings = asdict(cfg)
    settings.update(drive_cpu=drive_cpu, host_cpu=host_cpu)
    for k in ("group", "port", "progress_s", "arm_timeout_s"):
        settings.pop(k)
    res.update(
        settings=settings,
        machine=_machine(),
        load_average_1min_at_end=round(os.getloadavg()[0], 2),
    )
    return res


def _machine() -> dict[str, Any]:
    """What the figures were measured on: cores, CPU model, kernel, real-time throttling."""
    import platform
    from pathlib import Path

    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        rt = int(Path("/proc/sys/kernel/sched_rt_runtime_us").read_text())
    except (OSError, ValueError):
        rt = None
    return {
        "cpus": os.cpu_count(),
        "cpu_model": model,
        "kernel": platform.release(),
        "sched_rt_runtime_us": rt,
        "isolated_cpus": _isolated(),
    }


def _isolated() -> str:
    """The kernel's isolated cores (isolcpus=), '' when none."""
    from pathlib import Path

    try:
        return Path("/sys/devices/system/cpu/isolated").read_text().strip()
    except OSError:
        return ""
