"""Study specs: YAML -> validated `StudySpec` -> the list of tasks.

A study is variants x grid x draws.  Every task's inputs (its grid values, its random draw and
its plant seed) are a pure function of the spec and the task's own indices -- never of the
order tasks run in -- so a study gives the same table serially, on two local workers or on a
cluster, and a resumed study recomputes nothing.  See docs/study.md for the schema.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError
from fluxdrive.core.schema import check_value, markdown_table, param, specs
from fluxdrive.drive.control import ControllerConfig
from fluxdrive.drive.observers import ObserverConfig
from fluxdrive.drive.scenario import CONFIG_DIR, REPO_ROOT, machine_path, scenario_path

STUDY_DIR = CONFIG_DIR / "studies"

# scenario builders a spec may name (speed_rpm, load_pu and the variant are passed in)
BUILDERS = {
    "descent": "fluxdrive.experiments.beyond_common:descent",
    "sensorless": "fluxdrive.experiments.registry:sensorless",
    "encoder_run": "fluxdrive.experiments.registry:encoder_run",
}

# Uncertainty axes: name -> (per phase?, what it sets).  The observer and the controller
# believe the machine card's values (the datasheet, at 20 degC); these move the truth or
# the belief away from it.
PERTURBATIONS: dict[str, tuple[bool, str]] = {
    "r_hat_err": (False, "observer R^ = R_card (1 + x)"),
    "l_hat_err": (False, "observer L^ = L_card (1 + x)"),
    "lambda_hat_err": (False, "observer lambda^ = lambda_card (1 + x)"),
    "current_offset_pu": (True, "current-sensor offset per phase, x I_rated"),
    "current_gain_err": (True, "current-sensor gain per phase, 1 + x"),
    "current_noise_a": (False, "current-sensor noise RMS [A] (plant)"),
    "deadtime_s": (False, "inverter deadtime of the plant [s]"),
    "temperature_c": (
        False,
        "winding and magnet temperature [degC]: plant R (1 + 0.00393 dT), "
        "lambda (1 - 0.0012 dT), dT = T - 20; observer/controller keep "
        "the card's values",
    ),
}
PHASES = "abc"
OBSERVER_KEYS = {f.name for f in fields(ObserverConfig)} - {"variant", "extra"}
CONTROL_KEYS = {f.name for f in fields(ControllerConfig)} - {"position_source"}
DISTS = {"uniform": ("low", "high"), "normal": ("mean", "std"), "choice": ("values",)}
_TOP = {
    "name",
    "description",
    "seed",
    "scenario",
    "variants",
    "grid",
    "random",
    "draws",
    "rated_load_pu",
    "probability",
    "map",
}


@dataclass
class StudySpec:
    name: str
    source: str
    seed: int
    scenario: dict[str, Any]  # builder | file | bag (+ params); paths made absolute
    variants: dict[str, dict[str, Any]]
    grid: dict[str, list[Any]]
    random: dict[str, dict[str, Any]]
    draws: int
    description: str = ""
    rated_load_pu: float = 1.0
    probability: float = 0.95
    map_axes: tuple[str, str] = ("speed_rpm", "load_pu")
    raw: dict[str, Any] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        return "bag" if "bag" in self.scenario else "scenario"

    def random_columns(self) -> list[str]:
        cols = []
        for name in self.random:
            cols += [f"{name}_{p}" for p in PHASES] if PERTURBATIONS[name][0] else [name]
        return cols

    def tasks(self) -> list[dict[str, Any]]:
        """Every task's payload, in a fixed order (variant, grid point, draw)."""
        draws = [self.draw(d) for d in range(self.draws)]
        axes = list(self.grid)
        out = []
        for vname, vcfg in self.variants.items():
            for point in itertools.product(*(self.grid[a] for a in axes)):
                gv = dict(zip(axes, point, strict=True))
                for d, (seed, rv) in enumerate(draws):
                    tid = "|".join(
                        [vname] + [f"{a}={_fmt(v)}" for a, v in gv.items()] + [f"draw={d}"]
                    )
                    t = {
                        "task_id": tid,
                        "variant": vname,
                        "variant_cfg": dict(vcfg),
                        "grid": gv,
                        "draw": d,
                        "seed": seed,
                        "random": rv,
                        "scenario": self.scenario,
                    }
                    t["input_hash"] = input_hash(t)
                    out.append(t)
        return out

    def draw(self, d: int) -> tuple[int, dict[str, Any]]:
        """Draw d: the plant's noise seed and every random axis's value.  Derived from
        (spec seed, d) alone, and shared by every variant and grid point (common random
        numbers: variants are compared on the same machines)."""
        ss = np.random.SeedSequence(self.seed, spawn_key=(d,))
        seed = int(ss.generate_state(1, np.uint32)[0] & 0x7FFFFFFF)
        rng = np.random.default_rng(ss.spawn(1)[0])
        vals: dict[str, Any] = {}
        for name in sorted(self.random):  # fixed order: the spec's key order must not matter
            n = 3 if PERTURBATIONS[name][0] else 1
            x = [_sample(rng, self.random[name]) for _ in range(n)]
            vals[name] = x if n == 3 else x[0]
        return seed, vals


def input_hash(task: dict[str, Any]) -> str:
    """Hash of everything a task computes from: a resumed or extended study reuses a row only
    if its task's inputs are still the same."""
    keep = {k: v for k, v in task.items() if k not in ("task_id", "input_hash")}
    return hashlib.sha1(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _fmt(v: Any) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _sample(rng: np.random.Generator, d: dict[str, Any]) -> float:
    kind = d["dist"]
    if kind == "uniform":
        x = rng.uniform(d["low"], d["high"])
    elif kind == "normal":
        x = rng.normal(d["mean"], d["std"])
        x = min(max(x, d.get("clip_low", -math.inf)), d.get("clip_high", math.inf))
    else:
        x = d["values"][int(rng.integers(len(d["values"])))]
    return float(x)


def _err(src: str, msg: str) -> ConfigError:
    return ConfigError(f"{src}: {msg}")


MAX_TASKS = 1_000_000  # variants x grid points x draws: beyond this a spec is a typo


def _finite(src: str, key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _err(src, f"{key} must be a finite number, got {v!r}")
    return float(v)


@dataclass
class StudySettings:
    """A study spec's single-valued keys (the scenario, variants, grid, random axes and map
    have their own parsers); `load_spec` checks them here."""

    seed: int = param(
        0,
        unit="-",
        doc="every draw's random values and plant seed derive from (seed, draw index)",
        range=(0, 2**63 - 1),
        live=False,
    )
    draws: int = param(
        1,
        unit="-",
        doc="random draws (machines) per variant and grid point",
        range=(1, MAX_TASKS),
        live=False,
    )
    rated_load_pu: float = param(
        1.0,
        unit="pu",
        doc="the load of the maps' 'lowest speed' question",
        range=(1e-3, 100.0),
        live=False,
    )
    probability: float = param(
        0.95,
        unit="-",
        doc="the probability the lowest speed is held with",
        range=(1e-3, 0.999),
        live=False,
    )


DOC_PAGE = REPO_ROOT / "docs" / "study.md"  # its table of StudySettings


def docs_tables() -> dict[str, str]:
    """{block key: Markdown table} of the study page (`./fluxdrive docs params`)."""
    return {"study": markdown_table(StudySettings) + "\n"}


def study_settings(src: str, raw: dict[str, Any]) -> StudySettings:
    """The spec's single-valued keys, each checked by its field (absent: its default)."""
    kw = {}
    for name, s in specs(StudySettings).items():
        v = raw.get(name, StudySettings.__dataclass_fields__[name].default)
        check_value(s, v, f"{src}: '{name}'")
        kw[name] = s.kind(v)
    return StudySettings(**kw)


def _path_text(src: str, key: str, v: Any) -> str:
    if not isinstance(v, str) or not v or "\0" in v:
        raise _err(src, f"{key} must be a path, got {v!r}")
    return v


def load_spec(path: str | Path) -> StudySpec:
    """Load and validate a study spec; errors name the file and key."""
    p = Path(path)
    if not p.exists() and not p.suffix:
        p = STUDY_DIR / f"{p.name}.yaml"
    src = str(p)
    raw = _read_spec(src, p)
    st = study_settings(src, raw)
    draws = st.draws
    scen = _scenario(src, p.parent, raw.get("scenario"))
    vout = _variants(src, raw.get("variants"), scen)
    grid = _grid(src, raw.get("grid") or {}, scen)
    rnd = _random_axes(src, raw.get("random") or {}, grid, scen)
    for key in ("name", "description"):
        if not isinstance(raw.get(key, ""), str):
            raise _err(src, f"'{key}' must be a string, got {raw[key]!r}")
    axes = _map_axes(src, raw.get("map", {}) or {})
    n_tasks = len(vout) * draws * math.prod(len(v) for v in grid.values())
    if n_tasks > MAX_TASKS:
        raise _err(src, f"{n_tasks} tasks (variants x grid points x draws), more than {MAX_TASKS}")
    return StudySpec(
        name=str(raw.get("name", p.stem)),
        source=src,
        seed=st.seed,
        scenario=scen,
        variants=vout,
        grid=grid,
        random=rnd,
        draws=draws,
        description=str(raw.get("description", "")),
        rated_load_pu=st.rated_load_pu,
        probability=st.probability,
        map_axes=axes,
        raw=raw,
    )


def _read_spec(src: str, p: Path) -> dict[str, Any]:
    """The spec file's mapping, unknown top-level keys refused."""
    try:
        raw = yamlio.load_file(p)
    except (OSError, yamlio.YAMLError) as exc:
        raise _err(src, f"cannot read study spec: {yamlio.describe(exc)}") from exc
    if not isinstance(raw, dict):
        raise _err(src, "a study spec must be a mapping")
    bad = sorted(set(raw) - _TOP, key=str)
    if bad:
        raise _err(src, f"unknown key(s) {bad}; expected some of {sorted(_TOP)}")
    return raw


def _variants(src: str, variants: Any, scen: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """`variants`: name -> observer settings (checked against the observer's keys unless
    the study replays a bag, whose variants may be plugins)."""
    if not isinstance(variants, dict) or not variants:
        raise _err(
            src,
            "'variants' must be a mapping name -> observer settings "
            "(e.g. paper: {variant: paper, voltage_source: measured})",
        )
    vout: dict[str, dict[str, Any]] = {}
    for name, cfg in variants.items():
        if cfg is not None and not isinstance(cfg, dict):
            raise _err(src, f"variants.{name} must be a mapping of observer settings")
        cfg = dict(cfg or {})
        if not isinstance(cfg.get("variant", "paper"), str):
            raise _err(src, f"variants.{name}.variant must be a string")
        if scen.get("bag") is None:
            bad = sorted(set(cfg) - OBSERVER_KEYS - {"variant"}, key=str)
            if bad:
                raise _err(
                    src,
                    f"variants.{name}: unknown key(s) {bad}; expected 'variant' "
                    f"and observer settings {sorted(OBSERVER_KEYS)}",
                )
        vout[str(name)] = cfg
    return vout


def _grid(src: str, grid: Any, scen: dict[str, Any]) -> dict[str, list[float]]:
    """`grid`: axis -> the values swept (scalar axes only)."""
    if not isinstance(grid, dict):
        raise _err(src, "'grid' must be a mapping axis -> list of values")
    for a, vals in grid.items():
        if not isinstance(a, str):
            raise _err(src, f"grid: axis {a!r} must be a name")
        if not isinstance(vals, list) or not vals:
            raise _err(src, f"grid.{a} must be a non-empty list of values")
        _axis_kind(src, f"grid.{a}", a, scen)
        if a in PERTURBATIONS and PERTURBATIONS[a][0]:
            raise _err(
                src,
                f"grid.{a}: a per-phase axis can only be random (or set it in "
                f"the scenario's faults)",
            )
        for v in vals:
            _finite(src, f"grid.{a} values", v)
    return {a: [float(v) for v in vals] for a, vals in grid.items()}


def _random_axes(
    src: str, rnd: Any, grid: dict[str, list[float]], scen: dict[str, Any]
) -> dict[str, dict[str, Any]]:
    """`random`: perturbation axis -> distribution, none of them also a grid axis."""
    if not isinstance(rnd, dict):
        raise _err(src, "'random' must be a mapping axis -> distribution")
    for a, d in rnd.items():
        if not isinstance(a, str) or a not in PERTURBATIONS:
            raise _err(
                src, f"random.{a}: unknown random axis; expected one of {sorted(PERTURBATIONS)}"
            )
        if a in grid:
            raise _err(src, f"random.{a}: also a grid axis")
        _axis_kind(src, f"random.{a}", a, scen)
        _distribution(src, f"random.{a}", d)
    return rnd


def _distribution(src: str, key: str, d: Any) -> None:
    """{dist: uniform|normal|choice, ...} with the numbers its kind needs."""
    if not isinstance(d, dict) or not isinstance(d.get("dist"), str) or d["dist"] not in DISTS:
        raise _err(src, f"{key} must be {{dist: uniform|normal|choice, ...}}")
    need = DISTS[d["dist"]]
    miss = [k for k in need if k not in d]
    if miss:
        raise _err(src, f"{key}: dist {d['dist']} needs {list(need)}")
    bad = sorted(set(d) - set(need) - {"dist", "clip_low", "clip_high"}, key=str)
    if bad:
        raise _err(src, f"{key}: unknown key(s) {bad} for dist {d['dist']}")
    if d["dist"] == "choice":
        if not isinstance(d["values"], list) or not 1 <= len(d["values"]) <= 10_000:
            raise _err(src, f"{key}.values must be a list of 1..10000 numbers")
        for v in d["values"]:
            _finite(src, f"{key}.values", v)
        return
    for k in (*need, *(c for c in ("clip_low", "clip_high") if c in d)):
        _finite(src, f"{key}.{k}", d[k])
    if d["dist"] == "uniform" and d["low"] > d["high"]:
        raise _err(src, f"{key}: low {d['low']} is above high {d['high']}")
    if d["dist"] == "normal" and d["std"] < 0:
        raise _err(src, f"{key}.std must be >= 0, got {d['std']}")


def _map_axes(src: str, mp: Any) -> tuple[str, str]:
    """`map: {axes: [X, Y]}`: the two axes of the robustness map (default speed x load)."""
    axes = mp.get("axes", ["speed_rpm", "load_pu"]) if isinstance(mp, dict) else None
    if (
        not isinstance(axes, list)
        or len(axes) != 2
        or not all(isinstance(a, str) for a in axes)
        or (isinstance(mp, dict) and sorted(set(mp) - {"axes"}, key=str))
    ):
        raise _err(src, "'map' must be {axes: [X_AXIS, Y_AXIS]} (two axis names)")
    return (axes[0], axes[1])


def _scenario(src: str, base: Path, s: Any) -> dict[str, Any]:
    if not isinstance(s, dict):
        raise _err(
            src,
            "'scenario' must be a mapping with one of builder: NAME, file: SCENARIO, bag: BAG_DIR",
        )
    kinds = [k for k in ("builder", "file", "bag") if k in s]
    if len(kinds) != 1:
        raise _err(src, "'scenario' needs exactly one of builder, file, bag")
    out = dict(s)
    params = s.get("params", {}) or {}
    if not isinstance(params, dict):
        raise _err(src, "scenario.params must be a mapping")
    if not all(isinstance(k, str) for k in params):
        raise _err(src, "scenario.params keys must be names")
    out["params"] = params
    bad = sorted(
        set(s) - {"builder", "file", "bag", "params", "machine", "window_s", "encoder_offset_deg"},
        key=str,
    )
    if bad:
        raise _err(src, f"scenario: unknown key(s) {bad}")
    if "builder" in s:
        if not isinstance(s["builder"], str) or s["builder"] not in BUILDERS:
            raise _err(
                src, f"scenario.builder must be one of {sorted(BUILDERS)}, got {s['builder']!r}"
            )
    elif "file" in s:
        f = Path(_path_text(src, "scenario.file", s["file"]))
        cand = base / f
        try:
            out["file"] = str((cand if cand.exists() else scenario_path(str(f))).resolve())
        except ConfigError as exc:
            raise _err(src, f"scenario.file: {exc}") from exc
    else:
        b = Path(_path_text(src, "scenario.bag", s["bag"]))
        for cand in (base / b, REPO_ROOT / b, b):
            if cand.exists():
                out["bag"] = str(cand.resolve())
                break
        else:
            raise _err(src, f"scenario.bag: no bag at {b}")
    if "window_s" in s and s["window_s"] is not None:
        w = s["window_s"]
        if not isinstance(w, list) or len(w) != 2:
            raise _err(src, "scenario.window_s must be [start_s, end_s]")
        for x in w:
            _finite(src, "scenario.window_s", x)
    if "encoder_offset_deg" in s:
        _finite(src, "scenario.encoder_offset_deg", s["encoder_offset_deg"])
    if "machine" in s:  # a path relative to the spec, or a card name under config/machines
        m = base / _path_text(src, "scenario.machine", s["machine"])
        try:
            out["machine"] = str((m if m.exists() else machine_path(str(s["machine"]))).resolve())
        except ConfigError as exc:
            raise _err(src, f"scenario.machine: {exc}") from exc
    return out


def _axis_kind(src: str, where: str, name: str, scen: dict[str, Any]) -> str:
    """observer | control | perturbation | scenario; refuses what a replay cannot vary."""
    if name in OBSERVER_KEYS:
        return "observer"
    if name.startswith("control."):
        if name[8:] not in CONTROL_KEYS:
            raise _err(src, f"{where}: unknown controller setting '{name[8:]}'")
        kind = "control"
    elif name in PERTURBATIONS:
        kind = "perturbation"
    else:
        kind = "scenario"
    if "bag" in scen and not (
        kind == "perturbation" and name in ("r_hat_err", "l_hat_err", "lambda_hat_err")
    ):
        raise _err(
            src,
            f"{where}: a replay study (scenario.bag) can vary observer settings "
            f"and R^/L^/lambda^ errors only; '{name}' changes the recorded drive",
        )
    return kind


# scenario keys that may be a profile, [[t_s, value], ...]: a grid value for one of them is a
# level, so it scales the file's own profile (a load ramped in after the start stays ramped);
# a profile given as the grid value replaces it
PROFILE_KEYS = ("load_pu", "speed_pu", "speed_rpm")


def scenario_axis_value(raw: dict[str, Any], key: str, value: Any) -> tuple[Any, str]:
    """What a grid value of scenario key `key` sets in a scenario file `raw`, and the words
    for the report: a number for a key the file holds as a profile scales that profile so
    its largest magnitude is the value (the profile's shape and timing kept); anything
    else replaces the file's value (or sets the key the file leaves unset)."""
    base = raw.get(key)
    if key in PROFILE_KEYS and isinstance(value, (int, float)) and isinstance(base, list):
        peak = max((abs(float(v)) for _, v in base), default=0.0)
        if peak > 0.0:
            scaled = [[t, float(v) * float(value) / peak] for t, v in base]
            return scaled, (
                f"scales the scenario file's {key} profile {base} to peak at the axis value "
                f"(its shape and timing kept)"
            )
    if key in raw:
        return value, f"replaces the scenario file's {key} ({raw[key]})"
    return value, f"sets {key} (the scenario file leaves it unset)"


def axis_override_text(spec: StudySpec, name: str) -> str:
    """What grid axis `name` overrides, in the words the report uses."""
    kind = axis_kind(name)
    if kind == "observer":
        return "the observer setting of every variant"
    if kind == "control":
        return f"the controller setting {name[8:]}"
    if kind == "perturbation":
        return PERTURBATIONS[name][1]
    if "file" in spec.scenario:
        from fluxdrive.core import yamlio

        raw = yamlio.load_file(spec.scenario["file"]) or {}
        sample = spec.grid[name][0] if spec.grid.get(name) else 1.0
        return scenario_axis_value(raw, name, sample)[1]
    if "builder" in spec.scenario:
        return f"the builder {spec.scenario['builder']}'s {name}"
    return f"scenario key {name}"


def axis_kind(name: str) -> str:
    if name in OBSERVER_KEYS:
        return "observer"
    if name.startswith("control."):
        return "control"
    return "perturbation" if name in PERTURBATIONS else "scenario"
