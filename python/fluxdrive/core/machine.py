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

# how far a stated rated torque may be from K_t I_rated = 1.5 p lambda I_rated (a nameplate's
# rounding and its RMS/peak conventions agree far better; a mix-up is off by 20 % or more)
TORQUE_TOLERANCE = 0.05

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
        1.5e-4,
        unit="kg m^2",
        doc="inertia of the motor (a scenario's rig adds its load's)",
        range=(1e-09, 1000.0),
        live=False,
    )
    viscous_nms: float = param(
        1.0e-4,
        unit="N m s/rad",
        doc="viscous friction of the motor (a scenario's rig adds its load's)",
        range=(0.0, 1000.0),
        live=False,
    )
    stated_torque_nm: float = param(
        0.0,
        unit="N m",
        doc="rated torque as the nameplate states it (0: not stated); refused unless "
        f"1.5 p lambda x rated current agrees within {TORQUE_TOLERANCE:.0%}",
        range=(0.0, 1e6),
        live=False,
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
        if self.stated_torque_nm > 0.0:
            t = self.rated_torque_nm
            off = t / self.stated_torque_nm - 1.0
            if abs(off) > TORQUE_TOLERANCE:
                raise ConfigError(
                    f"{src}: stated_torque_nm {self.stated_torque_nm:g} N m disagrees with "
                    f"K_t x rated_current_a = 1.5 x {self.pole_pairs} x {self.flux_linkage_vs:g} "
                    f"V s x {self.rated_current_a:g} A = {t:.3g} N m ({off:+.0%}, tolerance "
                    f"{TORQUE_TOLERANCE:.0%})"
                )
        return self


def card_current_bandwidth_hz(card: MachineCard) -> float:
    """Current-loop bandwidth for a card: a tenth of the PWM rate (with the 1.5-period
    delay of a digital drive the discrete loop peaks beyond that), raised to three times
    the RL corner R/(2 pi L) for a machine whose own electrical pole is that fast (the loop
    must be quicker than the plant), never above a fifth of the PWM rate."""
    corner = card.resistance_ohm / (2 * math.pi * card.inductance_h)
    return min(max(0.1 * card.pwm_hz, 3.0 * corner), 0.2 * card.pwm_hz)


_SECTIONS = ("motor", "inverter", "sensors", "options")

# ---- the nameplate: what a motor's plate (or its datasheet's first table) states, in its
# own conventions (line-to-line values, RMS current, K_e in V per 1000 rpm), turned into the
# card's per-phase peak quantities; what a plate lacks is derived (NAMEPLATE_DERIVED, the
# same rules in docs/machines.md, "A card from the nameplate")
NAMEPLATE_KEYS: dict[str, str] = {
    "poles": "number of magnet poles (2 x pole_pairs)",
    "rated_voltage_v": "rated (DC-bus) voltage -> dc_bus_v",
    "rated_speed_rpm": "rated speed -> rated_speed_rpm",
    "rated_current_a_rms": "rated phase current, RMS -> rated_current_a = sqrt(2) x",
    "rated_torque_nm": "rated torque -> stated_torque_nm (checked against K_e and the current)",
    "ke_v_per_krpm": "back-EMF constant, line-to-line RMS volts per 1000 rpm -> flux_linkage_vs",
    "resistance_ll_ohm": "line-to-line resistance -> resistance_ohm = half of it",
    "inductance_ll_h": "line-to-line inductance -> inductance_h = half of it",
    "rotor_inertia_kgm2": "rotor inertia -> inertia_kgm2",
}
NAMEPLATE_REQUIRED = tuple(NAMEPLATE_KEYS)
NAMEPLATE_DERIVED: dict[str, str] = {
    "viscous_nms": "1 % of the rated torque at rated speed",
    "current_range_a": "2.5 x the rated peak current (above the 2.1 pu over-current trip)",
    "current_noise_a": "a thousandth of current_range_a (2 LSB of a 12-bit ADC)",
    "dc_bus_range_v": "1.5 x rated_voltage_v (above the 1.32 x over-voltage trip)",
}


def flux_from_ke(ke_v_per_krpm: float, pole_pairs: int) -> float:
    """Magnet flux, peak per phase [V s], from K_e in line-to-line RMS volts per 1000 rpm:
    e_phase,peak = sqrt(2/3) e_LL,rms = lambda p omega_m."""
    return ke_v_per_krpm * math.sqrt(2.0 / 3.0) / (pole_pairs * 1000.0 * 2.0 * math.pi / 60.0)


def _from_nameplate(src: str, plate: Any) -> dict[str, Any]:
    """The card keys a nameplate gives (and those it lacks, derived), or one line naming
    the key that is missing or wrong, or the disagreement between K_e, current and torque."""
    if not isinstance(plate, dict):
        raise ConfigError(f"{src}: 'nameplate' must be a mapping of {list(NAMEPLATE_KEYS)}")
    refuse_unknown_keys(src, plate, list(NAMEPLATE_KEYS), "nameplate")
    missing = [k for k in NAMEPLATE_REQUIRED if k not in plate]
    if missing:
        raise ConfigError(f"{src}: nameplate lacks {missing} (a card from the nameplate needs all)")
    poles = plate["poles"]
    if isinstance(poles, bool) or not isinstance(poles, int) or poles < 2 or poles % 2:
        raise ConfigError(f"{src}: 'nameplate.poles' must be an even integer >= 2, got {poles!r}")
    v = {
        k: _require_range(src, f"nameplate.{k}", plate[k], 1e-12, 1e9)
        for k in NAMEPLATE_KEYS
        if k != "poles"
    }
    p = poles // 2
    lam = flux_from_ke(v["ke_v_per_krpm"], p)
    i_pk = math.sqrt(2.0) * v["rated_current_a_rms"]
    torque = 1.5 * p * lam * i_pk
    off = torque / v["rated_torque_nm"] - 1.0
    if abs(off) > TORQUE_TOLERANCE:
        raise ConfigError(
            f"{src}: nameplate disagrees: ke_v_per_krpm {v['ke_v_per_krpm']:g} gives K_t "
            f"{torque / v['rated_current_a_rms']:.3g} N m/A rms, x rated_current_a_rms "
            f"{v['rated_current_a_rms']:g} A = {torque:.3g} N m, but rated_torque_nm is "
            f"{v['rated_torque_nm']:g} N m ({off:+.0%}, tolerance {TORQUE_TOLERANCE:.0%})"
        )
    w_r = v["rated_speed_rpm"] * 2.0 * math.pi / 60.0
    i_range = 2.5 * i_pk
    return {
        "pole_pairs": p,
        "rated_speed_rpm": v["rated_speed_rpm"],
        "flux_linkage_vs": lam,
        "resistance_ohm": 0.5 * v["resistance_ll_ohm"],
        "inductance_h": 0.5 * v["inductance_ll_h"],
        "rated_current_a": i_pk,
        "stated_torque_nm": v["rated_torque_nm"],
        "inertia_kgm2": v["rotor_inertia_kgm2"],
        "dc_bus_v": v["rated_voltage_v"],
        # what the plate lacks (NAMEPLATE_DERIVED)
        "viscous_nms": 0.01 * v["rated_torque_nm"] / w_r,
        "current_range_a": i_range,
        "current_noise_a": i_range / 1000.0,
        "dc_bus_range_v": 1.5 * v["rated_voltage_v"],
    }


def load_machine(path: str | Path) -> MachineCard:
    """Load a machine card YAML (flat keys, or grouped under motor/inverter/sensors/options;
    a `nameplate` section gives the motor in a plate's terms, see `_from_nameplate`)."""
    path = Path(path)
    try:
        raw = yamlio.load_file(path)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read machine card: {yamlio.describe(exc)}") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: a machine card must be a mapping")
    flat: dict[str, Any] = {}
    plate: dict[str, Any] = {}
    for key, value in raw.items():
        if key == "nameplate":
            plate = _from_nameplate(str(path), value)
        elif key in _SECTIONS and isinstance(value, dict):
            flat.update(value)
        else:
            flat[key] = value
    known = {f.name: f for f in fields(MachineCard)}
    unknown = sorted(set(flat) - set(known), key=str)
    if unknown:
        raise ConfigError(
            f"{path}: unknown machine-card key(s) {unknown}; expected some of {sorted(known)}"
        )
    twice = sorted(set(plate) & set(flat), key=str)
    if twice and "nameplate" in raw:
        raise ConfigError(f"{path}: {twice} given beside the nameplate that sets them")
    kwargs: dict[str, Any] = dict(plate)
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


# ---- the rig: what a scenario's test bench adds to the motor and keeps when the motor is
# swapped (`--machine`): the load machine's inertia and friction, the inverter's switching
# and the sensors' resolution and noise.  The bus voltage and the sensors' full scales are
# sized to the motor and come with its card.
RIG_DRIVE_KEYS: tuple[str, ...] = (
    "pwm_hz",
    "deadtime_s",
    "device_drop_v",
    "current_adc_bits",
    "current_noise_a",
    "capture_bits",
    "dc_bus_adc_bits",
    "dc_bus_noise_v",
    "encoder_lines",
)
_RIG_SECTIONS = ("load", "inverter", "sensors")


@dataclass(frozen=True)
class Rig:
    """A test rig: the load coupled to the motor (inertia and friction added to the card's)
    and the drive's inverter and sensor settings (RIG_DRIVE_KEYS, replacing the card's)."""

    name: str
    load_inertia_kgm2: float = 0.0
    load_viscous_nms: float = 0.0
    drive: dict[str, Any] = field(default_factory=dict)  # RIG_DRIVE_KEYS -> value
    source: str = ""

    def on(self, card: MachineCard, src: str = "rig") -> MachineCard:
        """`card`'s motor on this rig."""
        import dataclasses

        return dataclasses.replace(
            card,
            inertia_kgm2=card.inertia_kgm2 + self.load_inertia_kgm2,
            viscous_nms=card.viscous_nms + self.load_viscous_nms,
            **self.drive,
        ).validate(src)

    def describe(self) -> str:
        d = self.drive
        return (
            f"rig {self.name}: load J {self.load_inertia_kgm2:.3g} kg m^2, load friction "
            f"{self.load_viscous_nms:.3g} N m s/rad, PWM {d['pwm_hz']:g} Hz, deadtime "
            f"{d['deadtime_s']:.3g} s, {d['current_adc_bits']}-bit current ADC "
            f"({d['current_noise_a']:g} A rms noise), encoder {d['encoder_lines']} lines"
        )


def rig_of_card(card: MachineCard) -> Rig:
    """The rig a scenario without `rig:` keeps when `--machine` swaps its motor: its card's
    inverter and sensor settings, and the card's inertia and friction as the load's (a card
    that is a motor on its dyno -- the shipped cards' `motor + dyno` inertia -- cannot say
    which part is the motor's; the swapped motor's own add to it)."""
    return Rig(
        name=f"of the card {card.name}",
        load_inertia_kgm2=card.inertia_kgm2,
        load_viscous_nms=card.viscous_nms,
        drive={k: getattr(card, k) for k in RIG_DRIVE_KEYS},
    )


def load_rig(path: str | Path) -> Rig:
    """A rig file: `name`, `load: {inertia_kgm2, viscous_nms}`, `inverter: {pwm_hz,
    deadtime_s, device_drop_v}`, `sensors: {...}` (RIG_DRIVE_KEYS; a key left out: the
    default card's value).  A bad file: one line naming the file and the key."""
    path = Path(path)
    src = str(path)
    try:
        raw = yamlio.load_file(path)
    except (OSError, yamlio.YAMLError) as exc:
        raise ConfigError(f"{src}: cannot read rig file: {yamlio.describe(exc)}") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: a rig file must be a mapping")
    refuse_unknown_keys(src, raw, ["name", *_RIG_SECTIONS], "the top level")
    load = raw.get("load") or {}
    if not isinstance(load, dict):
        raise ConfigError(f"{src}: 'load' must be a mapping of inertia_kgm2, viscous_nms")
    refuse_unknown_keys(src, load, ["inertia_kgm2", "viscous_nms"], "load")
    drive_raw: dict[str, Any] = {}
    for sec in ("inverter", "sensors"):
        part = raw.get(sec) or {}
        if not isinstance(part, dict):
            raise ConfigError(f"{src}: '{sec}' must be a mapping")
        drive_raw.update(part)
    refuse_unknown_keys(src, drive_raw, list(RIG_DRIVE_KEYS), "inverter/sensors")
    default = MachineCard()
    lim = ranges(MachineCard)
    drive: dict[str, Any] = {}
    for key in RIG_DRIVE_KEYS:
        value = drive_raw.get(key, getattr(default, key))
        if isinstance(getattr(default, key), int):
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"{src}: '{key}' must be an integer, got {value!r}")
            _require_range(src, key, value, *lim[key])
            drive[key] = value
        else:
            drive[key] = _require_range(src, key, value, *lim[key])
    return Rig(
        name=str(raw.get("name", path.stem)),
        load_inertia_kgm2=_require_range(
            src, "load.inertia_kgm2", load.get("inertia_kgm2", 0.0), 0.0, 1000.0
        ),
        load_viscous_nms=_require_range(
            src, "load.viscous_nms", load.get("viscous_nms", 0.0), 0.0, 1000.0
        ),
        drive=drive,
        source=src,
    )


@dataclass
class Profile:
    """Piecewise-linear time profile: breakpoints (t_s, value)."""

    t_s: list[float] = field(default_factory=lambda: [0.0])
    value: list[float] = field(default_factory=lambda: [0.0])
