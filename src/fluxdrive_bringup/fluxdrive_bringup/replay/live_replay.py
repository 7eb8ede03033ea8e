"""`./fluxdrive replay BAG --live`: the bag's frames back onto the ROS graph.

The recorded CDR bytes of /drive/frame are published at a factor of real time, unchanged but
for their graph_id, which becomes the receiving graph's (`--graph-id`; fluxdrive_ros.graph);
frames of a bag recorded before messages carried graph_id are re-encoded from their rows;
the engine's replay lab (fluxdrive.replay.lab) owns the options and the offline replay, this
module only the ROS publisher (the engine package imports no ROS).
"""

from __future__ import annotations

import struct
import sys
import time
from pathlib import Path

import rclpy
from fluxdrive.cli.replay import build_parser
from fluxdrive.core.machine import ConfigError
from fluxdrive.io.bagio import BagError, read_run_bag
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy


def main(argv: list[str]) -> int:
    """`fluxdrive replay ... --live`: the same options as the offline replay."""
    args = build_parser().parse_args(argv)
    if len(args.bags) != 1:
        raise ConfigError("--live takes exactly one bag")
    if args.rate <= 0:
        raise ConfigError("--rate must be > 0")
    try:
        return live_replay(
            args.bags[0],
            args.rate,
            args.loop,
            args.start,
            args.max_frames,
            wait_s=args.wait_s,
            graph_id=args.graph_id,
        )
    except BagError as exc:
        print(f"fluxdrive replay: {exc}", file=sys.stderr)
        return 2


def for_graph(bag, graph_id: int) -> list[tuple[int, bytes]]:
    """The bag's frames as (log time [ns], CDR bytes) carrying `graph_id`."""
    from fluxdrive.io.cdr import Decoder
    from fluxdrive.io.messages import FrameWire, seq_offset
    from fluxdrive.io.topics import T_FRAME

    raw = bag.raw_frames
    gid = struct.pack("<Q", graph_id)
    if raw and Decoder(T_FRAME).layout_of(raw[0][1]).matches_prefix(raw[0][1]):
        out = []
        for t, b in raw:  # today's layout: graph_id right after seq
            off = seq_offset(b) + 8
            out.append((t, b[:off] + gid + b[off + 8 :]))
        return out
    # recorded before graph_id existed: encode the decoded rows with today's layout
    wire = FrameWire(graph_id=graph_id)
    out = []
    for t_s, row in zip(bag.t, bag.frames, strict=True):
        ns = int(round(float(t_s) * 1e9))
        out.append((ns, wire.pack(row, *divmod(ns, 1_000_000_000))))
    return out


def live_replay(
    bag_path: Path,
    rate: float,
    loop: bool,
    start_s: float,
    max_frames: int | None = None,
    topic: str = "/drive/frame",
    wait_s: float = 2.0,
    graph_id: int | None = None,
) -> int:
    """Publish the bag's frames (the recorded CDR bytes, graph_id set) at `rate` x real
    time."""
    bag = read_run_bag(bag_path, keep_raw=True)
    for pr in bag.problems:
        print(f"replay: warning: {pr}", file=sys.stderr)
    from fluxdrive_ros import graph

    raw = for_graph(bag, graph.env_id() if graph_id is None else int(graph_id))
    t_first = raw[0][0]
    raw = [(t, b) for t, b in raw if (t - t_first) * 1e-9 >= start_s]
    if not raw:
        raise BagError(f"{bag_path}: --start {start_s} s is past the end of the bag")
    try:
        from flux_drive_msgs.msg import PhaseFrame
    except ImportError as exc:
        raise ConfigError(f"--live needs the built flux_drive_msgs ({exc})") from None
    from rclpy.impl.implementation_singleton import rclpy_implementation

    rcl_error = rclpy_implementation.RCLError
    rclpy.init()
    node = rclpy.create_node("fluxdrive_replay")
    # KEEP_ALL + reliable: a reader that keeps all (a recorder, a counting probe) is
    # flow-controlled rather than overrun at high --rate (KEEP_LAST lost frames in bursts);
    # readers that keep only the last N still choose to drop on their side.
    pub = node.create_publisher(
        PhaseFrame,
        topic,
        QoSProfile(
            depth=100, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
        ),
    )
    sent = 0
    try:
        t_wait = time.monotonic() + wait_s
        while pub.get_subscription_count() == 0 and time.monotonic() < t_wait:
            time.sleep(0.05)
        while True:
            t0_bag = raw[0][0]
            t0_wall = time.monotonic()
            last_print = t0_wall
            for t_ns, data in raw:
                due = t0_wall + (t_ns - t0_bag) * 1e-9 / rate
                now = time.monotonic()
                if due > now + 2e-4:
                    time.sleep(due - now)
                _publish_flow_controlled(pub, data, rcl_error)
                sent += 1
                if max_frames is not None and sent >= max_frames:
                    return _live_done(sent, t0_wall)
                if now - last_print > 2.0:
                    last_print = now
                    print(
                        f"[live] {sent} frames, bag t={(t_ns - t_first) * 1e-9:.2f} s",
                        file=sys.stderr,
                        flush=True,
                    )
            if not loop:
                break
        return _live_done(sent, t0_wall)
    finally:
        # frames still in the writer's history would be lost with the process
        if sent and not pub.wait_for_all_acked(Duration(seconds=30.0)):
            print(
                "[live] warning: not every frame was acknowledged by the readers within 30 s",
                file=sys.stderr,
            )
        node.destroy_node()
        rclpy.try_shutdown()


def _publish_flow_controlled(
    pub, data: bytes, rcl_error: type[BaseException], give_up_s: float = 30.0
):
    """Publish, waiting while a KEEP_ALL reader is behind: the middleware blocks a full
    writer history for its max_blocking_time and then refuses the sample, so retry until
    the readers have caught up (a reader that stops acknowledging for `give_up_s` ends the
    replay with an error instead of losing frames)."""
    t_end = None
    while True:
        try:
            pub.publish(data)
            return
        except rcl_error as exc:
            now = time.monotonic()
            if t_end is None:
                t_end = now + give_up_s
            elif now > t_end:
                raise BagError(
                    f"live replay: the readers took no frame for {give_up_s:g} s ({exc})"
                ) from None
            time.sleep(0.002)


def _live_done(sent: int, t0_wall: float) -> int:
    print(f"[live] published {sent} frames in {time.monotonic() - t0_wall:.2f} s", file=sys.stderr)
    return 0
