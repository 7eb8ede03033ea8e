"""Any motor: every controller/protection default derives from the machine card, scenarios
carry speeds in per unit, the shipped cards all run the 2 % / 150 % sensorless case, and a
trip explains itself (fault, time, value, setting) in the output and in metrics.json."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from fluxdrive.analysis.metrics import compute, format_table
from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError, MachineCard, load_machine
from fluxdrive.drive.control import ControllerConfig
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario, scenario_path
from fluxdrive.drive.sim import run_scenario

ROOT = Path(__file__).resolve().parents[1]
CARDS = sorted(p.stem for p in (CONFIG_DIR / "machines").glob("*.yaml"))
# cards with a dyno folded into their inertia ("motor + dyno"); a card from a nameplate is a
# motor alone and runs the scenarios on a rig (`--machine`: tests/test_card_rig.py)
CARDS_ON_DYNO = [
    c for c in CARDS if "nameplate" not in yamlio.load_file(CONFIG_DIR / "machines" / f"{c}.yaml")
]


def test_defaults_on_the_default_card_are_the_tuned_values():
    """The per-unit rules reproduce what the testbed was tuned with on the default card."""
    r = ControllerConfig().resolved(MachineCard())
    assert r.current_bandwidth_hz == 1000.0 and r.speed_bandwidth_hz == 15.0
    assert r.encoder_pll_hz == 150.0 and r.speed_feedback_lpf_hz == 20.0
    assert r.handover_rpm == pytest.approx(30.0) and r.handback_rpm == pytest.approx(20.0)
    assert r.if_accel_rpm_s == pytest.approx(600.0)
    assert r.vdc_min_v == pytest.approx(20.16) and r.vdc_max_v == pytest.approx(95.04)


def test_defaults_follow_the_card_and_explicit_values_win():
    card = load_machine(CONFIG_DIR / "machines" / "servo_320v.yaml")
    r = ControllerConfig().resolved(card)
    assert r.vdc_max_v == pytest.approx(1.32 * 320.0)  # not the default card's 95 V
    assert r.vdc_min_v == pytest.approx(0.28 * 320.0)
    assert r.current_bandwidth_hz == pytest.approx(0.1 * card.pwm_hz)
    assert r.handover_rpm == pytest.approx(0.01 * card.rated_speed_rpm)
    # a fast RL corner raises the current loop to 3x the corner (capped at PWM/5)
    fast = MachineCard(resistance_ohm=4.0, inductance_h=0.5e-3)
    corner = 4.0 / (2 * math.pi * 0.5e-3)
    assert ControllerConfig().resolved(fast).current_bandwidth_hz == pytest.approx(
        min(3 * corner, 2000.0), rel=1e-6
    )
    assert ControllerConfig(vdc_max_v=95.0).resolved(card).vdc_max_v == 95.0


def test_observer_defaults_follow_the_card_rules(tmp_path):
    """Every observer frequency left unset is derived from the card (OBSERVER_RULES): per unit
    of the rated electrical frequency f_e, the PLL and speed LPF capped per unit of the
    current bandwidth f_i.  The numbers below follow from the rule and each card's R, L,
    PWM rate, rated speed and pole pairs (servo_320v: PLL at its cap, gimbal_24v: below);
    on the paper's card the literal observer gets the paper's w_c = 100 Hz (Sec. III-A)."""
    from fluxdrive.drive.observers import observer_config

    paper = observer_config("paper", card=MachineCard())
    assert paper.cutoff_hz == 100.0 and paper.pll_bandwidth_hz == 25.0
    assert paper.comp_freq_lpf_hz == 0.0  # eq. (8): the PLL's frequency, on every card
    for name in ("servo_320v", "gimbal_24v"):
        card = load_machine(CONFIG_DIR / "machines" / f"{name}.yaml")
        corner = card.resistance_ohm / (2 * math.pi * card.inductance_h)
        f_i = min(max(0.1 * card.pwm_hz, 3 * corner), 0.2 * card.pwm_hz)
        f_e = card.rated_speed_rpm / 60 * card.pole_pairs
        pll = min(0.125 * f_e, 0.025 * f_i)
        for variant in ("paper", "paper_robust"):
            c = observer_config(variant, card=card)
            assert c.cutoff_hz == pytest.approx(0.5 * f_e)
            assert c.pll_bandwidth_hz == pytest.approx(pll)
            assert c.omega_floor_rad_s == pytest.approx(2 * math.pi * f_e / (80 * math.pi))
            assert c.speed_lpf_hz == 0.0
        assert observer_config("paper_robust", card=card).comp_freq_lpf_hz == pytest.approx(
            0.01 * f_e
        )
        assert observer_config("paper", card=card).comp_freq_lpf_hz == 0.0
        emf = observer_config("emf", card=card)
        assert emf.pll_bandwidth_hz == pytest.approx(min(0.075 * f_e, 0.015 * f_i))
        assert emf.speed_lpf_hz == pytest.approx(min(0.1 * f_e, 0.02 * f_i))
        assert observer_config("lpf", card=card).cutoff_hz == pytest.approx(0.025 * f_e)
        assert observer_config("ortega", card=card).gamma_bw_rad_s == pytest.approx(f_i)
        # in a scenario: unset values from the swapped card on the scenario's rig (its PWM:
        # the default card's 10 kHz), and the speed loop is designed with the driving
        # observer's derived PLL; a value the scenario sets still wins
        sc = load_scenario(scenario_path("paper_2pct_150load"), machine=name)
        assert sc.machine.pwm_hz == MachineCard().pwm_hz
        f_i_rig = min(max(0.1 * sc.machine.pwm_hz, 3 * corner), 0.2 * sc.machine.pwm_hz)
        assert sc.observers["emf_measured"].pll_bandwidth_hz == pytest.approx(
            min(0.075 * f_e, 0.015 * f_i_rig)
        )
        assert sc.control.speed_observer_pll_hz == pytest.approx(min(0.125 * f_e, 0.025 * f_i_rig))
        f = tmp_path / f"{name}.yaml"
        f.write_text(
            f"machine: {CONFIG_DIR / 'machines' / (name + '.yaml')}\n"
            "observers:\n  x: {variant: paper, cutoff_hz: 50.0}\n"
        )
        x = load_scenario(f).observers["x"]
        assert x.cutoff_hz == 50.0 and x.pll_bandwidth_hz == pytest.approx(pll)


def test_per_unit_speeds_scale_with_the_card(tmp_path):
    sc = load_scenario(scenario_path("paper_2pct_150load"), machine="outer_rotor_48v")
    assert sc.speed_profile_rpm[0, 1] == pytest.approx(0.02 * 600.0)
    assert sc.control.handover_rpm == pytest.approx(600.0 * 0.0133333333333)
    f = tmp_path / "s.yaml"
    f.write_text(
        f"machine: {CONFIG_DIR / 'machines' / 'default_spm.yaml'}\n"
        "speed_pu: 0.02\nspeed_rpm: 60.0\n"
    )
    with pytest.raises(ConfigError, match="speed_rpm or speed_pu"):
        load_scenario(f)


def test_rpm_values_keep_their_per_unit_speed_on_another_card():
    """A scenario (or experiment) written in rpm for its own card runs on `--machine CARD`
    at the same per-unit speeds: every rpm value scales by the ratio of rated speeds."""
    gimbal = load_machine(CONFIG_DIR / "machines" / "gimbal_24v.yaml")
    k = gimbal.rated_speed_rpm / MachineCard().rated_speed_rpm  # its file names the default
    sc = load_scenario(scenario_path("can_2pct_decimated"), machine="gimbal_24v")
    assert sc.speed_profile_rpm[0, 1] == pytest.approx(60.0 * k)  # 2 % of 1200 rpm
    c = sc.control
    assert (c.handover_rpm, c.handback_rpm, c.if_accel_rpm_s) == pytest.approx(
        (40.0 * k, 20.0 * k, 300.0 * k)
    )
    same = load_scenario(scenario_path("can_2pct_decimated"))
    assert same.speed_profile_rpm[0, 1] == 60.0 and same.control.handover_rpm == 40.0
    # the experiments: the fig. 13/15 sensorless case at 2 % speed, `experiment --machine`;
    # the card comes in the experiment's context (no module state)
    from fluxdrive.experiments.common import Ctx

    ctx = Ctx(machine=CONFIG_DIR / "machines" / "gimbal_24v.yaml")
    sc = ctx.sensorless(ctx.rpm(0.02), 1.5)
    assert sc.machine.name == "gimbal_24v"
    assert sc.speed_profile_rpm[-1, 1] == pytest.approx(0.02 * gimbal.rated_speed_rpm)
    assert sc.control.handover_rpm == pytest.approx(40.0 * k)
    low = ctx.sensorless(ctx.rpm(0.01), 1.0)  # 1 %: starts at 4/3 %, hands over at 7/6 %
    assert low.speed_profile_rpm[:, 1] == pytest.approx([40.0 * k, 40.0 * k, 30.0 * k])
    assert low.control.handover_rpm == pytest.approx(35.0 * k)
    enc = ctx.encoder_run(ctx.rpm(0.1), 1.0)
    # a scenario file keeps its per-unit speeds on the context's card
    assert ctx.build(base="paper_2pct_150load").speed_profile_rpm[-1, 1] == pytest.approx(
        0.02 * gimbal.rated_speed_rpm
    )
    assert enc.speed_profile_rpm[0, 1] == pytest.approx(0.1 * gimbal.rated_speed_rpm)


def test_yaml_numbers_with_exponents_are_numbers(tmp_path):
    assert yamlio.loads("a: 1e-4\nb: 1.0e9\nc: 10\nd: '1e-4'") == {
        "a": 1e-4,
        "b": 1e9,
        "c": 10,
        "d": "1e-4",
    }
    raw = (CONFIG_DIR / "machines" / "default_spm.yaml").read_text()
    f = tmp_path / "card.yaml"
    f.write_text(
        raw.replace("inductance_h: 0.80e-3", "inductance_h: 8e-4").replace(
            "deadtime_s: 2.0e-6", "deadtime_s: 2e-6"
        )
    )
    card = load_machine(f)
    assert card.inductance_h == 8e-4 and card.deadtime_s == 2e-6


def test_negative_bandwidth_in_a_scenario_names_the_file(tmp_path):
    f = tmp_path / "neg.yaml"
    f.write_text(
        f"machine: {CONFIG_DIR / 'machines' / 'default_spm.yaml'}\n"
        "control: {speed_bandwidth_hz: -5.0}\n"
    )
    r = subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "sim", str(f)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    out = (r.stdout + r.stderr).strip()
    assert r.returncode == 2 and "Traceback" not in out and len(out.splitlines()) == 1
    assert str(f) in out and "speed_bandwidth_hz" in out


# ---------------------------------------------------------------- every shipped card
@pytest.mark.parametrize("card", CARDS_ON_DYNO)
def test_every_shipped_card_runs_2pct_150pct_sensorless(card):
    """The paper's 2 % / 150 % case on each card as its own drive (the scenario's `machine:`
    set to the card: its inverter, sensors and dyno inertia; `--machine` would keep the
    default card's) and nothing else changed (only the shadow observers left out, for time,
    and on the ideal bench: the paper bench's numbers are the paper rig's, its effect on the
    default card is in docs/engine.md): sensorless on the paper's flux observer, stable,
    speed on target, sub-degree angle error."""
    own = str(CONFIG_DIR / "machines" / f"{card}.yaml")
    sc = load_scenario(scenario_path("paper_2pct_150load"), overrides={"bench": {}, "machine": own})
    sc.observers = {"flux_measured": sc.observers["flux_measured"]}
    r = run_scenario(sc, progress=False)
    m = compute(r)
    fm = m["observers"]["flux_measured"]
    print(
        f"{card}: theta RMS {fm['theta_err_rms_deg']:.3f} deg, mean "
        f"{m['speed']['mean_rpm']:.2f} rpm, i_q {m['currents']['i_q_mean_a']:.2f} A"
    )
    assert m["stable"] and m["trip"] is None
    assert abs(m["speed"]["mean_error_rpm"]) < 0.05 * sc.speed_profile_rpm[0, 1]
    # 150 % load is carried: i_q ~ 1.5 rated (plus friction)
    assert m["currents"]["i_q_mean_a"] > 1.4 * sc.machine.rated_current_a
    assert fm["theta_err_rms_deg"] < 1.0


def test_gimbal_on_the_paper_bench_runs_at_its_stated_lowest_speed():
    """On the paper rig's non-ideal bench the gimbal card's lowest speed is 3 % (README): the
    bench's R^ error |1 - r_pu| R I at 150 % load equals the EMF lambda w_e at 2.3 % of rated
    speed (the resistive-drop bound with the bench's R^ error), so 2 % is below it and 3 %
    above; at 3 % the 150 % case runs sensorless on the shipped scenario and bench."""
    from fluxdrive.core import bench as benchmod

    sc = load_scenario(
        scenario_path("paper_2pct_150load"), machine="gimbal_24v", overrides={"speed_pu": 0.03}
    )
    card = sc.machine
    assert isinstance(sc.bench, benchmod.BenchConfig) and sc.bench.observer_model is not None
    d_r = abs(1.0 - sc.bench.observer_model.r_pu) * card.resistance_ohm
    w_min_e = d_r * 1.5 * card.rated_current_a / card.flux_linkage_vs  # error = EMF
    n_min_pu = w_min_e / card.pole_pairs / card.rated_speed_rad_s
    assert 0.02 < n_min_pu < 0.03  # 2.3 %
    sc.observers = {"flux_measured": sc.observers["flux_measured"]}
    m = compute(run_scenario(sc, progress=False))
    fm = m["observers"]["flux_measured"]
    print(
        f"gimbal_24v, paper bench, 3 %: theta RMS {fm['theta_err_rms_deg']:.2f} deg; bound "
        f"{100 * n_min_pu:.2f} %"
    )
    assert m["stable"] and m["trip"] is None
    assert abs(m["speed"]["mean_error_rpm"]) < 0.05 * sc.speed_profile_rpm[0, 1]
    assert m["currents"]["i_q_mean_a"] > 1.4 * card.rated_current_a
    assert fm["theta_err_rms_deg"] < 3.0


# ---------------------------------------------------------------- trips explain themselves
def _trip_scenario(tmp_path: Path) -> Path:
    f = tmp_path / "trip.yaml"
    f.write_text(
        f"name: trip_demo\nmachine: {CONFIG_DIR / 'machines' / 'servo_320v.yaml'}\n"
        "duration_s: 0.1\nspeed_pu: 0.02\ndriving: flux_measured\n"
        "control: {vdc_max_v: 95.0}\n"  # the old fixed default, on a 320 V bus
        "observers:\n  flux_measured: {variant: paper}\n  emf: {variant: emf}\n"
    )
    return f


def test_a_trip_says_what_when_and_why(tmp_path):
    sc = load_scenario(_trip_scenario(tmp_path))
    m = compute(run_scenario(sc, progress=False))
    want = "tripped at 0.000 s: DC-bus over-voltage 320.0 V > 95.0 V (control.vdc_max_v)"
    assert m["trip"]["message"] == want
    assert m["trip"]["t_s"] == 0.0 and m["trip"]["code"] == 3 and not m["stable"]
    table = format_table(m)
    assert table.splitlines()[0] == want
    for nm in ("flux_measured", "emf"):  # no numbers from a stopped drive
        assert not m["observers"][nm]["valid_data"]
        row = next(ln for ln in table.splitlines() if ln[1:].startswith(nm + " "))
        assert "no valid data in the window (drive tripped at 0.000 s)" in row


def test_a_trip_in_the_sim_command_output_and_metrics_json(tmp_path):
    out = tmp_path / "run"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "fluxdrive.cli",
            "sim",
            str(_trip_scenario(tmp_path)),
            "--out",
            str(out),
            "--no-plots",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 1 and "Traceback" not in r.stderr
    want = "tripped at 0.000 s: DC-bus over-voltage 320.0 V > 95.0 V (control.vdc_max_v)"
    assert want in r.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["trip"]["message"] == want and m["trip"]["fault"] == "DC-bus over-voltage"
