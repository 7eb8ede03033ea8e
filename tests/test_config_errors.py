"""Bad configuration gets a clear error naming the file, the key and what was expected."""

from __future__ import annotations

import pytest
import yaml
from fluxdrive.core.machine import ConfigError, load_machine
from fluxdrive.drive.observers import observer_config
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario


def _write(tmp_path, name, data):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def test_all_shipped_scenarios_load():
    for p in sorted((CONFIG_DIR / "scenarios").glob("*.yaml")):
        sc = load_scenario(p)
        assert sc.n_periods > 0 and sc.machine.pole_pairs > 0


@pytest.mark.parametrize(
    "patch, words",
    [
        ({"duration_s": -1.0}, ["duration_s"]),
        ({"speedrpm": 5}, ["unknown", "speedrpm"]),
        ({"driving": "nope"}, ["driving", "nope"]),
        ({"observers": {"x": {"variant": "magic"}}}, ["magic", "variant"]),
        ({"observers": {"x": {"cutoff_hz": "high"}}}, ["cutoff_hz"]),
        ({"faults": {"current_offset_pu": [0, 1]}}, ["current_offset_pu", "3"]),
        ({"control": {"current_bandwidth_hz": True}}, ["current_bandwidth_hz"]),
        ({"load_type": "magnetic"}, ["load_type"]),
    ],
)
def test_scenario_errors_name_file_and_key(tmp_path, patch, words):
    raw = {
        "machine": str(CONFIG_DIR / "machines" / "default_spm.yaml"),
        "duration_s": 1.0,
        "observers": {"x": {"variant": "paper"}},
        **patch,
    }
    p = _write(tmp_path, "bad.yaml", raw)
    with pytest.raises(ConfigError) as ei:
        load_scenario(p)
    msg = str(ei.value)
    assert str(p) in msg
    for w in words:
        assert w in msg


def test_malformed_yaml_names_the_file(tmp_path):
    p = _write(tmp_path, "broken.yaml", "duration_s: [1, 2\n")
    with pytest.raises(ConfigError, match="broken.yaml"):
        load_scenario(p)


def test_machine_card_range_and_type_errors(tmp_path):
    p = _write(tmp_path, "m.yaml", {"motor": {"pole_pairs": 2.5}})
    with pytest.raises(ConfigError, match="pole_pairs"):
        load_machine(p)
    p = _write(tmp_path, "m2.yaml", {"inverter": {"deadtime_s": 0.5}})
    with pytest.raises(ConfigError, match="deadtime_s"):
        load_machine(p)


def test_observer_overrides_are_validated():
    with pytest.raises(ConfigError, match="cutoff_hz"):
        observer_config("paper", cutoff_hz=-3.0)
    with pytest.raises(ConfigError, match="unknown observer parameter"):
        observer_config("paper", cutof_hz=3.0)
    with pytest.raises(ConfigError, match="voltage_source"):
        observer_config("paper", voltage_source="guessed")
