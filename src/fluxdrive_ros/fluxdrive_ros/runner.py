"""Run one or several fluxdrive nodes in a process (a "container"), the way every fluxdrive
process runs.

Executor: rclpy.experimental.EventsExecutor, driven by a `spin_once` loop.  In the Jazzy
wheels used here its `spin()` busy-waits on one core, never fires timers and ignores
SIGINT/SIGTERM, while `spin_once(timeout)` in a loop is fine (timers fire, idle costs
nothing, a signal ends it through ExternalShutdownException).  `FLUXDRIVE_EXECUTOR=single`
selects rclpy's SingleThreadedExecutor instead (slower; for comparison).

The services (parameters, fault reset, arming) are served by a thread of their own
(fluxdrive_ros.services): reads answered there, changes run on this executor between two of
its callbacks.  `FLUXDRIVE_SERVICE_THREAD=0` keeps them on this executor (for comparison).

Nodes that share a process share one DDS participant, so messages between them are
delivered in-process by the middleware (no transport), which is what makes a 10 kHz
lockstep loop cheap; other processes (recorder, inspection tools) still see every topic.

A node class derives from `FluxNode`; it sets `self.finished = True` when its work is done
(the container exits when all its nodes are finished) and may override `close()` (called
once on exit, also after Ctrl-C / SIGTERM, e.g. to finalise a bag).

A drive in a namespace: `--ros-args -r __ns:=/a` (what `launch`/`run --namespace /a` pass)
puts every node of the container under /a, keeping each node's own namespace below it (the
observers: /a/obs/<name>); rcl's own `__ns` would replace it.  Parameter files keep naming
the nodes as in a root-namespace drive (`/plant`, `/obs/**`), and `/clock` is remapped to
the drive's clock (/a/clock) for the nodes' time sources.  Topics are relative to the
drive (fluxdrive_ros.topics.in_drive), so the whole drive moves.

Container spec (JSON, given as `--spec FILE` or `--spec-json TEXT`):
  {"process": "drive",
   "nodes": [{"class": "spm_plant_sim.node:PlantNode", "name": "plant", "namespace": "/",
              "parameters": {"scenario": "...", "seed": 1}, "params_files": []}]}
"""

from __future__ import annotations

import importlib
import json
import os
import sys
import time
import traceback
from collections.abc import Callable
from typing import Any

import rclpy
from fluxdrive.core.schema import Parser
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter

# short names for the node classes, usable in graph files as `node: plant`
NODE_CLASSES = {
    "plant": "spm_plant_sim.node:PlantNode",
    "observer": "flux_observer_node.node:ObserverNode",
    "controller": "foc_controller_node.node:ControllerNode",
    "recorder": "fluxdrive_bringup.record.recorder:RecorderNode",
    "scope_tap": "fluxdrive_bringup.view.scope_tap:ScopeTapNode",
}


class FluxNode(Node):
    """Base of the fluxdrive nodes: a `finished` flag and a `close()` hook."""

    def __init__(self, name: str, namespace: str | None = None, **kw: Any):
        self._finished = False
        self._finish_hook: Callable[[], None] | None = None
        from . import services

        # the process's service side, if the runner opened one: this node's services --
        # the parameter services rclpy creates in Node.__init__ included -- are created there
        # (create_service below, fluxdrive_ros.services)
        ctx = kw.get("context")
        if ctx is None:
            from rclpy.utilities import get_default_context

            ctx = get_default_context()
        self._service_side = services.side_of(ctx)
        super().__init__(name, namespace=namespace or "", **kw)
        self.exit_code = 0
        # graph identity (fluxdrive_ros.graph): stamped on what it publishes, checked on
        # every raw subscription
        from . import graph
        from .params import declare

        self.graph = graph.Membership(self, declare(self, [graph.param()])["graph_id"])

    @property
    def finished(self) -> bool:
        return self._finished

    @finished.setter
    def finished(self, value: bool) -> None:
        self._finished = bool(value)
        if value:  # its last messages kept for block readers (fluxdrive_ros.intra) go now
            for pub in getattr(self, "raw_publishers", ()):
                pub.flush_rows()
        if value and self._finish_hook is not None:
            self._finish_hook()

    def create_timer(
        self,
        timer_period_sec: float,
        callback,
        callback_group=None,
        clock=None,
        autostart: bool = True,
    ):
        """A timer on the wall (steady) clock unless a clock is given: the nodes' timers are
        watchdogs, pacing and housekeeping, which must run on wall time also when the node
        follows the drive's /clock (use_sim_time, as in the sim graphs) -- ROS time there
        stands still until the first frame and then runs at the graph's pace."""
        if clock is None:
            from rclpy.clock import Clock, ClockType

            clock = Clock(clock_type=ClockType.STEADY_TIME)
        return super().create_timer(
            timer_period_sec, callback, callback_group, clock=clock, autostart=autostart
        )

    def create_service(self, srv_type, srv_name: str, callback, *, qos_profile=None, **kw):
        """A service server of this node: on the process's service side when there is one
        (fluxdrive_ros.services: answered beside the data path), else on this node."""
        from rclpy.qos import qos_profile_services_default

        qos = qos_profile if qos_profile is not None else qos_profile_services_default
        if self._service_side is not None and not kw:
            return self._service_side.create_service(self, srv_type, srv_name, callback, qos)
        return super().create_service(srv_type, srv_name, callback, qos_profile=qos, **kw)

    def close(self) -> None:
        """Called once when the process ends (normally or on a signal)."""

    def log(self, text: str, level: str = "info") -> None:
        """Log through rosout while the context lives, else straight to stdout (close())."""
        if self.context.ok():
            # one call site per severity: rclpy refuses a call site that logs at several
            lg = self.get_logger()
            if level == "error":
                lg.error(text)
            elif level == "warning":
                lg.warning(text)
            else:
                lg.info(text)
        else:
            say(f"[{level.upper()}] [{self.get_logger().name}]: {text}")

    def progress(self, text: str) -> None:
        """A machine-readable progress line for the launcher (not logged)."""
        say(f"@progress {text}")


def say(line: str) -> None:
    """One line on stdout (the launcher reads it). A launcher that is gone (killed) took its
    reader with it: from then on the lines go nowhere instead of raising BrokenPipeError in
    whatever callback wrote one -- the process still has its stop to make."""
    try:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()
    except (BrokenPipeError, OSError, ValueError):
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process


def make_executor(context=None):
    kind = os.environ.get("FLUXDRIVE_EXECUTOR", "events")
    if kind == "single":
        from rclpy.executors import SingleThreadedExecutor

        return SingleThreadedExecutor(context=context)
    from rclpy.experimental import EventsExecutor

    return EventsExecutor(context=context)


def spin(nodes: list[FluxNode], executor=None, poll_s: float = 0.5) -> int:
    """Spin until every node is finished or the context is shut down (signal).
    Returns the process exit code: 0 normally, else the first node's non-zero code.

    The loop is `spin_until_future_complete(all_finished, poll_s)`: the executor handles
    events back to back in C++ for up to poll_s (no Python between events); the future is
    completed when the last node sets `finished`."""
    from rclpy.task import Future

    ex = executor or make_executor()
    all_done = Future()

    def check() -> None:
        if all(n.finished for n in nodes) and not all_done.done():
            all_done.set_result(True)

    from .intra import share_sim_time

    share_sim_time(nodes)  # one /clock reader for the process, not one per node
    side = _service_side(nodes, ex)
    for n in nodes:
        n._finish_hook = check
        ex.add_node(n)
    failed: list[BaseException] = []

    def request_stop(*_a) -> None:
        _STOP_REQUESTS.append(True)
        if not all_done.done():
            all_done.set_result(False)

    _start_bus(ex, all_done, failed, request_stop)
    _stop_on_signals(request_stop)
    check()
    code = _spin_until_done(ex, all_done, poll_s)
    if side is not None:
        side.close()
    if failed:
        code = 1
    code = _close_nodes(nodes, code)
    flush_publishers(nodes, STOP_ACK_TIMEOUT_S)
    if os.environ.get("FLUXDRIVE_GRAPH_KEY"):  # started by the launcher: it checks the bag
        report_published(nodes)
    _shutdown(ex, nodes)
    return code


def _service_side(nodes: list[FluxNode], ex):
    """The process's service side (fluxdrive_ros.services), started on `ex`, if the process
    opened one before it built the nodes (open_service_side); else None, and the services
    stay on the data path's executor."""
    from . import services

    side = services.side_of(nodes[0].context) if nodes else None
    if side is not None:
        side.start(nodes, ex)
    return side


def open_service_side() -> None:
    """Before the nodes are built: open the process's service side, so that their services
    are created on it (fluxdrive_ros.services), unless FLUXDRIVE_SERVICE_THREAD=0."""
    from . import services

    services.open_side(log=lambda text, level: say(f"[{level.upper()}] [services]: {text}"))


def report_published(nodes: list[FluxNode]) -> None:
    """What the nodes published, per topic, once they are flushed: `@published` lines for
    the launcher, and the same in $FLUXDRIVE_STOP_DIR/<process>.published.json for a
    recorder of the graph to read when the launcher is gone (killed: no one reads the
    lines), see fluxdrive_bringup.record.recorder."""
    counts: dict[str, int] = {}
    for n in nodes:
        for pub in getattr(n, "raw_publishers", []):
            counts[pub.topic] = counts.get(pub.topic, 0) + int(pub.n_published)
    stop_dir, proc = os.environ.get(STOP_DIR_ENV, ""), os.environ.get(PROCESS_ENV, "")
    if stop_dir and proc:
        try:
            f = os.path.join(stop_dir, f"{proc}{PUBLISHED_SUFFIX}")
            with open(f + ".tmp", "w") as fh:
                json.dump(counts, fh)
            os.replace(f + ".tmp", f)  # whole or not at all when the recorder reads it
        except OSError:
            pass  # the launcher removed its directory: it is there to read the lines
    for topic, n_pub in counts.items():
        say(f"@published {topic} {n_pub}")


def _start_bus(ex, all_done, failed: list[BaseException], request_stop) -> None:
    """The intra-process bus (when nodes share it): an error in a delivery ends the spin,
    failed; an interrupt it sees stops it."""
    from . import intra

    bus = intra.bus()
    if bus is None:
        return

    def on_error(exc: BaseException) -> None:
        failed.append(exc)
        if not all_done.done():
            all_done.set_result(False)

    bus.on_error = on_error
    bus.on_interrupt = request_stop
    bus.start(ex)


def _stop_on_signals(request_stop) -> None:
    """Ctrl-C / SIGTERM: stop between callbacks, never a KeyboardInterrupt inside one."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, request_stop)
    if _EARLY_STOP:  # a signal arrived while the nodes were being built
        request_stop()


def _spin_until_done(ex, all_done, poll_s: float) -> int:
    """0, or 1 when a callback raised (reported)."""
    try:
        while rclpy.ok() and not all_done.done():
            ex.spin_until_future_complete(all_done, timeout_sec=poll_s)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:  # noqa: BLE001 - a callback raised: report, exit non-zero
        traceback.print_exc()
        return 1
    return 0


def _close_nodes(nodes: list[FluxNode], code: int) -> int:
    """Close every node (a failing close makes the code 1); the first non-zero code wins."""
    # nodes that record close last: what the others publish as they close (the plant's
    # final PWM-off frame) reaches them first
    for n in sorted(nodes, key=lambda n: bool(getattr(n, "closes_last", False))):
        try:
            n.close()
        except Exception:  # noqa: BLE001
            traceback.print_exc()
            code = code or 1
        g = getattr(n, "graph", None)
        if g is not None and g.foreign:
            n.log(g.summary(), "warning")
        code = code or int(getattr(n, "exit_code", 0) or 0)
    return code


def _shutdown(ex, nodes: list[FluxNode]) -> None:
    for n in nodes:
        try:
            ex.remove_node(n)
            n.destroy_node()
        except Exception:  # noqa: BLE001 - shutting down anyway
            pass
    try:
        ex.shutdown()
    except Exception:  # noqa: BLE001
        pass
    if rclpy.ok():
        rclpy.try_shutdown()


# stop requests (signals) this process got; a second one cuts a recorder's drain short
_STOP_REQUESTS: list[bool] = []


def stop_requests() -> int:
    return len(_STOP_REQUESTS)


# where the launcher writes, before it stops a process holding a recorder, how many messages
# the graph's nodes published per topic (their `@published` lines as they exited): the
# recorder finalises once it has received that many (fluxdrive_bringup.record.recorder)
STOP_COUNTS_ENV = "FLUXDRIVE_STOP_COUNTS"
# the launcher's directory for them, the process's name in the graph, and the graph's
# processes that report what they published (runner processes): each writes
# <dir>/<process>.published.json as it exits, so a recorder whose launcher was killed still
# knows what to wait for and what its bag lacks
STOP_DIR_ENV = "FLUXDRIVE_STOP_DIR"
PROCESS_ENV = "FLUXDRIVE_PROCESS"
REPORTING_ENV = "FLUXDRIVE_REPORTING_PROCESSES"
PUBLISHED_SUFFIX = ".published.json"

# a stopping process waits this long at most for its readers elsewhere (the recorder) to
# acknowledge what it published, so that none of it dies with its writers
STOP_ACK_TIMEOUT_S = 10.0


def flush_publishers(nodes: list[FluxNode], timeout_s: float) -> bool:
    """Wait until every reader in another process has acknowledged every message the
    nodes' sample publishers sent (reliable readers: it is in their history), at most
    timeout_s in all; a reader that stays behind is named in one line.  Without this a
    process that stops while the recorder lags it takes its unacknowledged tail with it."""
    from rclpy.duration import Duration

    t_end = time.monotonic() + timeout_s
    behind = []
    for n in nodes:
        for pub in getattr(n, "raw_publishers", []):
            try:
                left = max(0.0, t_end - time.monotonic())
                if not pub.wait_for_all_acked(Duration(seconds=left)):
                    behind.append(pub.topic)
            except Exception:  # noqa: BLE001 - the context is gone: nothing to wait for
                return False
    if behind:
        nodes[0].log(
            f"stopping: readers of {', '.join(behind)} did not acknowledge every message "
            f"within {timeout_s:g} s (a reader stalled or killed); the unacknowledged ones "
            f"are lost with this process",
            "warning",
        )
    return not behind


_EARLY_STOP: list[int] = []


def _early_stop(signum, frame) -> None:  # noqa: ARG001
    _EARLY_STOP.append(signum)


def _config_problem(exc: BaseException) -> bool:
    """Errors that are the user's configuration (reported in one line, no traceback)."""
    from rclpy.exceptions import ParameterException

    try:
        from rclpy._rclpy_pybind11 import RCLInvalidROSArgsError as ArgsError
    except ImportError:  # pragma: no cover - other rclpy builds
        ArgsError = ValueError  # noqa: N806
    return isinstance(
        exc, (ValueError, TypeError, KeyError, FileNotFoundError, ParameterException, ArgsError)
    )


def _describe(exc: BaseException) -> str:
    """One line for a start-up failure: configuration and security problems without a
    traceback, anything else with one."""
    from .security import describe_error

    why = describe_error(exc)
    if why is not None:
        return why
    if not _config_problem(exc):
        traceback.print_exc()
    return str(exc)


def _init(args: list[str], what: str) -> bool:
    """rclpy.init; False (after a one-line message) if it fails, e.g. ROS security is
    enforced without a usable keystore."""
    from .security import precheck

    why = precheck()
    if why:
        print(f"cannot start process '{what}': {why}", file=sys.stderr, flush=True)
        return False
    try:
        rclpy.init(args=args)
    except Exception as exc:  # noqa: BLE001
        print(f"cannot start process '{what}': {_describe(exc)}", file=sys.stderr, flush=True)
        return False
    return True


def load_class(spec: str):
    """The node class of `spec` (a known node or a user's module:Class); a module that does
    not import or has no such class is a ConfigError of one line (the user's module: its own
    error named, no traceback)."""
    from fluxdrive.core.errors import ConfigError

    spec = NODE_CLASSES.get(spec, spec)
    mod, _, cls = spec.partition(":")
    try:
        module = importlib.import_module(mod)
    except Exception as exc:  # noqa: BLE001 - whatever the user's module raises on import
        why = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
        raise ConfigError(f"node class {spec!r}: cannot import {mod!r} ({why})") from None
    if not cls or not hasattr(module, cls):
        raise ConfigError(f"node class {spec!r}: module {mod!r} has no {cls!r}")
    return getattr(module, cls)


def _param_overrides(params: dict[str, Any]) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in params.items()]


def split_namespace(args: list[str]) -> tuple[str, list[str]]:
    """The drive namespace of a `__ns:=NS` remapping among ROS arguments ('' if none) and
    the arguments without it (the container applies it itself, see the module notes)."""
    out: list[str] = []
    ns = ""
    i = 0
    while i < len(args):
        a = args[i]
        if a in ("-r", "--remap") and i + 1 < len(args) and args[i + 1].startswith("__ns:="):
            ns = args[i + 1][len("__ns:=") :]
            i += 2
            continue
        out.append(a)
        i += 1
    if out and out[-1] == "--ros-args":
        out.pop()
    ns = ns.rstrip("/")
    if ns and not ns.startswith("/"):
        ns = "/" + ns
    return ns, out


def build_node(spec: dict, drive_ns: str = "") -> FluxNode:
    """Construct a node from a container spec entry (under the drive namespace `drive_ns`,
    if any).  A bad parameter file or value ends in a ValueError naming the parameter and
    where it was set (file and key, or inline)."""
    from .params import blame, check_params_file, file_values_for

    cls = load_class(spec["class"])
    files = [str(f) for f in spec.get("params_files", []) or []]
    for f in files:
        check_params_file(f)  # rcl's own parser reports C source lines, not the key
    inline = spec.get("parameters", {}) or {}
    ns = (spec.get("namespace", "") or "").rstrip("/")
    fqn = f"{ns}/{spec['name']}" if ns.startswith("/") else f"/{spec['name']}"
    kw = {}
    overrides = dict(inline)
    if drive_ns:
        # the files name the node as in a root-namespace drive: their values for it, in
        # rcl's order (later files and entries win), under the inline values
        from_files: dict[str, Any] = {}
        for _f, _key, name, value in file_values_for(files, fqn):
            from_files[name] = value
        overrides = {**from_files, **inline}
    elif files:
        kw["cli_args"] = ["--ros-args"] + [a for f in files for a in ("--params-file", f)]
    try:
        node = cls(
            spec["name"],
            namespace=drive_ns + (("/" + ns.lstrip("/")) if ns.strip("/") else ""),
            parameter_overrides=_param_overrides(overrides),
            **kw,
        )
    except Exception as exc:
        if not _config_problem(exc):
            raise
        text = str(exc)
        raise ValueError(text + blame(text, fqn, files, inline)) from exc
    problem = unknown_parameter(node, fqn, files, inline)
    if problem:
        node.destroy_node()
        raise ValueError(problem)
    return node


def unknown_parameter(node: Node, fqn: str, files: list[str], inline: dict[str, Any]) -> str | None:
    """A parameter the files (or the graph's inline values) set for this node that the node
    does not declare -- a typo rcl would silently ignore -- as one line naming the file and
    key, with the closest declared name; None if every name is known.  Sections for every
    node (`/**`) may hold parameters of other node types and are not checked."""
    import difflib

    from .params import file_values_for

    def text(name: str, where: str) -> str:
        near = difflib.get_close_matches(name, list(node._parameters), n=1)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        return f"{where}: '{name}' is not a parameter of {fqn}{hint}"

    for f, key, name, _ in file_values_for(files, fqn):
        if key.strip("/") == "**" or node.has_parameter(name):
            continue
        return text(name, f"{f}: '{key}.ros__parameters.{name}'")
    for name in inline:
        if not node.has_parameter(name):
            return text(name, "inline in the graph")
    return None


def main_node(cls_spec: str, default_name: str, argv: list[str] | None = None) -> int:
    """Entry point of a single-node executable: `<exe> [--ros-args ...]`."""
    argv = sys.argv if argv is None else argv
    if not _init(argv, default_name):
        return 2
    try:
        open_service_side()  # its node is the process's first: a security failure shows here
        node = load_class(cls_spec)(default_name)
    except Exception as exc:  # noqa: BLE001 - configuration problems end the process
        why = _describe(exc)
        print(f"{default_name}: cannot start: {why}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    return spin([node])


def container_main(argv: list[str] | None = None) -> int:
    ap = Parser(prog="fluxdrive-container", description=__doc__.split("\n")[0])
    ap.add_argument("--spec", help="JSON spec file")
    ap.add_argument("--spec-json", help="JSON spec text")
    args, rest = ap.parse_known_args(argv)
    if args.spec:
        with open(args.spec) as fh:
            spec = json.load(fh)
    elif args.spec_json:
        spec = json.loads(args.spec_json)
    else:
        ap.error("--spec or --spec-json is required")
    drive_ns, rest = split_namespace(rest)
    if drive_ns:  # the nodes' time sources read the drive's own clock
        rest = [*rest, "--ros-args", "-r", f"/clock:={drive_ns}/clock"]
    if not _init(["fluxdrive-container", *rest], str(spec.get("process", "container"))):
        return 2
    import signal

    for sig in (signal.SIGINT, signal.SIGTERM):  # a stop while building: finish building
        signal.signal(sig, _early_stop)
    nodes = []
    ns: Any = {}
    try:
        open_service_side()  # its node is the process's first: a security failure shows here
        for ns in spec["nodes"]:
            nodes.append(build_node(ns, drive_ns))
    except Exception as exc:  # noqa: BLE001
        why = _describe(exc)
        name = ns.get("name", "?") if isinstance(ns, dict) else "?"
        print(f"cannot start node '{name}': {why}", file=sys.stderr, flush=True)
        for n in nodes:
            n.close()
            n.destroy_node()
        rclpy.try_shutdown()
        return 2
    t0 = time.perf_counter()
    prof = os.environ.get("FLUXDRIVE_PROFILE")
    if prof:  # development aid: cProfile of this process into <dir>/<process>.prof
        import cProfile

        pr = cProfile.Profile()
        pr.enable()
        code = spin(nodes)
        pr.disable()
        os.makedirs(prof, exist_ok=True)
        pr.dump_stats(os.path.join(prof, f"{spec.get('process', 'container')}.prof"))
    else:
        code = spin(nodes)
    if os.environ.get("FLUXDRIVE_DEBUG"):
        print(
            f"[{spec.get('process')}] exit {code} after {time.perf_counter() - t0:.1f} s",
            file=sys.stderr,
        )
    return code


if __name__ == "__main__":
    sys.exit(container_main())
