"""Frequency-response measurement: stepped-sine injection and single-bin correlation.

The injection is a sequence of sine bursts, each an integer number of cycles long, after a
settling time; gain and phase at each frequency come from correlating the response and the
reference with e^{-j w t} over the burst (a one-bin DFT, which rejects the harmonics and
the noise of everything else the drive does).  The -3 dB bandwidth is the first crossing
of |G| below 1/sqrt(2), interpolated in log frequency.
"""

from __future__ import annotations

import math

import numpy as np

# the injection is generated where the drive runs it (core); analysed here
from fluxdrive.core.excitation import Segment, stepped_sine

__all__ = ["Segment", "analyse", "bandwidth_hz", "correlate", "stepped_sine"]


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
