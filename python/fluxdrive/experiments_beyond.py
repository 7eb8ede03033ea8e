"""Past the paper: lowest sustainable speed, parameter mismatch and offsets, online R_s."""

from __future__ import annotations

EXPERIMENTS: dict = {}
