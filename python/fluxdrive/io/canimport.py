"""`./fluxdrive can-import LOG --out BAG`: a bench CAN capture -> a rosbag2 (MCAP) bag of
flux_drive_msgs/PhaseFrame on /drive/frame, the topic the graph uses, so a capture taken
with standard tools (candump .log, Vector .asc, .blf) replays through observer variants.

Decoding is :func:`fluxdrive.io.canlog.read_capture` (vectorised SAMPLE_FD codec, or the
classic 4-frame layout); the 16-bit sequence counter is unwrapped into the period index
k, ``header.stamp`` is the capture timestamp of the frame. Message definitions come from
the .msg text (no ROS import), embedded in the bag so readers need no message package.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.can.protocol import FRAME_FIELDS, FRAME_FLAG_ADC_CLIP, SEQ_BITS, unwrap_counter
from fluxdrive.io.canlog import read_capture

__all__ = ["PHASE_FRAME_TOPIC", "import_capture", "main"]

PHASE_FRAME_TOPIC = "/drive/frame"
PHASE_FRAME_TYPE = "flux_drive_msgs/msg/PhaseFrame"
STATUS_SENSOR_CLIP = 1
_MSG_DIR = Path(__file__).resolve().parents[3] / "src" / "flux_drive_msgs" / "msg"


def _typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    text = (_MSG_DIR / "PhaseFrame.msg").read_text()
    ts.register(get_types_from_msg(text, PHASE_FRAME_TYPE))
    return ts


def import_capture(log: str | Path, out: str | Path, *, topic: str = PHASE_FRAME_TOPIC,
                   frame_id: str = "drive") -> dict[str, Any]:
    """Decode ``log`` and write the bag directory ``out`` (must not exist). Returns the
    capture counts plus ``written``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    cap = read_capture(log)
    f = cap.frames
    seq = unwrap_counter(f[:, FRAME_FIELDS.index("seq")], SEQ_BITS) if len(f) else np.empty(0)
    if len(seq):
        seq = seq - (seq[0] - f[0, FRAME_FIELDS.index("seq")])  # keep the first wire value
    ts = _typestore()
    PhaseFrame = ts.types[PHASE_FRAME_TYPE]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    ix = {n: i for i, n in enumerate(FRAME_FIELDS)}
    outp = Path(out)
    written = 0
    with Writer(outp, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, PHASE_FRAME_TYPE, typestore=ts)
        for j in range(f.shape[0]):
            row = f[j]
            t = float(cap.timestamps[j])
            sec = int(np.floor(t))
            nsec = min(int(round((t - sec) * 1e9)), 999_999_999)
            flags = STATUS_SENSOR_CLIP if int(row[ix["flags"]]) & FRAME_FLAG_ADC_CLIP else 0
            msg = PhaseFrame(
                header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=frame_id),
                seq=int(seq[j]),
                i_abc=np.array(row[0:3], dtype=np.float64),
                v_ll=np.array(row[3:6], dtype=np.float64),
                vdc=float(row[ix["vdc"]]),
                duty_applied=np.array(row[7:10], dtype=np.float64),
                pwm_enabled=bool(row[ix["pwm_enabled"]] > 0.5),
                encoder_counts=float(row[ix["encoder_counts"]]),
                status_flags=flags,
            )
            writer.write(conn, sec * 1_000_000_000 + nsec,
                         ts.serialize_cdr(msg, PHASE_FRAME_TYPE))
            written += 1
    out_counts = dict(cap.counts)
    out_counts.update(written=written, layout=cap.layout, topic=topic, bag=str(outp))
    return out_counts


def main(argv: list[str] | None = None) -> int:
    """CLI: ``can-import LOG --out BAG [--topic T]``; prints counts, last line JSON."""
    ap = argparse.ArgumentParser(prog="fluxdrive can-import",
                                 description="CAN capture (.log/.asc/.blf) -> bag of PhaseFrames")
    ap.add_argument("log", help="capture file: candump .log, Vector .asc or .blf")
    ap.add_argument("--out", required=True, help="output bag directory (must not exist)")
    ap.add_argument("--topic", default=PHASE_FRAME_TOPIC)
    a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    if Path(a.out).exists():
        print(f"can-import: {a.out} exists; choose a new bag directory", file=sys.stderr)
        return 2
    try:
        res = import_capture(a.log, a.out, topic=a.topic)
    except (ValueError, FileNotFoundError) as exc:
        print(f"can-import: {exc}", file=sys.stderr)
        return 2
    print(f"[can-import] {res['decoded']} sample frames decoded, {res['malformed']} malformed, "
          f"{res['gaps']} gaps -> {res['written']} PhaseFrames on {a.topic} in {a.out}",
          file=sys.stderr)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
