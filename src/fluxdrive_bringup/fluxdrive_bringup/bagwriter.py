"""The recorder's bag-writing helper process: serialised messages in on stdin, a rosbag2
bag (rosbags Writer, MCAP storage, version 9, message definitions embedded) out.

Why a process: writing with rosbags costs about 5 us of Python per message; at 10 kHz with
ten topics that is half a core, and inside the recorder's process it would fight the
executor for the GIL.  Here it runs on the other core.  The recorder only appends bytes to
a buffer; a feeder thread ships the buffer down the pipe in batches.

It ignores SIGINT/SIGTERM (the recorder owns the run's end) and finalises the bag when its
input ends: on the recorder's end marker, or on EOF because the recorder died -- so even a
SIGKILLed recorder leaves a finalised bag with everything it had handed over.

Protocol on stdin (little endian):
  b"H" u32 n, JSON {"path": str, "custom_data": {key: str}}     first record; opens the bag
  b"C" u32 n, JSON {"id": int, "topic": str, "type": str}       a connection (before use)
  b"M" u16 id, i64 t_ns, u32 n, n bytes of CDR                   a message
  b"E"                                                          end: finalise and exit
On stdout: "ready" once the bag is open, "closed <messages>" once finalised; errors on
stderr with a non-zero exit.
"""

from __future__ import annotations

import json
import signal
import struct
import sys
from pathlib import Path

MSG_HDR = struct.Struct("<cHqI")  # b"M", id, t, n
U32 = struct.Struct("<I")


def pack_json(kind: bytes, obj: dict) -> bytes:
    raw = json.dumps(obj).encode()
    return kind + U32.pack(len(raw)) + raw


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from rosbags.rosbag2 import StoragePlugin, Writer

    from .bagio import typestore

    inp = sys.stdin.buffer
    read = inp.read
    writer = None
    conns: dict[int, object] = {}
    n_msgs = 0
    store = None

    def read_json() -> dict:
        (n,) = U32.unpack(read(4))
        return json.loads(read(n))

    try:
        while True:
            kind = read(1)
            if not kind or kind == b"E":
                break
            if kind == b"M":
                hdr = read(14)
                if len(hdr) < 14:
                    break
                cid, t, n = struct.unpack("<HqI", hdr)
                data = read(n)
                if len(data) < n:
                    break
                writer.write(conns[cid], t, data)
                n_msgs += 1
            elif kind == b"C":
                c = read_json()
                conns[c["id"]] = writer.add_connection(c["topic"], c["type"], typestore=store)
            elif kind == b"H":
                h = read_json()
                store = typestore()
                writer = Writer(Path(h["path"]), version=9, storage_plugin=StoragePlugin.MCAP)
                for k, v in (h.get("custom_data") or {}).items():
                    writer.set_custom_data(k, v)
                writer.open()
                try:
                    sys.stdout.write("ready\n")
                    sys.stdout.flush()
                except BrokenPipeError:
                    pass
            else:
                print(f"bagwriter: corrupt input (record type {kind!r})", file=sys.stderr)
                break
    finally:
        if writer is not None:
            writer.close()
            try:
                sys.stdout.write(f"closed {n_msgs}\n")
                sys.stdout.flush()
            except BrokenPipeError:  # the recorder is gone; the bag is finalised anyway
                pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
