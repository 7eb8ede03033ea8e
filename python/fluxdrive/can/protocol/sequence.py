"""Sequence counters of the CAN samples: gaps, duplicates and reordering in a received
stream (vectorised, or streamed by a bridge), which received samples are new
(:class:`SeqFilter`: the rest are classified, counted and dropped), and wrapping counters
unwrapped. No ROS imports.
"""

from __future__ import annotations

from collections import deque
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
    (seq went backwards, or jumped by half the counter range or more). A
    :class:`SeqFilter` also counts ``jumps`` (forward further than the stream can have
    gone: dropped), ``resyncs`` (the stream continued from a jump: taken from there on)
    and ``rejected`` (duplicates + out of order + jumps: never handed on)."""

    frames: int = 0
    gaps: int = 0
    lost: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    last: int | None = None
    jumps: int = 0
    resyncs: int = 0
    rejected: int = 0

    def as_dict(self) -> dict[str, int | None]:
        """Plain dict (for JSON / diagnostics)."""
        return {
            "frames": self.frames,
            "gaps": self.gaps,
            "lost": self.lost,
            "duplicates": self.duplicates,
            "out_of_order": self.out_of_order,
            "jumps": self.jumps,
            "resyncs": self.resyncs,
            "rejected": self.rejected,
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


class SeqFilter:
    """Which received samples are new, for a bridge (streamed) or an imported capture (one
    batch): each sample's ``bits``-wide wire counter against the newest sample taken,
    ``newest`` (unwrapped, a 64-bit count):

    * forward by ``0 < d <= max_jump`` (plus what the time since the newest allows, see
      :meth:`accept`): **new**, taken (``d != step``: a gap, ``d // step - 1`` lost);
    * ``d == 0``, or backwards onto a seq taken within the last ``window`` samples:
      **duplicate** (a repeat, a replay), dropped;
    * backwards onto a seq not taken: **out of order** (late), dropped -- the samples
      after it went on already;
    * forward further than that: a **jump** (a forged or corrupted counter), dropped. A
      real jump (a drive that restarted its counter) goes on from there: after
      ``resync_after`` dropped samples in a row that follow each other by ``step``, the
      stream is taken from the next one on (``resyncs``; 0: never -- a bridge then goes
      stale and faults instead, see :class:`fluxdrive.can.bridge.CanBridge`). A counter
      that went back (a drive restarted) is never followed: what comes after is dropped.

    Dropped samples are never handed on (``rejected``); a 16-bit counter cannot tell a
    replay of samples a whole counter wrap old from new ones."""

    def __init__(
        self,
        bits: int = SEQ_BITS,
        step: int = 1,
        *,
        max_jump: int = 1000,
        window: int = 4096,
        resync_after: int = 0,
    ) -> None:
        self.mod = 1 << bits
        self.step = max(int(step), 1)
        self.max_jump = max(int(max_jump), self.step)
        self.resync_after = int(resync_after)
        self.stats = SeqStats()
        self.newest: int | None = None
        self.newest_t: float | None = None
        self.last_reason = ""  # why the newest dropped sample was dropped
        self.reject_run = 0  # samples dropped since the last one taken
        self._anchor: int | None = None  # re-anchored: the next sample goes on from here
        self._seen: deque[int] = deque(maxlen=int(window))
        self._seen_set: set[int] = set()
        self._run: list[int] = []  # dropped forward jumps following each other (resync)

    def reanchor(self) -> None:
        """The next sample starts the stream again, forward of the newest (after a
        reconnect or a fault reset): the unwrapped count never goes back."""
        if self.newest is not None:
            self._anchor = self.newest
        self.newest = None
        self._run.clear()

    def _take(self, k: int, t: float | None) -> None:
        self.newest, self.newest_t = k, t
        self.reject_run = 0
        self._run.clear()
        if len(self._seen) == self._seen.maxlen:
            self._seen_set.discard(self._seen[0])
        self._seen.append(k)
        self._seen_set.add(k)

    def _drop(self, kind: str, why: str) -> None:
        st = self.stats
        setattr(st, kind, getattr(st, kind) + 1)
        st.rejected += 1
        self.reject_run += 1
        self.last_reason = why

    def accept(
        self,
        seqs: np.ndarray | Sequence[int],
        times: np.ndarray | Sequence[float] | None = None,
        rate_hz: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Classify a batch: (taken mask, unwrapped counts; meaningful where taken).
        With ``times`` [s] (receive or capture time per sample) and the counter's rate
        ``rate_hz`` (counts per second: the PWM frequency), a forward step is also new
        while it is no more than 1.5 times what the time since the newest allows."""
        s = np.asarray(seqs, dtype=np.int64).reshape(-1)
        keep = np.zeros(s.size, dtype=bool)
        out = np.zeros(s.size, dtype=np.int64)
        half = self.mod >> 1
        st = self.stats
        for i, w in enumerate(s.tolist()):
            t = None if times is None else float(times[i])
            st.frames += 1
            st.last = w
            if self.newest is None:
                a = self._anchor
                k = w if a is None else a + 1 + ((w - a - 1) % self.mod)
                self._anchor = None
                self._take(k, t)
                keep[i], out[i] = True, k
                continue
            d = (w - self.newest) % self.mod
            if d >= half:
                d -= self.mod
            k = self.newest + d
            allowed = self.max_jump
            if t is not None and self.newest_t is not None and rate_hz > 0:
                allowed += int(1.5 * max(t - self.newest_t, 0.0) * rate_hz)
            if 0 < d <= allowed:
                if d != self.step:
                    st.gaps += 1
                    st.lost += max(d // self.step - 1, 0)
                self._take(k, t)
                keep[i], out[i] = True, k
            elif d == 0 or (d < 0 and k in self._seen_set):
                self._drop("duplicates", f"seq {w} again: sample {k} was taken already")
            elif d < 0:
                self._drop("out_of_order", f"seq {w} late: {-d} behind the newest")
            else:
                self._drop("jumps", f"seq {w} jumps {d} ahead of the newest")
                if self._resync(k, t):
                    keep[i], out[i] = True, k
            out[i] = out[i] if keep[i] else k
        return keep, out

    def _resync(self, k: int, t: float | None) -> bool:
        """A dropped forward jump: does the stream go on from there (``resync_after``
        jumps in a row, each ``step`` after the one before)? Then this one is taken."""
        if self.resync_after <= 0:
            return False
        if self._run and k - self._run[-1] != self.step:
            self._run.clear()
        self._run.append(k)
        if len(self._run) <= self.resync_after:
            return False
        self.stats.resyncs += 1
        self.stats.jumps -= 1  # this one is taken after all
        self.stats.rejected -= 1
        self._take(k, t)
        return True


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
