"""`./fluxdrive compare`: Pareto fronts for any set of variants, a user's class included."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from fluxdrive.cli.compare import main

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "my_observer"
PLUGIN = "my_observer.flux_pll:FluxPllObserver"  # paper_robust's equations in plain Python


@pytest.fixture
def example_importable(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.setenv("PYTHONPATH", f"{EXAMPLE}:{os.environ.get('PYTHONPATH', '')}")


def test_compare_builtin_and_plugin_on_a_coarse_grid(tmp_path, example_importable, capsys):
    """paper_robust and a plugin written from the same equations (docs/engine.md), swept on
    one operating point: both get the same allowed speed bandwidths (the design rule sees
    the same PLL), a wider PLL allows more, and the two fronts agree point by point (the
    same estimator, so the same θ̃) -- the plugin really ran with the swept settings."""
    out = tmp_path / "cmp"
    argv = ["paper_robust", PLUGIN, "--quick", "--speeds", "0.1", "--loads", "0"]
    argv += ["--sources", "measured", "--settle-s", "0.3", "--window-s", "0.4"]
    argv += ["--workers", "1", "--out", str(out)]
    assert main(argv) == 0
    res = json.loads((out / "compare.json").read_text())
    assert (out / res["figure"]).stat().st_size > 0
    cell = res["cells"]["10pct_0load_measured"]
    ours, theirs = cell["paper_robust"], cell["flux_pll_observer"]
    bws = [p[0] for p in ours["points"]["rms"]]
    assert [p[0] for p in theirs["points"]["rms"]] == pytest.approx(bws)
    assert bws[2] > bws[1] > bws[0]  # PLL factors 0.6, 1.0, 1.6 of the card's rule
    for (_, a), (_, b) in zip(ours["points"]["rms"], theirs["points"]["rms"], strict=True):
        assert b == pytest.approx(a, abs=0.1)
    # the same estimator: θ̃ of the first over the second at equal allowed bandwidth is 1
    ratios = res["fronts"]["10pct_0load_measured"]["first_over_second"]["rms"]["ratios"]
    assert ratios and all(r == pytest.approx(1.0, abs=0.1) for r in ratios)
    # the cutoff sweep (half the card's w_c) sits at the card PLL's bandwidth
    assert ours["settings"][-1]["cutoff_hz"] == pytest.approx(0.5 * 100.0)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["variants"] == {
        "paper_robust": "paper_robust",
        "flux_pll_observer": PLUGIN,
    }


def test_matched_ratio_when_one_front_starts_above_the_other():
    """Fronts that do not overlap in bandwidth are still compared where both observers have
    settings: a family whose lower-bandwidth settings did no better than its best holds that
    θ̃ below it (a speed loop can be tuned slower than its observer allows), so the ratio runs
    from the higher of the two lowest swept bandwidths and says which front was held; below
    a family's lowest setting nothing is assumed."""
    from fluxdrive.experiments.fronts import matched_ratio, pareto

    flux_pts = [(6.0, 0.03), (15.0, 0.02), (29.0, 0.03)]  # the 6 Hz setting is dominated
    emf_pts = [(3.0, 0.04), (13.0, 0.10)]
    flux, emf = pareto(flux_pts), pareto(emf_pts)
    assert flux == [(15.0, 0.02), (29.0, 0.03)]
    cell = {
        "flux": {"f": flux, "points": {"f": flux_pts}},
        "emf": {"f": emf, "points": {"f": emf_pts}},
    }
    m = matched_ratio(cell, "flux", "emf", "f")
    assert m["matched_bw_hz"] == pytest.approx([6.0, 13.0])
    assert m["held_below_hz"] == {"flux": 15.0}
    # flux holds 0.02 over the whole range; EMF rises linearly from 0.04 at 3 Hz to 0.10 at 13
    assert len(m["ratios"]) == 9
    assert m["ratios"][0] == pytest.approx(0.02 / 0.058)
    assert m["ratios"][-1] == pytest.approx(0.02 / 0.10)
    # no bandwidth both allow, or no front at all: nothing compared, said as such
    low = {"flux": {"f": [(20.0, 0.1)]}, "emf": {"f": [(3.0, 0.1), (13.0, 0.2)]}}
    assert matched_ratio(low, "flux", "emf", "f")["ratios"] == []
    none = matched_ratio({"flux": {"f": flux}, "emf": {"f": []}}, "flux", "emf", "f")
    assert none["ratios"] == [] and none["matched_bw_hz"] is None


def test_variant_specs_take_fixed_settings_as_replay_does(example_importable, tmp_path):
    """`compare` takes replay's `TARGET:key=value` specs: the fixed setting rides in every
    swept config, PLL (and cutoff) still swept; a key the variant lacks is one line."""
    from fluxdrive.cli.compare import _parser, families_of, out_folder
    from fluxdrive.core.machine import ConfigError
    from fluxdrive.drive.config_blocks import default_card
    from fluxdrive.experiments.fronts import build_cases

    fams = families_of(["paper_robust:pll_damping=0.7", f"{PLUGIN}:rate_lpf_hz=5"])
    assert fams == {
        "paper_robust_pll_damping_0_7": "paper_robust:pll_damping=0.7",
        "flux_pll_observer_rate_lpf_hz_5_0": f"{PLUGIN}:rate_lpf_hz=5.0",
    }
    _, obs = build_cases(True, default_card(), fams, [(0.1, 0.0)], ("measured",))
    ours = [c for n, c in obs.items() if n.startswith("paper_robust")]
    theirs = [c for n, c in obs.items() if n.startswith("flux_pll")]
    assert {c["pll_damping"] for c in ours} == {0.7}
    assert len({c["pll_bandwidth_hz"] for c in ours}) == 3  # the quick PLL factors
    assert {c["extra"]["rate_lpf_hz"] for c in theirs} == {5.0}
    with pytest.raises(ConfigError):
        families_of(["paper_robust:no_such_key=1"])
    # nothing lands in the tracked results/ unless asked
    args = _parser().parse_args(["paper_robust"])
    assert out_folder(args).parts[-2:] == ("out", "compare")
    args = _parser().parse_args(["paper_robust", "--write"])
    assert out_folder(args).parts[-2:] == ("results", "compare")
