"""CDR (XCDR1, little endian) codec for the per-sample messages, generated from the .msg text.

Why: at 10 kHz every microsecond per message counts.  rclpy turns a Python message into a
C struct and serialises it (tens of microseconds with the setters' checks); a
`struct.Struct` over the fixed layout packs the same bytes in about one.  Nodes publish
these bytes with `Publisher.publish(bytes)` and take raw bytes from `raw=True`
subscriptions, so no Python message object exists on the hot path.  Everything else on the
graph (recorder, `./fluxdrive topic echo`, other tools) sees ordinary messages: the bytes are
exactly what rclpy's Fast-CDR serialiser produces (tests/test_graph_codec.py checks every
message type against `rclpy.serialization.serialize_message`).

Layout rules used (ROS 2 / Fast-CDR, plain CDR v1): a 4-byte encapsulation header
(00 01 00 00 = CDR little endian); each primitive aligned to its own size relative to the
start of the payload (after the header); a string is uint32 length (bytes + NUL), the bytes,
NUL; fixed arrays are their elements back to back with no length; nested messages are
inlined with no alignment of their own.  Variable-length sequences are not supported
(the per-sample messages use fixed-size arrays; docs/architecture.md, "Environment
notes"), so every message of a publisher has one size.

A `Codec` is specialised per set of string lengths (strings are nearly always constant per
publisher: the header's frame_id, an observer's variant name), so pack/unpack are one
`struct` call each.
"""

from __future__ import annotations

import operator
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from fluxdrive.io.topics import MSG_SRC_DIR

ENCAPSULATION = b"\x00\x01\x00\x00"

_PRIM = {  # ROS type -> (struct code, size)
    "float64": ("d", 8),
    "float32": ("f", 4),
    "int64": ("q", 8),
    "uint64": ("Q", 8),
    "int32": ("i", 4),
    "uint32": ("I", 4),
    "int16": ("h", 2),
    "uint16": ("H", 2),
    "int8": ("b", 1),
    "uint8": ("B", 1),
    "byte": ("B", 1),
    "char": ("B", 1),
    "bool": ("?", 1),
}

# Definitions of the few non-project types the project's messages use.
_BUILTIN = {
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "rosgraph_msgs/Clock": "builtin_interfaces/Time clock\n",
    "std_msgs/UInt64": "uint64 data\n",
    "std_msgs/String": "string data\n",
    "std_msgs/Empty": "",
}


def msg_dir() -> Path:
    """Directory of flux_drive_msgs' .msg files (the one set of definitions; the engine's
    bag typestore reads the same files)."""
    return MSG_SRC_DIR


# definitions of older layouts, as bags recorded them (`layout_type`): "pkg/Name@<digest>"
_RECORDED: dict[str, str] = {}


def _main_section(definition: str) -> str:
    """The top-level message of a rosbag2/MCAP definition (nested types follow '====')."""
    out = []
    for line in definition.splitlines():
        if line.startswith("=" * 8):
            break
        out.append(line)
    return "\n".join(out) + "\n"


def _shape(text: str) -> list[tuple[str, str]]:
    rows = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line and "=" not in line:
            typ, name = line.split()[:2]
            rows.append((typ, name))
    return rows


def layout_type(type_name: str, definition: str | None) -> str:
    """The codec type name for messages recorded with `definition` (a bag's own text of
    `type_name`): `type_name` itself when the fields are today's, else a name of its own for
    the recorded layout (a bag from before a field was added still decodes; fields it lacks
    are simply absent from the decoded columns)."""
    if not definition or "/" not in type_name:
        return type_name
    main = _main_section(definition)
    try:
        if _shape(main) == _shape(msg_text(type_name)):
            return type_name
    except KeyError:
        pass
    import hashlib

    pkg, _, name = type_name.replace("/msg/", "/").partition("/")
    key = f"{pkg}/msg/{name}@{hashlib.sha1(main.encode()).hexdigest()[:10]}"
    _RECORDED[key] = main
    return key


def msg_text(type_name: str) -> str:
    """.msg text of 'pkg/Name' or 'pkg/msg/Name' (or a recorded layout, `layout_type`)."""
    if type_name in _RECORDED:
        return _RECORDED[type_name]
    pkg, _, name = type_name.replace("/msg/", "/").partition("/")
    key = f"{pkg}/{name}"
    if key in _BUILTIN:
        return _BUILTIN[key]
    if pkg == "flux_drive_msgs":
        return (msg_dir() / f"{name}.msg").read_text()
    raise KeyError(f"no message definition known for {type_name}")


@dataclass(frozen=True)
class Leaf:
    path: str  # dotted field path, e.g. header.stamp.sec, i_abc[0]
    kind: str  # ROS primitive type or 'string'


@cache
def _fields(type_name: str) -> tuple[tuple[str, str, int | None], ...]:
    """(type, name, array length or None) of a message, constants and comments skipped."""
    pkg = type_name.replace("/msg/", "/").partition("/")[0]
    out = []
    for line in msg_text(type_name).splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or "=" in line.split()[-1] or re.search(r"\s\w+\s*=", line):
            continue
        typ, name = line.split()[:2]
        m = re.fullmatch(r"([\w/]+)\[(\d*)\]", typ)
        n = None
        if m:
            typ = m.group(1)
            if not m.group(2):
                raise ValueError(f"{type_name}.{name}: unbounded sequences are not supported")
            n = int(m.group(2))
        if typ not in _PRIM and typ != "string" and "/" not in typ:
            typ = f"{pkg}/{typ}"  # a type of the same package
        if typ == "Header":
            typ = "std_msgs/Header"
        out.append((typ, name, n))
    return tuple(out)


@cache
def leaves(type_name: str, prefix: str = "") -> tuple[Leaf, ...]:
    """Flattened primitive/string fields in wire order."""
    res: list[Leaf] = []
    for typ, name, n in _fields(type_name):
        for j in range(n if n is not None else 1):
            path = f"{prefix}{name}" + (f"[{j}]" if n is not None else "")
            if typ in _PRIM or typ == "string":
                res.append(Leaf(path, typ))
            else:
                res.extend(leaves(typ, path + "."))
    return tuple(res)


def _tuple_getter(idx: list[int]) -> Callable[[tuple], tuple]:
    """f(values) -> tuple(values[i] for i in idx), as a C-level itemgetter where it can."""
    if len(idx) >= 2:
        return operator.itemgetter(*idx)
    if len(idx) == 1:
        i = idx[0]
        return lambda v: (v[i],)
    return lambda v: ()


class Codec:
    """Pack/unpack one message type for fixed string contents/lengths.

    `pack(*values)` takes the non-string leaves in wire order (see `.fields`) and returns
    the serialised bytes (with the encapsulation header); `unpack(data)` returns the same
    tuple of non-string values.  Strings are those given at construction."""

    def __init__(self, type_name: str, strings: dict[str, str] | None = None):
        self.type_name = type_name
        self.leaves = leaves(type_name)
        strings = dict(strings or {})
        str_paths = [lf.path for lf in self.leaves if lf.kind == "string"]
        bad = sorted(set(strings) - set(str_paths))
        if bad:
            raise KeyError(f"{type_name}: no string field(s) {bad}; strings are {str_paths}")
        self.strings = {p: strings.get(p, "") for p in str_paths}
        fmt = ["<"]
        off = 0
        self._consts: list[tuple[int, int | bytes]] = []  # (struct arg index, value) of strings
        self.fields: list[str] = []
        self.offsets: list[int] = []  # byte offset of each numeric field in the message
        self.codes: list[str] = []  # its struct code
        n_args = 0
        for lf in self.leaves:
            if lf.kind == "string":
                raw = self.strings[lf.path].encode() + b"\x00"
                pad = (-off) % 4
                fmt.append("x" * pad + "I" + f"{len(raw)}s")
                off += pad + 4 + len(raw)
                self._consts.append((n_args, len(raw)))
                self._consts.append((n_args + 1, raw))
                n_args += 2
                continue
            code, size = _PRIM[lf.kind]
            pad = (-off) % size
            fmt.append("x" * pad + code)
            off += pad
            self.fields.append(lf.path)
            self.offsets.append(4 + off)
            self.codes.append(code)
            off += size
            n_args += 1
        self.struct = struct.Struct("".join(fmt))
        self.size = 4 + self.struct.size
        # the whole message, encapsulation header included: one struct call packs it
        self.message_struct = struct.Struct("<4s" + "".join(fmt[1:]))
        self._n_args = n_args
        # positions of the numeric leaves in the full struct tuple
        const_idx = {i for i, _ in self._consts}
        self._num_idx = [i for i in range(n_args) if i not in const_idx]
        self._len_checks = [(i, c) for i, c in self._consts if isinstance(c, int)]
        # the hot path (Decoder.decode, every message a node reads): C-level getters
        self._num_get = _tuple_getter(self._num_idx)
        self._chk_get = _tuple_getter([i for i, _ in self._len_checks])
        self._chk_vals = tuple(c for _, c in self._len_checks)
        self._np_dtypes: dict[int, Any] = {}  # numpy_dtype by item size
        self._build_pack()

    def _build_pack(self) -> None:
        # a tiny generated function: pack(*values) -> bytes with the strings spliced in
        env: dict[str, Any] = {}
        call = self.pack_call([f"v[{i}]" for i in range(len(self.fields))], env)
        exec(f"def pack(*v):\n    return {call}\n", env)  # noqa: S102 - from the definition
        self.pack = env["pack"]
        self.n_values = len(self.fields)

    def pack_call(self, values: list[str], env: dict[str, Any]) -> str:
        """For generated code: the expression that packs the whole message (header
        included) in one struct call from `values`, one Python expression per numeric field
        in `fields` order; the names it uses go into `env`."""
        consts = dict(self._consts)
        env["_H"] = ENCAPSULATION
        env["_S"] = self.message_struct.pack
        args, it = ["_H"], iter(values)
        for i in range(self._n_args):
            if i in consts:
                env[f"_c{i}"] = consts[i]
                args.append(f"_c{i}")
            else:
                args.append(next(it))
        return f"_S({', '.join(args)})"

    def unpack_source(self) -> tuple[list[int], list[tuple[int, int]]]:
        """For generated code reading `m = self.struct.unpack_from(data, 4)`: the position in
        `m` of each numeric field (`fields` order) and the (position, value) checks of the
        string lengths that make a message this layout (with len(data) == size)."""
        return list(self._num_idx), list(self._len_checks)

    def numpy_dtype(self, itemsize: int | None = None):
        """A numpy structured dtype over whole messages of this layout (field names =
        positions f0, f1, ... in `fields` order): np.frombuffer(b"".join(msgs), dtype).
        `itemsize`: the messages' length when it exceeds `size` (trailing padding).
        Built once per item size (a shadow observer asks for it at every block)."""
        key = itemsize or self.size
        dt = self._np_dtypes.get(key)
        if dt is None:
            dt = self._np_dtypes[key] = self._numpy_dtype(key)
        return dt

    def _numpy_dtype(self, itemsize: int):
        import numpy as np

        np_codes = {
            "d": "<f8",
            "f": "<f4",
            "q": "<i8",
            "Q": "<u8",
            "i": "<i4",
            "I": "<u4",
            "h": "<i2",
            "H": "<u2",
            "b": "i1",
            "B": "u1",
            "?": "?",
        }
        return np.dtype(
            {
                "names": [f"f{j}" for j in range(len(self.fields))],
                "formats": [np_codes[c] for c in self.codes],
                "offsets": self.offsets,
                "itemsize": itemsize,
            }
        )

    def index(self, path: str) -> int:
        """Position of a field in pack()/unpack() value tuples."""
        return self.fields.index(path)

    def matches(self, data: bytes) -> bool:
        """True if `data` has this codec's layout (string lengths and total size)."""
        if len(data) != self.size:
            return False
        vals = self.struct.unpack_from(data, 4)
        return all(vals[i] == c for i, c in self._len_checks)

    def matches_prefix(self, data: bytes) -> bool:
        """Like `matches`, but the message may carry trailing padding."""
        if not self.size <= len(data) < self.size + 8:
            return False
        vals = self.struct.unpack_from(data, 4)
        return all(vals[i] == c for i, c in self._len_checks)

    def unpack(self, data: bytes) -> tuple:
        return self._num_get(self.struct.unpack_from(data, 4))

    def unpack_all(self, data: bytes) -> tuple:
        """Raw struct tuple (strings and their lengths included)."""
        return self.struct.unpack_from(data, 4)


def read_strings(type_name: str, data: bytes) -> dict[str, str]:
    """The string fields of a serialised message (walks the layout; slow path)."""
    off = 0
    body = memoryview(data)[4:]
    out = {}
    for lf in leaves(type_name):
        if lf.kind == "string":
            off += (-off) % 4
            (n,) = struct.unpack_from("<I", body, off)
            out[lf.path] = bytes(body[off + 4 : off + 4 + n - 1]).decode()
            off += 4 + n
        else:
            code, size = _PRIM[lf.kind]
            off += (-off) % size + size
    return out


class Decoder:
    """Unpack a message type whatever its string contents: a `Codec` per layout, cached.

    `decode(data)` returns the numeric values (Codec.fields order) -- strings ignored."""

    def __init__(self, type_name: str):
        self.type_name = type_name
        self._last: Codec | None = None
        self._cache: dict[tuple, Codec] = {}

    def codec_for(self, data: bytes) -> Codec:
        c = self._last
        if c is not None and c.matches(data):
            return c
        for c in self._cache.values():  # several publishers with other strings
            if c.matches(data):
                self._last = c
                return c
        strings = read_strings(self.type_name, data)
        key = tuple(sorted(strings.items()))
        c = self._cache.get(key)
        if c is None:
            c = Codec(self.type_name, strings)
            if len(self._cache) < 64:
                self._cache[key] = c
        self._last = c
        return c

    def layout_of(self, data: bytes) -> Codec:
        """The codec of a message's layout, trailing padding allowed (len(data) >= size)."""
        c = self._last
        if c is not None and c.matches_prefix(data):
            return c
        for c in self._cache.values():
            if c.matches_prefix(data):
                self._last = c
                return c
        return self.codec_for(data)

    def decode(self, data: bytes) -> tuple:
        c = self._last
        if c is not None and len(data) == c.size:
            vals = c.struct.unpack_from(data, 4)
            if c._chk_get(vals) == c._chk_vals:
                return c._num_get(vals)
        c = self.codec_for(data)
        self._last = c
        return c.unpack(data)
