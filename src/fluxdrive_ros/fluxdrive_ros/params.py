"""Declared ROS parameters from one table per node: description, unit, range, choices,
read-only or live; plus the set-parameters callback that validates a change as a whole and
rejects it with a reason.

Conventions
- every tunable is declared with a description that ends in its unit, e.g. "[Hz]" ("[-]"
  for a dimensionless number);
- numbers carry a FloatingPointRange / IntegerRange, strings their choices (checked here,
  listed in additional_constraints);
- an integer given for a double parameter (YAML `250` for 250.0) is accepted and converted
  (rclpy itself refuses it at declare time);
- a node's `apply(changes)` is called with {name: value} of a proposed change; it raises
  ValueError (or fluxdrive's ConfigError) with the reason to reject, or returns a short
  note for the successful result (e.g. the sample at which the change took effect);
- every change a node accepts is published by the node itself as a ParameterMarker on
  drive/param_marker (seq = the first sample the new value holds for, source "node"), so
  a change from any client (`./fluxdrive param set`, the scope, Foxglove, a foreign node)
  is in the bag where it took effect and replay can apply it there
  (fluxdrive.io.bagio.RunBag.markers).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fluxdrive.core import schema, yamlio
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.parameter import Parameter

from fluxdrive_ros import qos, topics


@dataclass
class P:
    """One parameter: name, default, description, unit, range or choices, live or not."""

    name: str
    default: Any
    description: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = False
    # the schema field it is declared from (`P.of`); `declare` refuses a parameter without one
    spec: schema.Spec | None = None

    @property
    def numeric(self) -> bool:
        return isinstance(self.default, (int, float)) and not isinstance(self.default, bool)

    def descriptor(self) -> ParameterDescriptor:
        unit = self.unit or ("-" if self.numeric else "")  # [-]: dimensionless
        text = self.description + (f" [{unit}]" if unit else "")
        d = ParameterDescriptor(description=text, read_only=self.read_only)
        if self.choices:
            d.additional_constraints = "one of: " + ", ".join(self.choices)
        if self.lo is not None and self.hi is not None and isinstance(self.default, float):
            d.floating_point_range = [
                FloatingPointRange(from_value=float(self.lo), to_value=float(self.hi), step=0.0)
            ]
        elif (
            self.lo is not None
            and self.hi is not None
            and isinstance(self.default, int)
            and not isinstance(self.default, bool)
        ):
            d.integer_range = [IntegerRange(from_value=int(self.lo), to_value=int(self.hi), step=1)]
        return d

    def check(self, value: Any) -> str | None:
        """Reason why `value` is not acceptable, or None."""
        if self.choices and value not in self.choices:
            return f"{self.name} must be one of {list(self.choices)}, got {value!r}"
        if (
            self.lo is not None
            and self.hi is not None
            and isinstance(value, (int, float))
            and not isinstance(value, bool)
        ):
            if math.isnan(value) or not (self.lo <= value <= self.hi):
                return f"{self.name} = {value} is out of range [{self.lo}, {self.hi}]" + (
                    f" {self.unit}" if self.unit else ""
                )
        return None

    @classmethod
    def of(cls, spec: schema.Spec, value: Any, rng: tuple[float, float] | None = None) -> P:
        """The parameter of one schema field (`fluxdrive.core.schema`): its text, unit, range
        (`rng`: narrowed on the card) or choices, read-only unless the field is live."""
        text = spec.doc + (f"; unset: {spec.rule.text}" if spec.rule is not None else "")
        text += " (live)" if spec.live else ""
        lo, hi = rng if rng is not None else (spec.lo, spec.hi)
        fixed = not spec.live
        if spec.choices is not None or spec.kind is str:
            return P(spec.name, str(value), text, choices=spec.choices, read_only=fixed, spec=spec)
        if spec.kind is bool:
            return P(spec.name, bool(value), text, read_only=fixed, spec=spec)
        if spec.kind is tuple:  # a list of strings; ROS infers no type from [] so [""] for none
            return P(spec.name, [str(x) for x in value] or [""], text, read_only=fixed, spec=spec)
        value = int(value) if spec.kind is int else float(value)
        unit = "" if spec.unit == "-" else spec.unit
        return P(spec.name, value, text, unit, lo, hi, read_only=fixed, spec=spec)


def config_params(cfg, card=None, decimation: int = 1, *, skip: tuple[str, ...] = ()) -> list[P]:
    """The declared parameters of an engine config (ControllerConfig, ObserverConfig, ...),
    every field but `skip` from its schema: default from `cfg` (a model field left None: the
    card's value; a field whose None means "off": 0.0, as ROS has no None), text, unit and
    live from the field, range as accepted on `card` at `decimation` (`schema.ranges`)."""
    rng = schema.ranges(cfg, card, decimation)
    out = []
    for name, s in schema.specs(cfg).items():
        if name in skip:
            continue
        v = getattr(cfg, name)
        r = rng.get(name)
        if v is None and s.card_default is not None:
            v = getattr(card, s.card_default)
        if s.none_is_zero and r is not None:
            v, r = (0.0 if v is None else v), (0.0, r[1])
        out.append(P.of(s, v, r))
    return out


def to_config(cfg, values: dict[str, Any]):
    """`cfg` with the parameter values of its fields applied (0.0 -> None for a field whose
    None means "off")."""
    table = schema.specs(cfg)
    kw = {
        k: (None if table[k].none_is_zero and v == 0.0 else v)
        for k, v in values.items()
        if k in table
    }
    return dataclasses.replace(cfg, **kw)


@dataclass
class FrameInput:
    """What every node stepping on PhaseFrames declares: its input topic, the readers'
    durability, and whether it exits once the run's last frame is processed."""

    frame_topic: str = schema.param(
        topics.rel(topics.FRAME),
        unit="",
        doc="PhaseFrame input topic (relative: in the drive's namespace)",
        live=False,
    )
    input_durability: str = schema.param(
        "volatile",
        unit="",
        doc="durability of the sample-topic subscriptions: volatile (matches any publisher) "
        "or transient_local (also receives what was published before the match; the "
        "lockstep sim graphs use it)",
        choices=qos.INPUT_DURABILITY_CHOICES,
        live=False,
    )
    exit_on_done: bool = schema.param(
        True, unit="", doc="exit once the frame named by /drive/done is processed"
    )


def input_durability_param() -> P:
    """The durability of a node's sample-topic readers (observer, controller, recorder)."""
    return config_params(FrameInput(), skip=("frame_topic", "exit_on_done"))[0]


def frame_input_params() -> list[P]:
    """What every node stepping on PhaseFrames declares (`FrameInput`)."""
    return config_params(FrameInput())


def declare(node, specs: list[P]) -> dict[str, Any]:
    """Declare every parameter of `specs` on `node` and return {name: value}; each must come
    from a schema field (`P.of`, `config_params`): a hand-written one is a TypeError.  The
    fields are kept in `node.param_specs` ({parameter name: Spec})."""
    overrides = getattr(node, "_parameter_overrides", {})
    declared = node.__dict__.setdefault("param_specs", {})
    out = {}
    for s in specs:
        if s.spec is None:
            raise TypeError(f"parameter {s.name!r} is not declared from a schema field")
        declared[s.name] = s.spec
        ov = overrides.get(s.name)
        if ov is not None and isinstance(s.default, float) and ov.type_ == Parameter.Type.INTEGER:
            overrides[s.name] = Parameter(s.name, Parameter.Type.DOUBLE, float(ov.value))
        p = node.declare_parameter(s.name, s.default, s.descriptor())
        v = p.value
        reason = s.check(v)
        if reason:
            raise ValueError(f"{node.get_fully_qualified_name()}: {reason}")
        out[s.name] = v
    return out


MARKER_SOURCE = "node"  # ParameterMarker.source of a marker the changed node published


def value_text(value: Any) -> str:
    """A parameter value as marker text: JSON (also YAML), floats exact (repr)."""
    if isinstance(value, (list, tuple)):
        value = list(value)
    return json.dumps(value)


def on_set(
    node,
    specs: list[P],
    apply: Callable[[dict[str, Any]], str | None],
    sample: Callable[[], int] | None = None,
    ts_s: float = 0.0,
) -> None:
    """Install the validating set-parameters callback.  With `sample` (the seq of the
    first sample a change applied now holds for) and the sample period `ts_s`, every
    accepted change is also published as a ParameterMarker (one per parameter) on the
    node's relative drive/param_marker topic, stamped with that sample's instant."""
    table = {s.name: s for s in specs}
    marker = _MarkerPublisher(node, ts_s) if sample is not None else None

    def cb(params: list[Parameter]) -> SetParametersResult:
        changes = {}
        for p in params:
            s = table.get(p.name)
            if s is None:
                continue  # not ours (use_sim_time, ...): rclpy's own checks apply
            v = p.value
            if isinstance(s.default, float) and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)
            reason = s.check(v)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
            changes[p.name] = v
        if not changes:
            return SetParametersResult(successful=True)
        try:
            note = apply(changes)
        except (ValueError, TypeError) as exc:  # ConfigError is a ValueError
            return SetParametersResult(successful=False, reason=str(exc))
        if note:
            node.get_logger().info(f"parameters {changes}: {note}")
        # a marker marks a change: a set to the value in force (a client re-sending a request
        # it saw no answer to, inspect.commands._call) changes nothing and is not marked again
        changed = {n: v for n, v in changes.items() if not _holds(node, n, v)}
        if marker is not None and sample is not None and changed:
            marker.publish(sample(), changed, note or "")
        return SetParametersResult(successful=True, reason=note or "")

    node.add_on_set_parameters_callback(cb)


def _holds(node, name: str, value: Any) -> bool:
    """Whether the node's parameter `name` holds `value` already (same type and value)."""
    try:
        now = node.get_parameter(name).value
    except Exception:  # noqa: BLE001 - not declared (yet): a change
        return False
    return type(now) is type(value) and now == value


class _MarkerPublisher:
    """The node's own ParameterMarker writer (a plain rclpy publisher, not the intra-process
    bus: several nodes of a process and tools elsewhere publish the same topic)."""

    def __init__(self, node, ts_s: float):
        from fluxdrive.io.messages import Stamp

        import flux_drive_msgs.msg as fm

        self.node = node
        self.cls = fm.ParameterMarker
        self.stamp = Stamp(ts_s)
        self.pub = node.create_publisher(
            self.cls, topics.in_drive(node, topics.MARKER.lstrip("/")), qos.MARKERS
        )
        self.fqn = node.get_fully_qualified_name()
        graph = getattr(node, "graph", None)
        self.graph_id = int(getattr(graph, "id", 0))

    def publish(self, seq: int, changes: dict[str, Any], note: str) -> None:
        seq = max(int(seq), 0)
        sec, nsec = self.stamp(seq)
        for name, value in changes.items():
            m = self.cls()
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            m.seq, m.graph_id = seq, self.graph_id
            m.node, m.name, m.value = self.fqn, name, value_text(value)
            m.successful, m.reason, m.source = True, note, MARKER_SOURCE
            self.pub.publish(m)


# --------------------------------------------------------------- ros__parameters files
def _key_regex(key: str) -> re.Pattern:
    """rcl's node-name patterns in parameter files: /ns/node, node, /**, /ns/*."""
    k = key if key.startswith("/") else "/" + key
    out = ""
    for part in re.split(r"(\*\*|\*)", k):
        out += ".*" if part == "**" else "[^/]*" if part == "*" else re.escape(part)
    return re.compile(out.replace("/.*", "(/.*)?") + "$")


def _esc(name: Any) -> str:
    """A name from a file as one line (a key may hold a newline or control characters)."""
    return str(name).encode("unicode_escape").decode("ascii")


def check_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """Read a ros__parameters file; raise ValueError naming the file (and the key) if it
    is not what rcl accepts: {node pattern: {ros__parameters: {name: value}}} with scalar
    values or lists of one scalar type.  Returns {node pattern: {name: value}} (nested
    names flattened with dots)."""
    path = Path(path)
    try:
        raw = yamlio.load_file(path)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read parameter file: {exc.strerror}") from exc
    except yamlio.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise ValueError(
            f"{path}: not valid YAML{line}: {getattr(exc, 'problem', None) or exc}"
        ) from exc
    if not isinstance(raw, dict):
        raise ValueError(
            f"{path}: a parameter file is a mapping of node names to "
            f"{{ros__parameters: {{...}}}}, got {type(raw).__name__}"
        )
    out: dict[str, dict[str, Any]] = {}
    for node_key, body in raw.items():
        if not isinstance(body, dict) or "ros__parameters" not in body:
            raise ValueError(f"{path}: '{_esc(node_key)}' must hold a 'ros__parameters' mapping")
        params = body["ros__parameters"]
        if not isinstance(params, dict):
            raise ValueError(
                f"{path}: '{_esc(node_key)}.ros__parameters' must be a mapping of "
                f"parameter names to values, got {type(params).__name__}"
            )
        out[str(node_key)] = _flatten(path, str(node_key), params, "", {})
    return out


def _flatten(
    path: Path, node_key: str, d: dict, prefix: str, flat: dict[str, Any]
) -> dict[str, Any]:
    for name, value in d.items():
        key = f"{prefix}{name}"
        where = f"{path}: '{_esc(node_key)}.ros__parameters.{_esc(key)}'"
        if isinstance(value, dict):
            _flatten(path, node_key, value, key + ".", flat)
            continue
        if isinstance(value, list):
            kinds = {type(v) for v in value}
            if not value or len(kinds) > 1 or not kinds <= {bool, int, float, str}:
                raise ValueError(
                    f"{where} must be a non-empty list of one type (bools, "
                    f"integers, doubles or strings), got {value!r}"
                )
        elif value is None or not isinstance(value, (bool, int, float, str)):
            raise ValueError(
                f"{where} must be a value (number, string, bool or list), got {value!r}"
            )
        flat[key] = value
    return flat


def file_values_for(paths: list[str], node_fqn: str) -> list[tuple[str, str, str, Any]]:
    """(file, node pattern, name, value) of every parameter the files set for node_fqn."""
    out = []
    for p in paths:
        for key, params in check_params_file(p).items():
            if _key_regex(key).match(node_fqn):
                out += [(str(p), key, name, v) for name, v in params.items()]
    return out


def blame(message: str, node_fqn: str, paths: list[str], inline: dict[str, Any]) -> str:
    """Where a parameter named in an error `message` was set: ' (set in FILE as
    NODE.ros__parameters.NAME)' or ' (set inline ...)'; '' if it cannot tell."""

    def named(name: str) -> bool:
        return re.search(rf"(?<![\w.]){re.escape(name)}(?![\w])", message) is not None

    for name in inline:
        if named(name):
            return f" (set inline in the graph: {name} = {inline[name]!r})"
    try:
        hits = [h for h in file_values_for(paths, node_fqn) if named(h[2])]
    except ValueError:
        return ""
    if hits:
        f, key, name, _ = hits[-1]  # the last file wins, as in rcl
        return f" (set in {f} as {key}.ros__parameters.{name})"
    return ""
