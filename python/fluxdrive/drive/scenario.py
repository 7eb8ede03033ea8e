"""The one way to load a scenario: YAML -> validated Scenario (machine card included).

A scenario file names its machine card (path relative to the scenario file), the speed and
load profiles, which position source closes the loop, which observers run alongside in
shadow, the duration, the random seed and sensor faults.  Errors name the file, the key
and what was expected.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.core import yamlio
from fluxdrive.core.bench import BenchConfig, parse_bench
from fluxdrive.core.machine import (
    DEADTIME_RANGE_S,
    ConfigError,
    MachineCard,
    Rig,
    load_machine,
    load_rig,
    refuse_unknown_keys,
    required,
    rig_of_card,
)
from fluxdrive.core.paths import CONFIG_DIR, ROOT, project_file
from fluxdrive.core.schema import check_value, param, specs
from fluxdrive.drive.control import CARD_RULES, ControllerConfig
from fluxdrive.drive.observers import ObserverConfig, observer_config

# the help of every command's `--machine` (sim, run, bench --sil, study, experiment, ...)
MACHINE_HELP = (
    "run on this motor (a machine card: a path or a name under config/machines); the "
    "scenario's rig (load inertia and friction, PWM, deadtime, sensors) stays, per-unit speeds "
    "and every unset default follow the motor, and one line says what was kept"
)

REPO_ROOT = ROOT  # the checkout (fluxdrive.core.paths: FLUXDRIVE_ROOT or the one we sit in)
RPM = 2.0 * math.pi / 60.0


@dataclass
class Scenario:
    name: str
    machine: MachineCard
    duration_s: float
    seed: int
    speed_profile_rpm: np.ndarray  # (n, 2): t_s, rpm (mechanical)
    load_profile_pu: np.ndarray  # (n, 2): t_s, per unit of rated torque
    dyno_pu_per_rpm: float
    brake_band_rpm: float  # > 0: load is a passive brake (hysteresis dyno); 0: active torque
    control: ControllerConfig
    observers: dict[str, ObserverConfig]
    driving: str  # 'encoder' or an observer name
    steady_window_s: tuple[float, float]
    step_load_time_s: float | None = None
    current_offset_a: tuple[float, ...] = (0.0, 0.0, 0.0)  # phases a, b, c
    current_gain: tuple[float, ...] = (1.0, 1.0, 1.0)  # phases a, b, c
    plant_deadtime_s: float | None = None
    initial_angle_deg: float = 0.0
    id_injection: dict[str, Any] | None = None
    speed_injection: dict[str, Any] | None = None
    description: str = ""
    source: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    bench: BenchConfig = field(default_factory=BenchConfig)  # default: the ideal bench
    # what `--machine` kept of the scenario's rig, one line for the command to print ("": the
    # scenario's own card; not a setting: a file written from the scenario does not carry it)
    machine_note: str = ""

    @property
    def n_periods(self) -> int:
        return int(round(self.duration_s * self.machine.pwm_hz))

    def speed_ref_rad_s(self, t: np.ndarray) -> np.ndarray:
        p = self.speed_profile_rpm
        return np.interp(t, p[:, 0], p[:, 1]) * RPM

    def load_breakpoints_nm(self) -> tuple[np.ndarray, np.ndarray]:
        p = self.load_profile_pu
        return (
            np.ascontiguousarray(p[:, 0], dtype=float),
            np.ascontiguousarray(p[:, 1] * self.machine.rated_torque_nm, dtype=float),
        )

    def dyno_nm_per_rad_s(self) -> float:
        return self.dyno_pu_per_rpm * self.machine.rated_torque_nm / RPM


@dataclass
class ScenarioSettings:
    """The single-valued keys at a scenario file's top level (the profiles, the blocks and the
    faults have their own parsers and tables); `load_scenario` checks them here."""

    duration_s: float = param(
        2.0, unit="s", doc="simulated run length", range=(1e-3, 3600.0), live=False
    )
    seed: int = param(
        0,
        unit="-",
        doc="random seed of the sensor noise (numpy seeds are >= 0)",
        range=(0, 2**63 - 1),
        live=False,
    )
    load_type: str = param(
        "brake",
        unit="",
        doc="brake: the load profile acts as a passive brake (a hysteresis dyno: it opposes "
        "the motion, fading to zero within brake_band_rpm of standstill); active: a torque "
        "source (a dyno in torque mode)",
        choices=("brake", "active"),
        live=False,
    )
    brake_band_rpm: float = param(
        2.0,
        unit="rpm",
        doc="brake load: the speed band around standstill in which the brake torque fades to zero",
        range=(1e-3, 1e4),
        live=False,
    )
    dyno_pu_per_rpm: float = param(
        0.0,
        unit="pu/rpm",
        doc="speed-proportional load torque, per unit of rated torque per rpm",
        range=(-1.0, 1.0),
        live=False,
    )
    step_load_time_s: float | None = param(
        None,
        unit="s",
        doc="the load step's instant: the speed metrics split there (unset: no step)",
        range=(0.0, 3600.0),
        none_is_zero=True,
        live=False,
    )
    initial_angle_deg: float = param(
        0.0,
        unit="deg",
        doc="rotor angle at t = 0 (electrical; one turn either way)",
        range=(-360.0, 360.0),
        live=False,
    )


_SETTINGS = specs(ScenarioSettings)


def _setting(src: str, raw: dict[str, Any], key: str) -> Any:
    """A top-level key, checked by its schema field (absent: the field's default)."""
    default = ScenarioSettings.__dataclass_fields__[key].default
    v = raw.get(key, default)
    check_value(_SETTINGS[key], v, f"{src}: '{key}'")
    kind = _SETTINGS[key].kind
    return v if v is None or kind is str else kind(v)


def _num(src: str, key: str, v: Any, lo: float = -math.inf, hi: float = math.inf) -> float:
    """A finite number in [lo, hi] (yamlio keeps integers within int64, so float() holds)."""
    if (
        isinstance(v, bool)
        or not isinstance(v, (int, float))
        or not math.isfinite(float(v))
        or not (lo <= float(v) <= hi)
    ):
        where = f" in [{lo}, {hi}]" if math.isfinite(lo) or math.isfinite(hi) else ""
        raise ConfigError(f"{src}: '{key}' must be a finite number{where}, got {v!r}")
    return float(v)


def _int(src: str, key: str, v: Any, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ConfigError(f"{src}: '{key}' must be an integer in [{lo}, {hi}], got {v!r}")
    return v


def _mapping(src: str, key: str, v: Any) -> dict:
    """`v` as a mapping (absent/null: empty), or one line naming the key."""
    if v is None:
        return {}
    if not isinstance(v, dict):
        raise ConfigError(f"{src}: '{key}' must be a mapping, got {type(v).__name__}")
    return v


# stepped-sine injections (drive.sim._injection): key -> (kind, lo, hi)
_INJECTION_KEYS: dict[str, tuple[str, float, float]] = {
    "frequencies_hz": ("list", 1e-3, 1e6),
    "f_start_hz": ("num", 1e-3, 1e6),
    "f_stop_hz": ("num", 1e-3, 1e6),
    "n": ("int", 1, 1000),
    "amplitude": ("num", -1e6, 1e6),
    "start_s": ("num", 0.0, 3600.0),
    "cycles": ("int", 1, 10_000),
    "settle_cycles": ("int", 0, 10_000),
}


def _injection(src: str, key: str, v: Any) -> dict[str, Any] | None:
    if v is None:
        return None
    v = _mapping(src, key, v)
    refuse_unknown_keys(src, v, list(_INJECTION_KEYS), key)
    for k, x in v.items():
        kind, lo, hi = _INJECTION_KEYS[k]
        if kind == "int":
            _int(src, f"{key}.{k}", x, int(lo), int(hi))
        elif kind == "num":
            _num(src, f"{key}.{k}", x, lo, hi)
        else:
            if not isinstance(x, list) or not 1 <= len(x) <= 1000:
                raise ConfigError(f"{src}: '{key}.{k}' must be a list of 1..1000 frequencies")
            for f in x:
                _num(src, f"{key}.{k}", f, lo, hi)
    return v


def _profile(src: str, key: str, v: Any) -> np.ndarray:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return np.array([[0.0, float(v)]])
    try:
        arr = np.array(v, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(
            f"{src}: '{key}' must be a number or a list of [t_s, value] pairs"
        ) from exc
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 1:
        raise ConfigError(f"{src}: '{key}' must be a list of [t_s, value] pairs, got {v!r}")
    if np.any(np.diff(arr[:, 0]) < 0) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{src}: '{key}' breakpoint times must be finite and non-decreasing")
    return arr


def _dataclass_from(src: str, key: str, cls, data: dict, base=None):
    if not isinstance(data, dict):
        raise ConfigError(f"{src}: '{key}' must be a mapping")
    known = {f.name for f in fields(cls)}
    refuse_unknown_keys(src, data, sorted(known), key)
    for k in data:
        if not isinstance(k, str):
            raise ConfigError(f"{src}: '{key}': key {k!r} is not a name")
    obj = base if base is not None else cls()
    for k, v in data.items():
        cur = getattr(obj, k)
        if isinstance(cur, bool):
            if not isinstance(v, bool):
                raise ConfigError(f"{src}: '{key}.{k}' must be true/false, got {v!r}")
        elif isinstance(cur, (int, float)) or (
            cur is None and (k.endswith(("_ohm", "_h", "_vs", "_hz", "_rad_s")) or k in CARD_RULES)
        ):
            _num(src, f"{key}.{k}", v)
            v = float(v)
        elif isinstance(cur, str) and not isinstance(v, str):
            raise ConfigError(f"{src}: '{key}.{k}' must be a string, got {v!r}")
        setattr(obj, k, v)
    return obj


# control keys a scenario may give in per unit of the card's rated speed instead of rpm
_CONTROL_PU = {
    "handover_pu": "handover_rpm",
    "handback_pu": "handback_rpm",
    "if_accel_pu_s": "if_accel_rpm_s",
}

_TOP_KEYS = {
    "name",
    "description",
    "machine",
    "rig",
    "duration_s",
    "seed",
    "speed_rpm",
    "speed_pu",
    "load_pu",
    "dyno_pu_per_rpm",
    "load_type",
    "brake_band_rpm",
    "control",
    "observers",
    "driving",
    "steady_window_s",
    "step_load_time_s",
    "faults",
    "plant",
    "initial_angle_deg",
    "id_injection",
    "speed_injection",
    "extra",
    "bench",
}


def load_scenario(
    path: str | Path,
    machine: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    raw: dict[str, Any] | None = None,
) -> Scenario:
    """Load and validate a scenario; `machine` swaps the machine card.  `raw`: the scenario's
    mapping already in memory (nothing is read; `path` names it in messages and anchors its
    relative paths)."""
    path = Path(path)
    src = str(path)
    raw = _read_scenario(path, machine, overrides, raw)
    card, note = _scenario_card(path, raw, machine)
    duration = _setting(src, raw, "duration_s")
    seed = _setting(src, raw, "seed")
    bench_raw, bench_src = _bench_raw(src, path, raw.get("bench"))
    bench = parse_bench(bench_src, bench_raw, card)
    ctrl = _control_config(src, raw, card)
    observers = _observer_configs(src, raw, card, bench)
    driving = _driving(src, raw, ctrl, observers)
    win = _steady_window(src, raw, duration)
    off, gain = _current_faults(src, raw)
    plant = _mapping(src, "plant", raw.get("plant"))
    bad = sorted(set(plant) - {"deadtime_s"}, key=str)
    if bad:
        raise ConfigError(f"{src}: unknown plant key(s) {bad}; expected deadtime_s")
    td = plant.get("deadtime_s")
    td = None if td is None else _num(src, "plant.deadtime_s", td, *DEADTIME_RANGE_S)
    return Scenario(
        name=str(raw.get("name", path.stem)),
        description=str(raw.get("description", "")),
        machine=card,
        duration_s=duration,
        seed=seed,
        speed_profile_rpm=_speed_profile(src, raw, card),
        load_profile_pu=_profile(src, "load_pu", raw.get("load_pu", 0.0)),
        dyno_pu_per_rpm=_setting(src, raw, "dyno_pu_per_rpm"),
        brake_band_rpm=_load_band(src, raw),
        control=ctrl,
        observers=observers,
        driving=driving,
        steady_window_s=win,
        step_load_time_s=_setting(src, raw, "step_load_time_s"),
        current_offset_a=tuple(float(x) * card.rated_current_a for x in off),
        current_gain=tuple(float(x) for x in gain),
        plant_deadtime_s=td,
        initial_angle_deg=_setting(src, raw, "initial_angle_deg"),
        id_injection=_injection(src, "id_injection", raw.get("id_injection")),
        speed_injection=_injection(src, "speed_injection", raw.get("speed_injection")),
        source=src,
        extra=dict(_mapping(src, "extra", raw.get("extra"))),
        bench=bench,
        machine_note=note,
    )


def _read_scenario(
    path: Path,
    machine: str | Path | None,
    overrides: dict[str, Any] | None,
    raw: dict[str, Any] | None,
) -> dict[str, Any]:
    """The scenario's mapping (read from `path` unless given), its rpm values rescaled to a
    swapped card and the overrides applied; unknown top-level keys refused."""
    src = str(path)
    if raw is None:
        try:
            raw = yamlio.load_file(path)
        except (OSError, yamlio.YAMLError) as exc:
            raise ConfigError(f"{src}: cannot read scenario: {yamlio.describe(exc)}") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: a scenario must be a mapping")
    if machine is not None:  # --machine: the file's rpm values at the same per-unit speed
        raw = _rescale_rpm(src, path, raw, load_machine(machine_path(machine)))
    if overrides:
        raw = dict(raw)
        for pair in (("speed_rpm", "speed_pu"), ("speed_pu", "speed_rpm")):
            if pair[0] in overrides and pair[0] not in raw:
                raw.pop(pair[1], None)  # an override in the other unit replaces the profile
        raw.update(overrides)
    unknown = sorted(set(raw) - _TOP_KEYS, key=str)
    if unknown:
        raise ConfigError(f"{src}: unknown key(s) {unknown}; expected some of {sorted(_TOP_KEYS)}")
    return raw


def _scenario_card(
    path: Path, raw: dict[str, Any], machine: str | Path | None
) -> tuple[MachineCard, str]:
    """The motor (the card `--machine` names: a path, or a card name under config/machines;
    else the scenario's own) on the scenario's rig (`rig:`, a rig file relative to the
    scenario; else, for a swapped motor, the rig of its own card: `rig_of_card`), and with
    `--machine` one line saying what of the scenario it kept.  A bad card or rig is said to
    belong to this scenario."""
    own = _own_card_path(path, raw)
    same = machine is not None and machine_path(machine).resolve() == own.resolve()
    if same:  # the scenario's own card: nothing to swap
        machine = None
    try:
        motor = load_machine(machine_path(machine) if machine is not None else own)
        rig = _scenario_rig(path, raw, own if machine is not None else None)
        card = motor if rig is None else rig.on(motor, f"{path}: {rig.name} with {motor.name}")
        if rig is not None and "rig" in raw:  # a rig file: the card says so (reports name it)
            card = dataclasses.replace(card, name=f"{motor.name}+{rig.name}")
    except ConfigError as exc:  # the card's own line, said to belong to this scenario
        raise ConfigError(f"{path}: 'machine': {exc}") from exc
    if machine is None:
        return card, (
            f"--machine {card.name}: the scenario's own card, nothing swapped" if same else ""
        )
    assert rig is not None
    note = (
        f"--machine {motor.name}: the motor (and its bus and sensor full scales) from its "
        f"card; kept the scenario's {rig.describe()} (total J {card.inertia_kgm2:.3g} kg m^2)"
    )
    return card, note


def _scenario_rig(path: Path, raw: dict[str, Any], own: Path | None) -> Rig | None:
    """The scenario's rig file (`rig:`), else that of its own card (`own`; None: the card
    is used as it is)."""
    name = raw.get("rig")
    if name is None:
        return None if own is None else rig_of_card(load_machine(own))
    if not isinstance(name, str) or not name or "\0" in name:
        raise ConfigError(
            f"'rig' must be the path of a rig file (relative to the scenario), got {name!r}"
        )
    rpath = Path(name)
    return load_rig(rpath if rpath.is_absolute() else path.parent / rpath)


def _control_config(src: str, raw: dict[str, Any], card: MachineCard) -> ControllerConfig:
    """The `control` block (per-unit speeds in rpm of this card), checked on the card."""
    ctrl_raw = dict(_mapping(src, "control", raw.get("control")))
    for key_pu, key_rpm in _CONTROL_PU.items():
        if key_pu in ctrl_raw:
            if key_rpm in ctrl_raw:
                raise ConfigError(f"{src}: give control.{key_pu} or control.{key_rpm}, not both")
            ctrl_raw[key_rpm] = (
                _num(src, f"control.{key_pu}", ctrl_raw.pop(key_pu), 0.0, 100.0)
                * card.rated_speed_rpm
            )
    ctrl = _dataclass_from(src, "control", ControllerConfig, ctrl_raw)
    ctrl.check(card, f"{src}: control")  # on this card: a bad value names the file
    return ctrl


def _observer_configs(
    src: str, raw: dict[str, Any], card: MachineCard, bench: BenchConfig
) -> dict[str, ObserverConfig]:
    """The `observers` block: each a variant's defaults with the scenario's settings, the
    bench's observer model, and the card's rules for what is left unset."""
    obs_raw = raw.get("observers", {}) or {}
    if not isinstance(obs_raw, dict):
        raise ConfigError(f"{src}: 'observers' must be a mapping name -> settings")
    observers: dict[str, ObserverConfig] = {}
    for name, spec in obs_raw.items():
        spec = dict(_mapping(src, f"observers.{name}", spec))
        variant = spec.pop("variant", "paper")
        if not isinstance(variant, str):
            raise ConfigError(f"{src}: 'observers.{name}.variant' must be a name, got {variant!r}")
        try:
            base = observer_config(variant)
        except ConfigError as exc:
            raise ConfigError(f"{src}: observers.{name}: {exc}") from exc
        cfg = _dataclass_from(src, f"observers.{name}", ObserverConfig, spec, base)
        cfg = bench.apply_observer_model(cfg, card)  # R^, L^, lambda^ the observer leaves open
        # frequencies the scenario leaves unset: from this card (OBSERVER_RULES)
        observers[str(name)] = cfg.validate(f"{src}: observers.{name}").resolved(card)
    return observers


def _driving(
    src: str, raw: dict[str, Any], ctrl: ControllerConfig, observers: dict[str, ObserverConfig]
) -> str:
    """The position source ('encoder' or an observer's name), set on the controller with
    the speed path its speed loop is designed with."""
    driving = str(raw.get("driving", "encoder"))
    if driving != "encoder" and driving not in observers:
        raise ConfigError(
            f"{src}: 'driving' must be 'encoder' or one of the observers "
            f"{sorted(observers)}, got '{driving}'"
        )
    ctrl.position_source = "encoder" if driving == "encoder" else "estimate"
    if driving != "encoder" and ctrl.speed_observer_pll_hz is None:
        # the speed loop is designed with the driving observer's speed path, unless the
        # scenario fixes the design (e.g. to compare position sources on the same gains)
        d = observers[driving]
        ctrl.speed_observer_pll_hz = required(d.pll_bandwidth_hz, "pll_bandwidth_hz")
        ctrl.speed_observer_damping = d.pll_damping
        ctrl.speed_observer_lpf_hz = required(d.speed_lpf_hz, "speed_lpf_hz")  # resolved
    return driving


def _steady_window(src: str, raw: dict[str, Any], duration: float) -> tuple[float, float]:
    """[start, end] of the steady-state metrics, within the duration (default: 2nd half)."""
    win = raw.get("steady_window_s", [0.5 * duration, duration])
    if (
        not isinstance(win, (list, tuple))
        or len(win) != 2
        or not 0
        <= _num(src, "steady_window_s", win[0])
        < _num(src, "steady_window_s", win[1])
        <= duration + 1e-9
    ):
        raise ConfigError(f"{src}: 'steady_window_s' must be [start, end] within the duration")
    return float(win[0]), float(win[1])


def _current_faults(src: str, raw: dict[str, Any]) -> tuple[list, list]:
    """The `faults` block: per-phase current-sensor offsets [pu] and gains."""
    faults = _mapping(src, "faults", raw.get("faults"))
    bad = sorted(set(faults) - {"current_offset_pu", "current_gain"}, key=str)
    if bad:
        raise ConfigError(
            f"{src}: unknown fault key(s) {bad}; expected current_offset_pu, current_gain"
        )
    off = faults.get("current_offset_pu", [0.0, 0.0, 0.0])
    gain = faults.get("current_gain", [1.0, 1.0, 1.0])
    for key, val in (("faults.current_offset_pu", off), ("faults.current_gain", gain)):
        if not isinstance(val, list) or len(val) != 3:
            raise ConfigError(f"{src}: '{key}' must be a list of 3 numbers (phases a, b, c)")
        for x in val:
            _num(src, key, x)
    return off, gain


def _own_card_path(path: Path, raw: dict) -> Path:
    """The machine card a scenario file names (default: the default card)."""
    name = raw.get("machine", "../machines/default_spm.yaml")
    if not isinstance(name, str) or not name or "\0" in name:
        raise ConfigError(
            f"{path}: 'machine' must be the path of a machine card (relative to the "
            f"scenario file), got {name!r}"
        )
    mpath = Path(name)
    return mpath if mpath.is_absolute() else path.parent / mpath


def _rescale_rpm(src: str, path: Path, raw: dict, card: MachineCard) -> dict:
    """A scenario run on another card (`--machine`) keeps its per-unit speeds: every value
    the file gives in rpm (speed_rpm, control.handover_rpm/handback_rpm/if_accel_rpm_s,
    brake_band_rpm, speed_injection.amplitude; dyno_pu_per_rpm inversely) is scaled by the
    ratio of the swapped card's rated speed to that of the card the file names, so 60 rpm
    written for the 3000 rpm default card runs at 2 % of any card's rated speed."""
    ctrl = raw.get("control") or {}
    inj = raw.get("speed_injection") or {}
    keys = [k for k in ("speed_rpm", "brake_band_rpm", "dyno_pu_per_rpm") if k in raw]
    ckeys = (
        [k for k in ("handover_rpm", "handback_rpm", "if_accel_rpm_s") if k in ctrl]
        if isinstance(ctrl, dict)
        else []
    )
    has_inj = isinstance(inj, dict) and "amplitude" in inj
    if not (keys or ckeys or has_inj):
        return raw
    own = _own_card_path(path, raw)
    try:
        ref = load_machine(own)
    except ConfigError as exc:
        raise ConfigError(
            f"{src}: its rpm values are read per unit of the card it names "
            f"('machine'), which cannot be loaded: {exc}"
        ) from exc
    k = card.rated_speed_rpm / ref.rated_speed_rpm
    if k == 1.0:
        return raw
    out = dict(raw)

    def scale(key: str, v: Any, f: float) -> Any:
        if isinstance(v, bool):
            return v
        if isinstance(v, (int, float)):
            return float(v) * f
        if isinstance(v, list):  # a [[t_s, value], ...] profile: the values only
            return [
                [row[0], scale(key, row[1], f)] if isinstance(row, list) and len(row) == 2 else row
                for row in v
            ]
        return v  # not a number: the loader refuses it with its own message

    for key in keys:
        out[key] = scale(key, raw[key], 1.0 / k if key == "dyno_pu_per_rpm" else k)
    if ckeys:
        out["control"] = {**ctrl, **{c: scale(c, ctrl[c], k) for c in ckeys}}
    if has_inj:
        out["speed_injection"] = {**inj, "amplitude": scale("amplitude", inj["amplitude"], k)}
    return out


def _speed_profile(src: str, raw: dict, card: MachineCard) -> np.ndarray:
    """speed_rpm, or speed_pu (per unit of the card's rated speed) -> (t_s, rpm) rows."""
    if "speed_pu" in raw:
        if "speed_rpm" in raw:
            raise ConfigError(f"{src}: give speed_rpm or speed_pu, not both")
        prof = _profile(src, "speed_pu", raw["speed_pu"])
        _check_speed(src, "speed_pu", prof[:, 1], SPEED_MAX_PU)
        prof[:, 1] *= card.rated_speed_rpm
        return prof
    prof = _profile(src, "speed_rpm", raw.get("speed_rpm", 60.0))
    _check_speed(src, "speed_rpm", prof[:, 1], SPEED_MAX_PU * card.rated_speed_rpm)
    return prof


SPEED_MAX_PU = 10.0  # a speed reference beyond 10 x rated: a typo (1e308 overflowed to inf rpm)


def _check_speed(src: str, key: str, values: np.ndarray, limit: float) -> None:
    if np.max(np.abs(values)) > limit:
        raise ConfigError(
            f"{src}: '{key}' must stay within +-{limit:g} ({SPEED_MAX_PU:g} x the card's rated "
            f"speed), got {float(np.max(np.abs(values))):g}"
        )


def load_bench_file(path: Path, card: MachineCard) -> BenchConfig:
    """A bench file (the file a scenario's `bench:` names), validated for `card`."""
    raw, src = _bench_raw(str(path), Path(path).resolve(), str(Path(path).resolve()))
    return parse_bench(src, raw, card)


def _bench_raw(src: str, path: Path, v: Any, depth: int = 0) -> tuple[Any, str]:
    """The `bench:` entry: a mapping, or the path of a bench file (relative to the scenario);
    with the source its errors name (the scenario, and the bench file if there is one).  A
    bench file may start from another one (`base: FILE`, relative to it) and add to it."""
    if not isinstance(v, str):
        return v, src
    if not v or "\0" in v or depth > 4:
        raise ConfigError(f"{src}: 'bench' must be a mapping or a bench file's path, got {v!r}")
    bpath = Path(v) if Path(v).is_absolute() else path.parent / v
    try:
        raw = yamlio.load_file(bpath)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(
            f"{src}: 'bench': cannot read bench file {bpath}: {yamlio.describe(exc)}"
        ) from exc
    where = f"{src}: bench file {bpath}"
    if isinstance(raw, dict) and "base" in raw:
        rest = {k: x for k, x in raw.items() if k != "base"}
        base, _ = _bench_raw(where, bpath, raw["base"], depth + 1)
        if not isinstance(base, dict):
            raise ConfigError(f"{where}: 'base' must name a bench file of effects")
        return {**base, **rest}, where
    return ({} if raw is None else raw), where


def _load_band(src: str, raw: dict) -> float:
    if _setting(src, raw, "load_type") == "active":
        return 0.0
    return _setting(src, raw, "brake_band_rpm")


def _config_file(name_or_path: str | Path, folder: str, what: str) -> Path:
    """A path, or a bare name under config/<folder>/."""
    p = Path(name_or_path)
    if p.exists():
        return p
    cand = CONFIG_DIR / folder / (p.name if p.suffix else p.name + ".yaml")
    if cand.exists():
        return cand
    if not CONFIG_DIR.is_dir():
        project_file(CONFIG_DIR, "config/")  # the package is not pointed at a checkout
    raise ConfigError(f"{what} '{name_or_path}' not found (looked at {p} and {cand})")


# the scenario whose `observers` block is the project's observer set, declared once there: the
# graph files expand `observers_of:` it, the observer nodes take their settings from it, the
# experiments' OBS6 and beyond.VARIANTS read it (observer_set)
OBSERVER_SET_SCENARIO = "paper_2pct_150load"


def observer_set(path: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """A scenario file's `observers` block as written (name -> settings), without loading
    the rest; default: the project's observer set (OBSERVER_SET_SCENARIO)."""
    p = scenario_path(str(path or OBSERVER_SET_SCENARIO))
    try:
        raw = yamlio.load_file(p)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{p}: cannot read scenario: {yamlio.describe(exc)}") from exc
    obs = raw.get("observers") if isinstance(raw, dict) else None
    if not isinstance(obs, dict) or not all(isinstance(v, dict) for v in obs.values()):
        raise ConfigError(f"{p}: 'observers' must be a mapping name -> settings")
    return {str(k): dict(v) for k, v in obs.items()}


def observer_names(path: str | Path) -> list[str]:
    """The names of the observers a scenario file declares (in its order)."""
    return list(observer_set(path))


def scenario_path(name_or_path: str) -> Path:
    """Accept a path, or a bare scenario name under config/scenarios/."""
    return _config_file(name_or_path, "scenarios", "scenario")


def machine_path(name_or_path: str | Path) -> Path:
    """Accept a path, or a bare machine-card name under config/machines/."""
    return _config_file(name_or_path, "machines", "machine card")


def scenario_to_raw(sc: Scenario, machine_path: str) -> dict[str, Any]:
    """The YAML mapping that `load_scenario` turns back into `sc` (the machine card is
    referenced by `machine_path`; write it with `save_machine`)."""
    from dataclasses import asdict

    rated = sc.machine.rated_current_a

    def set_fields(obj) -> dict[str, Any]:  # None = "the machine card's" = the default
        return {k: v for k, v in asdict(obj).items() if v is not None}

    ctrl = set_fields(sc.control)
    ctrl.pop("position_source")  # follows from `driving`
    raw: dict[str, Any] = {
        "name": sc.name,
        "description": sc.description,
        "machine": machine_path,
        "duration_s": float(sc.duration_s),
        "seed": int(sc.seed),
        "speed_rpm": sc.speed_profile_rpm.tolist(),
        "load_pu": sc.load_profile_pu.tolist(),
        "dyno_pu_per_rpm": float(sc.dyno_pu_per_rpm),
        "load_type": "active" if sc.brake_band_rpm == 0.0 else "brake",
        "control": ctrl,
        "observers": {n: set_fields(c) for n, c in sc.observers.items()},
        "driving": sc.driving,
        "steady_window_s": [float(sc.steady_window_s[0]), float(sc.steady_window_s[1])],
        "faults": {
            "current_offset_pu": [float(x) / rated for x in sc.current_offset_a],
            "current_gain": [float(x) for x in sc.current_gain],
        },
        "initial_angle_deg": float(sc.initial_angle_deg),
        "extra": dict(sc.extra),
    }
    if sc.brake_band_rpm != 0.0:
        raw["brake_band_rpm"] = float(sc.brake_band_rpm)
    if sc.step_load_time_s is not None:
        raw["step_load_time_s"] = float(sc.step_load_time_s)
    if sc.plant_deadtime_s is not None:
        raw["plant"] = {"deadtime_s": float(sc.plant_deadtime_s)}
    if not sc.bench.ideal:
        raw["bench"] = sc.bench.to_raw()
    for key in ("id_injection", "speed_injection"):
        if getattr(sc, key) is not None:
            raw[key] = getattr(sc, key)
    return raw


def save_machine(card: MachineCard, path: str | Path) -> Path:
    from dataclasses import asdict

    path = Path(path)
    path.write_text(yamlio.dumps(asdict(card), sort_keys=False))
    return path


def save_scenario(sc: Scenario, path: str | Path) -> Path:
    """Write `sc` as a scenario file (plus its machine card next to it, `<stem>.machine.yaml`)
    that loads back into the same scenario -- for scenarios built or changed in memory that
    must run elsewhere (the node graph loads scenarios from files).  Raises ConfigError if
    the file would not reproduce `sc`."""
    path = Path(path)
    mpath = save_machine(sc.machine, path.with_name(path.stem + ".machine.yaml"))
    path.write_text(yamlio.dumps(scenario_to_raw(sc, mpath.name), sort_keys=False))
    back = load_scenario(path)
    diff = scenario_differences(sc, back)
    if diff:
        raise ConfigError(
            f"{path}: the scenario file does not reproduce the scenario ({', '.join(diff)})"
        )
    return path


def scenario_on_machine(
    path: Path, machine: str | Path | None, folder: Path
) -> tuple[Path, Scenario]:
    """`--machine` for the commands that hand a scenario file to other processes (the node
    graph, the drive emulator): the scenario on that motor written to `folder` (with its
    card), and the scenario, whose `machine_note` says what was kept; no machine: the file
    as it is."""
    sc = load_scenario(path, machine=machine)
    if machine is None:
        return path, sc
    folder.mkdir(parents=True, exist_ok=True)
    out = save_scenario(sc, folder / f"{path.stem}.yaml")
    return out, sc


def scenario_differences(a: Scenario, b: Scenario, rel_tol: float = 1e-15) -> list[str]:
    """Names of the fields in which two scenarios differ (numbers within `rel_tol`: a fault
    offset goes through per-unit and back)."""
    out = []
    for f in fields(Scenario):
        if f.name in ("source", "machine_note"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            same = x.shape == y.shape and np.allclose(x, y, rtol=rel_tol, atol=0.0)
        elif f.name == "current_offset_a":
            same = np.allclose(x, y, rtol=1e-12, atol=1e-15)
        else:
            same = x == y
        if not same:
            out.append(f.name)
    return out
