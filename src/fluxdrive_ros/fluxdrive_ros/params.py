"""Declared ROS parameters from one table per node: description, unit, range, choices,
read-only or live; plus the set-parameters callback that validates a change as a whole and
rejects it with a reason.

Conventions
- every tunable is declared with a description that ends in its unit, e.g. "[Hz]";
- numbers carry a FloatingPointRange / IntegerRange, strings their choices (checked here,
  listed in additional_constraints);
- an integer given for a double parameter (YAML `250` for 250.0) is accepted and converted
  (rclpy itself refuses it at declare time);
- a node's `apply(changes)` is called with {name: value} of a proposed change; it raises
  ValueError (or fluxdrive's ConfigError) with the reason to reject, or returns a short
  note for the successful result (e.g. the sample at which the change took effect).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.parameter import Parameter


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

    def descriptor(self) -> ParameterDescriptor:
        text = self.description + (f" [{self.unit}]" if self.unit else "")
        d = ParameterDescriptor(description=text, read_only=self.read_only)
        if self.choices:
            d.additional_constraints = "one of: " + ", ".join(self.choices)
        if self.lo is not None and isinstance(self.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(self.lo),
                                                         to_value=float(self.hi), step=0.0)]
        elif self.lo is not None and isinstance(self.default, int) and not isinstance(
                self.default, bool):
            d.integer_range = [IntegerRange(from_value=int(self.lo), to_value=int(self.hi),
                                            step=1)]
        return d

    def check(self, value: Any) -> str | None:
        """Reason why `value` is not acceptable, or None."""
        if self.choices and value not in self.choices:
            return f"{self.name} must be one of {list(self.choices)}, got {value!r}"
        if self.lo is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
            if math.isnan(value) or not (self.lo <= value <= self.hi):
                return (f"{self.name} = {value} is out of range [{self.lo}, {self.hi}]"
                        + (f" {self.unit}" if self.unit else ""))
        return None


def declare(node, specs: list[P]) -> dict[str, Any]:
    """Declare every parameter of `specs` on `node` and return {name: value}."""
    overrides = getattr(node, "_parameter_overrides", {})
    out = {}
    for s in specs:
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


def on_set(node, specs: list[P], apply: Callable[[dict[str, Any]], str | None]) -> None:
    """Install the validating set-parameters callback."""
    table = {s.name: s for s in specs}

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
        return SetParametersResult(successful=True, reason=note or "")

    node.add_on_set_parameters_callback(cb)
