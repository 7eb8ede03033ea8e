"""`./fluxdrive foxglove`: every topic and every parameter of a running graph, served to
Foxglove / Lichtblick with the Foxglove SDK (foxglove-sdk from PyPI).

    ./fluxdrive foxglove [--port 8765] [--host 127.0.0.1] [--domain-id N] [--clock /clock]
                         [--allow-origin ORIGIN] [--allow-host NAME] [--max-clients 100]

prints `foxglove: ws://127.0.0.1:8765/?token=...` -- connect a viewer to that URL ("Open
connection" -> "Foxglove WebSocket"), token included.  Only the operator connects: every
connection needs the token (drawn afresh per launch), a Host header naming this machine and,
from a browser, an Origin of this machine or one given with --allow-origin (a web viewer's,
e.g. `--allow-origin https://viewer.example`); at most --max-clients at once, the next is
refused at once (fluxdrive_bringup.view.gate; docs/safety.md).

The server speaks the WebSocket subprotocol `foxglove.sdk.v1` (foxglove-sdk 0.30); a client that
offers only the older name of the same protocol, `foxglove.websocket.v1` (Lichtblick <= 1.21,
@foxglove/ws-protocol's default), is served too: the gate renames the subprotocol in the
handshake both ways (docs/scope.md).

Topics: found by discovery (every second); each becomes a channel with message encoding
`cdr` and schema encoding `ros2msg` (the message definition with its dependencies, as a
rosbag2 MCAP file embeds it; generated from the project's .msg files and the Jazzy
standard types).  A ROS subscription (raw: the CDR bytes go out untouched) exists only while
a viewer subscribes to the channel; each message goes out with its receive time.  Reader
QoS follows the publishers: best effort if any publisher is, transient-local (the writer's
last messages at subscription) only for latched topics (every publisher transient-local
with a history of at most 100).

Capabilities: parameters, services, time.

Parameters: `/node.name` for every parameter of every node with parameter services
(`./fluxdrive param` underneath); a set the node refuses is reported to the viewer as a
warning status message with the node's reason, and the parameter keeps its value.  A viewer
subscribed to parameters (parametersSubscribe) gets every change of them, whoever made it
(`./fluxdrive param set`, the scope, another node): the bridge follows /parameter_events.

Services: every ResetFault (`<controller>/reset_fault`, a bench bridge's) and Arm
(`/drive/arm`) service of the graph, found by discovery, called with cdr request and
response; the bridge calls them as node /fluxdrive_operator (the operator the controller's
`allowed_operators` names, as `./fluxdrive fault reset` does) -- which is why only the
token's holder may connect at all.

Time: the graph's `/clock` (`--clock`, e.g. /bench_a/clock for a namespaced drive) is
broadcast as the server time, and every message goes out with the newest /clock time as its
log time (a stamped message: its own header stamp, the same sample time without racing the
clock), so a viewer's timeline is the drive's sample time; without a /clock (a bench) the
wall clock at reception.

Cost: every subscribed per-sample topic of a 10 kHz lockstep graph crosses DDS into this
process (as the split layout's recorder does): the graph slows accordingly.  For a live
view at full rate with little cost use `./fluxdrive scope` (decimated in the graph's process).
"""

from __future__ import annotations

import json
import os
import struct
import sys
import threading
import time
from typing import Any

from fluxdrive.core.schema import Parser, option
from fluxdrive.io.graphfile import GraphSettings, ServeOptions

from fluxdrive_bringup.view.gate import access_from_args, add_access_options

SUBPROTOCOL = "foxglove.sdk.v1"
BRIDGE_NODE = "fluxdrive_foxglove"
# services a viewer may call: ROS service type -> its .srv file in flux_drive_msgs
SERVICE_TYPES = ("flux_drive_msgs/srv/ResetFault", "flux_drive_msgs/srv/Arm")
TIME_BROADCAST_S = 0.02  # at most 50 server-time updates a second


def srv_schemas(srv_type: str) -> tuple[str, str]:
    """(request, response) ros2msg text of a flux_drive_msgs service (the .srv file's two
    halves; these services use built-in field types only)."""
    from fluxdrive.core.paths import MSG_DIR

    name = srv_type.rsplit("/", 1)[-1]
    text = (MSG_DIR.parent / "srv" / f"{name}.srv").read_text()
    req, _, resp = text.partition("\n---\n")
    return req.strip() + "\n", resp.strip() + "\n"


def ros2msg_schema(msgtype: str) -> str:
    """The ros2msg text of a type (definition + dependencies), from the project's one
    typestore (fluxdrive.io.bagio.typestore: Jazzy standard types + flux_drive_msgs)."""
    from fluxdrive.io.bagio import typestore

    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text


class Bridge:
    def __init__(self, args):
        import foxglove
        import rclpy
        from foxglove.websocket import Capability
        from rclpy.executors import SingleThreadedExecutor

        from fluxdrive_bringup.inspect.commands import Session

        self.args = args
        self.foxglove = foxglove
        self.ctx = rclpy.Context()
        rclpy.init(args=None, context=self.ctx, domain_id=args.domain_id)
        self.node = rclpy.create_node(BRIDGE_NODE, context=self.ctx, start_parameter_services=False)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.lock = threading.Lock()  # channels / subscriptions (ROS thread + SDK threads)
        self.channels: dict[str, Any] = {}  # topic -> foxglove Channel
        self.by_id: dict[int, str] = {}
        self.subs: dict[str, Any] = {}  # topic -> rclpy subscription
        # topics whose subscription the ROS thread is to make or drop: the SDK's threads ask,
        # the ROS thread (the one spinning the executor) does it -- an rclpy subscription
        # made from another thread while the executor waits may never be served
        self.to_change: set[str] = set()
        self.refs: dict[str, int] = {}  # topic -> subscribed viewers
        self.skipped: set[str] = set()
        self.params = Session(
            domain_id=args.domain_id, wait_s=3.0, node_name="fluxdrive_foxglove_params"
        )
        self.params_lock = threading.Lock()
        self.param_subs: set[str] = set()  # `/node.name` a viewer subscribed to
        self.services: dict[str, str] = {}  # ROS service -> type, offered to viewers
        self.operator = None  # Session as /fluxdrive_operator (service calls), on demand
        self.operator_lock = threading.Lock()
        self.sim_ns: int | None = None  # newest /clock [ns]
        self._clock_seen = False  # a publisher of the clock topic was seen
        self._t_time = 0.0
        # the SDK's server listens on a loopback port in TLS with a certificate of this
        # launch only the gate trusts; the gate owns the public port and its rules
        from fluxdrive_ros.security import loopback_tls_pair

        from fluxdrive_bringup.view.gate import FoxgloveGate

        cert, key = loopback_tls_pair()
        self.server = foxglove.start_server(
            name="fluxdrive",
            host="127.0.0.1",
            port=0,
            capabilities=[Capability.Parameters, Capability.Services, Capability.Time],
            server_listener=self,
            supported_encodings=["cdr"],
            tls_cert=cert,
            tls_key=key,
        )
        self.gate = FoxgloveGate(args.access, self.server.port, cert)
        try:
            self.gate.start(args.host, args.port)
        except BaseException:
            self.server.stop()
            raise
        self.stop = threading.Event()
        from rcl_interfaces.msg import ParameterEvent
        from rclpy.qos import qos_profile_parameter_events
        from rosgraph_msgs.msg import Clock

        self.node.create_subscription(
            ParameterEvent,
            "/parameter_events",
            self._on_parameter_event,
            qos_profile_parameter_events,
        )
        self.node.create_subscription(Clock, args.clock, self._on_clock, 10)

    # ------------------------------------------------------------------ channels
    def discover(self) -> None:
        self._discover_services()
        for topic, types in self.node.get_topic_names_and_types():
            if topic in self.channels or topic in self.skipped or not types:
                continue
            try:
                schema = ros2msg_schema(types[0])
            except Exception as exc:  # noqa: BLE001 - a type the typestore does not know
                self.skipped.add(topic)
                print(
                    f"foxglove: {topic} ({types[0]}) not served: no definition ({exc})", flush=True
                )
                continue
            ch = self.foxglove.Channel(
                topic,
                message_encoding="cdr",
                schema=self.foxglove.Schema(
                    name=types[0], encoding="ros2msg", data=schema.encode()
                ),
            )
            with self.lock:
                self.channels[topic] = (ch, types[0])
                self.by_id[ch.id()] = topic
            print(f"foxglove: serving {topic} ({types[0]})", flush=True)

    def _qos(self, topic: str):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        infos = self.node.get_publishers_info_by_topic(topic)
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
        latched = bool(infos) and all(
            i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
            and 0 < i.qos_profile.depth <= 100
            for i in infos
        )
        return QoSProfile(
            depth=1000,
            reliability=ReliabilityPolicy.BEST_EFFORT
            if best_effort
            else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        )

    # ServerListener (called from the SDK's threads)
    def on_subscribe(self, client, channel) -> None:
        topic = self.by_id.get(channel.id)
        if topic is None:
            return
        with self.lock:
            self.refs[topic] = self.refs.get(topic, 0) + 1
            self.to_change.add(topic)

    def on_unsubscribe(self, client, channel) -> None:
        topic = self.by_id.get(channel.id)
        if topic is None:
            return
        with self.lock:
            self.refs[topic] = max(0, self.refs.get(topic, 0) - 1)
            self.to_change.add(topic)

    def apply_subscriptions(self) -> None:
        """(ROS thread) Make the subscriptions clients asked for, drop the unwanted ones."""
        with self.lock:
            if not self.to_change:
                return
            todo, self.to_change = self.to_change, set()
            for topic in todo:
                wanted = self.refs.get(topic, 0) > 0
                if wanted and topic not in self.subs:
                    self.subs[topic] = self._subscribe(topic)
                elif not wanted and topic in self.subs:
                    self.node.destroy_subscription(self.subs.pop(topic))

    def _subscribe(self, topic: str):
        from fluxdrive_ros.topics import msg_class

        ch, mtype = self.channels[topic]
        log = ch.log
        fields = list(msg_class(mtype).get_fields_and_field_types().items())
        stamped = bool(fields) and fields[0] == ("header", "std_msgs/Header")

        def cb(data: bytes) -> None:
            t = self.sim_ns  # the drive's sample time when it has a /clock
            if stamped and len(data) >= 12 and self._graph_has_clock():
                # a sim graph: a stamped message's own stamp is its sample time on the
                # /clock's time base; the newest /clock would race it (DDS delivers the
                # two topics in any order, and a lockstep graph runs ahead of its clock)
                sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
                t = sec * 1_000_000_000 + nsec
            log(data, log_time=time.time_ns() if t is None else t)

        return self.node.create_subscription(
            msg_class(mtype), topic, cb, self._qos(topic), raw=True
        )

    # ------------------------------------------------------------------ time
    def _graph_has_clock(self) -> bool:
        """True once a publisher of the graph's clock topic is known (sim graphs)."""
        if not self._clock_seen:
            self._clock_seen = (
                self.sim_ns is not None or self.node.count_publishers(self.args.clock) > 0
            )
        return self._clock_seen

    def _on_clock(self, msg) -> None:
        self.sim_ns = msg.clock.sec * 1_000_000_000 + msg.clock.nanosec
        now = time.monotonic()
        if now - self._t_time >= TIME_BROADCAST_S:
            self._t_time = now
            self.server.broadcast_time(self.sim_ns)

    # ------------------------------------------------------------------ services
    def _discover_services(self) -> None:
        new = []
        for name, types in self.node.get_service_names_and_types():
            t = next((t for t in types if t in SERVICE_TYPES), None)
            if t is None or name in self.services:
                continue
            req, resp = srv_schemas(t)
            Schema, MessageSchema = self.foxglove.Schema, self.foxglove.websocket.MessageSchema  # noqa: N806
            new.append(
                self.foxglove.websocket.Service(
                    name,
                    schema=self.foxglove.websocket.ServiceSchema(
                        t,
                        request=MessageSchema(
                            encoding="cdr",
                            schema=Schema(
                                name=f"{t}_Request", encoding="ros2msg", data=req.encode()
                            ),
                        ),
                        response=MessageSchema(
                            encoding="cdr",
                            schema=Schema(
                                name=f"{t}_Response", encoding="ros2msg", data=resp.encode()
                            ),
                        ),
                    ),
                    handler=self._service_handler(name, t),
                )
            )
            self.services[name] = t
            print(f"foxglove: service {name} ({t})", flush=True)
        if new:
            self.server.add_services(new)

    def _service_handler(self, service: str, srv_type: str):
        """A viewer's call of `service`: the cdr request decoded, the ROS service called as
        the operator, the cdr response returned (an exception: a call failure with its text)."""
        import importlib

        from rclpy.serialization import deserialize_message, serialize_message

        pkg, _, name = srv_type.replace("/srv/", "/").partition("/")
        cls = getattr(importlib.import_module(f"{pkg}.srv"), name)

        def handler(request) -> bytes:
            from fluxdrive_bringup.inspect.commands import (
                OPERATOR_NODE,
                Session,
                _call,
                reset_fault,
            )

            req = (
                deserialize_message(bytes(request.payload), cls.Request)
                if request.payload
                else cls.Request()
            )
            with self.operator_lock:
                if self.operator is None:
                    self.operator = Session(
                        domain_id=self.args.domain_id, wait_s=5.0, node_name=OPERATOR_NODE
                    )
                if name == "ResetFault":
                    ok, message = reset_fault(self.operator, service)
                    resp = cls.Response(success=ok, message=message)
                else:
                    resp = _call(self.operator, cls, service, req)
            print(f"foxglove: call {service}: {resp.success} {resp.message!r}", flush=True)
            return serialize_message(resp)

        return handler

    # ------------------------------------------------------------------ parameters
    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        with self.params_lock:
            self.param_subs.update(param_names)

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        with self.params_lock:
            self.param_subs.difference_update(param_names)

    def _on_parameter_event(self, event) -> None:
        """A node's parameters changed (whoever set them): the new values to the viewers
        subscribed to them."""
        from rclpy.parameter import parameter_value_to_python

        Parameter = self.foxglove.Parameter  # noqa: N806
        with self.params_lock:
            subs = set(self.param_subs)
        out = []
        for p in [*event.new_parameters, *event.changed_parameters]:
            full = f"{event.node}.{p.name}"
            if full not in subs:
                continue
            v = parameter_value_to_python(p.value)
            v = list(v) if isinstance(v, (list, tuple)) or hasattr(v, "tolist") else v
            try:
                out.append(Parameter(full, value=v))
            except (TypeError, ValueError):
                out.append(Parameter(full, value=json.dumps(v)))
        if out:
            self.server.publish_parameter_values(out)

    def _nodes(self) -> list[str]:
        s = self.params
        out = []
        # by name, not by node: a process's services are served by a hidden node of its own
        # (fluxdrive_ros.services)
        svcs = {n for n, _ in s.node.get_service_names_and_types()}
        for name, ns in s.node.get_node_names_and_namespaces():
            fqn = f"{ns.rstrip('/')}/{name}"
            if f"{fqn}/get_parameters" in svcs:
                out.append(fqn)
        return sorted(set(out))

    def _values(self, names: list[str]) -> list:
        """foxglove Parameters for `/node.param` names; [] = every parameter of every node."""
        from fluxdrive_bringup.inspect.commands import _get, _list

        Parameter = self.foxglove.Parameter  # noqa: N806
        want: dict[str, list[str]] = {}
        if names:
            for full in names:
                node, _, pname = full.partition(".")
                if pname:
                    want.setdefault(node, []).append(pname)
        else:
            self.params.spin_for(0.1)
            for node in self._nodes():
                try:
                    want[node] = _list(self.params, node)
                except (LookupError, TimeoutError):
                    continue
        out = []
        for node, pnames in want.items():
            try:
                vals = _get(self.params, node, pnames)
            except (LookupError, TimeoutError):
                continue
            for pname, (typ, v) in zip(pnames, vals, strict=True):
                if typ == 0:
                    continue
                v = v.tolist() if hasattr(v, "tolist") else v
                try:
                    out.append(Parameter(f"{node}.{pname}", value=v))
                except (TypeError, ValueError):
                    out.append(Parameter(f"{node}.{pname}", value=json.dumps(v)))
        return out

    def on_get_parameters(self, client, param_names, request_id=None):
        with self.params_lock:
            return self._values(list(param_names))

    def on_set_parameters(self, client, parameters, request_id=None):
        from fluxdrive_bringup.inspect.commands import set_param

        names = []
        with self.params_lock:
            for p in parameters:
                node, _, pname = p.name.partition(".")
                names.append(p.name)
                v = p.get_value()
                text = v if isinstance(v, str) else json.dumps(v)
                try:
                    ok, reason, _ = set_param(self.params, node, pname, text)
                except (LookupError, TimeoutError, ValueError) as exc:  # ValueError: ConfigError
                    ok, reason = False, str(exc)
                print(
                    f"foxglove: set {node} {pname} = {text}: "
                    f"{'ok' if ok else 'REFUSED: ' + reason}",
                    flush=True,
                )
                if not ok:
                    self.server.publish_status(
                        f"{p.name} = {text} refused: {reason}",
                        self.foxglove.websocket.StatusLevel.Warning
                        if hasattr(self.foxglove.websocket, "StatusLevel")
                        else self.foxglove.StatusLevel.Warning,
                    )
            return self._values(names)

    # ------------------------------------------------------------------ run
    def run(self) -> int:
        host = self.args.host if self.args.host not in ("0.0.0.0", "::", "") else "127.0.0.1"
        print(
            f"foxglove: ws://{host}:{self.gate.port}/?token={self.args.access.token} "
            f"(WebSocket subprotocol {SUBPROTOCOL}; ROS_DOMAIN_ID={self.args.domain_id}; "
            f"at most {self.args.access.max_clients} clients)",
            flush=True,
        )
        import signal

        def on_signal(*_a) -> None:
            self.stop.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, on_signal)
        t_disc = 0.0
        try:
            while not self.stop.is_set() and self.ctx.ok():
                if time.monotonic() - t_disc > 1.0:
                    t_disc = time.monotonic()
                    self.discover()
                self.apply_subscriptions()
                self.ex.spin_once(timeout_sec=0.02)
        finally:
            self.gate.stop()
            self.server.stop()
            self.params.close()
            if self.operator is not None:
                self.operator.close()
            try:
                self.node.destroy_node()
                self.ex.shutdown()
                self.ctx.try_shutdown()
            except Exception:  # noqa: BLE001
                pass
        return 0


def main(argv: list[str] | None = None) -> int:
    ap = Parser(prog="fluxdrive foxglove", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default 127.0.0.1: this machine only; another address lets "
        "anyone who reaches it and holds the token operate the drive)",
    )
    option(ap, "--port", ServeOptions, help="TCP port (default 8765; 0: any)")
    add_access_options(ap)
    option(ap, "--domain-id", GraphSettings, help="ROS_DOMAIN_ID of the graph")
    ap.add_argument(
        "--clock",
        default="/clock",
        help="the graph's clock topic, served as the viewer's time (default /clock; a "
        "namespaced drive's: /NS/clock)",
    )
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.domain_id is None:
        args.domain_id = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    args.access = access_from_args(args, "foxglove")
    try:
        import foxglove  # noqa: F401
    except ImportError:
        print(
            "foxglove: foxglove-sdk is not installed; run ./fluxdrive help (set-up) first",
            file=sys.stderr,
        )
        return 2
    try:
        b = Bridge(args)
    except (RuntimeError, OSError) as exc:  # the gate or the SDK cannot bind its port
        print(
            f"foxglove: cannot start the server on {args.host}:{args.port}: {exc}", file=sys.stderr
        )
        return 1
    return b.run()


if __name__ == "__main__":
    sys.exit(main())
