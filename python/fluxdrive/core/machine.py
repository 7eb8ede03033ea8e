"""Machine card: the physical drive (motor, inverter, sensors) as one typed, validated record.

Loaded from config/machines/*.yaml.  Every other module derives its defaults from this card
(observer model parameters, controller gains), so a scenario runs on another machine by
swapping one file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from fluxdrive.core import yamlio


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the file, key and rule."""


def required(value: float | None, key: str) -> float:
    """A setting that `resolved(card)` has filled in: its value, or an error naming the key
    when it is still unset (used before it was resolved against a card)."""
    if value is None:
        raise ConfigError(f"{key} is unset: resolve the settings against a machine card first")
    return value


def refuse_unknown_keys(src: str, data: dict, known: list[str], where: str) -> None:
    """One line naming the file, the section and the keys it does not know (a typo is
    refused, never silently ignored); `known` is listed in the order given."""
    bad = sorted(set(data) - set(known), key=str)
    if bad:
        raise ConfigError(f"{src}: unknown key(s) {bad} under '{where}'; expected some of {known}")


def _require_range(src: str, key: str, value: Any, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{src}: '{key}' must be a number in [{lo}, {hi}], got {value!r}")
    v = float(value)
    if not (lo <= v <= hi) or not math.isfinite(v):
        raise ConfigError(f"{src}: '{key}' = {v} is out of range [{lo}, {hi}]")
    return v


@dataclass(frozen=True)
class MachineCard:
    """SPM machine + two-level inverter + sensors.  SI units throughout."""

    name: str = "default_spm"
    pole_pairs: int = 4
    rated_speed_rpm: float = 3000.0
    flux_linkage_vs: float = 0.0235  # magnet flux, peak per phase [V s]
    resistance_ohm: float = 0.40
    inductance_h: float = 0.80e-3
    rated_current_a: float = 9.0  # peak phase current
    inertia_kgm2: float = 1.5e-4  # motor + dyno
    viscous_nms: float = 1.0e-4  # [N m s/rad]
    dc_bus_v: float = 72.0
    pwm_hz: float = 10_000.0
    deadtime_s: float = 2.0e-6
    device_drop_v: float = 0.0  # switch/diode forward drop
    current_adc_bits: int = 12
    current_range_a: float = 20.0  # ADC full scale +-range
    current_noise_a: float = 0.02  # Gaussian, RMS (about 2 LSB of a 12-bit +-20 A ADC)
    capture_bits: int = 12  # line-voltage capture: resolution in bits of the period
    dc_bus_adc_bits: int = 12
    dc_bus_range_v: float = 100.0
    dc_bus_noise_v: float = 0.0
    encoder_lines: int = 2500
    flux_h5: float = 0.0  # 5th/7th magnet-flux harmonics, per unit of the fundamental
    flux_h7: float = 0.0
    saturation: float = 0.0  # L drops by this fraction at rated current (L = L0 (1 - s (i/I_r)^2))
    # winding thermal model (used when a scenario's bench turns it on): one thermal node,
    # winding to ambient; resistance_ohm is the value at resistance_ref_c
    thermal_resistance_k_per_w: float = 0.0
    thermal_time_constant_s: float = 0.0
    resistance_ref_c: float = 25.0
    copper_tempco_per_k: float = 0.00393  # annealed copper at 20 deg C (IEC 60028)

    # ---- derived quantities
    @property
    def ts_s(self) -> float:
        return 1.0 / self.pwm_hz

    @property
    def torque_constant_nm_per_a(self) -> float:
        return 1.5 * self.pole_pairs * self.flux_linkage_vs

    @property
    def rated_torque_nm(self) -> float:
        return self.torque_constant_nm_per_a * self.rated_current_a

    @property
    def rated_speed_rad_s(self) -> float:
        """Rated mechanical speed [rad/s]."""
        return self.rated_speed_rpm * 2.0 * math.pi / 60.0

    @property
    def rated_electrical_hz(self) -> float:
        """Electrical frequency at rated speed [Hz] (200 Hz on the default card)."""
        return self.rated_speed_rpm / 60.0 * self.pole_pairs

    def validate(self, src: str = "machine card") -> MachineCard:
        checks = {
            "pole_pairs": (1, 64),
            "rated_speed_rpm": (1.0, 1e6),
            "flux_linkage_vs": (1e-6, 10.0),
            "resistance_ohm": (0.0, 1e3),
            "inductance_h": (1e-7, 10.0),
            "rated_current_a": (1e-3, 1e4),
            "inertia_kgm2": (1e-9, 1e3),
            "viscous_nms": (0.0, 1e3),
            "dc_bus_v": (1.0, 1e4),
            "pwm_hz": (100.0, 1e6),
            "deadtime_s": (0.0, 1e-4),
            "device_drop_v": (0.0, 10.0),
            "current_adc_bits": (4, 24),
            "current_range_a": (1e-3, 1e5),
            "current_noise_a": (0.0, 1e3),
            "capture_bits": (4, 24),
            "dc_bus_adc_bits": (4, 24),
            "dc_bus_range_v": (1.0, 1e5),
            "dc_bus_noise_v": (0.0, 1e3),
            "encoder_lines": (1, 1 << 20),
            "flux_h5": (-0.5, 0.5),
            "flux_h7": (-0.5, 0.5),
            "saturation": (0.0, 0.7),
            "thermal_resistance_k_per_w": (0.0, 1e3),
            "thermal_time_constant_s": (0.0, 1e6),
            "resistance_ref_c": (-60.0, 250.0),
            "copper_tempco_per_k": (0.0, 0.01),
        }
        for key, (lo, hi) in checks.items():
            _require_range(src, key, getattr(self, key), lo, hi)
        if self.deadtime_s * self.pwm_hz >= 0.2:
            raise ConfigError(f"{src}: deadtime_s {self.deadtime_s} is >= 20 % of the PWM period")
        return self


def card_current_bandwidth_hz(card: MachineCard) -> float:
    """Current-loop bandwidth for a card: a tenth of the PWM rate (with the 1.5-period
    delay of a digital drive the discrete loop peaks beyond that), raised to three times
    the RL corner R/(2 pi L) for a machine whose own electrical pole is that fast (the loop
    must be quicker than the plant), never above a fifth of the PWM rate."""
    corner = card.resistance_ohm / (2 * math.pi * card.inductance_h)
    return min(max(0.1 * card.pwm_hz, 3.0 * corner), 0.2 * card.pwm_hz)


_SECTIONS = ("motor", "inverter", "sensors", "options")


def load_machine(path: str | Path) -> MachineCard:
    """Load a machine card YAML (flat keys, or grouped under motor/inverter/sensors/options)."""
    path = Path(path)
    try:
        raw = yamlio.load_file(path)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read machine card: {yamlio.describe(exc)}") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: a machine card must be a mapping")
    flat: dict[str, Any] = {}
    for key, value in raw.items():
        if key in _SECTIONS and isinstance(value, dict):
            flat.update(value)
        else:
            flat[key] = value
    known = {f.name: f for f in fields(MachineCard)}
    unknown = sorted(set(flat) - set(known), key=str)
    if unknown:
        raise ConfigError(
            f"{path}: unknown machine-card key(s) {unknown}; expected some of {sorted(known)}"
        )
    kwargs: dict[str, Any] = {}
    for key, value in flat.items():
        ftype = known[key].type
        if ftype in ("int", int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"{path}: '{key}' must be an integer, got {value!r}")
            kwargs[key] = value
        elif ftype in ("str", str):
            if not isinstance(value, str):
                raise ConfigError(f"{path}: '{key}' must be a string, got {value!r}")
            kwargs[key] = value
        else:
            kwargs[key] = _require_range(str(path), key, value, -math.inf, math.inf)
    return MachineCard(**kwargs).validate(str(path))


@dataclass
class Profile:
    """Piecewise-linear time profile: breakpoints (t_s, value)."""

    t_s: list[float] = field(default_factory=lambda: [0.0])
    value: list[float] = field(default_factory=lambda: [0.0])
