"""`./fluxdrive benchmark bench`: the host's side of a decimated CAN bench, on this machine.

At D = 4 on the FD layout (a real 1/5 Mbit/s bus needs D >= 4), with the drive emulator on a
python-can virtual bus in lockstep (it waits for each answer, so every sample is answered
and timed) and the host loop (bridge logic, observers, controller) in this process:

  host / split  answer latency of the host per sample -- the answer frame's bus timestamp
                minus its sample's (p50/p99/max [us]); host_compute_*: the host's own part
                (sample decoded -> answer sent: observers, controller, codec) -- against
                the link budget's host time
                (`fluxdrive.can.protocol.link_budget`: what is left of a sample period once
                the bus has carried the sample and the answer), the share of answers later
                than that, and how many answers came later than the drive's watchdog allows
                (`late_for_watchdog`; host mode: the duty-command watchdog, 1.5 sample
                periods; split mode: the reference timeout, 10 ms) -- each would be a trip
                on a drive that does not wait. The emulator shares the process (and
                Python's GIL) with the host: its D periods of plant between two samples are
                in the latency too, as load on the host's CPU would be. Host mode
                runs `config/scenarios/can_2pct_decimated.yaml` (tuned for control at D*Ts),
                split mode the paper's 2 % case with the drive closing the current loop.
  c_loop        the C drive core's current loop (split mode) measured with Fig. 17's
                protocol (flux drive, 10 % speed, half load, d-axis stepped sine) through the
                whole CAN loop in lockstep -- the C core and the plant behind the bus, the
                host's observer and reference step in front of it -- with the drive's
                deadtime feed-forward at the card's deadtime. At D = 1 (a sample every PWM
                period: the reference and the measurement reach up to the PWM rate's Nyquist
                frequency, which the bench's D = 4 would cut at 1 250 Hz) and up to 3 kHz, so
                the -3 dB point is a resolved crossing, not the sweep's top; its gains per
                frequency, and the loop model's phase and gain margins at the drive's gains
                (`fluxdrive.drive.control.current_loop_margins`) with the timing contract's
                one period of delay, and with two (host mode over CAN: the answer to sample
                k is written at k+1 and applies from k+2).
  in_process_*  the same sweep through the engine's in-process split loop (D = 4 and 1) and
                host mode at D = 1, for comparison.

Options: --duration S (drive seconds of each run, default 2), --decimation D.
The last line on stdout is a JSON object, also written to results/can/bench.json (docs/can.md
quotes it). No ROS.

--paced: the bench in real time instead (fluxdrive.can.paced): the drive (plant and C core)
in a process of its own paced by the wall clock at the PWM rate, a sample every D periods
(split mode, FD layout), the host's hot path (the bridge's decode, observers, reference step,
HOST_REF, in one thread: the bench_bridge node's CAN thread's real-time set-up) in another,
in real time (SCHED_FIFO at
--priority, memory locked, pinned, garbage collector off the hot path; what is not
permitted is said in one line; the drive at --drive-priority), over udp_multicast on
127.0.0.1, with --busy-cores busy loops beside them (default 1), for --minutes (default
10). Samples, references, those later than the drive's reference timeout, latency
p50/p99/max [us], the drive's missed periods; a progress line every 10 s; the JSON last
line also written to results/can/bench_paced.json (docs/can.md and the README quote it).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.analysis.freqresp import analyse
from fluxdrive.can.loop import run_can_loop
from fluxdrive.can.paced import PacedConfig, run_paced_bench, split_bench_scenario
from fluxdrive.can.protocol import LinkOptions, link_budget
from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.control import CO_ID, CO_ID_REF, CP_KI_I, CP_KP_I, current_loop_margins
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.drive.sim import DriveSetup, run_scenario

__all__ = [
    "bench_bench",
    "c_loop_current_sweep",
    "current_sweep_scenario",
    "latency_figures",
    "split_current_bandwidth_hz",
]

RESULTS_PATH = ROOT / "results" / "can" / "bench.json"
PACED_RESULTS_PATH = ROOT / "results" / "can" / "bench_paced.json"
SWEEP_HZ = [200.0, 500.0, 700.0, 850.0, 1000.0, 1200.0, 1500.0]
# the C loop's sweep at D = 1: on to 3 kHz (0.6 of the PWM rate's Nyquist frequency)
C_SWEEP_HZ = [*SWEEP_HZ, 2000.0, 2500.0, 3000.0]


def _say(text: str) -> None:
    print(f"[bench bench] {text}", file=sys.stderr, flush=True)


def latency_figures(lat_s: np.ndarray, budget_us: float) -> dict[str, Any]:
    """p50/p99/max of answer latencies [us] and the share above the host budget [%]."""
    us = np.asarray(lat_s, dtype=float) * 1e6
    if us.size == 0:
        return {"answers": 0}
    return {
        "answers": int(us.size),
        "p50_us": round(float(np.percentile(us, 50)), 1),
        "p99_us": round(float(np.percentile(us, 99)), 1),
        "max_us": round(float(us.max()), 1),
        "over_budget_pct": round(100.0 * float(np.mean(us > budget_us)), 2),
    }


def _live_run(sc: Any, decimation: int, budget_us: float, watchdog_s: float) -> dict[str, Any]:
    r = run_can_loop(sc, decimation=decimation)
    emu = r.emulator_stats
    lat = r.extra["answer_latency_s"]
    out = latency_figures(lat, budget_us)
    comp = latency_figures(r.extra["host_compute_s"], budget_us)
    out.update({f"host_compute_{k}": v for k, v in comp.items() if k != "answers"})
    out.update(
        samples=int(emu["samples_sent"]),
        wall_s=round(r.wall_s, 2),
        watchdog_ms=round(1e3 * watchdog_s, 3),
        late_for_watchdog=int(np.sum(lat > watchdog_s)),
        drive_faults=list(emu["fault_codes"]),
    )
    return out


def current_sweep_scenario(
    decimation: int = 4,
    deadtime_comp: bool = True,
    mode: str = "split",
    freqs_hz: list[float] | None = None,
):
    """Fig. 17's d-axis current sweep (10 % speed, flux observer on measured voltages) in
    `mode` at `decimation`, the drive's deadtime feed-forward on or off."""
    from fluxdrive.experiments.paper import _fr_scenario

    sc = _fr_scenario("flux_measured", freqs_hz or SWEEP_HZ, "current")
    kw: dict[str, Any] = {"mode": mode, "decimation": decimation if mode == "split" else 1}
    if deadtime_comp:
        kw["deadtime_comp_s"] = sc.machine.deadtime_s
    sc.control = dataclasses.replace(sc.control, **kw).check(sc.machine)
    return sc


def split_current_bandwidth_hz(
    decimation: int = 4, deadtime_comp: bool = True, mode: str = "split"
) -> float:
    """-3 dB of i_d/i_d* (drive frame) with Fig. 17's protocol, in-process."""
    sc = current_sweep_scenario(decimation, deadtime_comp, mode)
    r = run_scenario(sc, progress=False)
    fr = analyse(r.ctrl[:, CO_ID], r.ctrl[:, CO_ID_REF], r.segments["current_d"], sc.machine.ts_s)
    return round(float(fr["bandwidth_hz"]), 1)


def c_loop_current_sweep(
    deadtime_comp: bool = True, freqs_hz: list[float] | None = None
) -> dict[str, Any]:
    """Fig. 17's d-axis sweep through the C drive core in split mode at D = 1 over the
    in-process CAN loop (`run_can_loop`, lockstep): i_d (the host's Park of the drive's
    samples in the frame of the reference it sent) against i_d*; gains per frequency, the
    -3 dB crossing, and the loop model's margins at the drive's gains."""
    sc = current_sweep_scenario(1, deadtime_comp, "split", freqs_hz or C_SWEEP_HZ)
    ds = DriveSetup(sc)
    r = run_can_loop(sc)
    m = r.ctrl.shape[0]
    segs = [s for s in ds.segments["current_d"] if s.k_end <= m]
    fr = analyse(r.ctrl[:, CO_ID], r.ctrl[:, CO_ID_REF], segs, sc.machine.ts_s)
    bw = float(fr["bandwidth_hz"])
    kp, ki = float(ds.cp[CP_KP_I]), float(ds.cp[CP_KI_I])
    margins = {
        f"delay_{d}": {
            k: round(v, 2) if math.isfinite(v) else None
            for k, v in current_loop_margins(sc.machine, kp, ki, d).items()
        }
        for d in (1, 2)
    }
    return {
        "decimation": 1,
        "frequency_hz": fr["frequency_hz"],
        "gain_db": [round(g, 2) for g in fr["gain_db"]],
        "phase_deg": [round(p, 1) for p in fr["phase_deg"]],
        "coherence": [round(c, 3) for c in fr["coherence"]],
        # a crossing inside the band, or None: then the sweep did not resolve it
        "bandwidth_hz": round(bw, 1) if math.isfinite(bw) else None,
        "sweep_top_hz": max(fr["frequency_hz"]),
        "kp_v_per_a": round(kp, 4),
        "ki_v_per_as": round(ki, 1),
        "margins": margins,
        "drive_faults": list(r.emulator_stats["fault_codes"]),
        "lockstep_timeouts": int(r.emulator_stats["lockstep_timeouts"]),
        "wall_s": round(r.wall_s, 1),
    }


def paced_bench(cfg: PacedConfig, path: Any = None) -> dict[str, Any]:
    """`benchmark bench --paced`: one paced run, its record written to `path` (default
    results/can/bench_paced.json) and returned; a failed run is one line and exit 1."""
    try:
        res = run_paced_bench(cfg)
    except KeyboardInterrupt:
        print("fluxdrive benchmark bench --paced: interrupted, nothing written", file=sys.stderr)
        raise SystemExit(130) from None
    for key in ("error", "host_error"):
        if res.get(key):
            print(f"fluxdrive benchmark bench --paced: {res[key]}", file=sys.stderr)
            raise SystemExit(1)
    res["measured"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    out = Path(path) if path is not None else PACED_RESULTS_PATH
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    _say(
        f"{res['samples']} samples, {res['references']} references, "
        f"{res['late_beyond_timeout']} later than the {res['reference_timeout_ms']:g} ms "
        f"timeout, {res['unanswered']} unanswered; latency p50/p99/max "
        f"{res['latency_p50_us']}/{res['latency_p99_us']}/{res['latency_max_us']} us; "
        f"drive: {res['drive_missed_periods']} missed periods, faults {res['drive_faults']}"
    )
    _say(f"written {out.relative_to(ROOT) if out.is_relative_to(ROOT) else out}")
    return res


def bench_bench(argv: list[str]) -> dict[str, Any]:
    ap = Parser(prog="fluxdrive benchmark bench", description=__doc__)
    ap.add_argument("--duration", type=float, default=2.0, help="drive seconds per run")
    option(ap, "--decimation", LinkOptions)
    ap.add_argument("--paced", action="store_true", help="the bench in real time (see above)")
    option(ap, "--minutes", PacedConfig)
    option(ap, "--busy-cores", PacedConfig)
    option(ap, "--priority", PacedConfig)
    option(ap, "--drive-priority", PacedConfig)
    ap.add_argument(
        "--out", default=None, help="--paced: write the record here (default: the results file)"
    )
    args = ap.parse_args(argv)
    d = int(args.decimation)
    if args.paced:
        return paced_bench(
            PacedConfig(
                minutes=args.minutes,
                decimation=d,
                busy_cores=args.busy_cores,
                priority=args.priority,
                drive_priority=args.drive_priority,
            ),
            args.out,
        )
    host_sc = load_scenario(scenario_path("can_2pct_decimated"))
    pwm_hz = host_sc.machine.pwm_hz
    lb = link_budget("fd", decimation=d, pwm_hz=pwm_hz)
    budget_us = float(lb["host_budget_us_worst"])
    dur = float(args.duration)
    host_sc = load_scenario(
        scenario_path("can_2pct_decimated"),
        overrides={"duration_s": dur, "steady_window_s": [dur / 2, dur]},
    )
    split_sc = split_bench_scenario(dur, d)
    _say(f"D = {d}: host budget {budget_us:.0f}-{lb['host_budget_us_none']:.0f} us per sample")
    _say("warming up (compiling the kernels) ...")
    for sc in (host_sc, split_sc):
        run_can_loop(dataclasses.replace(sc, duration_s=0.02), decimation=d)
    out: dict[str, Any] = {
        "decimation": d,
        "sample_period_us": round(1e6 * d / pwm_hz, 1),
        "host_budget_us_worst": round(budget_us, 1),
        "host_budget_us_none": round(float(lb["host_budget_us_none"]), 1),
    }
    ts = host_sc.machine.ts_s
    # host mode: the bridge's duty watchdog (BridgeConfig.cmd_timeout_s, at least 1.5 samples)
    watchdogs = {"host": max(1e-3, 1.5 * d * ts), "split": split_sc.control.reference_timeout_s}
    for mode, sc in (("host", host_sc), ("split", split_sc)):
        _say(f"{mode} mode, {dur:g} s of drive time in lockstep ...")
        out[mode] = _live_run(sc, d, budget_us, watchdogs[mode])
        _say(f"{mode}: {out[mode]}")
    _say("current-loop sweep through the C drive core (Fig. 17 protocol, split, D = 1) ...")
    out["c_loop"] = c_loop_current_sweep()
    _say(f"C loop: {out['c_loop']}")
    _say("current-loop sweeps (Fig. 17 protocol, in-process) ...")
    out["in_process_split_current_bw_hz"] = split_current_bandwidth_hz(d, True)
    out["in_process_split_d1_current_bw_hz"] = split_current_bandwidth_hz(1, True)
    out["in_process_split_current_bw_hz_no_deadtime_comp"] = split_current_bandwidth_hz(d, False)
    out["in_process_host_d1_current_bw_hz_no_deadtime_comp"] = split_current_bandwidth_hz(
        1, False, "host"
    )
    RESULTS_PATH.parent.mkdir(parents=True, exist_ok=True)
    RESULTS_PATH.write_text(json.dumps(out, indent=2) + "\n")
    _say(f"written {RESULTS_PATH.relative_to(ROOT)}")
    return out
