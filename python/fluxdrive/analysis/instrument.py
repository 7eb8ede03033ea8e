"""The scope's instrument maths: amplitude spectra in Hz with a window, edge triggers, the
samples of a view.  No ROS, no drawing: the scope server (fluxdrive_bringup.view.scope)
feeds full-rate samples in and sends the results to the page, which only draws them.

Spectrum scaling (every window): *peak amplitude*.  With window w[n] over N samples and
X[k] = Σ w[n] x[n] e^(-j2πkn/N), a bin reads 2|X[k]|/Σw (|X[0]|/Σw at DC, and at the
Nyquist bin of an even N), so a sine x = A sin(2π f t) with f on a bin reads A whatever the
window (the window's coherent gain Σw/N is divided out).  Between two bins the reading is
lower by the window's scalloping loss: up to 36.3 % (rectangular), 15.1 % (Hann), 0.11 %
(flat-top) -- read amplitudes with the flat-top window, separate close tones with
Hann or rectangular.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fluxdrive.core.machine import ConfigError

WINDOWS = ("rectangular", "hann", "flattop")
# flat-top window coefficients (the 5-term window of D'Antona and Ferrero as SciPy's
# `flattop`): scalloping loss 0.11 % (0.01 dB), so a tone between bins still reads its amplitude
FLATTOP_A = (0.21557895, 0.41663158, 0.277263158, 0.083578947, 0.006947368)
EDGES = ("rising", "falling")
TRIGGER_MODES = ("normal", "auto", "single")


def window(name: str, n: int) -> np.ndarray:
    """The window `name` (one of WINDOWS) over n samples, periodic form (the DFT's period:
    w[n] for n = 0..N-1 of a window of length N+1 without its last point)."""
    if name not in WINDOWS:
        raise ConfigError(f"window: {name!r} is not one of {', '.join(WINDOWS)}")
    if n < 1:
        raise ConfigError("window: needs at least one sample")
    if name == "rectangular":
        return np.ones(n)
    ph = 2.0 * math.pi * np.arange(n) / n
    if name == "hann":
        return 0.5 - 0.5 * np.cos(ph)
    return sum((-1) ** k * a * np.cos(k * ph) for k, a in enumerate(FLATTOP_A))


@dataclass
class Spectrum:
    """An amplitude spectrum: bin frequencies [Hz], peak amplitudes [unit of the trace]."""

    f_hz: np.ndarray
    amplitude: np.ndarray
    window: str
    n: int  # samples transformed
    df_hz: float  # bin spacing 1/(n ts)

    def peak(self, f_lo_hz: float = 0.0, f_hi_hz: float = math.inf) -> tuple[float, float]:
        """The highest bin in [f_lo, f_hi]: (frequency [Hz], amplitude)."""
        sel = np.flatnonzero((self.f_hz >= f_lo_hz) & (self.f_hz <= f_hi_hz))
        if not len(sel):
            raise ValueError(f"no bin between {f_lo_hz} and {f_hi_hz} Hz")
        i = sel[np.argmax(self.amplitude[sel])]
        return float(self.f_hz[i]), float(self.amplitude[i])


def amplitude_spectrum(
    x: np.ndarray, ts_s: float, window_name: str = "hann", remove_mean: bool = False
) -> Spectrum:
    """Single-sided peak-amplitude spectrum of evenly sampled x (period ts_s) with the
    window `window_name`: bins 0, 1/(N ts), ... up to the Nyquist frequency 1/(2 ts).  NaN
    samples (a field a message lacked) are refused.  `remove_mean` (AC coupling): the mean
    is subtracted first, so a large DC part (i_q, a bus voltage) does not leak into the
    lowest bins through the window's main lobe (flat-top: bins 1..4, up to 1.9 times the DC)."""
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or len(x) < 2:
        raise ValueError("spectrum: needs at least two samples")
    if not np.isfinite(x).all():
        raise ValueError("spectrum: the samples hold NaN or inf")
    if not ts_s > 0:
        raise ValueError("spectrum: ts_s must be > 0")
    n = len(x)
    if remove_mean:
        x = x - x.mean()
    w = window(window_name, n)
    amp = np.abs(np.fft.rfft(w * x)) / w.sum()
    amp[1:] *= 2.0
    if n % 2 == 0:
        amp[-1] /= 2.0  # the Nyquist bin has no mirror image
    return Spectrum(np.fft.rfftfreq(n, ts_s), amp, window_name, n, 1.0 / (n * ts_s))


@dataclass
class TriggerEvent:
    """A trigger: the sample it fired at (seq) and whether it was an edge or the auto
    mode's free run (`auto`: no edge within the timeout)."""

    seq: int
    auto: bool = False


@dataclass
class EdgeTrigger:
    """An edge trigger with hysteresis on one trace, fed the trace's samples in order.

    - rising: fires at the first sample >= level after the trace was <= level - hysteresis
      (falling: <= level after >= level + hysteresis), so noise smaller than the
      hysteresis around the level fires once per edge, not at every crossing;
    - after firing it holds off for `holdoff_samples` (the acquisition after the trigger),
      then re-arms: *normal* waits for the next edge; *auto* also fires by itself
      (`auto=True`) when no edge came within `auto_timeout_samples` of the last firing or
      arming (the free run of a bench scope); *single* fires once and stops until `arm()`.
    """

    edge: str = "rising"
    level: float = 0.0
    hysteresis: float = 0.0
    mode: str = "normal"
    holdoff_samples: int = 0
    auto_timeout_samples: int = 1000
    armed: bool = True
    fired: int = 0
    # internal state: whether the trace has been beyond the hysteresis band (ready to
    # fire), the sample from which the trigger may fire again, the sample the auto
    # timeout counts from
    _ready: bool = field(default=False, repr=False)
    _hold_until: int | None = field(default=None, repr=False)
    _since: int | None = field(default=None, repr=False)
    _last_seq: int | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.edge not in EDGES:
            raise ConfigError(f"trigger edge: {self.edge!r} is not one of {', '.join(EDGES)}")
        if self.mode not in TRIGGER_MODES:
            raise ConfigError(
                f"trigger mode: {self.mode!r} is not one of {', '.join(TRIGGER_MODES)}"
            )
        if not (math.isfinite(self.level) and math.isfinite(self.hysteresis)):
            raise ConfigError("trigger level and hysteresis must be finite numbers")
        if self.hysteresis < 0:
            raise ConfigError(f"trigger hysteresis: {self.hysteresis} must be >= 0")
        if self.holdoff_samples < 0 or self.auto_timeout_samples < 1:
            raise ConfigError("trigger: holdoff >= 0 and auto timeout >= 1 samples")

    def arm(self) -> None:
        """Arm afresh (single shot: the next edge fires again)."""
        self.armed = True
        self._ready = False
        self._hold_until = None
        self._since = None

    def feed(self, seq: np.ndarray, x: np.ndarray) -> list[TriggerEvent]:
        """The events in this block of samples (seq increasing; samples at or before the
        last one fed are ignored, so overlapping blocks are harmless).  A plain state
        machine per sample (the samples are few next to what the tap decodes)."""
        seq = np.asarray(seq, dtype=np.int64)
        x = np.asarray(x, dtype=float)
        if self._last_seq is not None:
            keep = seq > self._last_seq
            seq, x = seq[keep], x[keep]
        out: list[TriggerEvent] = []
        if not len(seq):
            return out
        self._last_seq = int(seq[-1])
        sign = 1.0 if self.edge == "rising" else -1.0
        h, level, auto = self.hysteresis, self.level, self.mode == "auto"
        for s, v in zip(seq.tolist(), x.tolist(), strict=True):
            if not self.armed:
                break
            if self._since is None:
                self._since = s
            if self._hold_until is not None:
                if s < self._hold_until:
                    continue
                self._hold_until, self._ready = None, False
            if auto and s - self._since >= self.auto_timeout_samples:
                out.append(self._fire(s, auto=True))
                continue
            y = sign * (v - level)  # the edge goes from y <= -h up to y >= 0
            if not self._ready:
                self._ready = y <= -h if h > 0 else y < 0
            elif y >= 0:
                out.append(self._fire(s))
        return out

    def _fire(self, s: int, auto: bool = False) -> TriggerEvent:
        self.fired += 1
        self._since = s
        self._hold_until = s + max(self.holdoff_samples, 1)
        self._ready = False
        if self.mode == "single":
            self.armed = False
        return TriggerEvent(s, auto)


def in_view(seq: np.ndarray, ts_s: float, t0_s: float, t1_s: float) -> np.ndarray:
    """Indices of the samples whose time seq·ts lies in [t0, t1] (the view)."""
    t = np.asarray(seq, dtype=float) * ts_s
    eps = 1e-9 * max(abs(t0_s), abs(t1_s), ts_s)
    return np.flatnonzero((t >= t0_s - eps) & (t <= t1_s + eps))


class SampleBuffer:
    """The newest full-rate samples of named streams (seq and fields), at most
    `max_samples` per stream, in sample order without duplicates.  Blocks are kept as they
    come and joined only when read (a block a period, a read a second: no copy of the whole
    buffer per block); a sample at or before the newest one held is dropped."""

    def __init__(self, max_samples: int = 100_000):
        self.max_samples = max_samples
        self._chunks: dict[str, list[tuple[np.ndarray, dict[str, np.ndarray]]]] = {}
        self._n: dict[str, int] = {}

    def put(self, stream: str, seq: np.ndarray, fields: dict[str, np.ndarray]) -> None:
        seq = np.asarray(seq, dtype=np.int64)
        chunks = self._chunks.get(stream)
        if chunks and list(chunks[0][1]) != list(fields):  # other fields: start afresh
            chunks = None
        if chunks is None:
            chunks = self._chunks[stream] = []
            self._n[stream] = 0
        last = self.newest(stream)
        seq, first = np.unique(seq, return_index=True)  # sorted, first copy of a repeated seq
        keep = seq > last
        seq, first = seq[keep], first[keep]
        if not len(seq):
            return
        chunks.append((seq, {k: np.asarray(v, dtype=float)[first] for k, v in fields.items()}))
        self._n[stream] += len(seq)
        while len(chunks) > 1 and self._n[stream] - len(chunks[0][0]) >= self.max_samples:
            self._n[stream] -= len(chunks.pop(0)[0])

    def _joined(self, stream: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        chunks = self._chunks[stream]
        if len(chunks) > 1:
            seq = np.concatenate([c[0] for c in chunks])
            flds = {k: np.concatenate([c[1][k] for c in chunks]) for k in chunks[0][1]}
            chunks[:] = [(seq, flds)]
        seq, flds = chunks[0]
        cut = max(0, len(seq) - self.max_samples)
        if cut:
            seq, flds = seq[cut:], {k: v[cut:] for k, v in flds.items()}
            chunks[0] = (seq, flds)
            self._n[stream] = len(seq)
        return seq, flds

    @property
    def streams(self) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
        return {s: self._joined(s) for s, c in self._chunks.items() if c}

    def newest(self, stream: str) -> int:
        chunks = self._chunks.get(stream)
        return int(chunks[-1][0][-1]) if chunks else -1

    def oldest(self, stream: str) -> int:
        chunks = self._chunks.get(stream)
        if not chunks:
            return -1
        return (
            int(self._joined(stream)[0][0])
            if self._n[stream] > self.max_samples
            else int(chunks[0][0][0])
        )

    def trace(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """seq and values of `stream:field`."""
        stream, _, fld = name.rpartition(":")
        if not self._chunks.get(stream) or fld not in self._chunks[stream][0][1]:
            raise KeyError(name)
        seq, flds = self._joined(stream)
        return seq, flds[fld]

    def view(self, stream: str, ts_s: float, t0_s: float, t1_s: float):
        """seq and fields of `stream` within [t0, t1]."""
        if not self._chunks.get(stream):
            raise KeyError(stream)
        seq, flds = self._joined(stream)
        ix = in_view(seq, ts_s, t0_s, t1_s)
        return seq[ix], {k: v[ix] for k, v in flds.items()}


def contiguous(seq: np.ndarray) -> bool:
    """Whether seq is every sample from its first to its last (no gap)."""
    return len(seq) == 0 or int(seq[-1]) - int(seq[0]) + 1 == len(seq)
