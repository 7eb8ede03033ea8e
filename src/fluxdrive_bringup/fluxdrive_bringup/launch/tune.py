"""`./fluxdrive tune`: a steady operating point (speed, load) held paced until Ctrl-C, for
live tuning (`./fluxdrive param set ...`, `--scope`).

The graph is the scenario's (fluxdrive_bringup.launch.runs.graph_for_scenario) with the plant paced
to the wall clock at `--rate` x real time and no end (duration_s 0), and no recorder (an
indefinite run would fill the disk).  The hold point comes from a `tune_*` scenario
(default config/scenarios/tune_60rpm_80load.yaml); `--speed-rpm` and `--load-pu` replace its
speed and its load ramp (0.16 pu/s from 1 s on, the scenario's rate), written to
`<out>/tune_scenario.yaml` for the nodes.  Loads above the card's rated torque are refused:
the drive's I2t protection integrates (i/I_rated)^2 - 1 above rated current and would trip
after i2t_limit_pu2s / (L^2 - 1) s of a load L (the paper scenario's 150 %: 8 s).  On Ctrl-C
every node stops cleanly (the plant's last period with the PWM off) and the plant's pacing
record (lateness p50/p99/max, late periods and duties, slips, watchdog trips) is printed as
the last line (JSON)."""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

from fluxdrive.core.machine import ConfigError
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.scenario import REPO_ROOT, load_scenario, save_scenario, scenario_path
from fluxdrive.io.graphfile import GraphSettings, ServeOptions
from fluxdrive_ros.runner import load_class

from fluxdrive_bringup.launch.domains import choose_domain
from fluxdrive_bringup.launch.launcher import Launcher, add_scope
from fluxdrive_bringup.launch.runs import LAYOUTS, graph_for_scenario

TUNE_SCENARIO = "tune_60rpm_80load"
LOAD_RAMP_START_S = 1.0  # after the sensorless start (handover at ~0.3 s), as the scenario
LOAD_RAMP_PU_PER_S = 0.16  # the scenario's ramp: 0.8 pu over 5 s
DEFAULT_RATE = 0.05  # sim_paced's rate: 2 ms of wall time per 100 us period
# the plant's watchdog in wall time: a controller late by less than this is lateness (the
# plant holds the previous duty, counts it) and never switches the PWM off; only one
# silent this long is taken for dead
DEFAULT_WATCHDOG_S = 1.0


def hold_overrides(sc, speed_rpm: float | None, load_pu: float | None) -> tuple[dict, str]:
    """Scenario overrides for the hold point, or ({}, reason) when it cannot be held."""
    card = sc.machine
    over: dict = {}
    if speed_rpm is not None:
        handover = sc.control.handover_rpm
        if handover is None:
            handover = 0.01 * card.rated_speed_rpm
        if not (handover <= speed_rpm <= card.rated_speed_rpm):
            return {}, (
                f"--speed-rpm {speed_rpm:g}: hold between the handover speed "
                f"({handover:g} rpm; below it the drive runs open-loop I-f) and the card's "
                f"rated speed ({card.rated_speed_rpm:g} rpm)"
            )
        over["speed_rpm"] = float(speed_rpm)
    if load_pu is not None:
        if not (0.0 <= load_pu <= 1.0):
            i2t = sc.control.i2t_limit_pu2s
            trip = (
                f"; the I2t protection would trip after {i2t / (load_pu**2 - 1.0):.1f} s"
                if load_pu > 1.0
                else ""
            )
            return {}, (
                f"--load-pu {load_pu:g}: hold between 0 and the card's rated torque "
                f"(1.0 = {card.rated_torque_nm:.3g} N m){trip}"
            )
        t1 = LOAD_RAMP_START_S + load_pu / LOAD_RAMP_PU_PER_S
        over["load_pu"] = [[0.0, 0.0], [LOAD_RAMP_START_S, 0.0], [t1, float(load_pu)]]
    return over, ""


def pacing_record(log_dir: Path) -> dict | None:
    """The plant's `pacing {json}` line from the graph's logs (logged when it stops)."""
    for p in sorted(log_dir.glob("*.log")):
        m = re.search(r"pacing (\{.*\})", p.read_text(errors="replace"))
        if m:
            return json.loads(m.group(1))
    return None


def main(argv: list[str]) -> int:
    args = _tune_parser().parse_args(argv)
    try:
        sc, sp, out, dom = _prepare(args)
    except ConfigError as exc:
        print(f"[tune] {exc}", file=sys.stderr)
        return 2
    extra: dict[str, dict[str, object]] = {
        n: {"exit_on_done": False} for n in [*sc.observers, "controller"]
    }
    extra["plant"] = {"mode": "paced", "rate_factor": args.rate, "watchdog_s": args.watchdog_s}
    g = graph_for_scenario(sp, sc, None, args.layout, 0.0, dom, extra=extra)
    if args.scope:
        add_scope(g, port=args.scope_port, observers=list(sc.observers))
    return _hold(args, g, sc, out, dom)


def _tune_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="fluxdrive tune", description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--scenario", default=TUNE_SCENARIO, help="hold-point scenario (tune_*)")
    ap.add_argument("--speed-rpm", type=float, help="hold speed [rpm] (default: the scenario's)")
    ap.add_argument(
        "--load-pu", type=float, help="hold load, of rated torque, <= 1 (default: the scenario's)"
    )
    # the plant's own fields (rate_factor, watchdog_s): what it would accept, said at once
    timing = load_class("plant").TIMING_SETTINGS
    option(
        ap,
        "--rate",
        timing,
        "rate_factor",
        default=DEFAULT_RATE,
        help=f"rate_factor: simulated seconds per wall second (default {DEFAULT_RATE:g})",
    )
    option(
        ap,
        "--watchdog-s",
        timing,
        default=DEFAULT_WATCHDOG_S,
        help="PWM off when no duty command at all came for this much wall time: the "
        f"controller is dead (default {DEFAULT_WATCHDOG_S:g}); a later one is lateness, counted",
    )
    ap.add_argument("--layout", choices=LAYOUTS, default="composed")
    ap.add_argument("--out", type=Path, help="folder for logs and graph (default runs/tune-<time>)")
    option(ap, "--domain-id", GraphSettings, help="ROS_DOMAIN_ID (default: the environment's)")
    ap.add_argument("--quiet", action="store_true", help="hide the nodes' log lines")
    ap.add_argument("--scope", action="store_true", help="start the live scope (prints its URL)")
    option(ap, "--scope-port", ServeOptions, "port", help="the scope's TCP port")
    return ap


def _prepare(args):
    """(scenario, its file, the output folder, ROS domain) of the session: the chosen
    scenario with the hold point's overrides (saved to the output folder when there are
    any). Raises ConfigError naming why the session is refused."""
    base = scenario_path(args.scenario)
    over, why = hold_overrides(load_scenario(base), args.speed_rpm, args.load_pu)
    if why:
        raise ConfigError(why)
    sc = load_scenario(base, overrides=over)
    out = args.out or REPO_ROOT / "runs" / f"tune-{time.strftime('%Y%m%d-%H%M%S')}"
    out.mkdir(parents=True, exist_ok=True)
    sp = save_scenario(sc, out / "tune_scenario.yaml") if over else base
    from fluxdrive_ros.security import precheck

    refused = precheck()
    if refused:
        raise ConfigError(refused)
    dom, clash = choose_domain(args.domain_id, "tune")
    if dom is None:
        raise ConfigError(clash)
    return sc, sp, out, dom


def _hold(args, g, sc, out: Path, dom: int) -> int:
    """Run the held graph until Ctrl-C (exit 0) and print its pacing record (JSON)."""
    speed = sc.speed_profile_rpm[-1, 1]
    load = sc.load_profile_pu[-1, 1]
    print(
        f"[tune] {sc.name}: holding {speed:g} rpm at {load:g} pu brake load "
        f"({load * sc.machine.rated_torque_nm:.3g} N m) after the start, paced at "
        f"{args.rate:g} x real time (watchdog: no duty command for {args.watchdog_s:g} s of wall "
        f"time), ROS_DOMAIN_ID={dom}; Ctrl-C stops. Tune with e.g. "
        f"./fluxdrive param set /controller speed_bandwidth_hz 5.0",
        flush=True,
    )
    launcher = Launcher(g, quiet=args.quiet, log_dir=out / "logs")
    if args.scope and args.quiet:
        import threading

        from fluxdrive_bringup.launch.runs import _print_scope_url

        threading.Thread(target=_print_scope_url, args=(launcher,), daemon=True).start()
    code = launcher.run(None)
    pacing = pacing_record(out / "logs")
    if launcher.interrupted and code == 128 + int(launcher.stop_signal or 2):
        code = 0  # Ctrl-C is how a tuning session ends
    elif code == 0:
        code = 1  # a hold has no end of its own: a graph that ended by itself failed
    if code != 0:
        print(f"[tune] the graph failed (exit {code}); logs in {out / 'logs'}", file=sys.stderr)
    print(json.dumps({"scenario": sc.name, "speed_rpm": speed, "load_pu": load, **(pacing or {})}))
    return code
