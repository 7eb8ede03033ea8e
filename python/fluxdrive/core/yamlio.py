"""The one YAML reader of the project (engine, CLI and ROS side alike).

PyYAML resolves scalars by YAML 1.1, where a float needs a dot and a signed exponent:
`1e-4`, `1.0e9` and `5E3` come back as *strings* and then fail a range check far from the
file.  This loader adds YAML 1.2's float pattern (the one JSON and rcl's own parameter
parser accept), so every number a user writes in a config file is a number.

It is also the project's guard against hostile files: a document larger than
MAX_DOCUMENT_CHARS, nested deeper than MAX_DEPTH, whose aliases expand it by more than
ALIAS_BUDGET nodes and characters (a "billion laughs" bomb: nine aliases of nine aliases
of ... take a few hundred bytes, and gigabytes once a loader walks or prints them), with a
recursive alias, or
with an integer outside int64 (what a ROS parameter holds; a 400-digit integer would
overflow the first float() a loader calls) is refused with a YAMLError that names the line.
Every other failure while building Python values (an impossible date, text that is not
UTF-8) is a YAMLError as well, so a loader's `except (OSError, YAMLError)` covers any input.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

YAMLError = yaml.YAMLError

MAX_DOCUMENT_CHARS = 1 << 20  # 1 MiB: the largest config file of the project is a few kB
MAX_DEPTH = 64  # nested collections
# what aliases may add to a document (nodes plus scalar characters, counted as if every
# alias were a copy of its anchor) over its own size: a few kB of anchors reused freely
ALIAS_BUDGET = 100_000
INT64_MAX = (1 << 63) - 1


class LimitError(yaml.MarkedYAMLError):
    """A document the loader refuses (size, depth, alias expansion, int range, encoding)."""

    def __init__(self, problem: str, mark: Any = None):
        super().__init__(problem=problem, problem_mark=mark)


# YAML 1.2 core-schema floats: optional sign, digits with an optional fraction (or a
# leading-dot fraction), optional exponent with an optional sign; plus .inf/.nan
_FLOAT_12 = re.compile(
    r"""^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?
                         |[-+]?\.(?:inf|Inf|INF)
                         |\.(?:nan|NaN|NAN))$""",
    re.X,
)


class Loader(yaml.SafeLoader):
    """SafeLoader whose float resolver also takes YAML 1.2 floats (`1e-4`, `1.0e9`), with
    the limits of the module docstring."""

    _depth = 0
    _text_chars = 0  # set by loads()

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise LimitError(
                    f"nested deeper than {MAX_DEPTH} levels", self.peek_event().start_mark
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def compose_document(self) -> Any:
        node = super().compose_document()
        if node is not None:
            _check_expansion(node, 2 * self._text_chars + ALIAS_BUDGET)
        return node

    def construct_yaml_int(self, node: Any) -> int:
        try:
            value = super().construct_yaml_int(node)
        except ValueError as exc:  # more digits than int() converts (sys.int_info)
            raise LimitError(f"integer {node.value[:20]}... too long", node.start_mark) from exc
        if not -INT64_MAX - 1 <= value <= INT64_MAX:
            raise LimitError(
                f"integer {node.value[:20]}{'...' if len(node.value) > 20 else ''} "
                f"is outside the 64-bit range",
                node.start_mark,
            )
        return value


Loader.add_constructor("tag:yaml.org,2002:int", Loader.construct_yaml_int)


def _check_expansion(root: Any, limit: int) -> None:
    """Refuse a document whose aliases would expand it beyond `limit`, or that
    holds itself (a recursive alias).  Each node's expanded size is computed once (memo by
    identity), so the check costs the size of the document as written."""
    sizes: dict[int, int] = {}
    open_ids: set[int] = set()

    def size(node: Any) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_ids:
            raise LimitError("recursive alias (a node that contains itself)", node.start_mark)
        if isinstance(node, yaml.ScalarNode):
            n = 1 + len(node.value)
        else:
            open_ids.add(key)
            if isinstance(node, yaml.MappingNode):
                children = [c for pair in node.value for c in pair]
            else:
                children = node.value
            n = 1
            for child in children:
                n += size(child)
                if n > limit:
                    raise LimitError(
                        f"aliases expand the document by more than {ALIAS_BUDGET} nodes and "
                        f"characters (an alias bomb?)",
                        child.start_mark,
                    )
            open_ids.discard(key)
        sizes[key] = n
        return n

    size(root)


# rebuild the implicit resolvers: YAML 1.1 int first (so `10` stays an int), then 1.2 floats
Loader.yaml_implicit_resolvers = {
    k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _ch in list("-+.0123456789"):
    Loader.yaml_implicit_resolvers[_ch] = [
        (tag, rx)
        for tag, rx in Loader.yaml_implicit_resolvers.get(_ch, [])
        if tag != "tag:yaml.org,2002:float"
    ]
Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+.0123456789"))


def loads(text: str) -> Any:
    """Parse YAML text (safe: plain data only); any refusal is a YAMLError."""
    if len(text) > MAX_DOCUMENT_CHARS:
        raise LimitError(f"{len(text)} characters, more than the {MAX_DOCUMENT_CHARS} accepted")
    try:
        loader = Loader(text)
        loader._text_chars = len(text)
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError:
        raise
    except Exception as exc:  # noqa: BLE001 - PyYAML's constructors fail on some scalars
        # with built-in errors: a timestamp that is no date (2001-13-45, ValueError), an
        # empty `!!int` (IndexError), ...: each is the document's fault, said in one line
        raise LimitError(f"cannot build a value: {type(exc).__name__}: {exc}") from exc


def load_file(path: str | Path) -> Any:
    """Read and parse a YAML file; OSError / yaml.YAMLError (also for a file too large or
    not UTF-8) propagate to the caller, who names the file in its message."""
    path = Path(path)
    if path.exists() and not path.is_file():  # a FIFO or a device would block the read
        kind = "a folder" if path.is_dir() else "not a regular file (a FIFO, socket or device)"
        raise LimitError(f"{kind}: a YAML file is read whole, from a regular file only")
    if path.is_file() and path.stat().st_size > 4 * MAX_DOCUMENT_CHARS:
        raise LimitError(f"{path.stat().st_size} bytes, too large for a YAML file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise LimitError(f"not UTF-8 text (byte {exc.start})") from exc
    return loads(text)


def dumps(data: Any, **kw: Any) -> str:
    """yaml.safe_dump (floats such as 1e-05 are written as `1.0e-05`, which loads back)."""
    return yaml.safe_dump(data, **kw)


def problem_line(exc: BaseException) -> str:
    """' (line N)' of a YAML parse error, '' if it has no position."""
    mark = getattr(exc, "problem_mark", None)
    return f" (line {mark.line + 1})" if mark is not None else ""


def describe(exc: BaseException) -> str:
    """One line for a YAMLError or OSError: what is wrong and on which line (PyYAML's own
    str() spans several lines with the position)."""
    if isinstance(exc, OSError):
        return exc.strerror or str(exc)
    lines = str(exc).splitlines()
    problem = getattr(exc, "problem", None) or (lines[0] if lines else type(exc).__name__)
    return f"{problem}{problem_line(exc)}"
