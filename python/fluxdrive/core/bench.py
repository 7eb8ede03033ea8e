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
                           (|i|/I_rated)^2 (hexagonal flux locus under load)
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


@dataclass(frozen=True)
class VoltageCapture:
    """Line-voltage capture through a comparator and an isolating link into a capture timer.

    A switching edge of the line voltage is a ramp over `edge_time_s` (0 -> 100 % of the bus);
    the comparator toggles where the ramp crosses `threshold_pu` (of the card's bus, so a
    bench file works on any card), and the timer latches that
    instant `delay_rise_s` (pulse start) or `delay_fall_s` (pulse end) later, plus Gaussian
    jitter, floored to the timer tick.  A pulse whose ramp never reaches the threshold, or
    whose registered width is below `min_pulse_s`, is not seen at all."""

    threshold_pu: float = 0.0
    edge_time_s: float = 0.0
    delay_rise_s: float = 0.0
    delay_fall_s: float = 0.0
    min_pulse_s: float = 0.0
    jitter_s: float = 0.0
    resolution_bits: int | None = None  # None: the machine card's capture_bits

    def width_error_s(self) -> float:
        """Registered minus true width of a full-height pulse: the threshold crossing moves
        the start by (v_th - 1/2) t_edge and the end by the opposite, the link adds
        t_fall - t_rise."""
        slew = (1.0 - 2.0 * self.threshold_pu) * self.edge_time_s
        return slew + self.delay_fall_s - self.delay_rise_s


@dataclass(frozen=True)
class ObserverModel:
    """Observer model parameters relative to the machine card (1.0 = exact)."""

    r_pu: float = 1.0
    l_pu: float = 1.0
    lambda_pu: float = 1.0


@dataclass(frozen=True)
class Thermal:
    """Winding temperature: ambient and the temperature the run starts at [deg C]."""

    ambient_c: float = 25.0
    initial_winding_c: float = 25.0


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

    d_pu: float = 0.0
    d_exponent: float = 2.0
    q_pu: float = 0.0
    q_exponent: float = 2.0
    cross_pu: float = 0.0
    cross_exponent_d: float = 1.0
    cross_exponent_q: float = 0.0

    @property
    def on(self) -> bool:
        return self.d_pu != 0.0 or self.q_pu != 0.0 or self.cross_pu != 0.0


@dataclass(frozen=True)
class PhaseAsymmetry:
    """Per-phase winding resistance and (synchronous) inductance relative to the card."""

    resistance_pu: tuple[float, float, float] = (1.0, 1.0, 1.0)
    inductance_pu: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class SwitchingNoise:
    """A PWM voltage edge rings into the current sensors: a sample taken dt after an edge
    (dt < window_s) gets Gaussian noise of rms ringing_a exp(-dt/decay_s) per edge."""

    ringing_a: float = 0.0
    window_s: float = 0.0
    decay_s: float = 1e-6


@dataclass(frozen=True)
class BenchConfig:
    voltage_capture: VoltageCapture | None = None
    current_sample_skew_s: tuple[float, float, float] | None = None
    observer_model: ObserverModel | None = None
    thermal: Thermal | None = None
    spatial_saturation_h6_pu: float = 0.0
    inductance_saturation: InductanceSaturation | None = None
    phase_asymmetry: PhaseAsymmetry | None = None
    current_sensor_gain: tuple[float, float, float] | None = None
    output_capacitance_f: float = 0.0
    switching_noise: SwitchingNoise | None = None

    @property
    def ideal(self) -> bool:
        return self == BenchConfig()

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
        if self.spatial_saturation_h6_pu != 0.0:
            raw["spatial_saturation_h6_pu"] = float(self.spatial_saturation_h6_pu)
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


def _triple(src: str, key: str, v: Any, lo: float, hi: float) -> tuple[float, float, float]:
    if not isinstance(v, list) or len(v) != 3:
        raise ConfigError(f"{src}: 'bench.{key}' must be a list of 3 numbers (phases a, b, c)")
    a, b, c = (_num(src, key, x, lo, hi) for x in v)
    return (a, b, c)


def _section(src: str, key: str, cls, data: Any, ranges: dict[str, tuple[float, float]]):
    if not isinstance(data, dict):
        raise ConfigError(f"{src}: 'bench.{key}' must be a mapping")
    refuse_unknown_keys(src, data, [f.name for f in fields(cls)], f"bench.{key}")
    kw: dict[str, Any] = {}
    for k, v in data.items():
        lo, hi = ranges[k]
        if isinstance(getattr(cls(), k), tuple):  # per-phase values
            kw[k] = _triple(src, f"{key}.{k}", v, lo, hi)
        elif k == "resolution_bits":
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ConfigError(
                    f"{src}: 'bench.{key}.{k}' must be an integer in "
                    f"[{int(lo)}, {int(hi)}], got {v!r}"
                )
            kw[k] = v
        else:
            kw[k] = _num(src, f"{key}.{k}", v, lo, hi)
    return cls(**kw)


_CAPTURE_RANGES = {
    "threshold_pu": (0.0, 0.99),
    "edge_time_s": (0.0, 1e-5),
    "delay_rise_s": (0.0, 1e-5),
    "delay_fall_s": (0.0, 1e-5),
    "min_pulse_s": (0.0, 1e-5),
    "jitter_s": (0.0, 1e-6),
    "resolution_bits": (4, 30),
}
_MODEL_RANGES = {"r_pu": (0.0, 10.0), "l_pu": (0.01, 10.0), "lambda_pu": (0.01, 10.0)}
_THERMAL_RANGES = {"ambient_c": (-60.0, 200.0), "initial_winding_c": (-60.0, 250.0)}
# exponents of the flux map: 0..10; the pu gains 0..10 (10: the current 11x the linear one
# at the rated-current flux, far beyond any real machine)
_SATURATION_RANGES = {
    "d_pu": (0.0, 10.0),
    "d_exponent": (0.0, 10.0),
    "q_pu": (0.0, 10.0),
    "q_exponent": (0.0, 10.0),
    "cross_pu": (0.0, 10.0),
    "cross_exponent_d": (0.0, 10.0),
    "cross_exponent_q": (0.0, 10.0),
}
_ASYMMETRY_RANGES = {"resistance_pu": (0.1, 10.0), "inductance_pu": (0.1, 10.0)}
_SWITCHING_NOISE_RANGES = {
    "ringing_a": (0.0, 100.0),
    "window_s": (0.0, 1e-4),
    "decay_s": (1e-9, 1e-4),
}
_SENSOR_GAIN_RANGE = (0.5, 2.0)
_OUTPUT_CAPACITANCE_RANGE_F = (0.0, 1e-6)
BENCH_KEYS = (
    "voltage_capture",
    "current_sample_skew_s",
    "observer_model",
    "thermal",
    "spatial_saturation_h6_pu",
    "inductance_saturation",
    "phase_asymmetry",
    "current_sensor_gain",
    "output_capacitance_f",
    "switching_noise",
)


def parse_bench(src: str, raw: Any, card: MachineCard) -> BenchConfig:
    """Validate a scenario's `bench:` mapping (None/absent: the ideal bench)."""
    if raw is None:
        return BenchConfig()
    if not isinstance(raw, dict):
        raise ConfigError(f"{src}: 'bench' must be a mapping of effects ({', '.join(BENCH_KEYS)})")
    refuse_unknown_keys(src, raw, list(BENCH_KEYS), "bench")
    kw: dict[str, Any] = {}
    if raw.get("voltage_capture") is not None:
        cap = _section(
            src, "voltage_capture", VoltageCapture, raw["voltage_capture"], _CAPTURE_RANGES
        )
        kw["voltage_capture"] = cap
    if raw.get("current_sample_skew_s") is not None:
        v = raw["current_sample_skew_s"]
        if not isinstance(v, list) or len(v) != 3:
            raise ConfigError(
                f"{src}: 'bench.current_sample_skew_s' must be a list of 3 "
                f"numbers (phases a, b, c) [s]"
            )
        kw["current_sample_skew_s"] = _triple(
            src, "current_sample_skew_s", v, 0.0, 0.25 * card.ts_s
        )
    if raw.get("observer_model") is not None:
        kw["observer_model"] = _section(
            src, "observer_model", ObserverModel, raw["observer_model"], _MODEL_RANGES
        )
    if raw.get("thermal") is not None:
        th = raw["thermal"]
        th = {} if th is True else th
        # on a card without a thermal model (thermal_resistance_k_per_w or
        # thermal_time_constant_s 0) the winding stays at the start temperature
        kw["thermal"] = _section(src, "thermal", Thermal, th, _THERMAL_RANGES)
    if raw.get("spatial_saturation_h6_pu") is not None:
        kw["spatial_saturation_h6_pu"] = _num(
            src, "spatial_saturation_h6_pu", raw["spatial_saturation_h6_pu"], 0.0, 0.3
        )
    kw.update(_parse_circuit_effects(src, raw))
    return BenchConfig(**kw)


def _parse_circuit_effects(src: str, raw: dict) -> dict[str, Any]:
    """The machine and inverter effects: saturation, asymmetry, sensor gains, C_oss, ringing."""
    kw: dict[str, Any] = {}
    blocks = (
        ("inductance_saturation", InductanceSaturation, _SATURATION_RANGES),
        ("phase_asymmetry", PhaseAsymmetry, _ASYMMETRY_RANGES),
        ("switching_noise", SwitchingNoise, _SWITCHING_NOISE_RANGES),
    )
    for key, cls, ranges in blocks:
        if raw.get(key) is not None:
            kw[key] = _section(src, key, cls, raw[key], ranges)
    if raw.get("current_sensor_gain") is not None:
        kw["current_sensor_gain"] = _triple(
            src, "current_sensor_gain", raw["current_sensor_gain"], *_SENSOR_GAIN_RANGE
        )
    if raw.get("output_capacitance_f") is not None:
        kw["output_capacitance_f"] = _num(
            src, "output_capacitance_f", raw["output_capacitance_f"], *_OUTPUT_CAPACITANCE_RANGE_F
        )
    return kw
