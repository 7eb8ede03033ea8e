"""What the experiments share: scenario builders (`build`, `sensorless`, `encoder_run`), the card
values predictions use (`cv`), the run context (`Ctx`: the one parallel runner, figures), the
graph-runner hook and `claim` for rows beyond the paper.  The experiment modules (paper, fronts,
beyond) import this, and registry imports them: no import cycle."""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from fluxdrive.analysis.metrics import compute
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.plant import deadtime_volt_second_loss
from fluxdrive.drive.scenario import CONFIG_DIR, Scenario, load_scenario, scenario_path

DEFAULT_MACHINE = CONFIG_DIR / "machines" / "default_spm.yaml"

# flux_*: the flux observer that drives (paper_robust: the literal one loses lock, see the
# paper_robust experiment); paper_*: the paper's observer exactly as written, in shadow
OBS4 = {
    "flux_measured": {"variant": "paper_robust", "voltage_source": "measured"},
    "flux_commanded": {"variant": "paper_robust", "voltage_source": "commanded"},
    "emf_measured": {"variant": "emf", "voltage_source": "measured"},
    "emf_commanded": {"variant": "emf", "voltage_source": "commanded"},
}
LITERAL = {
    "paper_measured": {"variant": "paper", "voltage_source": "measured"},
    "paper_commanded": {"variant": "paper", "voltage_source": "commanded"},
}
OBS6 = {**OBS4, **LITERAL}


# ---------------------------------------------------------------- scenario building
_SCEN_DIR: Path | None = None
# `experiment --machine CARD`: the card every scenario of the run uses (None: the scenarios')
_MACHINE: dict[str, str | None] = {"path": None}


def _scen_dir() -> Path:
    global _SCEN_DIR
    if _SCEN_DIR is None:
        _SCEN_DIR = Path(tempfile.mkdtemp(prefix="fluxdrive-exp-"))
    return _SCEN_DIR


def build(machine_kw: dict | None = None, base: str | None = None, **raw) -> Scenario:
    """A scenario from keyword keys (the YAML schema), optionally over a named scenario
    file; `machine_kw` replaces machine-card fields (e.g. inertia_kgm2)."""
    swap = _MACHINE["path"]
    if base is not None:
        sc = load_scenario(scenario_path(base), machine=swap, overrides=raw or None)
    else:
        # the experiments give speeds in rpm of the default card; `experiment --machine`
        # runs every scenario on that card at the same per-unit speeds (load_scenario)
        raw.setdefault("machine", str(DEFAULT_MACHINE))
        d = _scen_dir()
        p = d / f"s{os.getpid()}_{len(list(d.iterdir()))}.yaml"
        p.write_text(yaml.safe_dump(raw))
        sc = load_scenario(p, machine=swap)
    if machine_kw:
        sc.machine = dataclasses.replace(sc.machine, **machine_kw).validate()
    return sc


def sensorless(
    speed_rpm: float,
    load_pu: float,
    *,
    driving: str = "flux_measured",
    observers: dict | None = None,
    ramp_pu_s: float = 0.19,
    settle_s: float = 0.5,
    window_s: float = 1.5,
    seed: int = 1,
    control: dict | None = None,
    machine_kw: dict | None = None,
    name: str = "exp",
    **extra,
) -> Scenario:
    """Sensorless start (align -> I-f -> handover at up to 40 rpm), then the speed, then a
    slow brake-load ramp (the paper's hysteresis dyno), then a steady window."""
    obs = dict(observers or {driving: OBS6.get(driving, {"variant": "paper"})})
    # handover on the filtered agreement (2 Hz): the per-sample check is reset by the unloaded
    # rotor's swing about the I-f vector and, on the non-ideal bench, delays the handover by
    # up to 1.5 s (into the steady window at no load: the fig13 experiment)
    ctrl = {
        "if_current_pu": 0.6,
        "handover_rpm": 35.0 if speed_rpm < 40 else 40.0,
        "handback_rpm": min(20.0, 0.5 * speed_rpm),
        "handover_agree_lpf_hz": 2.0,
    }
    ctrl.update(control or {})
    if speed_rpm < 40.0:
        speed = [[0.0, 40.0], [0.8, 40.0], [1.3, speed_rpm]]
        t_load = 1.8
    else:
        speed = [[0.0, speed_rpm]]
        t_load = 1.0 + speed_rpm / 300.0
    ramp = max(load_pu / ramp_pu_s, 0.01) if load_pu > 0 else 0.0
    t_end_ramp = t_load + ramp
    w0 = t_end_ramp + settle_s
    dur = w0 + window_s
    load = [[0.0, 0.0], [t_load, 0.0], [t_end_ramp, load_pu]] if load_pu > 0 else 0.0
    return build(
        machine_kw=machine_kw,
        name=name,
        duration_s=round(dur, 4),
        seed=seed,
        speed_rpm=speed,
        load_type="brake",
        load_pu=load,
        steady_window_s=[round(w0, 4), round(dur, 4)],
        driving=driving,
        control=ctrl,
        observers=obs,
        **extra,
    )


def encoder_run(
    speed_rpm: float,
    load_pu: float,
    *,
    observers: dict | None = None,
    ramp_s: float = 3.0,
    settle_s: float = 0.7,
    window_s: float = 1.5,
    seed: int = 1,
    control: dict | None = None,
    machine_kw: dict | None = None,
    name: str = "exp",
    **extra,
) -> Scenario:
    """Encoder-driven run (observers in shadow): speed, brake load ramp, steady window."""
    t_load = 0.3
    t1 = t_load + (ramp_s if load_pu > 0 else 0.0)
    w0 = t1 + settle_s
    dur = w0 + window_s
    load = [[0.0, 0.0], [t_load, 0.0], [t1, load_pu]] if load_pu > 0 else 0.0
    return build(
        machine_kw=machine_kw,
        name=name,
        duration_s=round(dur, 4),
        seed=seed,
        speed_rpm=speed_rpm,
        load_type="brake",
        load_pu=load,
        steady_window_s=[round(w0, 4), round(dur, 4)],
        driving="encoder",
        control=control or {},
        observers=observers or dict(OBS4),
        **extra,
    )


# ---------------------------------------------------------------- machine values
@dataclasses.dataclass(frozen=True)
class CardValues:
    """The machine values the predictions use, taken from the card the experiment's runs use
    (never copied here: change the card, or run `experiment --machine`, and they follow)."""

    r: float  # stator resistance [ohm]
    l: float  # inductance [H]
    lam: float  # magnet flux linkage [V s]
    p: int  # pole pairs
    i_rated: float  # rated current [A]
    vdt: float  # deadtime volt-second loss per leg, Vdc td / Ts [V]
    ts: float  # PWM (sample) period [s]
    j: float  # inertia [kg m^2]

    @property
    def v1_dt(self) -> float:
        """Fundamental of the +-V_dt square wave along the current [V]."""
        return 4.0 / math.pi * self.vdt

    @classmethod
    def of(cls, card: MachineCard) -> CardValues:
        return cls(
            card.resistance_ohm,
            card.inductance_h,
            card.flux_linkage_vs,
            card.pole_pairs,
            card.rated_current_a,
            deadtime_volt_second_loss(card.dc_bus_v, card.deadtime_s, card.ts_s),
            card.ts_s,
            card.inertia_kgm2,
        )


def cv() -> CardValues:
    """The values of the card `build` puts the experiments' scenarios on (`--machine` or the
    default card)."""
    return _card_values(_MACHINE["path"])


@functools.cache
def _card_values(machine: str | None) -> CardValues:
    return CardValues.of(build(duration_s=0.01).machine)


# ---------------------------------------------------------------- running
# --graph: every run goes through the ROS 2 node graph (lockstep, recorded, read back from
# the bag) instead of fluxdrive.drive.sim.run_scenario; the numbers are the same (the lockstep
# graph reproduces the in-process runner bit for bit), only slower (about real time).  The
# graph runner lives with the graph tools (fluxdrive_bringup.runs.graph_run), which install
# it here: the engine imports no ROS.
_RUNNER: dict[str, Callable[[Scenario], Any] | None] = {"graph": None}


def use_graph_runner(run: Callable[[Scenario], Any] | None) -> None:
    """Run every experiment scenario with `run` (scenario -> SimResult); None: in-process."""
    _RUNNER["graph"] = run


def _job(args):
    sc, extractor, kw = args
    from fluxdrive.drive.sim import run_scenario

    t0 = time.perf_counter()
    graph = _RUNNER["graph"]
    r = graph(sc) if graph is not None else run_scenario(sc, progress=False)
    m = compute(r)
    out = extractor(r, m, **(kw or {}))
    out["_wall_s"] = time.perf_counter() - t0
    out["_sim_s"] = sc.duration_s
    return out


@dataclasses.dataclass
class Ctx:
    out: Path
    quick: bool = False
    runner: Any = None  # fluxdrive.study.runner.Runner; None: in-process, in order
    name: str = ""
    echo: bool = True

    def log(self, msg: str) -> None:
        if self.echo:
            sys.stderr.write(f"[{self.name}] {msg}\n")
            sys.stderr.flush()

    def run(self, jobs: list[tuple[Scenario, Callable, dict | None]]) -> list[dict]:
        """Run (scenario, extractor, kwargs) jobs; results in order, progress on stderr."""
        return self.map(_job, jobs)

    def map(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        """fn over items through the runner (in-process without one); results in order."""
        from fluxdrive.study.runner import Progress, Runner

        runner = self.runner or Runner("serial")
        return runner.map(fn, list(items), Progress(len(items), label=self.name, echo=self.echo))

    def fig(self, fig, name: str) -> str:
        self.out.mkdir(parents=True, exist_ok=True)
        p = self.out / f"{name}.png"
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        import matplotlib.pyplot as plt

        plt.close(fig)
        return p.name


def claim(text: str, ours: str, holds: bool | None, why: str = "") -> dict:
    d = {"claim": text, "ours": ours, "holds": holds}
    if not holds and why:
        d["why"] = why
    elif why:
        d["note"] = why
    return d


def plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as p

    return p
