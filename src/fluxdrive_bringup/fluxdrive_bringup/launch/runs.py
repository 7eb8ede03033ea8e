"""A scenario through the ROS graph: `./fluxdrive run SCENARIO.yaml` and `./fluxdrive demo`.

1. the graph for the scenario: the plant (lockstep), one observer node per scenario
   observer (/obs/<name>, the driving one and the shadows), the controller (position from
   the driving observer's estimate topic, or the encoder), the recorder;
2. launched (fluxdrive_bringup.launch.launcher) with a domain of its own; the plant waits until
   every frame subscriber and the duty publisher are matched (plus a settling delay) before
   its first frame, and all per-sample topics are transient-local, so nothing published
   during discovery is lost;
3. the run goes to the end (progress line), every node exits after /drive/done, the
   recorder finalises the bag;
4. the bag is read back into the engine's arrays and reported with the same code as
   `./fluxdrive sim` (fluxdrive.analysis.report: metric table, metrics.json, plots).

Process layouts (`--layout`):
  composed  (default) every node in one process, like an rclcpp component container: one
            DDS participant, deliveries between the nodes in-process (fluxdrive_ros.intra),
            the bag written by the recorder's helper process on the other core; every topic
            is still on DDS for anything outside (topic echo, param set, a remote node);
  split     the drive nodes in one process, the recorder in another (all recording over DDS);
  separate  one process per node, the classic ROS layout (everything over DDS; slowest).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from fluxdrive.core.paths import check_output
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.scenario import (
    MACHINE_HELP,
    REPO_ROOT,
    ScenarioSettings,
    load_scenario,
    scenario_on_machine,
    scenario_path,
)
from fluxdrive.io.graphfile import GraphSettings, ServeOptions

from fluxdrive_bringup.launch.domains import choose_domain, pick_domain_id
from fluxdrive_bringup.launch.launcher import Graph, Launcher, NodeSpec, check_namespace

LAYOUTS = ("composed", "split", "separate")
# frames a shadow observer collects per kernel call (5 ms at 10 kHz)
SHADOW_BLOCK_FRAMES = 500
DEMO_SCENARIO = "paper_2pct_150load"


def graph_for_scenario(
    sc_path: Path,
    sc,
    bag_dir: Path | None,
    layout: str = "composed",
    duration_s: float | None = None,
    domain_id: int | None = None,
    start_delay_s: float = 0.5,
    extra: dict | None = None,
    namespace: str = "",
) -> Graph:
    """The lockstep graph of a scenario.  `extra` = {node name: {param: value}};
    `namespace`: the whole drive in it (/a: /a/drive/frame, /a/obs/<name>, ...)."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    names = list(sc.observers)
    sp = str(Path(sc_path).resolve())
    dur = {} if duration_s is None else {"duration_s": float(duration_s)}
    n_frame_subs = len(names) + 1 + (1 if bag_dir is not None else 0)

    def proc(name: str, group: str) -> str:
        return {
            "composed": "drive",
            "split": "recorder" if group == "rec" else "drive",
            "separate": name,
        }[layout]

    nodes = [
        NodeSpec(
            name="plant",
            node="plant",
            process=proc("plant", "plant"),
            parameters={
                "scenario": sp,
                "wait_frame_subscribers": n_frame_subs,
                "wait_duty_publishers": 1,
                "start_delay_s": start_delay_s,
                **dur,
            },
        )
    ]
    for nm in names:
        # shadows off the per-sample path: nothing waits for their estimates
        shadow = {} if nm == sc.driving else {"block_frames": SHADOW_BLOCK_FRAMES}
        nodes.append(
            NodeSpec(
                name=nm,
                node="observer",
                namespace="/obs",
                process=proc(f"obs_{nm}", "obs"),
                parameters={"scenario": sp, "observer": nm, **shadow},
            )
        )
    nodes.append(
        NodeSpec(
            name="controller",
            node="controller",
            process=proc("controller", "ctrl"),
            parameters={"scenario": sp},
        )
    )
    if bag_dir is not None:
        nodes.append(
            NodeSpec(
                name="recorder",
                node="recorder",
                process=proc("recorder", "rec"),
                parameters={"bag_dir": str(bag_dir), "observers": names, "scenario": sp, **dur},
            )
        )
    for n in nodes:
        # late-matched readers still get the first samples (lockstep must lose nothing)
        n.parameters["input_durability"] = "transient_local"
        # ROS time = the drive's sim time, the plant's /clock (the plant included: its own
        # stamps, e.g. of /diagnostics, then agree with the samples)
        n.parameters["use_sim_time"] = True
        n.parameters.update((extra or {}).get(n.name, {}))
    return Graph(name=f"{sc.name}-lockstep", nodes=nodes, domain_id=domain_id, namespace=namespace)


def shorten(sc, duration_s: float | None) -> None:
    """Cut a scenario to `duration_s`; a steady window beyond the end becomes the second
    half of the run."""
    if duration_s is None:
        return
    sc.duration_s = float(duration_s)
    w0, w1 = sc.steady_window_s
    if w1 > duration_s + 1e-9:
        sc.steady_window_s = (0.5 * duration_s, float(duration_s))


def result_from_bag(bag: Path, sc, duration_s: float | None = None, wall_s: float = 0.0):
    """fluxdrive.drive.sim.SimResult from a graph run's bag (the report's input)."""
    from fluxdrive.drive.control import CO_W_REF
    from fluxdrive.drive.sim import DriveSetup, SimResult
    from fluxdrive.io.bagio import load_run_arrays

    shorten(sc, duration_s)
    ds = DriveSetup(sc)
    arr = load_run_arrays(bag, ds.ts, names=list(sc.observers))
    n = arr["n"]
    ctrl = arr["ctrl"]
    w_ref = ctrl[:, CO_W_REF].copy()
    bad = ~np.isfinite(w_ref)
    w_ref[bad] = ds.w_ref[:n][bad] if n <= len(ds.w_ref) else 0.0
    res = SimResult(
        sc,
        list(sc.observers),
        sc.driving,
        np.arange(n) * ds.ts,
        arr["frames"],
        arr["truth"],
        arr["est"],
        ctrl,
        w_ref,
        ds.id_inj[:n],
        ds.segments,
        wall_s,
    )
    return res, arr


def run_graph(
    sc_path: Path,
    *,
    out: Path,
    bag: Path | None,
    layout: str = "composed",
    duration_s: float | None = None,
    domain_id: int | None = None,
    quiet: bool = False,
    timeout: float | None = None,
    extra: dict | None = None,
    progress: bool = True,
    scope: bool = False,
    scope_port: int = 8765,
    watch=None,
    namespace: str = "",
    shared_domain: bool = False,
) -> dict:
    """Launch the lockstep graph of a scenario, wait for the end.  Returns a summary dict
    (exit code, wall time, real-time factor, bag path).  scope: with the live scope
    (launch.add_scope); watch: called in a thread with the Launcher once it starts;
    bag None: no recorder."""
    sc = load_scenario(sc_path)
    shorten(sc, duration_s)
    dom = pick_domain_id() if domain_id is None else domain_id
    g = graph_for_scenario(
        sc_path, sc, bag, layout, duration_s, dom, extra=extra, namespace=namespace
    )
    g.shared_domain = shared_domain  # its /clock: the graph's own (Launcher.clock_topic)
    if scope:
        from fluxdrive_bringup.launch.launcher import add_scope

        add_scope(g, port=scope_port, exit_on_done=True, observers=list(sc.observers))
    out.mkdir(parents=True, exist_ok=True)
    (out / "graph.yaml").write_text(yaml.safe_dump(g.to_dict(), sort_keys=False))
    print(
        f"[run] {sc.name}: {sc.n_periods} periods ({sc.duration_s:g} s) through the graph, "
        f"layout {layout} ({', '.join(g.processes())}), ROS_DOMAIN_ID={dom}; "
        f"graph: {out / 'graph.yaml'}",
        flush=True,
    )
    launcher = Launcher(g, quiet=quiet, progress=progress, log_dir=out / "logs")
    if launcher.clock_topic != "/clock" and not namespace:
        print(f"[run] shared domain: this graph's sim time is on {launcher.clock_topic}")
    if watch is not None:
        import threading

        threading.Thread(target=watch, args=(launcher,), daemon=True).start()
    t0 = time.perf_counter()
    code = launcher.run(timeout)
    wall = time.perf_counter() - t0
    prog = launcher.progress
    rtf = None
    if prog and prog[2] > 0:
        rtf = prog[0] * sc.machine.ts_s / prog[2]
    return {
        "code": code,
        "wall_s": wall,
        "lockstep_rtf": rtf,
        "interrupted": launcher.interrupted,
        "stop_signal": launcher.stop_signal,
        "frames": prog[0] if prog else 0,
        "loop_wall_s": prog[2] if prog else None,
        "bag": str(bag),
        "scenario": sc,
        "graph": g,
        "domain_id": dom,
    }


def interrupted_bag_note(bag: Path) -> str:
    """What an interrupted run left: the frames the finalised bag holds (counted from the
    bag itself -- the plant's last progress report lags the recorder)."""
    from fluxdrive.io.bagio import topic_counts
    from fluxdrive.io.topics import FRAME

    try:
        n = topic_counts(bag).get(FRAME, 0)
    except Exception as exc:  # noqa: BLE001 - not finalised / damaged: say so
        return (
            f"bag {bag} is not readable ({type(exc).__name__}); try ./fluxdrive bag recover {bag}"
        )
    return f"the bag holds {n} frames (finalised): {bag}"


def main_run(argv: list[str], default_scenario: str | None = None) -> int:
    args = _run_parser(default_scenario).parse_args(argv)
    sp = scenario_path(args.scenario if default_scenario is None else default_scenario)
    sc = load_scenario(sp, machine=args.machine)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = check_output(args.out or REPO_ROOT / "runs" / f"{sc.name}-{stamp}", "--out")
    if args.machine is not None:  # the graph's nodes read the scenario on this motor
        sp, sc = scenario_on_machine(sp, args.machine, out)
        print(f"[run] {sc.machine_note}", flush=True)
    bag = args.bag or REPO_ROOT / "bags" / f"{sc.name}-{stamp}"
    dom, refused = _run_preflight(args, bag)
    if refused:
        print(f"[run] {refused}", file=sys.stderr)
        return 2
    r = run_graph(
        sp,
        out=out,
        bag=bag,
        layout=args.layout,
        duration_s=args.duration,
        domain_id=dom,
        quiet=args.quiet,
        timeout=args.timeout,
        scope=args.scope,
        scope_port=args.scope_port,
        watch=_print_scope_url if args.scope and args.quiet else None,
        namespace=check_namespace(args.namespace, "--namespace"),
        shared_domain=args.shared_domain,
    )
    failed = _run_outcome(r, out, bag)
    if failed is not None:
        return failed
    return _run_report(args, r, out, bag)


def _run_parser(default_scenario: str | None) -> argparse.ArgumentParser:
    ap = Parser(
        prog="fluxdrive run" if default_scenario is None else "fluxdrive demo",
        description=__doc__.split("\n\n")[0],
    )
    if default_scenario is None:
        ap.add_argument("scenario", help="scenario YAML (path, or a name under config/scenarios)")
    ap.add_argument("--machine", help=MACHINE_HELP)
    ap.add_argument("--out", type=Path, help="report folder (default runs/<name>-<time>)")
    ap.add_argument("--bag", type=Path, help="bag folder (default bags/<name>-<time>)")
    option(
        ap,
        "--duration",
        ScenarioSettings,
        "duration_s",
        default=None,
        help="simulate only this long (default: the scenario's duration_s)",
    )
    ap.add_argument(
        "--layout",
        choices=LAYOUTS,
        default="composed",
        help="process layout of the graph (default composed)",
    )
    option(
        ap,
        "--domain-id",
        GraphSettings,
        help="ROS_DOMAIN_ID (default: environment's, else a random one)",
    )
    ap.add_argument("--timeout", type=float, help="give up after this many seconds")
    ap.add_argument(
        "--namespace",
        default="",
        help="put the whole drive in this ROS namespace (e.g. /bench_a); the bag reads as "
        "a root-namespace run's",
    )
    ap.add_argument("--quiet", action="store_true", help="hide the nodes' log lines")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument(
        "--scope",
        action="store_true",
        help="watch it live: start the scope (prints its URL; see ./fluxdrive scope)",
    )
    option(
        ap,
        "--scope-port",
        ServeOptions,
        "port",
        help="the scope's TCP port (default 8765; 0: any free port)",
    )
    ap.add_argument(
        "--shared-domain",
        action="store_true",
        help="run even if other nodes "
        "live on the ROS domain (by default refused: graphs on one domain hear "
        "each other)",
    )
    return ap


def _run_preflight(args, bag: Path) -> tuple[int | None, str]:
    """Before anything starts: (the ROS domain, "") or (None, why the run is refused)."""
    if Path(bag).exists():
        # a failed run must never be mistaken for this old bag
        return None, f"bag directory {bag} exists already; choose a new one (--bag)"
    check_output(bag, "--bag", new=True)
    from fluxdrive_ros.security import precheck

    why = precheck()
    if why:
        return None, why
    dom = args.domain_id
    if not args.shared_domain:
        dom, why = choose_domain(args.domain_id, "run")
        if dom is None:
            return None, why
    return dom, ""


def _run_outcome(r: dict, out: Path, bag: Path) -> int | None:
    """The exit code of an interrupted or failed run (said why), None when it completed."""
    if r["interrupted"]:
        print(f"[run] interrupted: {interrupted_bag_note(bag)}", file=sys.stderr)
        return 128 + int(r.get("stop_signal") or 2)  # 130 (SIGINT) / 143 (SIGTERM)
    if r["code"] != 0:
        print(f"[run] the graph failed (exit {r['code']}); logs in {out / 'logs'}", file=sys.stderr)
        if Path(bag).exists():
            print(f"[run] partial bag: {bag}", file=sys.stderr)
        return r["code"]
    if r["lockstep_rtf"] is not None:
        print(
            f"[run] lockstep loop: {r['frames']} frames in {r['loop_wall_s']:.2f} s wall = "
            f"real-time factor {r['lockstep_rtf']:.3f} (whole command {r['wall_s']:.1f} s "
            f"incl. start-up and finalising)"
        )
    return None


def _run_report(args, r: dict, out: Path, bag: Path) -> int:
    """The bag read back, the report and graph_run.json; 1 when unstable or incomplete."""
    from fluxdrive.analysis.report import report

    t0 = time.perf_counter()
    res, arr = result_from_bag(bag, r["scenario"], args.duration, r["loop_wall_s"] or 0.0)
    miss = {k: v for k, v in arr["missing"].items() if v}
    print(
        f"[run] bag read back in {time.perf_counter() - t0:.1f} s: {arr['n']} frames"
        + (f"; MISSING samples: {miss}" if miss else "; every sample of every topic present")
    )
    m = report(res, out, plots=not args.no_plots)
    summary = {
        "scenario": r["scenario"].name,
        "bag": str(bag),
        "layout": args.layout,
        "domain_id": r["domain_id"],
        "frames": arr["n"],
        "missing": arr["missing"],
        "lockstep_rtf": r["lockstep_rtf"],
        "loop_wall_s": r["loop_wall_s"],
        "command_wall_s": r["wall_s"],
    }
    (out / "graph_run.json").write_text(json.dumps(summary, indent=2))
    print(f"[run] bag: {bag}")
    return 0 if m.get("stable", True) and not miss else 1


def _print_scope_url(launcher) -> None:
    """--quiet hides the nodes' lines: still say where the scope is."""
    t_end = time.monotonic() + 60.0
    while not launcher.scope_urls and time.monotonic() < t_end:
        time.sleep(0.1)
    if launcher.scope_urls:
        print(f"[run] scope: {launcher.scope_urls[0]}", flush=True)


def main_demo(argv: list[str]) -> int:
    return main_run(argv, default_scenario=DEMO_SCENARIO)


# ---------------------------------------------------------------- experiments --graph
def graph_run(sc, keep: bool = False):
    """One scenario through the lockstep node graph -> SimResult (read back from the bag);
    the runner `./fluxdrive experiment --graph` installs in the engine's registry."""
    import shutil
    import tempfile

    from fluxdrive.drive.scenario import save_scenario

    d = Path(tempfile.mkdtemp(prefix=f"fluxdrive-exp-graph-{sc.name}-"))
    sp = save_scenario(sc, d / f"{sc.name}.yaml")
    r = run_graph(
        sp,
        out=d / "run",
        bag=d / "bag",
        quiet=True,
        progress=False,
        timeout=max(600.0, 30.0 * sc.duration_s),
    )
    if r["code"] != 0:
        raise RuntimeError(
            f"graph run of {sc.name} failed (exit {r['code']}); logs in {d / 'run' / 'logs'}"
        )
    res, arr = result_from_bag(d / "bag", load_scenario(sp), wall_s=r["loop_wall_s"] or 0.0)
    missing = {k: v for k, v in arr["missing"].items() if v}
    if missing:
        raise RuntimeError(
            f"graph run of {sc.name}: samples missing from the bag {missing} ({d / 'bag'})"
        )
    if not keep:
        shutil.rmtree(d, ignore_errors=True)
    return res


def main_experiment_graph(argv: list[str]) -> int:
    """`./fluxdrive experiment ... --graph`: the engine's experiments, every run on the graph."""
    from fluxdrive.cli import experiment

    return experiment.main(argv, graph_run=graph_run)
