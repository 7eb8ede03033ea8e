"""Topic names and message types of the fluxdrive graph: one place, used by the engine's
bag I/O and replay (no ROS import) and by every node, the recorder, the launcher and the
inspection tools (through fluxdrive_ros.topics, which re-exports these)."""

from __future__ import annotations

from fluxdrive.core.paths import MSG_DIR

FRAME = "/drive/frame"  # flux_drive_msgs/PhaseFrame, plant (or bench bridge) -> all
TRUTH = "/drive/truth"  # flux_drive_msgs/PlantTruth, simulation only
DUTY = "/drive/duty"  # flux_drive_msgs/DutyCommand, controller -> plant
CONTROLLER_STATE = "/drive/controller_state"  # flux_drive_msgs/ControllerState
# flux_drive_msgs/CurrentReference, controller -> bench bridge (split mode, instead of duties)
CURRENT_REF = "/drive/current_ref"
DONE = "/drive/done"  # flux_drive_msgs/RunDone: last seq of a finished run (latched)
CLOCK = "/clock"  # rosgraph_msgs/Clock: sim time of the plant
ESTIMATE = "estimate"  # relative: /obs/<name>/estimate (flux_drive_msgs/RotorEstimate)
OBS_NAMESPACE = "/obs"
FAULT = "/drive/fault"  # flux_drive_msgs/DriveFault: a fault latched or cleared (controller)
MARKER = "/drive/param_marker"  # flux_drive_msgs/ParameterMarker: an operator set a parameter
SCOPE_ENVELOPE = "/scope/envelope"  # std_msgs/UInt8MultiArray: display envelopes of the scope tap

T_FRAME = "flux_drive_msgs/msg/PhaseFrame"
T_TRUTH = "flux_drive_msgs/msg/PlantTruth"
T_DUTY = "flux_drive_msgs/msg/DutyCommand"
T_STATE = "flux_drive_msgs/msg/ControllerState"
T_REFERENCE = "flux_drive_msgs/msg/CurrentReference"
T_ESTIMATE = "flux_drive_msgs/msg/RotorEstimate"
T_UINT64 = "std_msgs/msg/UInt64"
T_DONE = "flux_drive_msgs/msg/RunDone"
T_CLOCK = "rosgraph_msgs/msg/Clock"
T_MARKER = "flux_drive_msgs/msg/ParameterMarker"
T_FAULT = "flux_drive_msgs/msg/DriveFault"
T_STRING = "std_msgs/msg/String"

# the .msg sources (the interface package's definitions, embedded in every bag)
MSG_SRC_DIR = MSG_DIR


def estimate_topic(observer: str) -> str:
    return f"{OBS_NAMESPACE}/{observer}/{ESTIMATE}"


# the recorder's settings (machine card, observers, scenario: the bag metadata's JSON) also
# travel as one latched message, so they survive any conversion of the bag
SETTINGS = "/fluxdrive/settings"  # std_msgs/String, JSON, one message at the start

# QoS the graph's publishers offer per topic (fluxdrive_ros.qos), recorded in every bag
# (offered_qos_profiles) so a playback offers the same: (history depth, durability); all
# reliable, keep-last.
SAMPLE_DEPTH = 10000
# shared by every node of the domain (rcl's and fluxdrive_ros.diagnostics' publishers)
ROSOUT = "/rosout"  # rcl_interfaces/Log
DIAGNOSTICS = "/diagnostics"  # diagnostic_msgs/DiagnosticArray
OFFERED_QOS: dict[str, tuple[int, str]] = {
    DONE: (1, "transient_local"),  # latched: a late reader still gets the end of the run
    SETTINGS: (1, "transient_local"),
    MARKER: (100, "transient_local"),
    FAULT: (100, "transient_local"),
    # rcl's rosout profile: the last 1000 lines, kept 10 s, for late readers (a recorder
    # that starts after the nodes still gets their first lines)
    ROSOUT: (1000, "transient_local"),
    DIAGNOSTICS: (10, "volatile"),  # fluxdrive_ros.diagnostics.QOS
}
OFFERED_LIFESPAN_S: dict[str, float] = {ROSOUT: 10.0}  # others: infinite
SAMPLE_QOS = (SAMPLE_DEPTH, "transient_local")  # every per-sample topic and /clock


def offered_qos(topic: str) -> tuple[int, str]:
    return OFFERED_QOS.get(topic, SAMPLE_QOS)


def offered_lifespan_s(topic: str) -> float | None:
    """The lifespan a topic's publishers offer [s]; None: infinite."""
    return OFFERED_LIFESPAN_S.get(topic)
