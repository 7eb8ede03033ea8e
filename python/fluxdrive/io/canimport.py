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

from fluxdrive.can.protocol import FRAME_FIELDS, SEQ_BITS, unwrap_counter
from fluxdrive.drive.plant import FR_SEQ
from fluxdrive.io.bagio import typestore
from fluxdrive.io.canlog import read_capture
from fluxdrive.io.messages import FrameWire
from fluxdrive.io.topics import FRAME, T_FRAME

__all__ = ["PHASE_FRAME_TOPIC", "import_capture", "main"]

PHASE_FRAME_TOPIC = FRAME


def import_capture(log: str | Path, out: str | Path, *, topic: str = PHASE_FRAME_TOPIC,
                   frame_id: str = "drive") -> dict[str, Any]:
    """Decode ``log`` and write the bag directory ``out`` (must not exist). Returns the
    capture counts plus ``written``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    cap = read_capture(log)
    f = np.array(cap.frames, dtype=np.float64)
    i_seq = FRAME_FIELDS.index("seq")
    seq = unwrap_counter(f[:, i_seq], SEQ_BITS) if len(f) else np.empty(0)
    if len(seq):
        seq = seq - (seq[0] - f[0, i_seq])  # keep the first wire value
        f[:, FR_SEQ] = seq
    fw = FrameWire(frame_id)  # FRAME_FIELDS are the engine's FR_* columns
    outp = Path(out)
    written = 0
    with Writer(outp, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, T_FRAME, typestore=typestore())
        for j in range(f.shape[0]):
            t_ns = int(round(float(cap.timestamps[j]) * 1e9))
            writer.write(conn, t_ns, fw.pack(f[j], *divmod(t_ns, 1_000_000_000)))
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
