"""Stepped-sine excitation: the injection signal a frequency-response run feeds the drive
(a sequence of sine bursts, each an integer number of cycles long after a settling time) and
the segments over which fluxdrive.analysis.freqresp correlates the response."""

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
