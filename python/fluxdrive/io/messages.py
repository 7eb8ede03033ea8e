"""The one mapping between the engine's rows and the per-sample messages.

Every place that turns an engine row into a message or back -- the nodes (publishing CDR
bytes), the bag writer and reader (fluxdrive.io.bagio), the CAN-capture import
(fluxdrive.io.canimport), the bench bridge node -- goes through the tables below:

  PhaseFrame      <-> FR_* row (fluxdrive.drive.plant)       FRAME_MAP, seq = FR_SEQ
  PlantTruth      <-> TR_* row (fluxdrive.drive.plant)       TRUTH_MAP
  RotorEstimate   <-> ES_* row (fluxdrive.drive.observers)   ESTIMATE_MAP
  DutyCommand     <-> CO_* row (fluxdrive.drive.control)     DUTY_MAP
  ControllerState <-> CO_* row (fluxdrive.drive.control)     STATE_MAP
  CurrentReference <-> RF_* row (fluxdrive.drive.control)    REFERENCE_MAP (split mode)

The rows and the message fields are float64 alike, so a row survives a trip through a
message bit for bit (booleans are 0.0/1.0 in the rows, integers are exact below 2^53).
Field kinds come from the .msg text: a bool goes out as `row > 0.5`, an integer as int(row).

Conventions the mapping owns:
- header.stamp is the sample instant t_k = k Ts in integer nanoseconds (`Stamp`).
- PhaseFrame.status_flags: the engine's frame flag bits are the message's STATUS_* bits
  (FLAG_CLIP == STATUS_SENSOR_CLIP, FLAG_STALE == STATUS_STALE_COMMAND; the CAN bridge's
  stale-command bit is the same); a frame read back keeps only those two (FRAME_FLAGS_IN: the
  bits the observers and the controller use -- a stale frame with the PWM off is a lost
  interval to the observers).
- PlantTruth.theta_e goes out as the engine has it, in [0, 2 pi); a negative angle read
  back (a bag following the message comment) is wrapped into [0, 2 pi).
- ControllerState.fault_code is the engine's CO_FAULT (DriveFault codes); fault_reason is
  its name (`fault_name`: an unknown code reads "fault <N>" -- one rule everywhere).
- DutyCommand.commander carries the sender's access mark (fluxdrive_ros.access);
  header.frame_id is an ordinary frame name.
- graph_id (every per-sample message, the parameter marker and the run's end, right after
  seq) is the identity of the launch that published it: a codec packs its publisher's id as
  a constant; readers check it on the raw bytes (`graph_id_of`) before decoding anything and
  drop what is not their graph's (docs/graph.md, "Graph identity").  It is not an engine
  column: rows are the same whichever graph carried them.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Callable

import numpy as np

from fluxdrive.drive import plant as pl
from fluxdrive.drive.control import (
    CO_DA,
    CO_DB,
    CO_DC,
    CO_EN,
    CO_FAULT,
    CO_ID,
    CO_ID_REF,
    CO_IQ,
    CO_IQ_REF,
    CO_MODE,
    CO_N,
    CO_TH,
    CO_VD,
    CO_VQ,
    CO_W_FB,
    CO_W_REF,
    FAULT_NAMES,
    RF_EN,
    RF_ID_REF,
    RF_IQ_REF,
    RF_N,
    RF_TH,
    RF_W,
)
from fluxdrive.drive.observers import (
    ES_EA,
    ES_EB,
    ES_ERR,
    ES_LA,
    ES_LB,
    ES_N,
    ES_TH,
    ES_VALID,
    ES_W,
)
from fluxdrive.drive.plant import FLAG_CLIP, FLAG_STALE, FR_FLAGS, FR_N, FR_SEQ, TR_N, TR_THETA_E
from fluxdrive.io import topics
from fluxdrive.io.cdr import Codec, Decoder, leaves

# PhaseFrame.STATUS_* bits
STATUS_SENSOR_CLIP = 1
STATUS_SIMULATED = 2
STATUS_VOLTAGE_ESTIMATED = 4
STATUS_DUTY_CLAMPED = 8
STATUS_STALE_COMMAND = 16
# engine frame flag bits that travel (the rest of status_flags is the publisher's)
FRAME_FLAGS_OUT = STATUS_SENSOR_CLIP | STATUS_STALE_COMMAND
FRAME_FLAGS_IN = FLAG_CLIP | FLAG_STALE  # the engine's bits a frame read back keeps
assert FLAG_CLIP == STATUS_SENSOR_CLIP  # the engine's bits are the message's
assert FLAG_STALE == STATUS_STALE_COMMAND

TWO_PI = 2.0 * math.pi

# ---------------------------------------------------------------- the mapping tables
# (message field path, engine column); header.stamp and seq are handled by the codecs
FRAME_MAP: tuple[tuple[str, int], ...] = (
    ("i_abc[0]", pl.FR_IA),
    ("i_abc[1]", pl.FR_IB),
    ("i_abc[2]", pl.FR_IC),
    ("v_ll[0]", pl.FR_VAB),
    ("v_ll[1]", pl.FR_VBC),
    ("v_ll[2]", pl.FR_VCA),
    ("vdc", pl.FR_VDC),
    ("duty_applied[0]", pl.FR_DA),
    ("duty_applied[1]", pl.FR_DB),
    ("duty_applied[2]", pl.FR_DC),
    ("pwm_enabled", pl.FR_EN),
    ("encoder_counts", pl.FR_ENC),
    ("status_flags", FR_FLAGS),
)
TRUTH_MAP: tuple[tuple[str, int], ...] = (
    ("theta_e", TR_THETA_E),
    ("omega_m", pl.TR_WM),
    ("torque_e", pl.TR_TE),
    ("torque_load", pl.TR_TL),
    ("i_abc_true[0]", pl.TR_IA),
    ("i_abc_true[1]", pl.TR_IB),
    ("i_abc_true[2]", pl.TR_IC),
)
ESTIMATE_MAP: tuple[tuple[str, int], ...] = (
    ("theta_e", ES_TH),
    ("omega_e", ES_W),
    ("flux_ab[0]", ES_LA),
    ("flux_ab[1]", ES_LB),
    ("emf_ab[0]", ES_EA),
    ("emf_ab[1]", ES_EB),
    ("pll_error", ES_ERR),
    ("valid", ES_VALID),
)
DUTY_MAP: tuple[tuple[str, int], ...] = (
    ("duty[0]", CO_DA),
    ("duty[1]", CO_DB),
    ("duty[2]", CO_DC),
    ("enable", CO_EN),
)
STATE_MAP: tuple[tuple[str, int], ...] = (
    ("i_dq[0]", CO_ID),
    ("i_dq[1]", CO_IQ),
    ("i_dq_ref[0]", CO_ID_REF),
    ("i_dq_ref[1]", CO_IQ_REF),
    ("v_dq[0]", CO_VD),
    ("v_dq[1]", CO_VQ),
    ("omega_ref_m", CO_W_REF),
    ("omega_fb_m", CO_W_FB),
    ("theta_used", CO_TH),
    ("mode", CO_MODE),
    ("fault_code", CO_FAULT),
)

REFERENCE_MAP: tuple[tuple[str, int], ...] = (
    ("id_ref", RF_ID_REF),
    ("iq_ref", RF_IQ_REF),
    ("theta_e", RF_TH),
    ("omega_e", RF_W),
    ("enable", RF_EN),
)

# message type -> (mapping, row width)
MAPS: dict[str, tuple[tuple[tuple[str, int], ...], int]] = {
    topics.T_FRAME: (FRAME_MAP, FR_N),
    topics.T_TRUTH: (TRUTH_MAP, TR_N),
    topics.T_ESTIMATE: (ESTIMATE_MAP, ES_N),
    topics.T_DUTY: (DUTY_MAP, CO_N),
    topics.T_STATE: (STATE_MAP, CO_N),
    topics.T_REFERENCE: (REFERENCE_MAP, RF_N),
}

_INT_KINDS = {
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "byte",
    "char",
}


def field_kinds(mtype: str) -> dict[str, str]:
    """Field path -> ROS primitive kind of a message type (from the .msg text)."""
    return {lf.path: lf.kind for lf in leaves(mtype)}


def fault_name(code: int) -> str:
    """ControllerState.fault_reason of a fault code (0: no fault, empty)."""
    code = int(code)
    if code == 0:
        return ""
    return FAULT_NAMES.get(code, f"fault {code}")


def post_read(mtype: str, row: np.ndarray) -> None:
    """The read-back conventions on rows (or a 2-D block of rows) just filled from messages:
    frame flags keep FRAME_FLAGS_IN only; truth angles wrapped into [0, 2 pi)."""
    if mtype == topics.T_FRAME:
        f = row[..., FR_FLAGS]
        ok = ~np.isnan(f)
        f[ok] = (f[ok].astype(np.int64) & FRAME_FLAGS_IN).astype(np.float64)
    elif mtype == topics.T_TRUTH:
        th = row[..., TR_THETA_E]
        row[..., TR_THETA_E] = np.where(th < 0.0, th + TWO_PI, th)


# ---------------------------------------------------------------- generated codecs
def _pack_expr(kind: str, col: int) -> str:
    if kind == "bool":
        return f"v[{col}] > 0.5"
    if kind in _INT_KINDS:
        return f"int(v[{col}])"
    return f"v[{col}]"


def _unpack_expr(kind: str, i: int) -> str:
    if kind == "bool":
        return f"(1.0 if m[{i}] else 0.0)"
    return f"m[{i}]"


class RowCodec:
    """CDR bytes <-> an engine row for one message type, generated from its mapping table.

    `pack(row, seq, sec, nsec[, xf])` -> bytes (xf: extra PhaseFrame status bits);
    `unpack(data, out)` fills the mapped columns of `out` and returns seq;
    `row(values)` -> a new row from Decoder values.  Strings (the header's frame_id, an
    estimate's variant, ...) are fixed per codec."""

    def __init__(
        self,
        mtype: str,
        strings: dict[str, str] | None = None,
        flags_or: int = 0,
        graph_id: int = 0,
    ):
        mapping, self.width = MAPS[mtype]
        self.graph_id = int(graph_id)
        self.mtype = mtype
        self.codec = Codec(mtype, strings)
        self.decoder = Decoder(mtype)
        kinds = field_kinds(mtype)
        cols = dict(mapping)
        known = {"header.stamp.sec", "header.stamp.nanosec", "seq", "graph_id"}
        missing = [f for f in self.codec.fields if f not in cols and f not in known]
        if missing:  # the mapping must cover every numeric field of the message
            raise KeyError(f"{mtype}: fields {missing} have no engine column")
        args = []
        for f in self.codec.fields:
            if f == "header.stamp.sec":
                args.append("sec")
            elif f == "header.stamp.nanosec":
                args.append("nsec")
            elif f == "seq":
                args.append("seq")
            elif f == "graph_id":
                args.append(str(self.graph_id))
            elif mtype == topics.T_FRAME and f == "status_flags":
                args.append(f"(int(v[{cols[f]}]) & {FRAME_FLAGS_OUT}) | {int(flags_or)} | xf")
            else:
                args.append(_pack_expr(kinds[f], cols[f]))
        env: dict = {}
        call = self.codec.pack_call(args, env)  # one struct call a message
        src = f"def pack(row, seq, sec, nsec, xf=0):\n    v = row.tolist()\n    return {call}\n"
        exec(src, env)  # noqa: S102 - generated from the mapping table only
        self.pack: Callable[..., bytes] = env["pack"]
        self.flags_or = int(flags_or)
        self._pack_args = args
        idx = {f: i for i, f in enumerate(self.codec.fields)}
        self._kinds, self._mapping = kinds, mapping
        env = {}
        exec(self._fill_source("fill", list(range(len(idx)))), env)  # noqa: S102
        self.fill: Callable[[tuple, np.ndarray], int] = env["fill"]
        seq_i = idx["seq"]
        self._fast: dict[int, Callable[[bytes, np.ndarray], int]] = {}
        self.unpack: Callable[[bytes, np.ndarray], int] = self._unpack_for(self.codec)
        # unpack_block (PhaseFrames only): (column, field position) of the mapped fields
        self._block = [(c, idx[f]) for f, c in mapping] if mtype == topics.T_FRAME else []
        self._seq_i = seq_i
        self._flags_i = idx.get("status_flags", -1)
        # pack_block: (field position, source) -- a row column with its kind, or the stamp
        self._pack_src = [
            (idx[f], "", kinds[f], cols[f])
            if f in cols and not (mtype == topics.T_FRAME and f == "status_flags")
            else (idx[f], f, "", -1)
            for f in self.codec.fields
        ]
        self._template = b""
        self._plan: list[tuple[int, np.dtype, int, str, str, int]] | None = None
        self._void = np.dtype("V1")
        self.wire_row = self._build_wire_row()

    def _build_wire_row(self) -> Callable[..., np.ndarray] | None:
        """`wire_row(row, seq, xf=0)` -> the row a reader's `unpack` fills from the message
        `pack(row, seq, sec, nsec, xf)` makes -- without the bytes, for a reader in the same
        process (fluxdrive_ros.intra: rows delivered as rclcpp's intra-process delivery
        hands over the message, not its serialisation).  Generated from the same
        expressions: each column is `fill`'s expression of the field with `pack`'s
        expression of that field put in, so a row and its trip through CDR agree bit for bit
        (tests/test_graph_codec.py).  Columns the message does not carry are NaN.  None for
        a type with float32 fields (the trip through CDR rounds them)."""
        if any(self._kinds[f] == "float32" for f in self.codec.fields):
            return None
        args = {i: a for i, a in enumerate(self._pack_args)}
        exprs: dict[int, str] = {}
        src = self._fill_source("fill", list(range(len(self.codec.fields))))
        for line in src.split("\n")[1:]:
            hit = re.fullmatch(r"    out\[(\d+)\] = (.*)", line)
            if hit:  # the column's value: fill's expression of pack's expression
                expr = re.sub(r"m\[(\d+)\]", lambda g: f"({args[int(g.group(1))]})", hit[2])
                exprs[int(hit[1])] = re.sub(r"v\[(\d+)\]", r"row.item(\1)", expr)
        # every column carried: a copy of the row and the columns that are not the row's
        # own value (booleans, integers, seq, flags); else NaN and the carried columns
        moved = {c: e for c, e in exprs.items() if e != f"(row.item({c}))"}
        if len(exprs) == self.width:
            lines = ["    out = row.copy()"] + [f"    out[{c}] = {e}" for c, e in moved.items()]
        else:
            lines = ["    out = _nans.copy()"]
            lines += [f"    out[{c}] = {e}" for c, e in exprs.items()]
        fn = "def wire_row(row, seq, xf=0):\n" + "\n".join(lines) + "\n    return out\n"
        env: dict = {"_nans": np.full(self.width, math.nan)}
        exec(fn, env)  # noqa: S102 - generated from the mapping table only
        return env["wire_row"]

    def pack_block(
        self,
        rows: np.ndarray,
        seqs: list[int] | np.ndarray,
        stamp_ns: np.ndarray,
        xf: np.ndarray | None = None,
    ) -> list[bytes]:
        """`pack` of n rows at once: the messages of rows[i] with seq seqs[i] stamped
        stamp_ns[i] (integer ns) and, for PhaseFrames, extra status bits xf[i] (default
        none), built in one numpy pass over a block of messages -- the same bytes `pack`
        gives one by one (tests/test_graph_codec.py)."""
        n = rows.shape[0]
        if not n:
            return []
        if self._plan is None:  # the strings, the padding, graph_id; where the fields go
            self._template = self.pack(np.zeros(self.width), 0, 0, 0)
            self._plan = self._block_plan()
            self._void = np.dtype(f"V{self.codec.size}")
        buf = bytearray(self._template * n)
        size = self.codec.size
        stamp = np.asarray(stamp_ns, dtype=np.int64)
        for off, dt, k, src, kind, col in self._plan:
            if not src:  # k fields from row columns col.. at once
                f = np.ndarray((n, k), dt, buf, off, (size, dt.itemsize))
                v = rows[:, col : col + k]
                # as `pack`: bool is v > 0.5; integers truncate toward zero (int())
                f[:] = v > 0.5 if kind == "bool" else np.trunc(v) if kind in _INT_KINDS else v
                continue
            f = np.ndarray((n,), dt, buf, off, (size,))
            if src == "header.stamp.sec":
                f[:] = stamp // 1_000_000_000
            elif src == "header.stamp.nanosec":
                f[:] = stamp % 1_000_000_000
            elif src == "seq":
                f[:] = seqs
            elif src == "status_flags":  # as `pack`: (flags & OUT) | the codec's | xf
                bits = (
                    np.trunc(rows[:, FR_FLAGS]).astype(np.int64) & FRAME_FLAGS_OUT
                ) | self.flags_or
                f[:] = bits if xf is None else bits | np.asarray(xf, dtype=np.int64)
        # each message's bytes: numpy makes the n bytes objects (a slice each costs more)
        return np.frombuffer(buf, self._void).tolist()

    def _block_plan(self) -> list[tuple[int, np.dtype, int, str, str, int]]:
        """pack_block's writes, (offset, dtype, count, source, kind, first column): a run of
        float64 fields from consecutive columns is one write; graph_id is left to the
        template (`pack` writes it as a constant)."""
        dtype = self.codec.numpy_dtype()
        plan: list[list] = []
        for j, src, kind, col in self._pack_src:
            if src == "graph_id":
                continue
            dt, off = dtype.fields[f"f{j}"][:2]
            last = plan[-1] if plan else None
            if (
                last is not None
                and not src
                and not last[3]
                and kind == last[4] == "float64"
                and col == last[5] + last[2]
                and off == last[0] + 8 * last[2]
            ):
                last[2] += 1
            else:
                plan.append([off, dt, 1, src, kind, col])
        return [(int(p[0]), p[1], int(p[2]), p[3], p[4], int(p[5])) for p in plan]

    def _fill_source(self, name: str, pos: list[int]) -> str:
        """The body of a generated `name(m, out)` that fills the mapped columns of `out`
        from a value tuple `m` in which field j (`Codec.fields` order) is m[pos[j]]."""
        idx = {f: pos[i] for i, f in enumerate(self.codec.fields)}
        kinds = self._kinds
        sets = [f"    out[{c}] = {_unpack_expr(kinds[f], idx[f])}" for f, c in self._mapping]
        seq_i = idx["seq"]
        if self.mtype == topics.T_FRAME:
            sets.append(f"    out[{FR_SEQ}] = m[{seq_i}]")
            sets.append(f"    out[{FR_FLAGS}] = m[{idx['status_flags']}] & {FRAME_FLAGS_IN}")
        elif self.mtype == topics.T_TRUTH:
            th = idx["theta_e"]
            sets[0] = f"    out[{TR_THETA_E}] = m[{th}] + {TWO_PI!r} if m[{th}] < 0.0 else m[{th}]"
        return f"def {name}(m, out):\n" + "\n".join(sets) + f"\n    return m[{seq_i}]\n"

    def _unpack_for(self, codec) -> Callable[[bytes, np.ndarray], int]:
        """`unpack` for messages of `codec`'s layout: one struct call and the column
        sets; a message of another layout goes through the decoder (and the next one of
        that layout through a function of its own)."""
        fast = self._fast.get(id(codec))
        if fast is not None:
            return fast
        pos, checks = codec.unpack_source()
        test = " and ".join([f"len(data) == {codec.size}"] + [f"m[{i}] == {c}" for i, c in checks])
        body = self._fill_source("_fill", pos).replace("\n    ", "\n        ")
        src = (
            "def unpack(data, out):\n"
            f"    m = _U(data, 4) if len(data) == {codec.size} else None\n"
            f"    if m is not None and {test}:\n"
            + "\n".join(body.split("\n")[1:]).rstrip()
            + "\n    return _slow(data, out)\n"
        )
        env = {"_U": codec.struct.unpack_from, "_slow": self._unpack_other}
        exec(src, env)  # noqa: S102 - generated from the mapping table only
        fast = env["unpack"]
        if len(self._fast) < 16:
            self._fast[id(codec)] = fast
        return fast

    def _unpack_other(self, data: bytes, out: np.ndarray) -> int:
        """A message of a layout `unpack` was not made for (another frame_id, variant):
        decoded here; `unpack` is now made for its layout."""
        seq = self.fill(self.decoder.decode(data), out)
        c = self.decoder._last
        if c is not None:
            self.unpack = self._unpack_for(c)
        return seq

    def unpack_block(self, datas: list[bytes], out: np.ndarray) -> list[int] | None:
        """Rows out[:n] from n PhaseFrames of one layout (one publisher's) in one numpy
        pass over their bytes -- the columns `unpack` fills, with the same values; returns
        their seqs, or None when the type or the messages' layouts do not allow it (then
        unpack them one by one)."""
        if not self._block or not datas:
            return None
        c = self.decoder.codec_for(datas[0])
        if list(c.strings) != ["header.frame_id"]:
            return None
        n, size = len(datas), c.size
        if len(datas[0]) != size or len(set(map(len, datas))) != 1:
            return None
        raw = b"".join(datas)
        u8 = np.frombuffer(raw, dtype=np.uint8).reshape(n, size)
        if not (u8[:, 12:16] == u8[0, 12:16]).all():  # the frame_id's length: the layout
            return None
        arr = np.frombuffer(raw, dtype=c.numpy_dtype())
        for col, j in self._block:
            out[:n, col] = arr[f"f{j}"]
        seq = arr[f"f{self._seq_i}"]
        out[:n, FR_SEQ] = seq
        out[:n, FR_FLAGS] = arr[f"f{self._flags_i}"] & FRAME_FLAGS_IN
        return seq.tolist()

    def row(self, values: tuple, out: np.ndarray | None = None) -> np.ndarray:
        """A row (zeros where unmapped) from decoded values (Codec.fields order)."""
        out = np.zeros(self.width) if out is None else out
        self.fill(values, out)
        return out


class Stamp:
    """t_k = k Ts as (sec, nanosec), in integer nanoseconds (Ts is a whole number of ns)."""

    def __init__(self, ts_s: float, offset_ns: int = 0):
        self.ts_ns = int(round(ts_s * 1e9))
        self.offset_ns = int(offset_ns)

    def ns(self, k: int) -> int:
        return k * self.ts_ns + self.offset_ns

    def __call__(self, k: int) -> tuple[int, int]:
        return divmod(k * self.ts_ns + self.offset_ns, 1_000_000_000)

    def ns_block(self, ks) -> np.ndarray:
        """t_k in integer ns of many k at once (int64)."""
        return np.asarray(ks, dtype=np.int64) * self.ts_ns + self.offset_ns


# ---------------------------------------------------------------- per-message helpers
class FrameWire:
    """PhaseFrame <-> FR_* row."""

    def __init__(self, frame_id: str = "", extra_flags: int = 0, graph_id: int = 0):
        self.rc = RowCodec(topics.T_FRAME, {"header.frame_id": frame_id}, extra_flags, graph_id)

    def pack(self, fr: np.ndarray, sec: int, nsec: int, extra_flags: int = 0) -> bytes:
        return self.rc.pack(fr, int(fr[FR_SEQ]), sec, nsec, extra_flags)

    def unpack(self, data: bytes, out: np.ndarray) -> int:
        """Fill an FR_* row; returns seq."""
        return self.rc.unpack(data, out)

    def unpack_block(self, datas: list[bytes], out: np.ndarray) -> list[int] | None:
        """Fill FR_* rows out[:n] from n frames at once; their seqs (None: unpack each)."""
        return self.rc.unpack_block(datas, out)


class TruthWire:
    """PlantTruth <-> TR_* row (TR_T is not on the wire: t = seq Ts)."""

    def __init__(self, frame_id: str = "", graph_id: int = 0):
        self.rc = RowCodec(topics.T_TRUTH, {"header.frame_id": frame_id}, graph_id=graph_id)

    def pack(self, tr: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        return self.rc.pack(tr, seq, sec, nsec)


class EstimateWire:
    """RotorEstimate <-> ES_* row."""

    def __init__(self, variant: str, frame_id: str = "", graph_id: int = 0):
        self.rc = RowCodec(
            topics.T_ESTIMATE, {"header.frame_id": frame_id, "variant": variant}, graph_id=graph_id
        )

    def pack(self, es: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        return self.rc.pack(es, seq, sec, nsec)

    def unpack(self, data: bytes, out: np.ndarray) -> int:
        return self.rc.unpack(data, out)

    def pack_block(
        self, es: np.ndarray, seqs: list[int] | np.ndarray, stamp_ns: np.ndarray
    ) -> list[bytes]:
        """The messages of n ES_* rows at once (RowCodec.pack_block)."""
        return self.rc.pack_block(es, seqs, stamp_ns)


class ControlWire:
    """DutyCommand and ControllerState <-> CO_* row.  `commander`: the sender's access mark
    (DutyCommand.commander)."""

    def __init__(self, frame_id: str = "", commander: str = "", graph_id: int = 0):
        self.duty = RowCodec(
            topics.T_DUTY, {"header.frame_id": frame_id, "commander": commander}, graph_id=graph_id
        )
        self.frame_id = frame_id
        self.graph_id = int(graph_id)
        self.state_codecs: dict[int, RowCodec] = {}

    def pack_duty(self, co: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        return self.duty.pack(co, seq, sec, nsec)

    def pack_state(self, co: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        return self.state_codec(co).pack(co, seq, sec, nsec)

    def state_codec(self, co: np.ndarray) -> RowCodec:
        """The ControllerState codec of a CO_* row: one per fault text (the string is part
        of the layout)."""
        code = int(co[CO_FAULT])
        c = self.state_codecs.get(code)
        if c is None:
            c = RowCodec(
                topics.T_STATE,
                {"header.frame_id": self.frame_id, "fault_reason": fault_name(code)},
                graph_id=self.graph_id,
            )
            self.state_codecs[code] = c
        return c


class ReferenceWire:
    """CurrentReference <-> RF_* row (split mode).  `commander`: the sender's access mark."""

    def __init__(self, frame_id: str = "", commander: str = "", graph_id: int = 0):
        self.rc = RowCodec(
            topics.T_REFERENCE,
            {"header.frame_id": frame_id, "commander": commander},
            graph_id=graph_id,
        )

    def pack(self, ref: np.ndarray, seq: int, sec: int, nsec: int) -> bytes:
        return self.rc.pack(ref, seq, sec, nsec)

    def unpack(self, data: bytes, out: np.ndarray) -> int:
        """Fill an RF_* row (RF_MODE/RF_FAULT are not on the wire); returns seq."""
        return self.rc.unpack(data, out)


_ROW_CODECS: dict[str, RowCodec] = {}


def row_codec(mtype: str) -> RowCodec:
    """A shared RowCodec of a type (for reading: strings do not matter)."""
    c = _ROW_CODECS.get(mtype)
    if c is None:
        c = _ROW_CODECS[mtype] = RowCodec(mtype)
    return c


def duty_commander(data: bytes) -> bytes:
    """DutyCommand.commander of a serialised message, without decoding the rest (the power
    stage checks it on every command): header (stamp, frame_id), seq, graph_id, duty[3],
    enable, then the commander string."""
    n = int.from_bytes(data[12:16], "little")
    off = 12 + n  # payload offset (after the 4-byte encapsulation header) past frame_id
    off += (-off) % 8 + 16 + 24 + 1  # seq aligned to 8, graph_id, duty[3], enable
    off += (-off) % 4
    m = int.from_bytes(data[4 + off : 8 + off], "little")
    return bytes(data[8 + off : 8 + off + m - 1]) if m > 0 else b""


# ---------------------------------------------------------------- graph identity
# the message types that carry graph_id right after seq (Header, uint64 seq, uint64 graph_id)
GRAPH_TYPES = frozenset(
    {
        topics.T_FRAME,
        topics.T_TRUTH,
        topics.T_ESTIMATE,
        topics.T_DUTY,
        topics.T_STATE,
        topics.T_REFERENCE,
        topics.T_MARKER,
        topics.T_DONE,
    }
)
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


def seq_offset(data: bytes) -> int:
    """Byte offset of `seq` in a serialised GRAPH_TYPES message (past the header's
    frame_id, aligned to 8 in the payload)."""
    off = 16 + _U32.unpack_from(data, 12)[0]
    return off + (-(off - 4)) % 8


def message_seq(data: bytes) -> int:
    """seq of a serialised GRAPH_TYPES message, without decoding the rest."""
    return _U64.unpack_from(data, seq_offset(data))[0]


def graph_id_of(data: bytes) -> int:
    """graph_id of a serialised GRAPH_TYPES message, without decoding the rest."""
    return _U64.unpack_from(data, seq_offset(data) + 8)[0]
