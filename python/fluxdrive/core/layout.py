"""Index constants of the kernels' float64 arrays, each name written once.

Every compiled kernel works on small parameter/state/row arrays addressed by module-level
integer constants (`cp[CP_TS]`); numba reads module globals at compile time, so they cost
nothing at run time.  A `Layout` hands out those integers in the order the names are
written, and its length is counted, not typed:

    _CP = Layout("CP")
    CP_TS = _CP.index()                 # PWM period [s]
    CP_P = _CP.index()                  # pole pairs
    CP_OFF_A, CP_OFF_B = _CP.indices(2)  # a contiguous group (sliced as a block)
    CP_N = _CP.close(globals())

Adding a field is one line anywhere in the block.  `close` checks that the module's
`CP_*` integers are exactly 0..N-1, each once (an index typed by hand, a duplicate or a
gap is refused at import), and records the field names in order (`_CP.names`) for code
that maps rows to messages or columns by name: a name given where the index is handed out
(`_FR.index("vdc")`, `_FR.indices(3, "i_a i_b i_c")`), else the constant's name after the
prefix in lower case.
"""

from __future__ import annotations

from collections.abc import Mapping


class Layout:
    """Consecutive indices 0, 1, ... of one kernel array whose constants start `prefix`_."""

    def __init__(self, prefix: str):
        self.prefix = prefix
        self.n = 0
        self.names: tuple[str, ...] = ()
        self._given: dict[int, str] = {}  # index -> the name given with it
        self._closed = False

    def index(self, name: str | None = None) -> int:
        """The next index; `name`: the column's name outside the kernels (default: the
        constant's)."""
        if self._closed:
            raise RuntimeError(f"layout {self.prefix} is closed; add fields before close()")
        self.n += 1
        if name is not None:
            self._given[self.n - 1] = name
        return self.n - 1

    def indices(self, count: int, names: str | None = None) -> tuple[int, ...]:
        """The next `count` indices (a block the kernel slices as a whole); `names`: their
        names, separated by spaces."""
        given: list[str | None] = list(names.split()) if names else [None] * count
        if len(given) != count:
            raise ValueError(f"layout {self.prefix}: {count} indices, names {names!r}")
        return tuple(self.index(name) for name in given)

    def close(self, namespace: Mapping[str, object]) -> int:
        """Check the module's `prefix`_* integers against the layout; return its length."""
        head = self.prefix + "_"
        found = {
            k: v
            for k, v in namespace.items()
            if k.startswith(head)
            and k != head + "N"
            and isinstance(v, int)
            and not isinstance(v, bool)
        }
        by_index = sorted(found, key=lambda k: found[k])
        if [found[k] for k in by_index] != list(range(self.n)):
            raise RuntimeError(
                f"layout {self.prefix}: constants {found} are not exactly "
                f"0..{self.n - 1} from {self.prefix}.index()"
            )
        self.names = tuple(self._given.get(found[k], k[len(head) :].lower()) for k in by_index)
        self._closed = True
        return self.n

    def __len__(self) -> int:
        return self.n
