"""Topic names and message types of the fluxdrive graph (one place, used by every node,
the recorder, the launcher and the inspection tools).  Defined in fluxdrive.io.topics (the
engine's bag I/O needs them without ROS); this module adds what needs rclpy."""

from __future__ import annotations

from fluxdrive.io.topics import (  # noqa: F401 - re-exported: the one definition
    CLOCK,
    CONTROLLER_STATE,
    DONE,
    DUTY,
    ESTIMATE,
    FRAME,
    MARKER,
    OBS_NAMESPACE,
    SCOPE_ENVELOPE,
    T_CLOCK,
    T_DONE,
    T_DUTY,
    T_ESTIMATE,
    T_FRAME,
    T_MARKER,
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
