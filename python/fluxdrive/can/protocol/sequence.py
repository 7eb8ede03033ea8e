"""Sequence counters of the CAN samples: gaps, duplicates and reordering in a received
stream (vectorised, or streamed by a bridge), and wrapping counters unwrapped. No ROS imports.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

SEQ_BITS = 16
"""Width of the sample sequence counter (wraps at 2**16)."""


# --------------------------------------------------------------------------- sequences


@dataclass
class SeqStats:
    """Sequence-counter statistics: ``frames`` seen, ``gaps`` (gap events), ``lost``
    (frames missing inside gaps), ``duplicates`` (same seq again) and ``out_of_order``
    (seq went backwards, or jumped by half the counter range or more)."""

    frames: int = 0
    gaps: int = 0
    lost: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    last: int | None = None

    def as_dict(self) -> dict[str, int | None]:
        """Plain dict (for JSON / diagnostics)."""
        return {
            "frames": self.frames,
            "gaps": self.gaps,
            "lost": self.lost,
            "duplicates": self.duplicates,
            "out_of_order": self.out_of_order,
            "last": self.last,
        }


def count_seq_gaps(
    seq: np.ndarray | Sequence[int],
    *,
    bits: int = SEQ_BITS,
    step: int = 1,
    prev: int | None = None,
) -> SeqStats:
    """Vectorised gap count over a received sequence-counter stream (``bits`` wide,
    wrapping). ``step`` is the nominal increment (the decimation factor D,
    either layout). A forward jump ``d != step`` with ``0 < d < 2**(bits-1)`` (modulo the
    counter width) counts as one gap with ``d // step - 1`` lost frames; ``d == 0`` is a
    duplicate; a backwards jump is out of order. ``prev`` is the last seq of a previous
    chunk."""
    s = np.asarray(seq, dtype=np.int64).reshape(-1)
    stats = SeqStats(frames=int(s.size))
    if s.size == 0:
        stats.last = prev
        return stats
    if prev is not None:
        s_full = np.concatenate(([int(prev)], s))
    else:
        s_full = s
    mod = 1 << bits
    d = np.mod(np.diff(s_full), mod)
    half = mod >> 1
    fwd = (d > 0) & (d < half)
    gap = fwd & (d != step)
    stats.gaps = int(np.count_nonzero(gap))
    stats.lost = int(np.sum(np.maximum(d[gap] // step - 1, 0)))
    stats.duplicates = int(np.count_nonzero(d == 0))
    stats.out_of_order = int(np.count_nonzero(d >= half))
    stats.last = int(s[-1])
    return stats


class SeqTracker:
    """Streaming version of :func:`count_seq_gaps` for a bridge: call :meth:`update`
    per received frame (or :meth:`update_many` per batch); totals in :attr:`stats`."""

    def __init__(self, bits: int = SEQ_BITS, step: int = 1) -> None:
        self.bits = bits
        self.step = step
        self.stats = SeqStats()

    def update(self, seq: int) -> int:
        """Account one frame; return the number of frames lost just before it."""
        before = self.stats.lost
        self.update_many([seq])
        return self.stats.lost - before

    def update_many(self, seqs: np.ndarray | Sequence[int]) -> SeqStats:
        """Account a batch; return the batch's own statistics."""
        st = count_seq_gaps(seqs, bits=self.bits, step=self.step, prev=self.stats.last)
        t = self.stats
        t.frames += st.frames
        t.gaps += st.gaps
        t.lost += st.lost
        t.duplicates += st.duplicates
        t.out_of_order += st.out_of_order
        t.last = st.last
        return st

    def reset(self) -> None:
        """Forget all history (e.g. after a reconnect)."""
        self.stats = SeqStats()


def unwrap_counter(values: np.ndarray, bits: int, prev: float | None = None) -> np.ndarray:
    """Unwrap a ``bits``-wide two's-complement counter (e.g. the classic layout's 24-bit
    encoder) into a continuous float64 count, assuming |step| < 2**(bits-1) between
    consecutive samples. ``prev`` is the last unwrapped value of a previous chunk."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        return v
    mod = float(1 << bits)
    half = mod / 2
    first = v[0]
    if prev is not None:
        first = prev + ((v[0] - prev + half) % mod - half)
    d = (np.diff(v) + half) % mod - half
    return first + np.concatenate(([0.0], np.cumsum(d)))
