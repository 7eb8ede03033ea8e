"""A drive's process stand-in for tests/test_scope_instrument_browser.py: publishes a known
tone on /drive/frame (every sample of a 10 kHz drive: seq, stamp, i_abc, vdc) at
`--rate` samples a wall second, with the scope tap in the same process (as `--scope` puts
it into the drive's), so the samples reach the tap through the intra-process bus, as in a
graph, and only the envelopes cross DDS.

    python tests/scope_tone.py --domain-id N [--rate 2500]
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

TS_S = 1e-4  # the tap's default sample period: a 10 kHz drive
TONE_HZ = 250.0  # 40 samples a period
AMP_A = 2.0
VDC_V = 48.0


def i_abc(seq: np.ndarray) -> np.ndarray:
    """The published phase currents of samples seq, shape (3, n)."""
    ph = 2 * math.pi * TONE_HZ * np.asarray(seq, dtype=np.int64) * TS_S
    return AMP_A * np.stack(
        [np.sin(ph), np.sin(ph - 2 * math.pi / 3), np.sin(ph + 2 * math.pi / 3)]
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--domain-id", type=int, required=True)
    ap.add_argument("--rate", type=float, default=2500.0, help="samples per wall second")
    args = ap.parse_args(argv)
    import rclpy
    from fluxdrive_bringup.view.scope_tap import ScopeTapNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import serialize_message

    from flux_drive_msgs.msg import PhaseFrame
    from fluxdrive_ros import intra, qos

    rclpy.init(domain_id=args.domain_id)
    node = rclpy.create_node("tone_source")
    pub = intra.RawPublisher(node, PhaseFrame, "/drive/frame", qos.SAMPLES)
    tap = ScopeTapNode("scope_tap")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    ex.add_node(tap)
    bus = intra.bus()
    if bus is not None:
        bus.start(ex)
    t0 = time.monotonic()
    sent = 0

    def tick() -> None:
        nonlocal sent
        due = min(int((time.monotonic() - t0) * args.rate), sent + 1000)
        if due <= sent:
            return
        seq = np.arange(sent, due)
        cur = i_abc(seq)
        m = PhaseFrame()
        m.vdc = VDC_V
        for j, k in enumerate(seq.tolist()):
            m.seq = k
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(k * 100_000, 1_000_000_000)
            m.i_abc = cur[:, j].tolist()
            pub.publish(serialize_message(m))
        sent = due

    node.create_timer(0.02, tick)
    print("tone: publishing", flush=True)
    try:
        ex.spin()
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
