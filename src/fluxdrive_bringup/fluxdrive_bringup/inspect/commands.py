"""Inspection of a running graph without ros2cli (the wheel set has none):

  ./fluxdrive topic list [-v]                    topics, types, publisher/subscriber counts
  ./fluxdrive topic echo TOPIC [-n N] [--field F] messages as YAML (first N)
  ./fluxdrive topic hz TOPIC [-w SECONDS]        message rate, once a second
  ./fluxdrive node list                          nodes of the graph
  ./fluxdrive param list NODE                    parameter names
  ./fluxdrive param get NODE NAME                value (and description, range with -v)
  ./fluxdrive param set NODE NAME VALUE          set; prints the node's answer (the reason
                                                 if rejected, exit 1)
  ./fluxdrive param dump NODE [-o FILE]          all parameters as a ros__parameters file

All of them are rclpy clients in the same ROS_DOMAIN_ID (pass --domain-id or set the
variable) with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless set.  Discovery takes 1-2 s,
so each command first waits for the graph (--wait, default 2 s).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time
from dataclasses import dataclass
from typing import Any

import yaml
from fluxdrive.core import yamlio
from fluxdrive.core.errors import ConfigError
from fluxdrive.core.paths import check_output
from fluxdrive.core.schema import Parser, option, param
from fluxdrive.io.graphfile import GraphSettings
from fluxdrive_ros.topics import check_node_name, check_ros_name, check_service_name


@dataclass
class InspectOptions:
    """The inspection commands' numeric options, ranged once."""

    window_s: float = param(1.0, unit="s", doc="report period", range=(0.01, 3600.0))
    duration_s: float = param(
        0.0, unit="s", doc="stop after this long (0: until Ctrl-C)", range=(0.0, 1e6)
    )
    timeout_s: float = param(
        0.0, unit="s", doc="give up after this long (0: never)", range=(0.0, 1e6)
    )
    wait_s: float = param(
        5.0,
        unit="s",
        doc="longest discovery wait (`list` returns once discovery has settled)",
        range=(0.0, 3600.0),
    )


def check_field_path(cls, path: str, flag: str = "--field") -> None:
    """A dotted field path (`header.stamp.sec`, `i_abc.0`) that messages of `cls` have, or
    ConfigError naming the option, the type and the fields there are."""
    d: Any = _msg_to_plain(cls())
    for part in path.split("."):
        if isinstance(d, list):
            if not part.isdigit():
                raise ConfigError(f"{flag} {path}: '{part}' is not an index into a list")
            d = d[int(part)] if int(part) < len(d) else None
        elif isinstance(d, dict):
            if part not in d:
                raise ConfigError(
                    f"{flag} {path}: {cls.__name__} has no field '{part}' here; fields: "
                    f"{', '.join(d)}"
                )
            d = d[part]
        elif d is not None:
            raise ConfigError(f"{flag} {path}: '{part}' is below a plain value")


def _common(ap: argparse.ArgumentParser) -> None:
    option(ap, "--domain-id", GraphSettings, help="ROS_DOMAIN_ID of the graph")
    option(ap, "--wait", InspectOptions, "wait_s")


# A participant that missed another's first announcements learns of it from the next
# periodic one, 3 s later with Fast DDS's defaults (measured here: 0.1-0.2 s normally, 2.8 s
# now and then); `topic list` / `node list` wait this long before calling discovery settled.
SETTLE_MIN_S = 3.2


class Session:
    """A private rclpy context with one helper node, spun with a plain executor (usable
    from tests next to other rclpy users: it never touches the default context)."""

    def __init__(
        self,
        args=None,
        domain_id: int | None = None,
        wait_s: float = 3.0,
        node_name: str | None = None,
    ):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        if args is not None:
            domain_id = args.domain_id if args.domain_id is not None else domain_id
            wait_s = args.wait
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        if domain_id is None:
            domain_id = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
        self.domain_id = domain_id
        self.rclpy = rclpy
        from fluxdrive_ros.security import precheck

        why = precheck()
        if why:  # rcl would fail with a traceback
            print(f"fluxdrive: {why}", file=sys.stderr)
            raise SystemExit(2)
        self.ctx = rclpy.Context()
        rclpy.init(args=None, context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node(
            node_name or f"fluxdrive_inspect_{os.getpid()}",
            context=self.ctx,
            start_parameter_services=False,
        )
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.wait_s = wait_s

    def ok(self) -> bool:
        return self.ctx.ok()

    def spin_for(self, seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end and self.ctx.ok():
            self.ex.spin_once(timeout_sec=min(0.05, max(t_end - time.monotonic(), 0.0)))

    def discover(self, until=None) -> None:
        """Spin until `until()` is true or the wait elapses; without `until`, until
        discovery has settled: the graph has not changed for a second (at least 1 s) and
        every node seen has its endpoints known too (a node is announced before its
        publishers and subscriptions are matched; a list taken in between misses topics),
        and at least SETTLE_MIN_S have passed -- at most the wait."""
        t0 = time.monotonic()
        t_end = t0 + self.wait_s
        last, t_last = None, t0
        me = self.node.get_name()
        while time.monotonic() < t_end:
            self.spin_for(0.1)
            if until is not None:
                if until():
                    return
                continue
            now = time.monotonic()
            nodes = sorted(self.node.get_node_names_and_namespaces())
            snap = (nodes, sorted((n, tuple(t)) for n, t in self.node.get_topic_names_and_types()))
            if snap != last:
                last, t_last = snap, now
            elif (
                now - t0 > SETTLE_MIN_S and now - t_last > 1.0 and self._endpoints_known(nodes, me)
            ):
                return

    def _endpoints_known(self, nodes: list[tuple[str, str]], me: str) -> bool:
        """Every node (but this one) shows at least one publisher (every rclpy/rclcpp node
        has /rosout): its endpoints have been discovered, not only its name."""
        for name, ns in nodes:
            if name == me:
                continue
            try:
                if not self.node.get_publisher_names_and_types_by_node(name, ns):
                    return False
            except Exception:  # noqa: BLE001 - the node left meanwhile
                return False
        return True

    def close(self) -> None:
        try:
            self.ex.shutdown()
            self.node.destroy_node()
            self.ctx.try_shutdown()
        except Exception:  # noqa: BLE001
            pass


def _topic_type(s: Session, topic: str) -> str | None:
    found: dict[str, list[str]] = {}

    def have() -> bool:
        found.update(dict(s.node.get_topic_names_and_types()))
        return topic in found

    s.discover(have)
    types = found.get(topic)
    return types[0] if types else None


def _msg_to_plain(msg) -> Any:
    if hasattr(msg, "get_fields_and_field_types"):
        return {k: _msg_to_plain(getattr(msg, k)) for k in msg.get_fields_and_field_types()}
    if hasattr(msg, "tolist"):
        return msg.tolist()
    if isinstance(msg, (list, tuple)):
        return [_msg_to_plain(x) for x in msg]
    if isinstance(msg, float) and not math.isfinite(msg):
        return str(msg)
    return msg


# --------------------------------------------------------------------------- topic
def main_topic(argv: list[str]) -> int:
    ap = Parser(prog="fluxdrive topic", description="topic list|echo|hz")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="topics with types")
    p.add_argument("-v", "--verbose", action="store_true", help="publisher/subscriber counts")
    _common(p)
    p = sub.add_parser("echo", help="print messages")
    p.add_argument("topic")
    p.add_argument("-n", "--count", type=int, default=0, help="stop after N messages")
    p.add_argument("--field", help="print only this field (dotted path)")
    option(p, "--timeout", InspectOptions, "timeout_s")
    _common(p)
    p = sub.add_parser("hz", help="message rate")
    p.add_argument("topic")
    option(p, "--window", InspectOptions, "window_s", short="-w")
    option(p, "--duration", InspectOptions, "duration_s")
    _common(p)
    args = ap.parse_args(argv)
    if args.cmd != "list":
        check_ros_name(args.topic, "TOPIC", "topic name")
    s = Session(args)
    try:
        if args.cmd == "list":
            s.discover()
            rows = sorted(s.node.get_topic_names_and_types())
            for name, types in rows:
                if args.verbose:
                    print(
                        f"{name} [{', '.join(types)}] publishers: "
                        f"{s.node.count_publishers(name)}, subscribers: "
                        f"{s.node.count_subscribers(name)}"
                    )
                else:
                    print(f"{name} [{', '.join(types)}]")
            return 0
        ty = _topic_type(s, args.topic)
        if ty is None:
            print(
                f"fluxdrive topic: '{args.topic}' not found in the graph (ROS_DOMAIN_ID="
                f"{s.domain_id})",
                file=sys.stderr,
            )
            return 1
        from fluxdrive_ros.topics import msg_class

        cls = msg_class(ty)
        if args.cmd == "echo" and args.field:
            check_field_path(cls, args.field)
        if args.cmd == "echo":
            return _echo(s, args, cls)
        return _hz(s, args, cls)
    except KeyboardInterrupt:
        return 0
    finally:
        s.close()


def _echo(s: Session, args, cls) -> int:
    from fluxdrive_ros import qos

    got = [0]

    def cb(msg) -> None:
        if args.count and got[0] >= args.count:
            return
        got[0] += 1
        d = _msg_to_plain(msg)
        if args.field:
            for part in args.field.split("."):
                d = d[int(part)] if isinstance(d, list) else d[part]
        print(yaml.safe_dump(d, sort_keys=False, default_flow_style=None).rstrip())
        print("---", flush=True)

    s.node.create_subscription(cls, args.topic, cb, qos.WATCH)
    t_end = time.monotonic() + args.timeout if args.timeout else None
    while s.ok() and (not args.count or got[0] < args.count):
        s.spin_for(0.1)
        if t_end and time.monotonic() > t_end:
            break
    return 0 if got[0] else 1


def _hz(s: Session, args, cls) -> int:
    from fluxdrive_ros import qos

    n = [0]
    sub = s.node.create_subscription(
        cls, args.topic, lambda d: n.__setitem__(0, n[0] + 1), qos.WATCH, raw=True
    )
    s.discover(lambda: sub.get_publisher_count() > 0)
    s.spin_for(0.2)
    n[0] = 0
    t0 = time.monotonic()
    last_t, last_n, total_reports = t0, 0, 0
    while s.ok():
        s.spin_for(args.window)
        now = time.monotonic()
        rate = (n[0] - last_n) / (now - last_t)
        print(f"{args.topic}: {rate:10.1f} msg/s ({n[0]} received)", flush=True)
        last_t, last_n = now, n[0]
        total_reports += 1
        if args.duration and now - t0 >= args.duration:
            break
    return 0


# --------------------------------------------------------------------------- node
def main_node(argv: list[str]) -> int:
    ap = Parser(prog="fluxdrive node", description="node list")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="nodes of the graph")
    _common(p)
    args = ap.parse_args(argv)
    s = Session(args)
    try:
        s.discover()
        me = s.node.get_name()
        names = sorted(  # hidden nodes (a leading '_': a process's service node) left out
            {
                f"{ns.rstrip('/')}/{n}"
                for n, ns in s.node.get_node_names_and_namespaces()
                if n != me and not n.startswith("_")
            }
        )
        for n in names:
            print(n)
        return 0
    finally:
        s.close()


# --------------------------------------------------------------------------- param
def _call(s: Session, srv_type, name: str, req, timeout: float = 5.0):
    check_service_name(name, "service")  # before rclpy: it raises its own types on a bad one
    # one client per service and session (a long-lived session, the scope's, calls often)
    cache = s.__dict__.setdefault("_clients", {})
    cli = cache.get((srv_type, name))
    if cli is None:
        cli = cache[(srv_type, name)] = s.node.create_client(srv_type, name)
    t_end = time.monotonic() + max(s.wait_s, 5.0)
    while not cli.service_is_ready() and time.monotonic() < t_end:
        s.spin_for(0.05)
    if not cli.service_is_ready():
        raise LookupError(
            f"service {name} not available (is the node running, same ROS_DOMAIN_ID={s.domain_id}?)"
        )
    # an answer can be lost: a server answers before its writer has matched this client's
    # response reader (discovery lags on a loaded machine) and DDS drops it. So a request not
    # answered within a second goes out again (then after 2 s, ...) until the deadline; the
    # first answer counts. Every service called here is idempotent: get, list, describe, a
    # set to one value, a fault reset
    t_end = time.monotonic() + timeout
    futs = []
    wait_s = CALL_RESEND_S
    while True:
        futs.append(cli.call_async(req))
        t_try = min(t_end, time.monotonic() + wait_s)
        while time.monotonic() < t_try and not any(f.done() for f in futs):
            s.spin_for(0.02)
        done = next((f for f in futs if f.done()), None)
        if done is not None:
            for f in futs:
                if f is not done:
                    cli.remove_pending_request(f)
            return done.result()
        if time.monotonic() >= t_end:
            for f in futs:
                cli.remove_pending_request(f)
            sent = f" ({len(futs)} requests)" if len(futs) > 1 else ""
            raise TimeoutError(f"{name}: no answer within {timeout} s{sent}")
        wait_s *= 2


# a service request not answered within this long is sent again (see _call)
CALL_RESEND_S = 1.0


def _node_fqn(node: str) -> str:
    return node if node.startswith("/") else "/" + node


PARAM_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def check_param_name(name: str, where: str = "NAME") -> None:
    if len(name) > 255 or not PARAM_NAME_RE.fullmatch(name):
        raise ConfigError(
            f"{where} must be a parameter name (letters, digits, _ and dots), got {name[:80]!r}"
        )


def _get(s: Session, node: str, names: list[str]):
    from rcl_interfaces.srv import GetParameters
    from rclpy.parameter import parameter_value_to_python

    res = _call(s, GetParameters, f"{node}/get_parameters", GetParameters.Request(names=names))
    # a name the node does not have: no value at all (rclpy nodes answer an empty list when
    # any name is unknown) or type 0, PARAMETER_NOT_SET (rclpy's conversion raises on it)
    if len(res.values) != len(names):
        if len(names) == 1:
            return [(0, None)]
        return [_get(s, node, [n])[0] for n in names]
    return [(v.type, parameter_value_to_python(v) if v.type else None) for v in res.values]


def _list(s: Session, node: str) -> list[str]:
    from rcl_interfaces.srv import ListParameters

    res = _call(s, ListParameters, f"{node}/list_parameters", ListParameters.Request())
    return sorted(res.result.names)


def _describe(s: Session, node: str, names: list[str]):
    from rcl_interfaces.srv import DescribeParameters

    res = _call(
        s,
        DescribeParameters,
        f"{node}/describe_parameters",
        DescribeParameters.Request(names=names),
    )
    return res.descriptors


def parse_value(text: str, current_type: int | None):
    """Command-line text -> Python value of the parameter's type (an integer given for a
    double parameter becomes a float, like the nodes accept in their files)."""
    from rcl_interfaces.msg import ParameterType

    try:
        v = yamlio.loads(text)
    except yamlio.LimitError as exc:  # e.g. an integer outside int64
        raise ConfigError(f"value {text[:60]!r}: {yamlio.describe(exc)}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(
            f"value {text[:60]!r} is not valid YAML: {yamlio.describe(exc)}"
        ) from None
    check_param_value(v, text)
    if isinstance(v, list) and any(isinstance(x, float) for x in v):
        v = [float(x) for x in v]  # [1, 2.5]: a list of doubles
    if (
        current_type == ParameterType.PARAMETER_DOUBLE
        and isinstance(v, int)
        and not isinstance(v, bool)
    ):
        v = float(v)
    if current_type == ParameterType.PARAMETER_STRING and not isinstance(v, str):
        v = text
    return v


INT64 = (-(2**63), 2**63 - 1)


def check_param_value(v: Any, text: str) -> None:
    """A value a ROS parameter can hold: a bool, an int64, a double, a string, or a list of
    one of these (ints and doubles may mix: a list of doubles); else ConfigError."""
    shown = text[:60]

    def scalar(x: Any) -> type | None:
        if isinstance(x, bool):
            return bool
        if isinstance(x, int):
            if not INT64[0] <= x <= INT64[1]:
                raise ConfigError(f"value {shown!r}: an integer parameter is int64")
            return int
        return float if isinstance(x, float) else str if isinstance(x, str) else None

    if isinstance(v, list):
        kinds = {scalar(x) for x in v}
        if (None in kinds or len(kinds) > 1) and not kinds <= {int, float}:
            names = sorted(k.__name__ if k else "nested" for k in kinds)
            raise ConfigError(
                f"value {shown!r}: a list parameter holds one type (bools, integers, "
                f"numbers or strings), got {names}"
            )
    elif v is None or scalar(v) is None:
        what = "a mapping" if isinstance(v, dict) else "nothing" if v is None else type(v).__name__
        raise ConfigError(
            f"value {shown!r}: a parameter is a bool, integer, number, string or a list of "
            f"one of these, got {what}"
        )


def set_param(s: Session, node: str, name: str, text: str) -> tuple[bool, str, Any]:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    node = _node_fqn(node)
    ((typ, _cur),) = _get(s, node, [name])
    if typ == 0:
        return False, f"{node} has no parameter '{name}'", None
    value = parse_value(text, typ)
    msg = Parameter(name, value=value).to_parameter_msg()
    res = _call(s, SetParameters, f"{node}/set_parameters", SetParameters.Request(parameters=[msg]))
    r = res.results[0]
    return r.successful, r.reason, value


def main_param(argv: list[str]) -> int:
    ap = Parser(prog="fluxdrive param", description="param list|get|set|dump")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="parameter names of a node")
    p.add_argument("node")
    _common(p)
    p = sub.add_parser("get", help="a parameter's value")
    p.add_argument("node")
    p.add_argument("name")
    p.add_argument("-v", "--verbose", action="store_true", help="also description and range")
    _common(p)
    p = sub.add_parser("set", help="set a parameter (the node validates it)")
    p.add_argument("node")
    p.add_argument("name")
    p.add_argument("value", help="YAML value, e.g. 50.0, measured, true, [1, 2]")
    _common(p)
    p = sub.add_parser("dump", help="all parameters as a ros__parameters YAML file")
    p.add_argument("node")
    p.add_argument("-o", "--output", help="write to this file instead of stdout")
    _common(p)
    args = ap.parse_args(argv)
    node = check_node_name(args.node, "NODE")
    if args.cmd in ("get", "set"):
        check_param_name(args.name)
    if args.cmd == "set":
        parse_value(args.value, None)  # the value's form, before any ROS call
    if args.cmd == "dump" and args.output:
        check_output(args.output, "--output", kind="file")
    s = Session(args)
    try:
        if args.cmd == "list":
            for n in _list(s, node):
                print(n)
            return 0
        if args.cmd == "get":
            ((typ, val),) = _get(s, node, [args.name])
            if typ == 0:
                print(f"{node} has no parameter '{args.name}'", file=sys.stderr)
                return 1
            print(f"{args.name}: {val!r}")
            if args.verbose:
                d = _describe(s, node, [args.name])[0]
                print(f"  description: {d.description}")
                for r in d.floating_point_range:
                    print(f"  range: [{r.from_value}, {r.to_value}]")
                for r in d.integer_range:
                    print(f"  range: [{r.from_value}, {r.to_value}]")
                if d.additional_constraints:
                    print(f"  constraints: {d.additional_constraints}")
                print(f"  read-only: {d.read_only}")
            return 0
        if args.cmd == "set":
            ok, reason, value = set_param(s, node, args.name, args.value)
            if ok:
                print(f"set {node} {args.name} = {value!r}" + (f": {reason}" if reason else ""))
                return 0
            print(f"rejected: {node} {args.name} = {args.value}: {reason}", file=sys.stderr)
            return 1
        names = _list(s, node)
        vals = _get(s, node, names)
        params = {n: v for n, (_, v) in zip(names, vals, strict=True)}
        text = yaml.safe_dump({node: {"ros__parameters": params}}, sort_keys=True)
        if args.output:
            with open(args.output, "w") as fh:
                fh.write(text)
            print(f"wrote {args.output}")
        else:
            print(text, end="")
        return 0
    except (LookupError, TimeoutError) as exc:
        print(f"fluxdrive param: {exc}", file=sys.stderr)
        return 1
    finally:
        s.close()


OPERATOR_NODE = "fluxdrive_operator"  # fluxdrive_ros.access.DEFAULT_OPERATORS


def main_fault(argv: list[str]) -> int:
    """`./fluxdrive fault reset [SERVICE]`: clear a latched drive fault (the only way one is
    cleared).  Runs as node /fluxdrive_operator, the name the controller's
    allowed_operators (and a bench bridge's allowed_commanders, if listed) must contain."""
    ap = Parser(prog="fluxdrive fault", description=main_fault.__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("reset", help="clear a latched fault")
    p.add_argument(
        "service",
        nargs="?",
        default="/controller/reset_fault",
        help="ResetFault service (default /controller/reset_fault; the bench "
        "bridge's is /drive/reset_fault)",
    )
    _common(p)
    args = ap.parse_args(argv)
    check_service_name(args.service, "SERVICE")
    s = Session(args, node_name=OPERATOR_NODE)
    try:
        ok, message = reset_fault(s, args.service)
    except (LookupError, TimeoutError) as exc:
        print(f"fault reset: {exc}", file=sys.stderr)
        return 1
    finally:
        s.close()
    print(f"{args.service}: {'ok' if ok else 'REFUSED'}: {message}")
    return 0 if ok else 1


def reset_fault(s: Session, service: str = "/controller/reset_fault") -> tuple[bool, str]:
    """Ask `service` (ResetFault) to clear a latched fault, as the operator: `s` must be a
    Session whose node is OPERATOR_NODE (the name the controller's allowed_operators holds).
    Used by `fault reset` and the scope's reset button.  (success, the server's message);
    LookupError/TimeoutError if the service does not answer."""
    from flux_drive_msgs.srv import ResetFault

    t_end = time.monotonic() + max(s.wait_s, 5.0)
    while True:
        res = _call(s, ResetFault, service, ResetFault.Request())
        # the server checks its clients by discovery, which may not show us yet
        if (
            res.success
            or "not known to the graph yet" not in res.message
            or time.monotonic() > t_end
        ):
            return bool(res.success), str(res.message)
        s.spin_for(0.3)
