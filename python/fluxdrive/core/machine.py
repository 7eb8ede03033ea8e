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
from fluxdrive.core.errors import ConfigError as ConfigError  # its home for importers
from fluxdrive.core.schema import param, ranges

# what an inverter deadtime (or a feed-forward of it) may be, in seconds: one range for the card,
# the plant override of a scenario, the controller's, observers' and drive's feed-forward
DEADTIME_RANGE_S: tuple[float, float] = (0.0, 1e-4)


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
    if not math.isfinite(v):
        raise ConfigError(f"{src}: '{key}' must be a finite number, got {v}")
    if not lo <= v <= hi:
        raise ConfigError(f"{src}: '{key}' = {value!r} is out of range [{lo}, {hi}]")
    return v


@dataclass(frozen=True)
class MachineCard:
    """SPM machine + two-level inverter + sensors.  SI units throughout."""

    name: str = param("default_spm", unit="", doc="the card's name", live=False)
    pole_pairs: int = param(4, unit="-", doc="pole pairs", range=(1, 64), live=False)
    rated_speed_rpm: float = param(
        3000.0, unit="rpm", doc="rated mechanical speed", range=(1.0, 1000000.0), live=False
    )
    flux_linkage_vs: float = param(
        0.0235, unit="V s", doc="magnet flux, peak per phase", range=(1e-06, 10.0), live=False
    )
    resistance_ohm: float = param(
        0.40,
        unit="ohm",
        doc="stator resistance per phase (at resistance_ref_c)",
        range=(0.0, 1000.0),
        live=False,
    )
    inductance_h: float = param(
        0.80e-3, unit="H", doc="synchronous inductance", range=(1e-07, 10.0), live=False
    )
    rated_current_a: float = param(
        9.0, unit="A", doc="rated current, peak per phase", range=(0.001, 10000.0), live=False
    )
    inertia_kgm2: float = param(
        1.5e-4, unit="kg m^2", doc="inertia of motor and dyno", range=(1e-09, 1000.0), live=False
    )
    viscous_nms: float = param(
        1.0e-4, unit="N m s/rad", doc="viscous friction", range=(0.0, 1000.0), live=False
    )
    dc_bus_v: float = param(72.0, unit="V", doc="DC-bus voltage", range=(1.0, 10000.0), live=False)
    pwm_hz: float = param(
        10_000.0, unit="Hz", doc="PWM (and sample) frequency", range=(100.0, 1000000.0), live=False
    )
    deadtime_s: float = param(
        2.0e-6,
        unit="s",
        doc="inverter deadtime (below 20 % of the PWM period)",
        range=DEADTIME_RANGE_S,
        live=False,
    )
    device_drop_v: float = param(
        0.0, unit="V", doc="switch/diode forward drop", range=(0.0, 10.0), live=False
    )
    current_adc_bits: int = param(
        12, unit="bits", doc="current ADC resolution", range=(4, 24), live=False
    )
    current_range_a: float = param(
        20.0, unit="A", doc="current ADC full scale (+-)", range=(0.001, 100000.0), live=False
    )
    current_noise_a: float = param(
        0.02,
        unit="A",
        doc="current-sample noise, Gaussian rms (about 2 LSB of a 12-bit +-20 A ADC)",
        range=(0.0, 1000.0),
        live=False,
    )
    capture_bits: int = param(
        12,
        unit="bits",
        doc="line-voltage capture: resolution in bits of the period",
        range=(4, 24),
        live=False,
    )
    dc_bus_adc_bits: int = param(
        12, unit="bits", doc="DC-bus ADC resolution", range=(4, 24), live=False
    )
    dc_bus_range_v: float = param(
        100.0, unit="V", doc="DC-bus ADC full scale", range=(1.0, 100000.0), live=False
    )
    dc_bus_noise_v: float = param(
        0.0, unit="V", doc="DC-bus sample noise, Gaussian rms", range=(0.0, 1000.0), live=False
    )
    encoder_lines: int = param(
        2500,
        unit="lines",
        doc="encoder lines per revolution (4x counts)",
        range=(1, 1 << 20),
        live=False,
    )
    flux_h5: float = param(
        0.0,
        unit="pu",
        doc="5th magnet-flux harmonic, per unit of the fundamental",
        range=(-0.5, 0.5),
        live=False,
    )
    flux_h7: float = param(
        0.0,
        unit="pu",
        doc="7th magnet-flux harmonic, per unit of the fundamental",
        range=(-0.5, 0.5),
        live=False,
    )
    saturation: float = param(
        0.0,
        unit="-",
        doc="L drops by this fraction at rated current (L = L0 (1 - s (i/I_r)^2))",
        range=(0.0, 0.7),
        live=False,
    )
    thermal_resistance_k_per_w: float = param(
        0.0,
        unit="K/W",
        doc="winding-to-ambient thermal resistance (0: no thermal model)",
        range=(0.0, 1000.0),
        live=False,
    )
    thermal_time_constant_s: float = param(
        0.0,
        unit="s",
        doc="winding thermal time constant (0: no thermal model)",
        range=(0.0, 1000000.0),
        live=False,
    )
    resistance_ref_c: float = param(
        25.0, unit="degC", doc="temperature of resistance_ohm", range=(-60.0, 250.0), live=False
    )
    copper_tempco_per_k: float = param(
        0.00393,
        unit="1/K",
        doc="resistance temperature coefficient (annealed copper at 20 deg C, IEC 60028)",
        range=(0.0, 0.01),
        live=False,
    )

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
        for key, (lo, hi) in ranges(MachineCard).items():
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
