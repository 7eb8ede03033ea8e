"""The non-ideal bench: a scenario's `bench:` entries, typed and validated.

Each entry switches one imperfection of a real test bench on (absent = ideal, so
`bench: {}` is the ideal bench).  The numbers and where they come from are written next to
them in the scenario files and in docs/engine.md ("Non-ideal bench").

  voltage_capture          comparator threshold, edge time, propagation delays (rise/fall),
                           minimum registered pulse, timer resolution and jitter
  current_sample_skew_s    per-phase sampling instant (a, b, c) before the carrier valley
  observer_model           every observer's R^, L^, lambda^ relative to the machine card
  thermal                  winding temperature from I^2 R (card: thermal resistance, time
                           constant, tempco), so R drifts while R^ does not (a card without
                           a thermal model keeps the winding at its start temperature)
  spatial_saturation_h6_pu 6th order of |lambda_pm| per unit at rated current, growing with
                           (|i|/I_rated)^2, split evenly into the 5th and 7th (a hexagon of
                           pure radius under load)
  spatial_saturation_h5_pu the 5th and 7th magnet-flux harmonics of that saturation, each on
  spatial_saturation_h7_pu its own (signed; added to the even split): an unequal pair also
                           moves the flux angle, by (h7 - h5) sin 6 theta
  inductance_saturation    L_d, L_q falling with i_d, i_q, with cross-saturation (an algebraic
                           flux map; the plant then integrates the stator flux)
  phase_asymmetry          per-phase resistance and inductance multipliers (a, b, c)
  current_sensor_gain      per-phase current-sensor gains (a, b, c), on top of the
                           scenario's faults
  output_capacitance_f     device output capacitance: the deadtime commutation takes
                           2 C_oss V_dc/|i| (current-dependent deadtime voltage error)
  switching_noise          current-sample disturbance from PWM edges just before the sample
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from fluxdrive.core.machine import ConfigError, MachineCard, refuse_unknown_keys
from fluxdrive.core.schema import Limit, Spec, check_value, param, ranges, specs


@dataclass(frozen=True)
class VoltageCapture:
    """Line-voltage capture through a comparator and an isolating link into a capture timer.

    A switching edge of the line voltage is a ramp over `edge_time_s` (0 -> 100 % of the bus);
    the comparator toggles where the ramp crosses `threshold_pu` (of the card's bus, so a
    bench file works on any card), and the timer latches that
    instant `delay_rise_s` (pulse start) or `delay_fall_s` (pulse end) later, plus Gaussian
    jitter, floored to the timer tick.  A pulse whose ramp never reaches the threshold, or
    whose registered width is below `min_pulse_s`, is not seen at all."""

    threshold_pu: float = param(
        0.0,
        unit="pu",
        doc="comparator threshold, per unit of the card's DC bus",
        range=(0.0, 0.99),
        live=False,
    )
    edge_time_s: float = param(
        0.0, unit="s", doc="switching edge: 0 -> 100 % of the bus", range=(0.0, 1e-5), live=False
    )
    delay_rise_s: float = param(
        0.0, unit="s", doc="link delay of a pulse start", range=(0.0, 1e-5), live=False
    )
    delay_fall_s: float = param(
        0.0, unit="s", doc="link delay of a pulse end", range=(0.0, 1e-5), live=False
    )
    min_pulse_s: float = param(
        0.0,
        unit="s",
        doc="shortest registered pulse (a shorter one is not seen)",
        range=(0.0, 1e-5),
        live=False,
    )
    jitter_s: float = param(
        0.0, unit="s", doc="rms Gaussian jitter of a latched edge", range=(0.0, 1e-6), live=False
    )
    resolution_bits: int | None = param(
        None,
        unit="bits",
        doc="capture timer resolution over the PWM period",
        range=(4, 30),
        card_default="capture_bits",
        live=False,
        kind=int,
    )

    def width_error_s(self) -> float:
        """Registered minus true width of a full-height pulse: the threshold crossing moves
        the start by (v_th - 1/2) t_edge and the end by the opposite, the link adds
        t_fall - t_rise."""
        slew = (1.0 - 2.0 * self.threshold_pu) * self.edge_time_s
        return slew + self.delay_fall_s - self.delay_rise_s


@dataclass(frozen=True)
class ObserverModel:
    """Observer model parameters relative to the machine card (1.0 = exact)."""

    r_pu: float = param(
        1.0, unit="pu", doc="observers' R^ per unit of the card's", range=(0.0, 10.0), live=False
    )
    l_pu: float = param(
        1.0, unit="pu", doc="observers' L^ per unit of the card's", range=(0.01, 10.0), live=False
    )
    lambda_pu: float = param(
        1.0,
        unit="pu",
        doc="observers' lambda^ per unit of the card's",
        range=(0.01, 10.0),
        live=False,
    )


@dataclass(frozen=True)
class Thermal:
    """Winding temperature: ambient and the temperature the run starts at [deg C]."""

    ambient_c: float = param(
        25.0, unit="degC", doc="ambient temperature", range=(-60.0, 200.0), live=False
    )
    initial_winding_c: float = param(
        25.0,
        unit="degC",
        doc="winding temperature at the start of the run",
        range=(-60.0, 250.0),
        live=False,
    )


# exponents of the flux map: 0..10; the pu gains 0..10 (10: the current 11x the linear one
# at the rated-current flux, far beyond any real machine)
_FLUX_MAP_RANGE = (0.0, 10.0)


@dataclass(frozen=True)
class InductanceSaturation:
    """Saturation and cross-saturation as an algebraic flux map (Hinkkanen et al., IEEE Trans.
    Ind. Appl. 53(3), 2017), with the armature d-flux psi_d - lambda_pm for psi_d.  In flux
    per unit of psi_b = L I_rated (x = (psi_d - lambda)/psi_b, y = psi_q/psi_b), current per
    unit of I_rated:
        i_d = x (1 + d_pu |x|^S + cross_pu/(V+2) |x|^U |y|^(V+2))
        i_q = y (1 + q_pu |y|^T + cross_pu/(U+2) |x|^(U+2) |y|^V)
    (S, T, U, V = the exponents), the gradient of one magnetic energy, so the incremental
    inductances are reciprocal.  All pu zero: the linear machine."""

    d_pu: float = param(
        0.0, unit="pu", doc="d-axis saturation gain", range=_FLUX_MAP_RANGE, live=False
    )
    d_exponent: float = param(
        2.0, unit="-", doc="d-axis saturation exponent S", range=_FLUX_MAP_RANGE, live=False
    )
    q_pu: float = param(
        0.0, unit="pu", doc="q-axis saturation gain", range=_FLUX_MAP_RANGE, live=False
    )
    q_exponent: float = param(
        2.0, unit="-", doc="q-axis saturation exponent T", range=_FLUX_MAP_RANGE, live=False
    )
    cross_pu: float = param(
        0.0, unit="pu", doc="cross-saturation gain", range=_FLUX_MAP_RANGE, live=False
    )
    cross_exponent_d: float = param(
        1.0,
        unit="-",
        doc="cross-saturation exponent U (of the d flux)",
        range=_FLUX_MAP_RANGE,
        live=False,
    )
    cross_exponent_q: float = param(
        0.0,
        unit="-",
        doc="cross-saturation exponent V (of the q flux)",
        range=_FLUX_MAP_RANGE,
        live=False,
    )

    @property
    def on(self) -> bool:
        return self.d_pu != 0.0 or self.q_pu != 0.0 or self.cross_pu != 0.0


@dataclass(frozen=True)
class PhaseAsymmetry:
    """Per-phase winding resistance and (synchronous) inductance relative to the card."""

    resistance_pu: tuple[float, float, float] = param(
        (1.0, 1.0, 1.0),
        unit="pu",
        doc="winding resistance of phases a, b, c per unit of the card's",
        range=(0.1, 10.0),
        live=False,
        kind=float,
    )
    inductance_pu: tuple[float, float, float] = param(
        (1.0, 1.0, 1.0),
        unit="pu",
        doc="inductance of phases a, b, c per unit of the card's",
        range=(0.1, 10.0),
        live=False,
        kind=float,
    )


@dataclass(frozen=True)
class SwitchingNoise:
    """A PWM voltage edge rings into the current sensors: a sample taken dt after an edge
    (dt < window_s) gets Gaussian noise of rms ringing_a exp(-dt/decay_s) per edge."""

    ringing_a: float = param(
        0.0,
        unit="A",
        doc="rms current-sample noise of an edge just before the sample",
        range=(0.0, 100.0),
        live=False,
    )
    window_s: float = param(
        0.0,
        unit="s",
        doc="an edge this close before the sample disturbs it",
        range=(0.0, 1e-4),
        live=False,
    )
    decay_s: float = param(
        1e-6, unit="s", doc="decay time of the ringing", range=(1e-9, 1e-4), live=False
    )


@dataclass(frozen=True)
class BenchConfig:
    voltage_capture: VoltageCapture | None = None
    current_sample_skew_s: tuple[float, float, float] | None = param(
        None,
        unit="s",
        doc="per-phase sampling instant (a, b, c) before the carrier valley; unset: none",
        range=(0.0, 1e-3),
        limit=Limit(
            "at most a quarter of the PWM period", lambda card, decimation: (None, 0.25 * card.ts_s)
        ),
        none_is_zero=True,
        live=False,
        kind=float,
    )
    observer_model: ObserverModel | None = None
    thermal: Thermal | None = None
    spatial_saturation_h6_pu: float = param(
        0.0,
        unit="pu",
        doc="6th order of |lambda_pm| per unit at rated current, growing with (|i|/I_rated)^2, "
        "split evenly into the 5th and 7th magnet-flux harmonics (a hexagon of pure radius)",
        range=(0.0, 0.3),
        live=False,
    )
    spatial_saturation_h5_pu: float = param(
        0.0,
        unit="pu",
        doc="5th magnet-flux harmonic (e^{-j5 theta}) per unit of lambda at rated current, "
        "growing with (|i|/I_rated)^2; added to half of spatial_saturation_h6_pu",
        range=(-0.3, 0.3),
        live=False,
    )
    spatial_saturation_h7_pu: float = param(
        0.0,
        unit="pu",
        doc="7th magnet-flux harmonic (e^{j7 theta}) per unit of lambda at rated current, "
        "growing with (|i|/I_rated)^2; added to half of spatial_saturation_h6_pu",
        range=(-0.3, 0.3),
        live=False,
    )
    inductance_saturation: InductanceSaturation | None = None
    phase_asymmetry: PhaseAsymmetry | None = None
    current_sensor_gain: tuple[float, float, float] | None = param(
        None,
        unit="-",
        doc="per-phase current-sensor gains (a, b, c); unset: 1",
        range=(0.5, 2.0),
        none_is_zero=True,
        live=False,
        kind=float,
    )
    output_capacitance_f: float = param(
        0.0,
        unit="F",
        doc="device output capacitance: the deadtime commutation takes 2 C_oss V_dc/|i|",
        range=(0.0, 1e-6),
        live=False,
    )
    switching_noise: SwitchingNoise | None = None

    @property
    def ideal(self) -> bool:
        return self == BenchConfig()

    def spatial_saturation_h5_h7(self) -> tuple[float, float]:
        """The spatial saturation's 5th and 7th magnet-flux harmonics at rated current [pu]:
        half of the 6th order each (pure radius) plus the separate 5th and 7th."""
        half = 0.5 * self.spatial_saturation_h6_pu
        return half + self.spatial_saturation_h5_pu, half + self.spatial_saturation_h7_pu

    def apply_observer_model(self, cfg, card: MachineCard):
        """`cfg` (an ObserverConfig) with R^, L^, lambda^ set from the card times the bench's
        model errors, where the observer does not set them itself."""
        om = self.observer_model
        if om is None:
            return cfg
        kw = {}
        if cfg.r_hat_ohm is None:
            kw["r_hat_ohm"] = card.resistance_ohm * om.r_pu
        if cfg.l_hat_h is None:
            kw["l_hat_h"] = card.inductance_h * om.l_pu
        if cfg.lambda_hat_vs is None:
            kw["lambda_hat_vs"] = card.flux_linkage_vs * om.lambda_pu
        return replace(cfg, **kw) if kw else cfg

    def to_raw(self) -> dict[str, Any]:
        """The `bench:` mapping that `parse_bench` turns back into this config."""
        from dataclasses import asdict

        raw: dict[str, Any] = {}
        if self.voltage_capture is not None:
            raw["voltage_capture"] = {
                k: v for k, v in asdict(self.voltage_capture).items() if v is not None
            }
        if self.current_sample_skew_s is not None:
            raw["current_sample_skew_s"] = [float(x) for x in self.current_sample_skew_s]
        if self.observer_model is not None:
            raw["observer_model"] = asdict(self.observer_model)
        if self.thermal is not None:
            raw["thermal"] = asdict(self.thermal)
        for key in (
            "spatial_saturation_h6_pu",
            "spatial_saturation_h5_pu",
            "spatial_saturation_h7_pu",
        ):
            if getattr(self, key) != 0.0:
                raw[key] = float(getattr(self, key))
        for name in ("inductance_saturation", "phase_asymmetry", "switching_noise"):
            block = getattr(self, name)
            if block is not None:
                raw[name] = {
                    k: [float(x) for x in v] if isinstance(v, tuple) else v
                    for k, v in asdict(block).items()
                }
        if self.current_sensor_gain is not None:
            raw["current_sensor_gain"] = [float(x) for x in self.current_sensor_gain]
        if self.output_capacitance_f != 0.0:
            raw["output_capacitance_f"] = float(self.output_capacitance_f)
        return raw


def _num(src: str, key: str, v: Any, lo: float, hi: float) -> float:
    if (
        isinstance(v, bool)
        or not isinstance(v, (int, float))
        or not math.isfinite(float(v))
        or not (lo <= float(v) <= hi)
    ):
        raise ConfigError(f"{src}: 'bench.{key}' must be a number in [{lo}, {hi}], got {v!r}")
    return float(v)


def _triple(
    src: str, key: str, v: Any, lo: float, hi: float, unit: str
) -> tuple[float, float, float]:
    if not isinstance(v, list) or len(v) != 3:
        raise ConfigError(
            f"{src}: 'bench.{key}' must be a list of 3 numbers (phases a, b, c) [{unit}]"
        )
    a, b, c = (_num(src, key, x, lo, hi) for x in v)
    return (a, b, c)


def _value(src: str, key: str, spec: Spec, v: Any, lo: float, hi: float, phases: bool) -> Any:
    """One entry checked against its schema (`lo`, `hi`: its range on the card)."""
    if phases:
        return _triple(src, key, v, lo, hi, spec.unit)
    if spec.kind is int:
        check_value(replace(spec, lo=lo, hi=hi), v, f"{src}: 'bench.{key}'")
        return int(v)
    return _num(src, key, v, lo, hi)


def _section(src: str, key: str, cls, data: Any):
    if not isinstance(data, dict):
        raise ConfigError(f"{src}: 'bench.{key}' must be a mapping")
    refuse_unknown_keys(src, data, [f.name for f in fields(cls)], f"bench.{key}")
    table, rng = specs(cls), ranges(cls)
    kw: dict[str, Any] = {}
    for k, v in data.items():
        if v is None and table[k].optional:
            continue
        kw[k] = _value(src, f"{key}.{k}", table[k], v, *rng[k], per_phase(cls, k))
    return cls(**kw)


BENCH_KEYS = (
    "voltage_capture",
    "current_sample_skew_s",
    "observer_model",
    "thermal",
    "spatial_saturation_h6_pu",
    "spatial_saturation_h5_pu",
    "spatial_saturation_h7_pu",
    "inductance_saturation",
    "phase_asymmetry",
    "current_sensor_gain",
    "output_capacitance_f",
    "switching_noise",
)


# the sub-blocks of `bench:`, each a mapping of its own fields
SECTIONS: dict[str, type] = {
    "voltage_capture": VoltageCapture,
    "observer_model": ObserverModel,
    "thermal": Thermal,
    "inductance_saturation": InductanceSaturation,
    "phase_asymmetry": PhaseAsymmetry,
    "switching_noise": SwitchingNoise,
}


def per_phase(cls, name: str) -> bool:
    """A field given as [a, b, c] (its annotation says tuple)."""
    return "tuple[" in str(next(f.type for f in fields(cls) if f.name == name))


def parse_bench(src: str, raw: Any, card: MachineCard) -> BenchConfig:
    """Validate a scenario's `bench:` mapping (None/absent: the ideal bench)."""
    if raw is None:
        return BenchConfig()
    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: 'bench' must be a mapping of effects ({', '.join(BENCH_KEYS)})")
    refuse_unknown_keys(src, raw, list(BENCH_KEYS), "bench")
    kw: dict[str, Any] = {}
    for key, cls in SECTIONS.items():
        if raw.get(key) is not None:
            # `thermal: true`: the defaults (on a card without a thermal model,
            # thermal_resistance_k_per_w or thermal_time_constant_s 0, the winding stays at
            # the start temperature)
            data = {} if key == "thermal" and raw[key] is True else raw[key]
            kw[key] = _section(src, key, cls, data)
    rng = ranges(BenchConfig, card)  # the sample skew: at most a quarter of the PWM period
    for key, spec in specs(BenchConfig).items():
        if raw.get(key) is not None:
            kw[key] = _value(src, key, spec, raw[key], *rng[key], per_phase(BenchConfig, key))
    return BenchConfig(**kw)
