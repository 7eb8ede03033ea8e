"""The fronts' analysis on synthetic runs: the EMF speed LPF swept apart from the PLL (off
included) at the same θ̃, settings that slipped never on a front, four fronts per family,
verdicts per seed with an interval."""

from __future__ import annotations

import math

import pytest
from fluxdrive.core.machine import MachineCard
from fluxdrive.experiments import fronts as fr


def _run(observers, theta_of, slipped=()):
    """One run's extract: every observer's θ̃ numbers from theta_of(name)."""
    return {
        "obs": {
            n: {
                "rms_deg": theta_of(n),
                "mean_deg": 0.1 * theta_of(n),
                "h6_deg": 0.5 * theta_of(n),
                "noise_deg": 0.2 * theta_of(n),
                "slipped": n in slipped,
            }
            for n in observers
        }
    }


def test_lpf_placed_apart_slips_off_the_front_and_verdict_per_seed():
    card = MachineCard()
    points, observers = fr.build_cases(True, card, points=[(0.02, 1.5)], sources=("measured",))
    emf = [n for n in observers if n.startswith("emf_measured_")]
    assert all(observers[n]["speed_lpf_hz"] == 0.0 for n in emf)  # off in the run
    # the EMF's settings: each PLL once per LPF factor, the same θ̃, off allowing the most
    bws = {
        lpf: fr.allowed_bandwidth_hz(card, {**observers[emf[0]], "speed_lpf_hz": lpf})
        for lpf in (0.0, 10.0)
    }
    assert bws[0.0] > bws[10.0]
    slipped = {"flux_measured_2"}  # the widest PLL

    # θ̃ grows with the bandwidth a setting allows (LPF off), by a factor per family: at
    # equal allowed bandwidth the ratio of two fronts is the ratio of their factors
    bw_off = {n: fr.allowed_bandwidth_hz(card, cfg) for n, cfg in observers.items()}

    def theta(n: str) -> float:
        return {"flux": 1.0, "literal": 2.0, "emf": 1.5}[n.split("_")[0]] * bw_off[n]

    cells = fr.analyse(points, observers, [_run(observers, theta, slipped)], card)
    cell = cells["2pct_150load_measured"]
    lpf_rule = fr._lpf_rule_hz("emf", card)
    assert len(cell["emf"]["settings"]) == len(emf) * len(fr.LPF_FACTORS)
    assert {s["speed_lpf_hz"] for s in cell["emf"]["settings"]} == {
        round(f * lpf_rule, 6) for f in fr.LPF_FACTORS
    } | {0.0}
    # the EMF front: only LPF-off settings (the LPF costs bandwidth, never θ̃)
    front_bw = {p[0] for p in cell["emf"]["front_rms"]}
    off_bw = {fr.allowed_bandwidth_hz(card, observers[n]) for n in emf}
    assert front_bw <= off_bw
    # the slipped flux setting is drawn apart, on no front
    for q in fr.QUANTITIES:
        assert cell["flux"]["slipped_points"][q] and f"front_{q}" in cell["flux"]
    drawn = cell["flux"]["slipped_points"]["rms"]
    assert drawn == [(bw_off["flux_measured_2"], theta("flux_measured_2"))]
    assert drawn[0] not in cell["flux"]["front_rms"]
    m = cell["matched"]["flux"]["rms"]["ratios"]
    assert m and all(r == pytest.approx(1.0 / 1.5) for r in m)
    assert all(r == pytest.approx(2.0 / 1.5) for r in cell["matched"]["literal"]["noise"]["ratios"])
    # per seed: 8 seeds with ratios 0.6..0.67 -> "better" for paper_robust's noise
    per_seed = []
    for k in range(8):
        f = 1.0 + 0.01 * k

        def th(n: str, f: float = f) -> float:
            return theta(n) * (f if n.startswith("flux") else 1.0)

        per_seed.append(fr.analyse(points, observers, [_run(observers, th, slipped)], card))
    claims = fr.judge_fronts(cells, per_seed)
    c = next(c for c in claims if c["id"] == "fronts.snr_matched[paper_robust, measured voltages]")
    assert c["stats"]["n"] == 8 and c["stats"]["outcome"] == "better" and c["verdict"] == "held"
    lit = next(
        c
        for c in claims
        if c["id"] == "fronts.position_error_matched[paper (literal), measured voltages]"
    )
    assert lit["stats"]["outcome"] == "worse" and math.isclose(lit["value"], 2.0 / 1.5)
