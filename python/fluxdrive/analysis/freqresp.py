"""Frequency-response measurement: stepped-sine injection and single-bin correlation.

The injection is a sequence of sine bursts, each an integer number of cycles long, after a
settling time; gain and phase at each frequency come from correlating the response and the
reference with e^{-j w t} over the burst (a one-bin DFT, which rejects the harmonics and
the noise of everything else the drive does).  The -3 dB bandwidth is the first crossing
of |G| below 1/sqrt(2), interpolated in log frequency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Segment:
    frequency_hz: float
    k_start: int  # first sample of the analysed cycles
    k_end: int  # one past the last


def stepped_sine(
    freqs_hz: list[float],
    amplitude: float,
    ts_s: float,
    start_s: float,
    cycles: int = 8,
    settle_cycles: int = 3,
    min_segment_s: float = 0.02,
    settle_min_s: float = 0.01,
) -> tuple[np.ndarray, list[Segment], int]:
    """Injection signal (length n) and the analysis segments.  Each burst lasts at least
    `cycles` cycles and `min_segment_s`; each is preceded by at least `settle_cycles`
    cycles and `settle_min_s` of the same sine."""
    parts: list[np.ndarray] = []
    segs: list[Segment] = []
    k = int(round(start_s / ts_s))
    parts.append(np.zeros(k))
    for f in freqs_hz:
        period = 1.0 / f
        n_cyc = max(cycles, int(math.ceil(min_segment_s / period)))
        n_set = max(settle_cycles, int(math.ceil(settle_min_s / period)))
        n_an = int(round(n_cyc * period / ts_s))
        n_st = int(round(n_set * period / ts_s))
        kk = np.arange(n_st + n_an)
        parts.append(amplitude * np.sin(2 * math.pi * f * kk * ts_s))
        segs.append(Segment(f, k + n_st, k + n_st + n_an))
        k += n_st + n_an
    return np.concatenate(parts), segs, k


def correlate(
    response: np.ndarray, reference: np.ndarray, seg: Segment, ts_s: float
) -> tuple[complex, float]:
    """Complex gain response/reference at the segment's frequency, and the coherence-like
    ratio of the bin's power to the response's total AC power (1 = clean sine)."""
    k = np.arange(seg.k_start, seg.k_end)
    ph = np.exp(-1j * 2 * math.pi * seg.frequency_hz * k * ts_s)
    y = response[seg.k_start : seg.k_end]
    x = reference[seg.k_start : seg.k_end]
    cy = np.mean((y - y.mean()) * ph)
    cx = np.mean((x - x.mean()) * ph)
    g = cy / cx if abs(cx) > 0 else complex("nan")
    power = np.mean((y - y.mean()) ** 2)
    coh = float(min(2 * abs(cy) ** 2 / power, 1.0)) if power > 0 else 0.0
    return complex(g), coh


def bandwidth_hz(freqs: np.ndarray, gain: np.ndarray) -> float:
    """First -3 dB crossing (interpolated in log f); nan if the gain never drops."""
    mag = np.abs(gain)
    thr = 1.0 / math.sqrt(2.0)
    for i in range(1, len(freqs)):
        if mag[i] < thr <= mag[i - 1]:
            lf0, lf1 = math.log(freqs[i - 1]), math.log(freqs[i])
            a = (mag[i - 1] - thr) / (mag[i - 1] - mag[i])
            return float(math.exp(lf0 + a * (lf1 - lf0)))
    return float("nan")


def analyse(
    response: np.ndarray, reference: np.ndarray, segments: list[Segment], ts_s: float
) -> dict:
    freqs = np.array([s.frequency_hz for s in segments])
    res = [correlate(response, reference, s, ts_s) for s in segments]
    g = np.array([r[0] for r in res])
    coh = np.array([r[1] for r in res])
    return {
        "frequency_hz": freqs.tolist(),
        "gain_db": (20 * np.log10(np.abs(g))).tolist(),
        "phase_deg": np.degrees(np.unwrap(np.angle(g))).tolist(),
        "coherence": coh.tolist(),
        "bandwidth_hz": bandwidth_hz(freqs, g),
    }
