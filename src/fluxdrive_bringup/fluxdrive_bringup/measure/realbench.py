"""`./fluxdrive bench` (without --sil): the real bench -- the drive on a CAN bus, the graph
of config/graphs/bench_real.yaml (bench_bridge in split mode at D = 4, observers,
controller, recorder), after a pre-flight (fluxdrive.can.preflight) that refuses to arm in
one line, exit code 2 and nothing started, when the interface is missing, no drive answers,
its protocol version differs, it is not calibrated/ready, a fault is latched, it runs another
layout or D, or it does not acknowledge a drive parameter.

The interface and channel come from the command line (`--interface socketcan --channel can0`;
pcan, kvaser, slcan, ... as python-can names them) or else from the bridge's parameters in
the graph (config/ros/bench_bridge.yaml); other python-can arguments (a `udp_multicast`
port, a PCAN bus's own settings) from python-can's CAN_CONFIG environment variable, as the
bridge node reads them.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from fluxdrive.can.bridge import BridgeConfig, bus_factory_from_params
from fluxdrive.can.preflight import (
    calibrate,
    drive_param_name,
    preflight,
    scenario_drive_params,
)
from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.control import DRIVE_PARAM_RANGES
from fluxdrive.drive.scenario import REPO_ROOT
from fluxdrive.io.graphfile import GraphSettings

from fluxdrive_bringup.launch.domains import choose_domain
from fluxdrive_bringup.launch.launcher import (
    Graph,
    Launcher,
    NodeSpec,
    _apply_sets,
    load_graph,
    set_value,
)

BRIDGE_MODULE = "bench_bridge.bridge_node"
DEFAULT_GRAPH = "bench_real"
# the bridge's settings a command-line option overrides (option -> ROS parameter)
BUS_OPTIONS = {
    "interface": "interface",
    "channel": "channel",
    "bitrate": "bitrate",
    "data_bitrate": "data_bitrate",
}


def bridge_entry(g: Graph) -> NodeSpec:
    """The graph's bench_bridge process (a `cmd` running bench_bridge.bridge_node)."""
    for n in g.nodes:
        if n.cmd and BRIDGE_MODULE in n.cmd:
            return n
    raise ConfigError(
        f"{g.source or g.name}: no node entry runs the bench bridge "
        f"(a cmd with '-m {BRIDGE_MODULE}')"
    )


def bridge_parameters(n: NodeSpec) -> dict[str, Any]:
    """The bridge's parameters as its command gives them: its --params-file sections for
    /** and /bench_bridge, then its -p NAME:=VALUE (later ones win), like rcl."""
    out: dict[str, Any] = {}
    cmd = list(n.cmd or [])
    for i, a in enumerate(cmd[:-1]):
        nxt = cmd[i + 1]
        if a == "--params-file":
            f = Path(nxt) if Path(nxt).is_absolute() else REPO_ROOT / nxt
            try:
                data = yamlio.load_file(f) or {}
            except (OSError, yamlio.YAMLError) as exc:
                raise ConfigError(f"{f}: cannot read parameters: {yamlio.describe(exc)}") from exc
            for key in ("/**", "**", "/bench_bridge", "bench_bridge"):
                sec = data.get(key) if isinstance(data, dict) else None
                if isinstance(sec, dict) and isinstance(sec.get("ros__parameters"), dict):
                    out.update(sec["ros__parameters"])
        elif a in ("-p", "--param") and ":=" in nxt:
            k, _, v = nxt.partition(":=")
            out[k] = yamlio.loads(v)
    return out


def _set_bridge(n: NodeSpec, name: str, value: Any) -> None:
    """Append `-p name:=value` to the bridge's command (after its parameter files)."""
    text = str(value).lower() if isinstance(value, bool) else str(value)
    assert n.cmd is not None
    if "--ros-args" not in n.cmd:
        n.cmd.append("--ros-args")
    n.cmd += ["-p", f"{name}:={text}"]


def drive_parameters(pv: dict[str, Any]) -> dict[str, float]:
    """Split mode: the DRIVE_PARAM values the bridge writes before arming (its scenario's
    design, its drive.* parameters over them); host mode: none."""
    if not pv.get("control_split"):
        return {}
    vals = scenario_drive_params(str(pv.get("scenario") or ""))
    for prm in DRIVE_PARAM_RANGES:
        if drive_param_name(prm) in pv:
            vals[prm] = float(pv[drive_param_name(prm)])
    return {prm: vals[prm] for prm in DRIVE_PARAM_RANGES if prm in vals}


def bridge_config(pv: dict[str, Any]) -> BridgeConfig:
    """The supervisor settings the pre-flight speaks with: the bridge's own."""
    cfg = BridgeConfig()
    for name in ("decimation", "control_split", "stale_timeout_s", "cmd_timeout_s"):
        if name in pv:
            setattr(cfg, name, type(getattr(cfg, name))(pv[name]))
    return cfg


def _parser() -> argparse.ArgumentParser:
    ap = Parser(prog="fluxdrive bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--interface", help="python-can interface: socketcan, pcan, kvaser, slcan, ...")
    ap.add_argument(
        "--channel", help="python-can channel: can0, PCAN_USBBUS1, 0, /dev/ttyACM0, ..."
    )
    ap.add_argument("--bitrate", type=int, help="CAN FD arbitration bit rate [bit/s]")
    ap.add_argument("--data-bitrate", type=int, help="CAN FD data-phase bit rate [bit/s]")
    ap.add_argument(
        "--graph", default=DEFAULT_GRAPH, help="graph file (default config/graphs/bench_real.yaml)"
    )
    ap.add_argument("--check", action="store_true", help="the pre-flight only; nothing starts")
    ap.add_argument(
        "--calibrate",
        action="store_true",
        help="the drive's current/capture offset calibration (motor at standstill, PWM off); "
        "nothing else starts",
    )
    ap.add_argument(
        "--status-wait", type=float, default=1.0, help="wait this long for the drive's STATUS [s]"
    )
    ap.add_argument("--duration", type=float, help="stop the bench after this long [s]")
    ap.add_argument("--bag", type=Path, help="bag folder (default bags/bench-<time>)")
    option(ap, "--domain-id", GraphSettings)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NODE.PARAM=VALUE",
        help="override a node parameter (YAML value), e.g. controller.speed_ref_mode=constant "
        "or bench_bridge.drive.cur_limit_a=2.0 (the pre-flight writes that one too)",
    )
    return ap


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    if args.status_wait <= 0 or (args.duration is not None and args.duration <= 0):
        print("[bench] --status-wait and --duration must be > 0", file=sys.stderr)
        return 2
    g = load_graph(args.graph)
    bridge = bridge_entry(g)
    for opt, prm in BUS_OPTIONS.items():
        if getattr(args, opt) is not None:
            _set_bridge(bridge, prm, getattr(args, opt))
    ours = [x for x in args.set if x.partition(".")[0] == bridge.name]
    for item in ours:  # the bridge is a command: its sets become -p NAME:=VALUE
        key, eq, val = item.partition("=")
        if not eq or not key.partition(".")[2]:
            raise ConfigError(f"--set {item!r}: expected {bridge.name}.PARAM=VALUE")
        _set_bridge(bridge, key.partition(".")[2], set_value(item, val))
    _apply_sets(g, [x for x in args.set if x not in ours])
    pv = bridge_parameters(bridge)
    factory = bus_factory_from_params(
        str(pv.get("interface", "virtual")),
        str(pv.get("channel", "fluxdrive")),
        int(pv.get("bitrate", 1_000_000)),
        bool(pv.get("fd", True)),
        int(pv.get("data_bitrate", 5_000_000)),
    )
    if args.calibrate:
        res = calibrate(factory, bridge_config(pv), status_wait_s=args.status_wait)
        print(f"[bench] {res.line}", file=sys.stdout if res.ok else sys.stderr)
        return 0 if res.ok else 2
    res = preflight(factory, bridge_config(pv), drive_parameters(pv), args.status_wait)
    if not res.ok:
        print(f"[bench] refused to arm: {res.line}; nothing started", file=sys.stderr)
        return 2
    print(f"[bench] {res.line}", flush=True)
    if args.check:
        return 0
    return _run(g, args)


def _run(g: Graph, args) -> int:
    """The graph after a passed pre-flight: until Ctrl-C or --duration."""
    dom, why = choose_domain(args.domain_id, "bench")
    if dom is None:
        print(f"[bench] {why}", file=sys.stderr)
        return 2
    g.domain_id = dom
    bag = args.bag or REPO_ROOT / "bags" / f"bench-{time.strftime('%Y%m%d-%H%M%S')}"
    for n in g.nodes:
        if n.is_recorder:
            n.parameters["bag_dir"] = str(bag)
    logs = Path(str(bag) + "-logs")
    print(f"[bench] graph {g.name}, ROS_DOMAIN_ID={dom}; bag {bag}; logs {logs}", flush=True)
    launcher = Launcher(g, progress=False, log_dir=logs)
    code = launcher.run(args.duration)
    if code == 1 and launcher.timed_out and not launcher.failed:
        code = 0  # --duration: the planned end
    for b in launcher.bags:
        print(f"[bench] bag: {b}")
    if code not in (0, 130):
        print(f"[bench] the bench failed (exit {code}){launcher.failure_text()}", file=sys.stderr)
    return code
