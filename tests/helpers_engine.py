"""Small helpers shared by the engine tests (scenario building without YAML files)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import yaml
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario

IDEAL_SENSORS = dict(current_noise_a=0.0, current_adc_bits=24, capture_bits=24, dc_bus_adc_bits=24)


def make_scenario(tmp_path: Path, machine: MachineCard | None = None, **raw):
    """Write a scenario (and optionally a machine card) to tmp_path and load it."""
    if machine is not None:
        mpath = tmp_path / "machine.yaml"
        mpath.write_text(yaml.safe_dump({k: v for k, v in dataclasses.asdict(machine).items()}))
        raw.setdefault("machine", str(mpath))
    else:
        raw.setdefault("machine", str(CONFIG_DIR / "machines" / "default_spm.yaml"))
    p = tmp_path / f"{raw.get('name', 'test')}.yaml"
    p.write_text(yaml.safe_dump(raw))
    return load_scenario(p)


def ideal_machine(**kw) -> MachineCard:
    return dataclasses.replace(MachineCard(), **{**IDEAL_SENSORS, **kw})
