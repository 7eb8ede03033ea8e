"""QoS profiles shared by every fluxdrive node (publishers and subscribers must agree).

Lockstep never drops: per-sample topics are RELIABLE with a deep KEEP_LAST history (a
second of samples at 10 kHz), so a reader that falls behind (the recorder, a shadow
observer) catches up instead of losing samples, and TRANSIENT_LOCAL, so a reader whose
discovery completes a little after the first samples still gets them from the writer's
history.  Readers that only watch (topic echo/hz) use VOLATILE and get live data only.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

SAMPLE_DEPTH = 10000

# per-sample data written by the drive nodes (frames, truth, estimates, duty, state)
SAMPLES = QoSProfile(depth=SAMPLE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                     history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# readers in the loop / the recorder: the same, so they also receive the writer's history
SAMPLES_READER = SAMPLES


def reader(durability: str = "transient_local") -> QoSProfile:
    """Sample-topic reader QoS.  transient_local (default) also gets what was published
    before the match; volatile is needed to hear a volatile writer (a transient-local reader
    does not match one), e.g. a bench bridge publishing with plain depth-100 QoS."""
    if durability == "volatile":
        return QoSProfile(depth=SAMPLE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
    return SAMPLES_READER


INPUT_DURABILITY_CHOICES = ("transient_local", "volatile")

# live watchers (inspection tools): volatile, shallow
WATCH = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                   history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
# latched single events: /drive/done (last seq), /drive/start
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# /clock: like rosgraph's default for the clock (keep last, reliable, volatile)
CLOCK = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                   history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
