"""Each experiment's core assertion, on its quick version (in-process, serial)."""

from __future__ import annotations

import json
import math
import re
import statistics

import pytest
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.experiments.registry import run_experiment, write_report


def _run(name, tmp_path):
    res = run_experiment(name, tmp_path, quick=True, runner=None, echo=False)
    write_report(tmp_path, {name: res})
    return res


def _value(res, cid):
    """The number a registered claim (config/claims.yaml) rests on, by its id."""
    return next(c for c in res["claims"] if c.get("id") == cid)["value"]


def test_claims_table_is_the_experiments_registry():
    """Every claim the experiments judge is registered (the paper's table or the one past the
    paper), and every registered claim is judged; a reproduction names how it fails, the
    others why they cannot count."""
    import re
    from pathlib import Path

    from fluxdrive.experiments.claims import count, judge
    from fluxdrive.experiments.claims import table as claims_table
    from fluxdrive.experiments.registry import experiment_modules

    table = claims_table()
    # every experiment module the registry lists (a claim judged anywhere is registered)
    src = "".join(Path(m.__file__).read_text() for m in experiment_modules())
    from fluxdrive.experiments.fronts import FRONT_CLAIMS

    used = set(re.findall(r'judge\(\s*"([a-z0-9_.]+)"', src)) | set(FRONT_CLAIMS)
    assert used == set(table)
    for row in table.values():
        assert row["if_fails"] in ("disagreement", "modelling_gap")
        assert (
            row["class"] in ("reproduction", "beyond")
            or row.get("calibration")
            or row.get("design")
        )
    # a model number fitted to a figure does not judge it; rows true by construction apart
    for cid in ("fig14.measured_6th_gone", "fig19.step_dip", "fig18.emf"):
        assert table[cid]["class"] == "calibrated"
    for cid in ("fig17.flux", "fig18.flux", "robust.departures_leak"):
        assert table[cid]["class"] == "by_design"
    # the verdict is the table's test: a calibrated claim that passes is not "held"
    c = judge("fig13.fullload_hexagon", "x", 10.0)
    assert c["passes"] and c["holds"] is None and c["verdict"] == "calibrated"
    r = judge("fig14.stable", "x", 0.5)
    assert r["verdict"] == "disagreement" and r["holds"] is False
    # a by-design row that fails its own test counts as the failure it names, not apart
    leak = judge("robust.departures_leak", "x", 0.9)
    assert leak["verdict"] == "disagreement" and leak["holds"] is None
    assert count([c, r, leak, judge("fig14.stable", "x", 1.0)]) == {
        "held": 1,
        "disagreement": 2,
        "modelling_gap": 0,
        "undecided": 0,
        "calibrated": 1,
        "by_design": 0,
    }


def test_experiments_are_found_by_listing_the_package(tmp_path, monkeypatch):
    """A module with EXPERIMENTS and GROUP in the experiments package is an experiment (no
    hand-kept list); the groups follow GROUP; a beyond-the-paper row is judged like a
    reproduction but counted apart from the paper's claims in the report."""
    import sys

    import fluxdrive.experiments as pkg
    from fluxdrive.experiments import registry
    from fluxdrive.experiments.claims import judge

    names = {m.__name__.rsplit(".", 1)[1] for m in registry.experiment_modules()}
    past = {"lowest_speed", "mismatch", "sensitivity", "speed_reversal", "hexagon"}
    assert {"paper", "fronts", "emf_start", "peers_fail", "rs_adapt"} | past <= names
    # one experiment per module past the paper, named after it
    for m in registry.experiment_modules():
        if m.GROUP == "beyond":
            assert list(m.EXPERIMENTS) == [m.__name__.rsplit(".", 1)[1]], m.__name__
    (tmp_path / "extra_probe.py").write_text(
        'GROUP = "beyond"\nEXPERIMENTS = {"probe": (lambda ctx: {"claims": []}, "probe")}\n'
    )
    monkeypatch.setattr(pkg, "__path__", [*pkg.__path__, str(tmp_path)])
    registry.experiment_modules.cache_clear()
    try:
        assert "probe" in registry.groups()["beyond"]
        assert "probe" in registry.experiments() and "probe" not in registry.groups()["paper"]
    finally:
        registry.experiment_modules.cache_clear()
        sys.modules.pop("fluxdrive.experiments.extra_probe", None)
    row = judge("emf_start.speed_holds", "x", 1.0)
    assert row["verdict"] == "held" and row["class"] == "beyond"
    paper_row = judge("fig14.stable", "x", 1.0)
    registry.write_report(tmp_path, {"a": {"claims": [row, paper_row]}})
    import json

    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["counts"]["held"] == 1 and doc["counts_beyond"]["held"] == 1


# what only the judge decides: an experiment module that names one of these in its code (a
# string, a row key) or builds a claim row itself decides a verdict
_VERDICT_WORDS = {"held", "failed", "holds", "passes", "verdict", "disagreement"}
_VERDICT_WORDS |= {"modelling_gap", "undecided", "calibrated", "by_design"}


def test_no_experiment_module_decides_a_verdict():
    """Every listed experiment module (and what they share) is read as code: no string
    constant that is a verdict or a verdict key (held, failed, verdict, holds, passes, the
    classes' verdicts), no function `claim`; rows are `judge(...)` (a registered test decides)
    or `observe(...)` (no verdict).  And the registry refuses at run time a row that carries a
    verdict the judge did not give."""
    import ast
    from pathlib import Path

    import fluxdrive.experiments as pkg
    from fluxdrive.experiments.claims import judge
    from fluxdrive.experiments.registry import check_rows, experiment_modules

    mods = [Path(m.__file__) for m in experiment_modules()]
    mods += [Path(pkg.__path__[0]) / "beyond_common.py", Path(pkg.__path__[0]) / "common.py"]
    assert len(mods) >= 11
    for path in mods:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                where = f"{path.name}:{node.lineno}: {node.value!r}"
                assert node.value not in _VERDICT_WORDS, where
            if isinstance(node, ast.FunctionDef):
                assert node.name != "claim", f"{path.name}:{node.lineno}"
    row = judge("mismatch.l_angle", "x", 1.0)
    assert row["verdict"] == "held" and row["class"] == "beyond"
    check_rows("probe", [row, {"claim": "a measurement", "ours": "x"}])
    for bad in (
        {"claim": "decided here", "ours": "x", "holds": True},  # no registered claim
        {**row, "verdict": "disagreement"},  # not what the registered test says of 1.0
        {**row, "value": 9.0},  # the value changed after judging
    ):
        with pytest.raises(ValueError, match="probe"):
            check_rows("probe", [bad])


def test_every_claim_past_the_paper_is_produced_by_a_listed_experiment():
    """The second table (config/claims_beyond.yaml) is frozen at its registered version, holds
    only class `beyond`, shares no id with the paper's table, and each of its rows names a
    listed experiment of group beyond whose module judges that id."""
    import re
    from pathlib import Path

    from fluxdrive.experiments.claims import (
        BEYOND_FILE,
        BEYOND_HISTORY_FILE,
        CLAIMS_FILE,
        registered,
        registry_info,
    )
    from fluxdrive.experiments.registry import experiment_modules

    info = registry_info(BEYOND_FILE, BEYOND_HISTORY_FILE)
    assert info["problems"] == [] and info["registered"]
    rows = registered(BEYOND_FILE)
    assert len(rows) >= 20 and not set(rows) & set(registered(CLAIMS_FILE))
    by_name = {n: m for m in experiment_modules() for n in m.EXPERIMENTS}
    for cid, row in rows.items():
        assert row["class"] == "beyond", cid
        mod = by_name[row["experiment"]]
        assert mod.GROUP == "beyond", cid
        judged = set(re.findall(r'judge\(\s*"([a-z0-9_.]+)"', Path(mod.__file__).read_text()))
        assert cid in judged, (cid, mod.__name__)


def test_emf_start_rows_rest_on_a_sensorless_handover(tmp_path):
    """emf_start (quick: 2 seeds): every seed hands over to the EMF observer on the I-f ramp
    and holds 60 rpm at 150 %; each registered row says which handover it rests on."""
    r = _run("emf_start", tmp_path)
    for cid in ("emf_start.clean", "emf_start.theta_bounded", "emf_start.speed_holds"):
        row = next(c for c in r["claims"] if c["id"] == cid)
        assert row["verdict"] == "held", row
        assert "handover to emf_measured" in row["ours"]
    assert all(x["clean"] for x in r["data"]["runs"])


def test_claims_table_is_frozen_at_its_registered_version():
    """The table's claims hash to the SHA-256 registered for its version in
    config/claims_history.yaml (a change to a claim needs a new version there)."""
    from fluxdrive.core import yamlio
    from fluxdrive.experiments.claims import CLAIMS_FILE, content_hash, registry_info

    info = registry_info()
    computed = content_hash(yamlio.load_file(CLAIMS_FILE)["claims"])
    assert info["problems"] == [], f"the claims now hash to {computed}"
    assert info["registered"] and info["version"] == info["history"][-1]["version"] >= 2


def test_a_threshold_changed_without_a_new_version_is_refused(tmp_path):
    """Relax one threshold in a copy of the table: its hash no longer matches the version's;
    registering a new version (the table's version, its hash, a history entry) makes it
    frozen again.  Reformatting the YAML alone changes nothing."""
    from fluxdrive.core import yamlio
    from fluxdrive.experiments.claims import CLAIMS_FILE, HISTORY_FILE, content_hash, registry_info

    text = CLAIMS_FILE.read_text()
    hist = HISTORY_FILE.read_text()
    table, history = tmp_path / "claims.yaml", tmp_path / "history.yaml"
    table.write_text(text.replace("# ", "#  "))  # comments only
    history.write_text(hist)
    assert registry_info(table, history)["problems"] == []
    relaxed = text.replace("threshold: 0.25\n", "threshold: 0.3\n", 1)
    assert relaxed != text
    table.write_text(relaxed)
    problems = registry_info(table, history)["problems"]
    assert any("register a new version" in p for p in problems)
    version = yamlio.load_file(table)["version"]
    new_hash = content_hash(yamlio.load_file(table)["claims"])
    relaxed = re.sub(r"^sha256: \S+", f"sha256: {new_hash}", relaxed, flags=re.M)
    table.write_text(relaxed)  # the table's own hash updated, the version not
    assert any(
        "changed without a new version" in p for p in registry_info(table, history)["problems"]
    )
    table.write_text(relaxed.replace(f"version: {version}", f"version: {version + 1}", 1))
    history.write_text(
        hist + f"  - version: {version + 1}\n    sha256: {new_hash}\n"
        '    date: "2026-11-30"\n    what: relaxed for the test\n'
    )
    assert registry_info(table, history)["problems"] == []


def test_verdicts_over_seeds_have_intervals_margins_and_original_tests():
    """Mean and 95 % Student-t interval of the per-seed values; a comparison is better /
    worse / no difference / undecided against threshold ± margin; the row changed before
    registration is judged under both tests."""
    from fluxdrive.experiments.claims import compare, interval, judge

    st = interval([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0])
    half = 2.365 * math.sqrt(6.0) / math.sqrt(8.0)  # t(0.975, 7)·s/√n, s² = 6
    assert st["mean"] == 4.5 and st["ci95"] == pytest.approx([4.5 - half, 4.5 + half])
    assert interval([1.0])["ci95"] == [-math.inf, math.inf]  # one seed bounds nothing
    assert math.isinf(interval([1.0, math.nan])["ci95"][1])  # a run that stopped
    assert compare("<", 1.0, 0.05, [0.80, 0.90]) == "better"
    assert compare("<", 1.0, 0.05, [1.10, 1.20]) == "worse"
    assert compare("<", 1.0, 0.05, [0.97, 1.02]) == "no difference"
    assert compare("<", 1.0, 0.05, [0.90, 1.02]) == "undecided"
    # flux/EMF noise 0.98 ± 0.01 over 8 seeds: "no difference", so not held -- never a coin
    # flip on one seed; the original test also wanted the total RMS lower
    seeds = [0.97, 0.98, 0.99, 0.98, 0.97, 0.99, 0.98, 0.98]
    c = judge("fig14.measured_snr", "x", math.nan, samples=seeds, also={"theta_rms_ratio": 0.5})
    assert c["stats"]["outcome"] == "no difference" and c["verdict"] == "disagreement"
    better = [0.6 + 0.01 * k for k in range(8)]
    c = judge("fig14.measured_snr", "x", math.nan, samples=better, also={"theta_rms_ratio": 1.1})
    assert c["verdict"] == "held" and c["original"]["verdict"] == "disagreement"
    wide = [0.2, 1.8, 0.3, 1.7, 0.2, 1.8, 0.3, 1.7]
    assert judge("fig14.measured_snr", "x", math.nan, samples=wide)["verdict"] == "undecided"


def test_a_one_seed_experiments_rows_are_judged_over_its_seeds():
    """The registry's seed runs: per-seed rows -> the mean with its t-interval, the margin's
    outcome, every seed's value in the text; a run lost on every seed (inf) fails, on some
    seeds leaves a test undecided."""
    from fluxdrive.experiments.claims import judge, over_seeds

    def seed_rows(k: int, tight: float, rec: float) -> list[dict]:
        return [
            judge("fig13.fullload_flux_tighter", f"seed {k}", tight),
            judge("fig19.fullload_4pct", "x", 1.0),
            judge("fig17.flux", "x", rec),
        ]

    tight = [0.50, 0.52, 0.48, 0.51, 0.49, 0.50, 0.53, 0.47]
    inf = math.inf
    rows = over_seeds([seed_rows(k, x, inf) for k, x in enumerate(tight, 1)])
    t0, full, lost = rows
    half = 2.365 * statistics.stdev(tight) / math.sqrt(8)
    assert t0["value"] == pytest.approx(0.5) and t0["stats"]["ci95"] == pytest.approx(
        [0.5 - half, 0.5 + half]
    )
    assert t0["stats"]["outcome"] == "better" and t0["verdict"] == "held"
    assert t0["per_seed"] == tight and "per seed: 0.5, 0.52" in t0["ours"]
    assert full["stats"]["outcome"] == "passes" and full["stats"]["n"] == 8
    assert lost["verdict"] == "disagreement" and lost["stats"]["outcome"] == "fails"
    some = over_seeds([seed_rows(k, 0.5, inf if k == 3 else 0.01) for k in range(1, 9)])
    assert some[2]["verdict"] == "undecided"


def test_experiments_and_their_seeds_run_at_once_on_a_cluster_with_the_same_rows(
    tmp_path, monkeypatch
):
    """On a runner with a cluster, `run_experiments` has every experiment, and each one's
    seeds, in flight at once (the runner sees their maps overlap: each map waits for another
    one to start), and the rows are those of the in-process run, one after the other."""
    import threading

    from fluxdrive.experiments import registry
    from fluxdrive.experiments.claims import judge
    from fluxdrive.experiments.common import plt

    saved: list[tuple[int, bool]] = []

    def probe(ctx):
        vals = ctx.map(lambda x: x * x, [ctx.seed, ctx.seed + 1])
        row = judge("fig19.fullload_4pct", f"seed {ctx.seed}", 1.0 + 0.01 * sum(vals))
        name = ctx.fig(plt().figure(figsize=(1, 1)), f"probe_{ctx.name}")
        saved.append((ctx.seed, (ctx.out / name).exists()))
        return {"claims": [row], "figures": [name], "data": {"seed": ctx.seed}}

    class Cluster:  # the runner's interface; `client` set: the experiments run in turns
        client = object()

        def __init__(self) -> None:
            self.pairs = threading.Barrier(2, timeout=60)
            self.maps = 0

        def map(self, fn, items, progress=None):
            self.maps += 1
            self.pairs.wait()  # breaks (the test fails) unless another map is in flight
            return [fn(x) for x in items]

    monkeypatch.setattr(registry, "_registry", lambda: {"a": (probe, "a"), "b": (probe, "b")})
    rows: dict[str, dict[str, list]] = {"cluster": {}, "in-process": {}}
    cluster = Cluster()
    for how, runner in (("cluster", cluster), ("in-process", None)):
        registry.run_experiments(
            ["a", "b"],
            tmp_path,
            lambda n, res, how=how: rows[how].__setitem__(n, res["claims"]),
            lambda n, exc: pytest.fail(f"{n}: {exc!r}"),
            runner,
            seeds=3,
            echo=False,
        )
    assert cluster.maps == 6  # 2 experiments x 3 seeds, each map met another in flight
    # the figures are seed 1's: a rerun on another seed draws them but saves none
    assert sorted(saved) == [(1, True)] * 4 + [(2, False)] * 4 + [(3, False)] * 4
    assert rows["cluster"] == rows["in-process"]
    row = rows["cluster"]["a"][0]
    assert row["stats"]["n"] == 3 and row["per_seed"] == pytest.approx([1.05, 1.13, 1.25])


def test_deltas_say_which_reproductions_hold_on_both_cards():
    """`experiment deltas` (e.g. a second card against the default one): per reproduction both
    reports judged, whether it holds in both, in one only or in neither; a calibrated row and
    a claim only one report has are not among them."""
    from fluxdrive.cli.experiment import verdict_deltas
    from fluxdrive.experiments.claims import judge

    def report(tight: float, full: float) -> dict:
        rows = [
            judge("fig13.fullload_flux_tighter", "x", tight),
            judge("fig19.fullload_4pct", "x", full),
            judge("fig14.measured_6th_gone", "x", 0.01),  # calibrated
        ]
        return {"experiments": {"e": {"claims": rows}}}

    base, new = report(0.5, 1.0), report(2.0, 1.0)
    new["experiments"]["f"] = {"claims": [judge("fig14.stable", "x", 1.0)]}
    rep = verdict_deltas(base, new)["reproduction"]
    assert rep["claims"] == 2
    assert rep["held_both"] == ["fig19.fullload_4pct"]
    assert rep["held_base_only"] == ["fig13.fullload_flux_tighter"]
    assert rep["held_new_only"] == [] and rep["held_neither"] == []


def test_groups_name_the_papers_figures():
    """`experiment paper` runs exactly the paper's figures, once each, in the report's order."""
    from fluxdrive.experiments import paper
    from fluxdrive.experiments.registry import expand, experiments

    assert expand("paper") == list(paper.EXPERIMENTS)
    assert expand("fig18,paper") == ["fig18"] + [n for n in paper.EXPERIMENTS if n != "fig18"]
    assert sorted(expand("paper") + expand("beyond")) == sorted(experiments())
    assert expand("all") == list(experiments())


def test_fig14_measured_voltages_remove_6th_flux_has_better_snr(tmp_path):
    r = _run("fig14", tmp_path)
    for v in ("paper_robust", "paper (literal)"):
        assert _value(r, f"fig14.commanded_6th[{v}]") > 3.0  # deg: the deadtime's 6th order
    # on the non-ideal bench the capture chain leaves a 6th-order residue (a quarter or less)
    assert _value(r, "fig14.measured_6th_gone[paper_robust]") < 0.25
    assert _value(r, "fig14.measured_snr[paper_robust]") < 1.0  # noise: flux over EMF
    assert _value(r, "fig14.stable") == 1.0
    rep = json.loads((tmp_path / "report.json").read_text())["experiments"]["fig14"]
    assert all({"id", "claim", "ours", "value", "verdict"} <= set(c) for c in rep["claims"])
    assert "**Claims: held " in (tmp_path / "report.md").read_text()
    assert (tmp_path / "report.md").exists() and (tmp_path / "fig14_theta_error.png").exists()


def test_fig13_flux_locus_radius_and_tighter_than_emf_under_load(tmp_path):
    d = _run("fig13", tmp_path)["data"]
    # (on the non-ideal bench the light rotor hunts at no load, which spreads omega |lambda^|)
    assert d["no load"]["flux_mean_v"] == pytest.approx(0.59, abs=0.1)
    fl = d["full load"]
    assert fl["flux_v"][1] - fl["flux_v"][0] < fl["emf_1ms"][1] - fl["emf_1ms"][0]
    assert fl["flux_v"][1] - fl["flux_v"][0] < 0.3 * (fl["emf_raw"][1] - fl["emf_raw"][0])


def test_fig2_4_offset_drift_and_deadtime_follow_the_equations(tmp_path):
    r = _run("fig2_4", tmp_path)
    assert _value(r, "fig2.offset") < 0.1  # locus centre within 10 % of eq. (6)'s
    assert _value(r, "fig3.drift") < 0.15  # drift rate within 15 % of R^ |delta i|
    assert _value(r, "fig4.magnitude") > 0.2  # |lambda^| off by more than 20 %
    assert _value(r, "fig4.integration_reduces") < 0.5  # a pure integral divides order n by n
    # our finding at 2 % speed: LPF + inverse HPF keeps the EMF's relative 5th/7th
    assert _value(r, "fig4.proposed_reduces") > 0.7


def test_fig17_flux_drive_keeps_the_encoder_current_bandwidth(tmp_path):
    d = _run("fig17", tmp_path)["data"]
    enc, flux = d["encoder"]["ctrl"]["bandwidth_hz"], d["flux_measured"]["ctrl"]["bandwidth_hz"]
    assert 750 < enc < 1100
    assert flux == pytest.approx(enc, rel=0.15)


def test_fig19_rig_inertia_recovers_within_the_papers_time(tmp_path):
    """paper_6pct_stepload runs on the rig card (motor + dyno inertia inferred from the
    paper's dip and recovery, config/machines/paper_rig.yaml): the 100 % step at 6 % speed
    recovers within the paper's 0.2 s (+25 % margin)."""
    r = _run("fig19", tmp_path)
    rows = {x["J_scale"]: x for x in r["data"]["step_vs_inertia"]}
    assert rows[1]["stable"] and rows[1]["recovery_s"] is not None
    assert rows[1]["recovery_s"] < 0.25
    assert _value(r, "fig19.fullload_4pct") == 1.0


def test_fig15_16_emf_thd_rises_at_low_speed_and_measured_voltages_cut_it(tmp_path):
    r = _run("fig15_16", tmp_path)
    assert _value(r, "fig15.emf_thd_speed") == 1.0  # every bandwidth: higher THD at low speed
    assert _value(r, "fig15.measured_lowers_emf") == 1.0  # THD lower at every point


def test_fig18_speed_bandwidth_encoder_and_flux_10hz(tmp_path):
    """Encoder and flux drives both meet the 10 Hz speed design (the PI is designed with
    the observer's speed path).  The paper's 'EMF only 7 Hz' is a documented disagreement:
    in our model the EMF path's speed LPF costs phase margin, not bandwidth."""
    r = _run("fig18", tmp_path)
    assert _value(r, "fig18.encoder") < 0.3  # within 30 % of the design
    assert _value(r, "fig18.flux") < 0.2  # within 20 % of the encoder drive's


def test_mismatch_r_is_a_magnitude_error_l_an_angle_error(tmp_path):
    """Shadow observers at 2 %/150 % (i_d = 0): R^ = kR moves only the flux magnitude,
    |λ̂| = λ + (R − R^) i_q/ω; L^ = kL only the angle, atan((L − L^) i_q/λ); λ^ neither --
    each measured row against that prediction, computed here from the card and the run's
    operating point (ω, i_q)."""
    r = _run("mismatch", tmp_path)
    card = load_scenario(scenario_path("paper_2pct_150load")).machine
    R, L, lam = card.resistance_ohm, card.inductance_h, card.flux_linkage_vs  # noqa: N806
    d = r["data"]
    we, iq = d["we"], d["iq"]
    rows = {x["param"]: x for x in d["shadow"]}
    r_rows = [(float(p[3:-1]), x) for p, x in rows.items() if p.startswith("R^=")]
    l_rows = [(float(p[3:-1]), x) for p, x in rows.items() if p.startswith("L^=")]
    lam_rows = [x for p, x in rows.items() if p.startswith("λ^=")]
    assert len(r_rows) == 4 and len(l_rows) == 4 and len(lam_rows) == 2
    for k, x in r_rows:
        pred = abs(lam + (R - k * R) * iq / we)
        assert abs(x["mag"] - pred) < 0.2 * pred + 2e-3, (k, x["mag"], pred)
    for k, x in l_rows:
        pred_deg = math.degrees(math.atan2((L - k * L) * iq, lam))
        assert abs(x["mean_deg"] - pred_deg) < 3.0, (k, x["mean_deg"], pred_deg)
    assert all(abs(x["mean_deg"]) < 1.0 for x in lam_rows), lam_rows
    # the tolerances tell the two apart: L^ = 0.5 L turns the angle by more than 3°, and
    # R^ = 1.3 R moves the magnitude by more than its 20 %
    assert math.degrees(math.atan2(0.5 * L * iq, lam)) > 3.0
    assert abs(0.3 * R * iq / we) > 0.2 * abs(lam - 0.3 * R * iq / we) + 2e-3


def test_rs_adapt_recovers_a_30pct_resistance_error(tmp_path):
    r = _run("rs_adapt", tmp_path)
    rows = r["data"]["runs"]
    assert not next(x for x in rows if not x["adaptive"])["stable"]
    # adaptive: stable, and R^ ends within 5 % of the card's R (what the claim rests on)
    R = load_scenario(scenario_path("paper_2pct_150load")).machine.resistance_ohm  # noqa: N806
    adaptive = [x for x in rows if x["adaptive"]]
    assert adaptive and all(x["stable"] for x in adaptive), adaptive
    assert all(abs(x["r_hat_end"] - R) < 0.05 * R for x in adaptive), (R, adaptive)


def test_lowest_speed_flux_measured_holds_2pct_full_and_150pct_load(tmp_path):
    """Descent under load from 480 rpm: the flux observer on measured voltages holds 2 %
    speed at 100 % and 150 % load (far below the bound (0.2 R I + V_dt)/lambda, which it
    does not suffer from); the EMF observer on commanded voltages does not hold 60 rpm."""
    r = _run("lowest_speed", tmp_path)
    d = r["data"]["lowest"]
    card = MachineCard()
    vdt = card.dc_bus_v * card.deadtime_s / card.ts_s  # deadtime volt-seconds per leg [V]
    for load in ("100%", "150%"):
        f = d["flux_measured"][load]
        # the bound of measured voltages has no V_dt term: 0.2 R I / lambda (73 rpm at 100 %)
        i = float(load[:-1]) / 100 * card.rated_current_a
        assert f["bound_rpm"] == pytest.approx(
            0.2
            * card.resistance_ohm
            * i
            / card.flux_linkage_vs
            / card.pole_pairs
            * 60
            / (2 * math.pi)
        )
        # held well below the bound (neither of its terms applies): under half of it
        assert f["lowest_rpm"] is not None and f["lowest_rpm"] < 0.5 * f["bound_rpm"], f
    e = d["emf_commanded"]["100%"]
    # commanded voltages: V_dt = Vdc td/Ts (1.44 V) dominates, (0.2 R I + V_dt)/lambda = 219
    # rpm; below it the observer loses the rotor, not far below it (the bound is the rule of
    # thumb of a 0.2 R I margin) it still holds
    assert e["bound_rpm"] == pytest.approx(
        (0.2 * card.resistance_ohm * card.rated_current_a + vdt)
        / card.flux_linkage_vs
        / card.pole_pairs
        * 60
        / (2 * math.pi)
    )
    # (the Fig. 5 baseline -- 15 Hz PLL, 20 Hz speed LPF, a 7 Hz speed loop -- may already
    # lose the rotor on the way up: the I-f handover at 40 rpm is far below that bound)
    assert e["lowest_rpm"] is None or (
        e["first_lost_rpm"] < e["bound_rpm"] and e["lowest_rpm"] > 0.5 * e["bound_rpm"]
    )
    assert (tmp_path / "beyond_lowest_speed.png").exists()


def test_sensitivity_per_variant_follows_the_fundamental_model(tmp_path):
    """Shadow observers at 60 rpm / 150 %: R^ is a magnitude error for the paper observer and
    an angle error for the magnitude-forcing ones, L^ an angle error atan(dL i_q/lambda) for
    all; the uncompensated LPF leads by atan(w_c/w); hinkkanen_luomi and ortega see the same
    deadtime residue (gone with an ideal inverter)."""
    r = _run("sensitivity", tmp_path)
    t = r["data"]["table"]
    for kind in ("paper", "hinkkanen_luomi", "lpf"):
        # every R^/L^/lambda^ row the model has an equilibrium for and the estimate is steady
        # at: mean theta~ within 3 deg + 10 % of the model's
        rows = {k: x for k, x in t[kind].items() if re.fullmatch(r"(r|l|lam)[\d.]+", k)}
        used = {k: x for k, x in rows.items() if x["pred_deg"] is not None and x["steady"]}
        assert used, (kind, rows)
        for k, x in used.items():
            err = abs((x["mean_deg"] - x["pred_deg"] + 180.0) % 360.0 - 180.0)
            assert err <= 3.0 + 0.1 * abs(x["pred_deg"]), (kind, k, x)
    # cut-off: the uncompensated LPF leads by atan(w_c/w) (its steady rows), the paper's
    # LPF + inverse HPF stays at a mean under 2 deg at every cut-off
    fc = [k for k in t["lpf"] if k.startswith("fc")]
    assert fc and any(t["lpf"][k]["steady"] for k in fc)
    for k in fc:
        x = t["lpf"][k]
        err = abs((x["mean_deg"] - x["pred_deg"] + 180.0) % 360.0 - 180.0)
        assert not x["steady"] or err < 3.0, (k, x)
        assert abs(t["paper"][k]["mean_deg"]) < 2.0, (k, t["paper"][k])
    _gain_sweep_follows_k_delta_over_w2_lambda(r["data"])
    assert (
        abs(t["hinkkanen_luomi"]["r0.85"]["mean_deg"] - t["hinkkanen_luomi"]["r0.85"]["pred_deg"])
        < 2.0
        and t["hinkkanen_luomi"]["r0.85"]["pred_deg"] > 20.0
    )
    assert abs(t["paper"]["r0.85"]["mean_deg"]) < 1.0


# the gain sweep's points against theta~ = k delta/(w^2 lambda): within 0.05 deg + 15 % of
# the fit (measured on the quick sweep: the lowest gain 0.03-0.04 deg off the line through
# the origin, the next 0.01 deg)
GAIN_FIT_TOL_DEG, GAIN_FIT_TOL_REL = 0.05, 0.15


def _gain_sweep_follows_k_delta_over_w2_lambda(data: dict) -> None:
    """The magnitude-forcing pair (hinkkanen_luomi's w_c, ortega's gamma lambda^2: equivalent
    gain k = 2 pi f) turns one q-axis EMF residue delta into theta~ = k delta/(w^2 lambda)
    while linear: over the low-gain end of the sweep (steady, |theta~| < 5 deg, one sign) each
    point lies on one fitted line through the origin, both see the same delta (within 30 %),
    and without deadtime the residue is gone (|theta~| < 0.3 deg)."""
    lam = load_scenario(scenario_path("paper_2pct_150load")).machine.flux_linkage_vs
    w = data["we_rad_s"]
    deltas = {}
    for kind in ("hinkkanen_luomi", "ortega"):
        rows = data["table"][kind]
        pts: list[tuple[float, float]] = []  # (k [rad/s], theta~ [rad]) in rising k
        for f in sorted(float(k[2:]) for k in rows if k.startswith("fc")):
            x = rows[f"fc{f}"]
            if not (x["steady"] and abs(x["mean_deg"]) < 5.0):
                break
            if pts and x["mean_deg"] * pts[0][1] < 0.0:
                break
            pts.append((2 * math.pi * f, math.radians(x["mean_deg"])))
        assert len(pts) >= 2, (kind, rows)
        # least squares through the origin: theta~ = (delta/(w^2 lambda)) k
        slope = sum(k * y for k, y in pts) / sum(k * k for k, _ in pts)
        deltas[kind] = slope * w * w * lam
        for k, y in pts:
            fit = math.degrees(slope * k)
            err = abs(math.degrees(y) - fit)
            print(f"{kind} k {k:.1f} rad/s: {math.degrees(y):.3f} deg, fit {fit:.3f} deg")
            assert err <= GAIN_FIT_TOL_DEG + GAIN_FIT_TOL_REL * abs(fit), (kind, k, y, fit)
    print("fitted delta [mV]: " + ", ".join(f"{n} {1e3 * d:.3f}" for n, d in deltas.items()))
    a, b = deltas.values()
    assert a * b > 0 and abs(a - b) <= 0.3 * max(abs(a), abs(b)), deltas
    assert all(abs(v) < 0.3 for v in data["no_deadtime_mean_deg"].values()), data


def test_speed_reversal_through_zero_under_brake_load(tmp_path):
    """+60 -> -60 rpm with 0.4 pu brake load, sensorless: hand-back to I-f, through zero,
    handover on the other side; no loss of synchronism, sub-degree theta~ on both sides."""
    r = _run("speed_reversal", tmp_path)
    x = r["data"]["runs"]["brake 0.4 pu"][0]
    assert x["stable"] and x["fault"] == "none"
    assert 0.5 < x["if_time_s"] < 1.5
    assert x["handover_ref_rpm"] < -40.0
    assert x["rms_pos_deg"] < 0.5 and x["rms_neg_deg"] < 0.5
    assert x["if_load_angle_max_deg"] < 45.0
    assert x["mean_neg_rpm"] == pytest.approx(-60.0, abs=3.0)


def test_peers_fail_commanded_reduced_order_observers_lose_the_rotor(tmp_path):
    """60 rpm, rated load, 2 us deadtime uncompensated: closing the loop on the EMF or the
    ortega observer with commanded voltages loses the rotor, the paper's flux observer with
    measured voltages holds it; in shadow ortega-commanded sits at acos(wl/(wl+(4/pi)V_dt))."""
    r = _run("peers_fail", tmp_path)
    d = r["data"]
    # in shadow (current on the true q axis) the deadtime's fundamental (4/pi) V_dt, V_dt =
    # Vdc td/Ts, lies along q: the paper observer on commanded voltages sees |flux^| =
    # lambda + (4/pi) V_dt / w, ortega turns it into its angle, the EMF observer keeps its mean
    card = load_scenario(scenario_path("paper_2pct_150load")).machine
    vdt = card.dc_bus_v * card.deadtime_s / card.ts_s
    assert d["vdt_v"] == pytest.approx(vdt) and d["v1_dt_v"] == pytest.approx(4 / math.pi * vdt)
    so, w = d["shadow"], d["we_rad_s"]
    pred_mag = card.flux_linkage_vs + 4 / math.pi * vdt / w
    assert abs(so["flux_commanded"]["mag"] - pred_mag) < 0.1 * pred_mag, (so, pred_mag)
    assert abs(so["ortega_commanded"]["mean_deg"] - d["pred"]["ortega_commanded_deg"]) < 5.0
    assert abs(so["emf_commanded"]["mean_deg"]) < 5.0
    # closing the loop: every seed of the flux drive holds, none of the commanded ones
    sw = d["switched"]
    assert all(x["stable"] for x in sw["flux_measured@2us"])
    assert not any(x["stable"] for x in sw["emf_commanded@2us"] + sw["ortega_commanded@2us"])


def test_graph_flag_runs_through_the_node_graph_with_the_same_numbers(tmp_path):
    """`experiment --graph`: a scenario built in memory (machine changed too) is saved to a
    file that reproduces it, run through the lockstep graph, read back from the bag, and
    gives the in-process runner's arrays and metrics exactly."""
    pytest.importorskip("rclpy")
    import numpy as np
    from fluxdrive.analysis.metrics import compute
    from fluxdrive.drive.scenario import load_scenario, save_scenario, scenario_differences
    from fluxdrive.drive.sim import run_scenario
    from fluxdrive.experiments.registry import sensorless
    from fluxdrive_bringup.launch.runs import graph_run

    sc = sensorless(
        120.0,
        0.3,
        name="exp_graph",
        ramp_pu_s=1.0,
        settle_s=0.1,
        window_s=0.2,
        observers={"flux_measured": {"variant": "paper"}, "emf_measured": {"variant": "emf"}},
        machine_kw={"inertia_kgm2": 3.0e-4},
    )
    p = save_scenario(sc, tmp_path / "s.yaml")
    assert scenario_differences(sc, load_scenario(p)) == []
    a = run_scenario(sc, progress=False)
    b = graph_run(sc)
    for name in ("frames", "truth", "ctrl"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for o in sc.observers:
        assert np.array_equal(a.estimate(o), b.estimate(o)), o
    ma, mb = compute(a), compute(b)
    assert ma["observers"] == mb["observers"]
    print(
        sc.duration_s, "s simulated; θ̃ RMS", mb["observers"]["flux_measured"]["theta_err_rms_deg"]
    )


def _card_numbers(card) -> set[str]:
    """What the experiments' texts quote of a card, formatted as they format it: speeds at 2-16
    %, the flux and EMF observers' cut-off and PLL, the current loop, V_dt and its fundamental,
    L/Ts, the back-EMF at 2 %, the deadtime."""
    from fluxdrive.core.machine import card_current_bandwidth_hz
    from fluxdrive.drive.observers import observer_config
    from fluxdrive.experiments.common import CardValues

    mc = CardValues.of(card)
    rpm = [f"{pu * card.rated_speed_rpm:.0f} rpm" for pu in (0.02, 0.04, 0.06, 0.1, 0.16)]
    hz = [observer_config(v, card) for v in ("paper_robust", "emf")]
    hz = [f"{x:.0f} Hz" for o in hz for x in (o.cutoff_hz, o.pll_bandwidth_hz)]
    hz.append(f"{card_current_bandwidth_hz(card):.0f} Hz")
    volts = [f"{mc.vdt:.2f} V", f"{mc.v1_dt:.2f} V", f"{mc.l / mc.ts:.1f} Ω"]
    emf_2pct = 0.02 * card.rated_speed_rpm * 2 * math.pi / 60 * mc.p * mc.lam
    volts.append(f"(ω·λ = {emf_2pct:.2f} V)")
    return set(rpm + hz + volts + [f"{1e6 * card.deadtime_s:g} µs"])


def test_a_second_card_reports_its_own_numbers(tmp_path):
    """`experiment --machine`: a quick subset (Figs. 13, 14, 19) on the gimbal card, whose
    rated speed, PWM, deadtime, cut-off and PLLs all differ from the default card's.  Its texts
    quote that card's numbers: none of the default card's speeds, frequencies and voltages
    appears in what the runs report (the claims' registered text quotes the paper, not
    checked)."""
    from fluxdrive.core.machine import load_machine, load_rig
    from fluxdrive.drive.scenario import CONFIG_DIR

    gimbal = CONFIG_DIR / "machines" / "gimbal_24v.yaml"
    default = _card_numbers(MachineCard())
    own = _card_numbers(load_machine(gimbal))
    assert len(default - own) >= 10  # the cards differ in what the texts quote

    texts = []
    for name in ("fig13", "fig14", "fig19"):
        res = run_experiment(name, tmp_path, quick=True, echo=False, machine=gimbal)
        texts += [
            c["ours"] + " " + c.get("why", "") + " " + c.get("note", "") for c in res["claims"]
        ]
    prose = "\n".join(texts)
    # the card's own numbers are there: its ω·λ at 2 % speed (fig13) and its J (fig19)
    assert next(x for x in own if x.startswith("(ω·λ")) in prose
    # fig19 runs the scenario's rig (config/rigs/paper_rig.yaml): the card's rotor on its dyno
    rig_j = load_rig(CONFIG_DIR / "rigs" / "paper_rig.yaml").load_inertia_kgm2
    assert f"J = {load_machine(gimbal).inertia_kgm2 + rig_j:.3g} kg·m²" in prose
    stale = sorted(x for x in default - own if x in prose)
    assert not stale, f"default-card numbers in the gimbal card's report: {stale}"


# one switched run's analysed row (peers_fail._switch_job's keys, no series)
_PEER_ROW = {
    "stable": True,
    "fault": "none",
    "rms_deg": 1.0,
    "pre_mean_deg": 0.0,
    "pre_rms_deg": 1.0,
    "lost_after_s": None,
}


def test_past_the_paper_texts_quote_the_card_they_ran_on():
    """The texts the experiments past the paper build around their runs (lowest_speed's
    notes, sensitivity's and peers_fail's explanations) on the gimbal card: its deadtime
    fundamental, EMF noise L/Ts sigma_i, gamma lambda^2, inertia and 2 % speed are there, none
    of the default card's.  Text builders only, fed the card's numbers (no runs: milliseconds)."""
    from fluxdrive.core.machine import load_machine
    from fluxdrive.drive.scenario import CONFIG_DIR
    from fluxdrive.experiments import beyond_common, lowest_speed, peers_fail, sensitivity
    from fluxdrive.experiments.common import Ctx

    def texts(ctx) -> tuple[str, set[str]]:
        mc, cr = ctx.cv, beyond_common.card_rates(ctx)
        w, rpm = cr["w2"], ctx.rpm(0.02)
        pred = peers_fail._peers_pred(ctx, w, mc.i_rated)
        ctl = peers_fail._peers_control_claim(
            {"emf_measured@2us": [_PEER_ROW]},
            mc,
            w,
            cr,
        )
        nom = {"steady": False}
        parts = [
            *lowest_speed.lowest_notes(ctx, {}).values(),
            peers_fail._peers_mechanism_why(mc, w, rpm, pred),
            ctl[0].get("why", ctl[0].get("note", "")),
            sensitivity._sens_kind_why("ortega", nom, [], [], [], rpm, mc, w, cr["k_ortega"]),
            sensitivity.SENS_DESC["ortega"].format(k=cr["k_ortega"]),
            peers_fail._peers_headline_claim({}, 1, rpm, ctx.card.deadtime_s)["ours"],
        ]
        quoted = _card_numbers(ctx.card) | {
            f"{mc.v1_dt:.2f} V",
            f"≈ {cr['emf_noise_v']:.2g} V",
            f"γλ² = {cr['k_ortega']:.0f} s⁻¹",
            f"{mc.j:.3g} kg·m²",
            f"≈{cr['rpm_3lam']:.0f} rpm",
        }
        return "\n".join(parts), quoted

    gimbal = Ctx(machine=CONFIG_DIR / "machines" / "gimbal_24v.yaml")
    prose, own = texts(gimbal)
    _, default = texts(Ctx())
    assert load_machine(gimbal.machine).name == "gimbal_24v"
    k_ortega = beyond_common.card_rates(gimbal)["k_ortega"]
    for x in (f"γλ² = {k_ortega:.0f} s⁻¹", f"{gimbal.cv.j:.3g} kg·m²"):
        assert x in prose, x
    assert f"{gimbal.rpm(0.02):.0f} rpm" in prose
    stale = sorted(x for x in default - own if x in prose)
    assert not stale, f"default-card numbers in the gimbal card's texts: {stale}"
