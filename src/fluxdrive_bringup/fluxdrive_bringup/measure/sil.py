"""`./fluxdrive bench --sil [SCENARIO]`: the whole bench path in one command, software in the
loop. `--pil`: the same graph with the board image that would be flashed
(firmware/board/nucleo_g474) on the virtual board (fluxdrive.can.vboard) as the drive.

The scenario's lockstep graph (runs.graph_for_scenario) with its plant replaced by the bench:
- the drive: `./fluxdrive can-emulator` (the C firmware core as the MCU, lockstep,
  the project's plant in that process), on python-can's `udp_multicast` bus with a port of
  its own and TTL 0 (the datagrams never leave this host); it is the graph's required
  process: its last period ends the run;
- the bench_bridge node (control_split per --mode, decimation D) on the same bus;
- the observer node(s), the controller (control_mode, decimation) and the recorder, as in
  `./fluxdrive run`.
The bag is read back like `run`'s; the plant's true state (the drive process's, written
to truth.npy beside the bag, sampled at the decimated sample instants) fills the truth rows
the bridge cannot publish, and the same metric table is printed.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from fluxdrive.can.bridge import software_bus_endpoint
from fluxdrive.can.protocol import LinkOptions
from fluxdrive.can.vboard import BOARD_DECIMATIONS
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.scenario import (
    MACHINE_HELP,
    REPO_ROOT,
    ScenarioSettings,
    load_scenario,
    scenario_on_machine,
    scenario_path,
)
from fluxdrive.io.graphfile import GraphSettings

from fluxdrive_bringup.inspect.commands import OPERATOR_NODE
from fluxdrive_bringup.launch.domains import choose_domain
from fluxdrive_bringup.launch.launcher import Launcher, NodeSpec
from fluxdrive_bringup.launch.runs import graph_for_scenario, shorten
from fluxdrive_bringup.record.recorder import DEFAULT_TOPICS
from fluxdrive_ros import topics

MODES = ("host", "split")
# the drive's exit ends the run, and nothing else of this graph ends by itself (no plant, so
# no /drive/done): the graph's stop_grace_s (default 20 s) would pass idle every run.  The
# lockstep drive has its answers of all but its last sample when it exits; this is time for
# that last sample's frame, estimate and answer -- the stop then hands the recorder what
# each node published (fluxdrive_bringup.launch.launcher)
STOP_GRACE_S = 3.0
SWEEP_RESULTS = REPO_ROOT / "results" / "can" / "sil_current_sweep.json"
PIL_RESULTS = REPO_ROOT / "results" / "can" / "pil_vs_sil.json"


def _drive_node(
    sp: Path, sc, mcu: str, group: str, port: int, d: int, truth_out, inject: str | None = None
) -> NodeSpec:
    """The drive of the graph: `can-emulator` (plant + C core or the virtual board) on the
    run's udp_multicast group, lockstep, its truth recorded to `truth_out`; `inject`: a
    fault case injected (`CASE@T`, fluxdrive.can.faultcases)."""
    cmd = [sys.executable, "-m", "fluxdrive.cli", "can-emulator", str(sp), "--mcu", mcu]
    cmd += ["--interface", "udp_multicast", "--channel", group, "--port", str(port)]
    cmd += ["--hop-limit", "0", "--decimation", str(d), "--duration", repr(float(sc.duration_s))]
    cmd += ["--lockstep-wait", "1.0", "--wait-armed", "120", "--record-out", str(truth_out)]
    cmd += ["--inject", inject] if inject else []
    return NodeSpec(name="drive", cmd=cmd, required=True)


def sil_graph(
    sp: Path,
    sc,
    bag: Path,
    *,
    mode: str,
    decimation: int,
    domain_id: int,
    truth_out,
    mcu="c",
    inject: str | None = None,
):
    """The lockstep graph of `sc` with the plant replaced by the C drive on a udp_multicast
    bus and the bench_bridge node. `mcu`: "c" (the core's host build, SIL) or "pil" (the
    board image on the virtual board, processor in the loop)."""
    group, port = software_bus_endpoint()
    d = int(decimation)
    ctrl = {"control_mode": mode, "decimation": d}
    extra = {"controller": ctrl, **{nm: {"decimation": d} for nm in sc.observers}}
    g = graph_for_scenario(sp, sc, bag, "separate", None, domain_id, extra=extra)
    g.name = f"{sc.name}-sil"
    # the bridge's sample stamps are seq * D * ts_s on the wall clock's graph: no /clock
    for n in g.nodes:
        n.parameters["use_sim_time"] = False
        if n.node == "recorder":
            n.parameters["exit_on_done"] = False  # the drive's exit ends the run
            n.parameters.pop("duration_s", None)
            if mode == "split":  # the controller's answers are current references
                n.parameters["topics"] = [*DEFAULT_TOPICS, topics.rel(topics.CURRENT_REF)]
    g.nodes = [n for n in g.nodes if n.node != "plant"]
    emulator = _drive_node(sp, sc, mcu, group, port, d, truth_out, inject)
    bridge_params = {
        "interface": "udp_multicast",
        "channel": group,
        "decimation": d,
        "control_split": mode == "split",
        "scenario": str(sp),
        "ts_s": float(sc.machine.ts_s),
        "armed": True,
        "stale_timeout_s": 30.0,
        "arm_wait_s": 120.0,
    }
    if inject and _before_arming(inject):  # the uncalibrated arming is what is injected
        bridge_params["calibrate_before_arming"] = False
    ros_args = [
        f"{k}:={str(v).lower() if isinstance(v, bool) else v}" for k, v in bridge_params.items()
    ]
    if inject and "," in inject:  # a schedule: the operator resets and re-arms in between
        ros_args.append(f"allowed_commanders:=['/controller', '/{OPERATOR_NODE}']")
    bridge = NodeSpec(
        name="bench_bridge",
        cmd=[
            sys.executable,
            "-m",
            "bench_bridge.bridge_node",
            "--ros-args",
            *[a for kv in ros_args for a in ("-p", kv)],
        ],
    )
    g.nodes = [emulator, bridge, *g.nodes]
    g.stop_grace_s = STOP_GRACE_S
    g.env["CAN_CONFIG"] = json.dumps({"port": port, "hop_limit": 0})
    return g


def _before_arming(inject: str) -> bool:
    """The (first) injected case is one before arming (fluxdrive.can.faultcases)."""
    from fluxdrive.can.faultcases import case

    try:
        return case(inject.split(",")[0].split("@")[0].strip()).before_arming
    except (KeyError, ValueError):
        return False


def _parser() -> Parser:
    """The options of `fluxdrive bench --sil/--pil`."""
    ap = Parser(prog="fluxdrive bench", description=__doc__.split("\n\n")[0])
    kind = ap.add_mutually_exclusive_group(required=True)
    kind.add_argument("--sil", action="store_true", help="software in the loop")
    kind.add_argument(
        "--pil",
        action="store_true",
        help="processor in the loop: the board image that would be flashed, on the virtual "
        f"board (fluxdrive.can.vboard; D in {BOARD_DECIMATIONS})",
    )
    ap.add_argument("scenario", nargs="?", default="paper_2pct_150load")
    ap.add_argument("--machine", help=MACHINE_HELP)
    ap.add_argument("--mode", choices=MODES, default="split", help="where the current loop runs")
    option(ap, "--decimation", LinkOptions)
    option(ap, "--duration", ScenarioSettings, "duration_s", default=None)
    ap.add_argument("--bag", type=Path, help="bag folder (default bags/<name>-sil-<time>)")
    option(ap, "--domain-id", GraphSettings)
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument(
        "--inject",
        default=None,
        metavar="CASE@T",
        help="inject a drive protection's condition at T s of drive time (a case of "
        "fluxdrive.can.faultcases); prints the drive's reaction instead of the metrics, "
        "exit 0 if it latched the case's fault within its bound",
    )
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument(
        "--sweep-current",
        action="store_true",
        help="instead of SCENARIO: Fig. 17's d-axis current sweep at 10 %% speed through the "
        "whole bench (split mode); prints the -3 dB bandwidth, last line JSON, and writes "
        f"{SWEEP_RESULTS.relative_to(REPO_ROOT)}",
    )
    ap.add_argument(
        "--versus-sil",
        action="store_true",
        help="with --pil: run SCENARIO on the SIL bench first, then on the virtual board, and "
        f"write both θ̃ RMS to {PIL_RESULTS.relative_to(REPO_ROOT)} (last line JSON); the whole "
        "scenario over its own steady window unless --duration cuts it",
    )
    return ap


def main(argv: list[str]) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if not 1 <= args.decimation <= 64:
        print("[bench] --decimation must be in 1..64", file=sys.stderr)
        return 2
    if args.pil and args.decimation not in BOARD_DECIMATIONS:
        print(
            f"[bench] --pil: the board image is built for --decimation in {BOARD_DECIMATIONS}, "
            f"not {args.decimation}",
            file=sys.stderr,
        )
        return 2
    if args.sweep_current:
        return sweep_current(args)
    sp = scenario_path(args.scenario)
    if args.machine is not None:  # the drive process and the nodes read it on this motor
        tag = "pil" if args.pil else "sil"
        stem = f"{sp.stem}-{Path(args.machine).stem}-{tag}-{time.strftime('%Y%m%d-%H%M%S')}"
        args.bag = args.bag or REPO_ROOT / "bags" / stem
        sp, sc = scenario_on_machine(sp, args.machine, Path(str(args.bag) + "-report"))
        print(f"[bench] {sc.machine_note}", flush=True)
    sc = load_scenario(sp)
    shorten(sc, args.duration)
    if args.versus_sil:
        if not args.pil or args.inject:
            print("[bench] --versus-sil goes with --pil and no --inject", file=sys.stderr)
            return 2
        return versus_sil(sp, sc, args)
    if args.inject:
        from fluxdrive.can.faultcases import parse_injections

        try:
            parse_injections(args.inject, sc.machine.ts_s)
        except ValueError as exc:
            print(f"[bench] {exc}", file=sys.stderr)
            return 2
    code, res, arr, out = run_sil(sp, sc, args)
    if args.inject:
        report_dir = Path(str(args.bag_used) + "-report")
        return code or injection_result(args.inject, report_dir / "logs" / "drive.log")
    if res is None:
        return code
    from fluxdrive.analysis.report import report

    m = report(res, out, plots=False)
    print(f"[bench] bag: {args.bag_used}")
    return 0 if m.get("stable", True) and not arr["missing_real"] else 1


def versus_sil(sp: Path, sc, args) -> int:
    """`bench --pil --versus-sil`: the same scenario, mode and D on the SIL bench (the C
    core's host build) and then with the board image on the virtual board; each run's θ̃
    RMS of the driving observer from its bag, their difference, every sample present;
    written to PIL_RESULTS under "<mode>_d<D>" (other entries kept)."""
    from fluxdrive.analysis.metrics import compute

    runs: dict[str, dict] = {}
    for tag in ("sil", "pil"):
        args.pil = tag == "pil"
        args.bag = None
        code, res, arr, _out = run_sil(sp, sc, args)
        if res is None:
            return code
        m = compute(res)
        bag = Path(args.bag_used)
        runs[tag] = {
            "theta_rms_deg": round(float(m["observers"][sc.driving]["theta_err_rms_deg"]), 4),
            "stable": bool(m["stable"]),
            "samples": int(arr["n"]),
            "missing_samples": arr["missing_real"],
            "bag": str(bag.relative_to(REPO_ROOT) if bag.is_relative_to(REPO_ROOT) else bag),
        }
    diff = runs["pil"]["theta_rms_deg"] - runs["sil"]["theta_rms_deg"]
    entry = {
        "scenario": sc.name,
        "duration_s": float(sc.duration_s),
        "steady_window_s": [float(x) for x in sc.steady_window_s],
        "mode": args.mode,
        "decimation": int(args.decimation),
        "observer": sc.driving,
        **runs,
        "pil_minus_sil_deg": round(diff, 4),
        "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "never_run_on_hardware": True,
    }
    table = json.loads(PIL_RESULTS.read_text()) if PIL_RESULTS.exists() else {}
    table[f"{args.mode}_d{int(args.decimation)}"] = entry
    PIL_RESULTS.parent.mkdir(parents=True, exist_ok=True)
    PIL_RESULTS.write_text(json.dumps(table, indent=2, sort_keys=True) + "\n")
    ok = all(not r["missing_samples"] for r in runs.values())
    print(
        f"[bench] theta~ RMS ({sc.driving}): SIL {runs['sil']['theta_rms_deg']:.3f} deg, "
        f"virtual board {runs['pil']['theta_rms_deg']:.3f} deg ({diff:+.3f}); "
        f"written {PIL_RESULTS.relative_to(REPO_ROOT)}"
    )
    print(json.dumps(entry))
    return 0 if ok else 1


def run_sil(sp: Path, sc, args):
    """Run `sc` (saved at `sp`) on the SIL bench; (exit code, SimResult or None, the bag's
    arrays, report folder). Missing samples are printed and kept in arr["missing_real"]."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    tag = "pil" if getattr(args, "pil", False) else "sil"
    bag = args.bag or REPO_ROOT / "bags" / f"{sc.name}-{tag}-{stamp}"
    args.bag_used = bag
    if Path(bag).exists():
        print(f"[bench] bag directory {bag} exists already; choose a new one (--bag)")
        return 2, None, None, None
    if tag == "pil":  # built here, not inside the drive's process while the graph waits
        from fluxdrive.can.vboard import build_board

        build_board()
    dom, why = choose_domain(args.domain_id, "bench")
    if dom is None:
        print(f"[bench] {why}", file=sys.stderr)
        return 2, None, None, None
    out = Path(str(bag) + "-report")
    out.mkdir(parents=True, exist_ok=True)
    truth_out = out / "truth.npy"
    g = sil_graph(
        sp,
        sc,
        bag,
        mode=args.mode,
        decimation=args.decimation,
        domain_id=dom,
        truth_out=truth_out,
        mcu="pil" if tag == "pil" else "c",
        inject=getattr(args, "inject", None),
    )
    (out / "graph.yaml").write_text(yaml.safe_dump(g.to_dict(), sort_keys=False))
    print(
        f"[bench] {sc.name}: "
        + ("board image on the virtual board" if tag == "pil" else "C drive")
        + f" + plant, {args.mode} mode, D={args.decimation}, "
        f"{sc.duration_s:g} s, ROS_DOMAIN_ID={dom}; graph: {out / 'graph.yaml'}",
        flush=True,
    )
    t0 = time.perf_counter()
    launcher = Launcher(g, quiet=args.quiet, progress=False, log_dir=out / "logs")
    operator = None
    if "," in (getattr(args, "inject", None) or ""):
        operator = InjectionOperator(dom)
        operator.start()
    try:
        code = launcher.run(args.timeout)
    finally:
        if operator is not None:
            operator.stop()
    wall = time.perf_counter() - t0
    if code != 0 or not truth_out.exists():
        print(
            f"[bench] the bench failed (exit {code}){launcher.failure_text()}; logs in "
            f"{out / 'logs'}",
            file=sys.stderr,
        )
        return code or 1, None, None, None
    res, arr = result_from_sil_bag(bag, sc, args.decimation, truth_out, wall)
    # truth: from the drive's process; duty: split mode answers with current references
    skip = {"truth", "duty"} if args.mode == "split" else {"truth"}
    miss = {k: v for k, v in arr["missing"].items() if v and k not in skip}
    print(
        f"[bench] {arr['n']} samples in {wall:.1f} s wall"
        + (f"; MISSING samples: {miss}" if miss else "; every sample of every topic present")
    )
    arr["missing_real"] = miss
    note_can_link(bag)
    return 0, res, arr, out


def injection_result(inject: str, drive_log: Path) -> int:
    """The drive's reaction to each case of `inject` (its last log line, the JSON of
    can-emulator): one line per case, the last line JSON (a list of outcomes); 0 if every
    requirement of every case held."""
    from fluxdrive.can.faultcases import NOT_MADE, case, outcome

    cases = [case(p.partition("@")[0].strip()) for p in inject.split(",")]
    lines = drive_log.read_text().splitlines() if drive_log.is_file() else []
    stats = next((json.loads(x) for x in reversed(lines) if x.startswith("{")), None)
    if stats is None:
        print(f"[bench] --inject {inject}: no final report of the drive in {drive_log}")
        return 1
    recs = stats["injections"]
    out = []
    for i, fc in enumerate(cases):
        res = outcome(fc, recs[i] if i < len(recs) else NOT_MADE)
        bad = [k for k, ok in res["checks"].items() if not ok]
        print(
            f"[bench] injected {fc.name} ({res['level']}): PWM off after {res['reaction']} "
            f"periods (bound {res['bound']}), FAULT codes {res['fault_codes'][:3]}"
            + (f"; NOT MET: {', '.join(bad)}" if bad else "")
        )
        out.append(res)
    print(json.dumps(out))
    return 0 if all(r["ok"] for r in out) else 1


class InjectionOperator:
    """The operator of an injection schedule (`--inject A@T,B,C`), as node
    /fluxdrive_operator: after each drive fault the bridge reports (a latched DriveFault from
    the drive), it asks the bridge's /drive/reset_fault until the drive reports the fault
    cleared (the drive removes the condition INJECT_HOLD periods after its PWM went off),
    clears the controller's latch if it has one (/controller/reset_fault: repeated lost
    intervals latch it), and re-arms (/drive/arm) -- what a person at the bench does."""

    def __init__(self, domain_id: int) -> None:
        import threading

        self.domain_id = domain_id
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="operator", daemon=True)
        self.resets = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(15.0)

    def _run(self) -> None:
        from collections import deque

        from flux_drive_msgs.msg import DriveFault
        from flux_drive_msgs.srv import Arm, ResetFault
        from fluxdrive_bringup.inspect.commands import OPERATOR_NODE, Session, _call
        from fluxdrive_ros import qos as fluxdrive_qos

        s = Session(domain_id=self.domain_id, node_name=OPERATOR_NODE, wait_s=3.0)
        events: deque = deque()
        # as the bridge offers it (transient local): a fault latched before this reader
        # matched the bridge's writer (the first case, early in the run) still reaches it
        s.node.create_subscription(
            DriveFault, "/drive/fault", lambda m: events.append(m), fluxdrive_qos.MARKERS
        )
        latched = False
        try:
            while not self._stop.is_set():
                s.spin_for(0.05)
                while events:
                    ev = events.popleft()
                    if ev.source.startswith("drive via"):
                        latched = bool(ev.latched)
                        if latched:  # as a person would: not before the condition is gone
                            s.spin_for(0.2)
                        if not latched and not self._stop.is_set():  # cleared: re-arm
                            _call(s, ResetFault, "/controller/reset_fault", ResetFault.Request())
                            _call(s, Arm, "/drive/arm", Arm.Request(arm=True))
                if latched and not self._stop.is_set():
                    _call(s, ResetFault, "/drive/reset_fault", ResetFault.Request())
                    self.resets += 1
                    s.spin_for(0.1)
        except Exception as exc:  # noqa: BLE001 - the graph is going down: said, not raised
            if not self._stop.is_set():
                print(f"[bench] operator: {exc}", file=sys.stderr)
        finally:
            s.close()


# the bench bridge's counts of what it took and dropped


# the bench bridge's counts of what it took and dropped (fluxdrive.can.bridge diagnostics)
CAN_LINK_COUNTS = (
    "frames_out",
    "seq_gaps",
    "seq_lost",
    "seq_duplicates",
    "seq_out_of_order",
    "seq_jumps",
    "seq_rejected",
    "malformed",
    "rx_other",
)


def note_can_link(bag: Path) -> dict[str, int]:
    """The bench bridge's last reported link counts (its /diagnostics in the bag): printed
    and kept in the bag's metadata (custom_data fluxdrive_can_link)."""
    from fluxdrive.io.bagio import CAN_LINK_KEY, last_status, note_custom

    vals = last_status(bag, "bench_bridge")
    link = {k: int(vals[k]) for k in CAN_LINK_COUNTS if vals.get(k, "").lstrip("-").isdigit()}
    if link:
        note_custom(bag, CAN_LINK_KEY, link)
        print(
            "[bench] CAN link (the bridge's last report): "
            + ", ".join(f"{k} {v}" for k, v in link.items())
        )
    return link


def sweep_current(args) -> int:
    """Fig. 17's d-axis sweep in split mode through the whole bench: i_d (the host's Park of
    the drive's samples, in the frame of the reference it sends) against i_d* at D*Ts, over
    the sweep frequencies below the sample rate's Nyquist frequency."""
    from fluxdrive.analysis.freqresp import analyse
    from fluxdrive.cli.hostbench import SWEEP_HZ, current_sweep_scenario, split_current_bandwidth_hz
    from fluxdrive.core.excitation import Segment
    from fluxdrive.drive.control import CO_ID, CO_ID_REF
    from fluxdrive.drive.scenario import save_scenario

    d = int(args.decimation)
    probe = current_sweep_scenario(d)
    nyquist_hz = 0.5 * probe.machine.pwm_hz / d
    freqs = [f for f in SWEEP_HZ if f < nyquist_hz]
    sc = current_sweep_scenario(d, freqs_hz=freqs)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    work = REPO_ROOT / "runs" / f"sil-current-sweep-{stamp}"
    work.mkdir(parents=True, exist_ok=True)
    sp = save_scenario(sc, work / "current_sweep.yaml")
    sc = load_scenario(sp)
    args.mode = "split"
    args.bag = args.bag or work / "bag"
    code, res, arr, _ = run_sil(sp, sc, args)
    if res is None:
        return code
    ctrl = arr["ctrl"]
    segs = [
        Segment(s.frequency_hz, -(-s.k_start // d), s.k_end // d) for s in res.segments["current_d"]
    ]
    fr = analyse(ctrl[:, CO_ID], ctrl[:, CO_ID_REF], segs, sc.machine.ts_s * d)
    bw = float(fr["bandwidth_hz"])
    passed = [f for f, g in zip(fr["frequency_hz"], fr["gain_db"], strict=True) if g > -3.0]
    out = {
        "decimation": d,
        "sample_rate_hz": round(sc.machine.pwm_hz / d, 1),
        "frequency_hz": fr["frequency_hz"],
        "gain_db": [round(g, 2) for g in fr["gain_db"]],
        "coherence": [round(c, 3) for c in fr["coherence"]],
        # -3 dB crossing; none within the swept band: the bandwidth is at least its top
        "graph_bandwidth_hz": round(bw, 1) if math.isfinite(bw) else None,
        "graph_bandwidth_at_least_hz": round(bw, 1) if math.isfinite(bw) else max(passed),
        "in_process_bandwidth_hz": split_current_bandwidth_hz(d, True),
        "missing_samples": arr["missing_real"],
        "bag": str(args.bag_used),
    }
    SWEEP_RESULTS.parent.mkdir(parents=True, exist_ok=True)
    SWEEP_RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out))
    return 0 if not arr["missing_real"] else 1


def result_from_sil_bag(bag: Path, sc, decimation: int, truth_npy: Path, wall_s: float = 0.0):
    """SimResult at the sample rate (D * ts_s) from a SIL bag and the drive's true state."""
    from fluxdrive.drive.control import CO_W_REF
    from fluxdrive.drive.plant import TR_T
    from fluxdrive.drive.sim import DriveSetup, SimResult
    from fluxdrive.io.bagio import load_run_arrays

    d = int(decimation)
    ds = DriveSetup(sc)
    arr = load_run_arrays(bag, ds.ts * d, names=list(sc.observers))
    n = arr["n"]
    truth = np.load(truth_npy)[::d][:n]
    arr["truth"][: len(truth)] = truth
    arr["truth"][:, TR_T] = np.arange(n) * ds.ts * d
    w_ref = arr["ctrl"][:, CO_W_REF].copy()
    bad = ~np.isfinite(w_ref)
    w_ref[bad] = 0.0
    res = SimResult(
        sc,
        list(sc.observers),
        sc.driving,
        np.arange(n) * ds.ts * d,
        arr["frames"],
        arr["truth"],
        arr["est"],
        arr["ctrl"],
        w_ref,
        ds.id_inj[::d][:n],
        ds.segments,
        wall_s,
    )
    return res, arr
