"""QoS profiles shared by every fluxdrive node (publishers and subscribers must agree).

Lockstep never drops: per-sample topics are RELIABLE with a deep KEEP_LAST history (a
second of samples at 10 kHz), so a reader that falls behind (the recorder, a shadow
observer) catches up instead of losing samples, and TRANSIENT_LOCAL, so a reader whose
discovery completes a little after the first samples still gets them from the writer's
history -- if it asks for TRANSIENT_LOCAL too (`input_durability`, set by the lockstep sim
graphs).  By default readers are VOLATILE, which matches any writer.
"""

from __future__ import annotations

import os

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

SAMPLE_DEPTH = 10000

# per-sample data written by the drive nodes (frames, truth, estimates, duty, state)
SAMPLES = QoSProfile(
    depth=SAMPLE_DEPTH,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# readers that want the writer's history (transient-local writers only)
SAMPLES_READER = SAMPLES


def restarted() -> int:
    """How often the launcher has restarted this process (on_death: restart), 0 at first."""
    try:
        return int(os.environ.get("FLUXDRIVE_RESTART_COUNT", "0") or 0)
    except ValueError:
        return 0


def reader(durability: str = "volatile") -> QoSProfile:
    """Sample-topic reader QoS.  volatile (the nodes' default) matches every writer, also a
    volatile one (a bench bridge or a bag replay publishing with plain depth-100 QoS: a
    transient-local reader would not match it); transient_local also gets what was
    published before the match (the lockstep sim graphs, whose writers are all ours).
    A process the launcher restarted reads volatile: it starts at the live samples instead
    of replaying (and answering) up to SAMPLE_DEPTH samples of the writers' history."""
    if durability == "volatile" or restarted():
        return QoSProfile(
            depth=SAMPLE_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE,
            history=HistoryPolicy.KEEP_LAST,
            durability=DurabilityPolicy.VOLATILE,
        )
    return SAMPLES_READER


INPUT_DURABILITY_CHOICES = ("transient_local", "volatile")

# live watchers (inspection tools): volatile, shallow
WATCH = QoSProfile(
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.VOLATILE,
)
# latched single events: /drive/done (last seq).  One message per writer; the depth is for
# readers: with a second graph on the domain (fluxdrive_ros.graph) its /drive/done must not
# displace this graph's own in a reader's one-sample history before the callback took it
LATCHED = QoSProfile(
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# operator markers (/drive/param_marker): rare, every one kept for a late recorder
MARKERS = QoSProfile(
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# /clock: written like the samples (reliable, deep, transient-local) so that the recorder
# keeps every tick; compatible with the usual clock readers (best effort or reliable, depth 1)
CLOCK = SAMPLES


# /rosout as rcl's publishers offer it (fluxdrive.io.topics.OFFERED_QOS): a transient-local
# reader gets each node's last lines (kept 10 s) from before it matched, so a recorder that
# starts after the nodes still records their start-up lines
ROSOUT_READER = QoSProfile(
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
