"""Topic names and message types of the fluxdrive graph (one place, used by every node,
the recorder, the launcher and the inspection tools).  Defined in fluxdrive.io.topics (the
engine's bag I/O needs them without ROS); this module adds what needs rclpy."""

from __future__ import annotations

import re
from typing import Any

from fluxdrive.core.machine import ConfigError
from fluxdrive.io.topics import (  # noqa: F401 - re-exported: the one definition
    CLOCK,
    CONTROLLER_STATE,
    CURRENT_REF,
    DIAGNOSTICS,
    DONE,
    DUTY,
    ESTIMATE,
    FAULT,
    FRAME,
    MARKER,
    OBS_NAMESPACE,
    ROSOUT,
    SCOPE_ENVELOPE,
    T_CLOCK,
    T_DONE,
    T_DUTY,
    T_ESTIMATE,
    T_FAULT,
    T_FRAME,
    T_MARKER,
    T_REFERENCE,
    T_STATE,
    T_STRING,
    T_TRUTH,
    T_UINT64,
    TRUTH,
    estimate_topic,
)


def msg_class(type_name: str):
    """rclpy message class of 'pkg/msg/Name'."""
    import importlib

    pkg, _, name = type_name.replace("/msg/", "/").partition("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def drive_namespace(node) -> str:
    """The namespace of the drive a node belongs to: its own namespace, without the
    observers' trailing /obs (an observer /a/obs/flux_measured belongs to drive /a)."""
    ns = node.get_namespace().rstrip("/")
    if ns == OBS_NAMESPACE or ns.endswith(OBS_NAMESPACE):
        ns = ns[: -len(OBS_NAMESPACE)]
    return ns or "/"


def rel(topic: str) -> str:
    """The drive-relative name of a canonical graph topic: '/drive/frame' -> 'drive/frame'."""
    return topic.lstrip("/")


def drive_topic(node, canonical: str) -> str:
    """A canonical graph topic (fluxdrive.io.topics, e.g. FRAME) in `node`'s drive."""
    return in_drive(node, rel(canonical))


def drive_names(node, names: list[str]) -> list[str]:
    """Node names of a drive-relative allow-list (`/controller`) in `node`'s drive
    (`/a/controller` in drive /a); '*' and '' stay."""
    ns = drive_namespace(node).rstrip("/")
    return [n if (not n or n == "*" or not ns) else ns + "/" + n.lstrip("/") for n in names]


def in_drive(node, topic: str) -> str:
    """A graph topic for `node`: a relative name (`drive/frame`) resolves in the node's
    drive namespace (so `__ns:=/a` moves the whole drive to /a/drive/frame); an absolute
    name is kept (a user's `frame_topic: /elsewhere/frame`).  The canonical names of
    fluxdrive.io.topics (`/drive/frame`) are the drive-relative names with a leading /."""
    if topic.startswith("/") or topic.startswith("~"):
        return topic
    ns = drive_namespace(node)
    return (ns.rstrip("/") + "/" + topic) if ns != "/" else "/" + topic


ROS_NAME_RE = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def check_ros_name(value: Any, where: str, kind: str = "name") -> str:
    """A node, topic or service name as a user gave it ('plant' -> '/plant'), or ConfigError
    naming `where` -- checked before rclpy sees it (rclpy raises its own exception types,
    or a 500 in a server, on names it cannot form)."""
    if not isinstance(value, str) or len(value) > 255 or not ROS_NAME_RE.fullmatch(value):
        shown = repr(value)[:80]
        raise ConfigError(
            f"{where} must be a ROS {kind} like /controller/reset_fault (letters, digits, _ "
            f"between slashes, not starting with a digit), got {shown}"
        )
    return value if value.startswith("/") else "/" + value


def check_service_name(value: Any, where: str) -> str:
    return check_ros_name(value, where, "service name")


def check_node_name(value: Any, where: str) -> str:
    return check_ros_name(value, where, "node name")


def check_namespace(value: Any, where: str) -> str:
    """A drive namespace ('/a', 'a/b' -> '/a/b'; None or '' -> ''), or ConfigError naming
    `where`."""
    if value is None or value == "":
        return ""
    text = str(value).strip("/")
    if not isinstance(value, str) or not re.fullmatch(
        r"[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*", text
    ):
        raise ConfigError(
            f"{where} must be a ROS namespace like /bench_a (letters, digits, _), got {value!r}"
        )
    return "/" + text
