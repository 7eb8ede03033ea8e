"""What the experiments share: scenario builders (`build`, `sensorless`, `encoder_run`), the card
values predictions use (`cv`), the run context (`Ctx`: the one parallel runner, figures), the
turns of experiments run at once on one runner (`Turns`), the graph-runner hook and `observe` for
rows that measure without claiming.  The experiment modules import this, and registry imports
them: no import cycle."""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fluxdrive.analysis.metrics import compute
from fluxdrive.core.machine import ConfigError, MachineCard, load_machine
from fluxdrive.drive.plant import deadtime_volt_second_loss
from fluxdrive.drive.scenario import (
    CONFIG_DIR,
    Scenario,
    load_bench_file,
    load_scenario,
    machine_path,
    observer_set,
    scenario_path,
)

DEFAULT_MACHINE = CONFIG_DIR / "machines" / "default_spm.yaml"
# the non-ideal bench of the paper scenarios (`experiment --bench FILE` runs FILE in its place)
PAPER_BENCH = CONFIG_DIR / "benches" / "paper_lab.yaml"

# the project's observer set, declared once (the demo scenario's `observers`:
# fluxdrive.drive.scenario.observer_set): flux_* the flux observer that drives (paper_robust:
# the literal one loses lock, see the paper_robust experiment), emf_* the back-EMF observer;
# paper_*: the paper's observer exactly as written, in shadow
OBS6 = observer_set()
OBS4 = {k: v for k, v in OBS6.items() if not k.startswith("paper_")}
LITERAL = {k: v for k, v in OBS6.items() if k.startswith("paper_")}


# ---------------------------------------------------------------- scenario building
# per unit of the card's rated speed: the experiments' start-up (I-f up to 4/3 %, handover there
# or at 7/6 % below it, hand-back at 2/3 % at most) and the 10 %/s ramp that sets the load's
# start after a speed step
START_PU = 0.04 / 3.0
HANDOVER_LOW_PU = 0.035 / 3.0
HANDBACK_MAX_PU = 0.02 / 3.0
SPEED_STEP_PU_S = 0.1


def build(
    machine_kw: dict | None = None,
    base: str | None = None,
    *,
    card: str | Path | None = None,
    **raw,
) -> Scenario:
    """A scenario from keyword keys (the YAML schema), built in memory, or over a named
    scenario file (`base`, the keys override it); `card` is the machine card it runs on (its
    rpm values are that card's; a base file keeps its per-unit speeds on it), None: the
    default card or the file's; `machine_kw` replaces machine-card fields (e.g. inertia_kgm2)."""
    if base is not None:
        sc = load_scenario(scenario_path(base), machine=card, overrides=raw or None)
    else:
        raw.setdefault("machine", str(card or DEFAULT_MACHINE))
        where = CONFIG_DIR / "scenarios" / f"<experiment {raw.get('name', 'exp')}>"
        sc = load_scenario(where, raw=raw)
    if machine_kw:
        sc.machine = dataclasses.replace(sc.machine, **machine_kw).validate()
    return sc


def rated_rpm(card: str | Path | None = None) -> float:
    """The rated speed [rpm] of `card` (None: the default card)."""
    return _card(str(card or DEFAULT_MACHINE)).rated_speed_rpm


@functools.cache
def _card(path: str) -> MachineCard:
    return load_machine(machine_path(path))


def card_values(card: str | Path | None = None) -> CardValues:
    """The values predictions use, of `card` (None: the default card)."""
    return CardValues.of(_card(str(card or DEFAULT_MACHINE)))


def pu_rpm(speed_pu: float, card: str | Path | None) -> float:
    """A speed in per unit of `card`'s rated speed (None: the default card), in rpm."""
    return round(speed_pu * rated_rpm(card), 9)


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
    card: str | Path | None = None,
    **extra,
) -> Scenario:
    """Sensorless start (align -> I-f -> handover at up to 4/3 % of rated speed), then the
    speed (rpm of `card`), then a slow brake-load ramp (the paper's hysteresis dyno), then a
    steady window."""
    obs = dict(observers or {driving: OBS6.get(driving, {"variant": "paper"})})
    start = pu_rpm(START_PU, card)
    # handover on the filtered agreement (2 Hz): the per-sample check is reset by the unloaded
    # rotor's swing about the I-f vector and, on the non-ideal bench, delays the handover by
    # up to 1.5 s (into the steady window at no load: the fig13 experiment)
    ctrl = {
        "if_current_pu": 0.6,
        "handover_rpm": pu_rpm(HANDOVER_LOW_PU, card) if speed_rpm < start else start,
        "handback_rpm": min(pu_rpm(HANDBACK_MAX_PU, card), 0.5 * speed_rpm),
        "handover_agree_lpf_hz": 2.0,
    }
    ctrl.update(control or {})
    if speed_rpm < start:
        speed = [[0.0, start], [0.8, start], [1.3, speed_rpm]]
        t_load = 1.8
    else:
        speed = [[0.0, speed_rpm]]
        t_load = 1.0 + speed_rpm / (rated_rpm(card) * SPEED_STEP_PU_S)
    ramp = max(load_pu / ramp_pu_s, 0.01) if load_pu > 0 else 0.0
    t_end_ramp = t_load + ramp
    w0 = t_end_ramp + settle_s
    dur = w0 + window_s
    load = [[0.0, 0.0], [t_load, 0.0], [t_end_ramp, load_pu]] if load_pu > 0 else 0.0
    return build(
        machine_kw=machine_kw,
        card=card,
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
    card: str | Path | None = None,
    **extra,
) -> Scenario:
    """Encoder-driven run (observers in shadow) at speed_rpm (rpm of `card`): speed, brake
    load ramp, steady window."""
    t_load = 0.3
    t1 = t_load + (ramp_s if load_pu > 0 else 0.0)
    w0 = t1 + settle_s
    dur = w0 + window_s
    load = [[0.0, 0.0], [t_load, 0.0], [t1, load_pu]] if load_pu > 0 else 0.0
    return build(
        machine_kw=machine_kw,
        card=card,
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


# ---------------------------------------------------------------- running
def _job(args):
    """One run and its analysis, where the runner puts it; the extractor's output with what the
    run cost: `_wall_s`, `_sim_s` (simulated seconds), `_cpu_run_s` (the simulation) and
    `_cpu_analysis_s` (metrics and extractor), CPU seconds of the process that ran it."""
    sc, extractor, kw, graph_run = args
    from fluxdrive.drive.sim import run_scenario

    t0, c0 = time.perf_counter(), time.process_time()
    r = graph_run(sc) if graph_run is not None else run_scenario(sc, progress=False)
    c1 = time.process_time()
    m = compute(r)
    out = extractor(r, m, **(kw or {}))
    out["_wall_s"] = time.perf_counter() - t0
    out["_sim_s"] = sc.duration_s
    out["_cpu_run_s"] = c1 - c0
    out["_cpu_analysis_s"] = time.process_time() - c1
    return out


class Turns:
    """Several experiments, and an experiment's seeds, at once on one parallel runner: each in
    a thread of its own, so the runner's queue holds all their runs together (the workers of a
    cluster never wait on one experiment's few runs or on its analysis), while only one thread
    at a time runs experiment code: it holds the turn and gives it up only while it waits on
    the runner (`Ctx.map`).  Experiment code (analysis, judging, pyplot, which is not
    thread-safe) so runs as if alone, in an order that changes no number: every run is seeded
    by its scenario and every experiment reads only its own results."""

    def __init__(self) -> None:
        self._lock = threading.Lock()

    @contextmanager
    def away(self) -> Iterator[None]:
        """The caller holds the turn: give it up while blocked, take it back after."""
        self._lock.release()
        try:
            yield
        finally:
            self._lock.acquire()

    def all(self, fns: list[Callable[[], Any]], holding: bool = False) -> list[Any]:
        """Each fn in a thread of its own, each running in its turn; their results in order.
        `holding`: the caller holds the turn (an experiment starting its seeds) and gives it
        up until they end.  The first exception one raised is raised here, after all end."""
        out: list[Any] = [None] * len(fns)
        err: list[BaseException | None] = [None] * len(fns)

        def body(i: int, fn: Callable[[], Any]) -> None:
            with self._lock:
                try:
                    out[i] = fn()
                except BaseException as exc:  # raised in the caller's thread below
                    err[i] = exc

        threads = [
            threading.Thread(target=body, args=(i, fn), daemon=True) for i, fn in enumerate(fns)
        ]
        for t in threads:
            t.start()
        if holding:
            with self.away():
                for t in threads:
                    t.join()
        else:
            for t in threads:
                t.join()
        for e in err:
            if e is not None:
                raise e
        return out


COST_KEYS = ("_wall_s", "_sim_s", "_cpu_run_s", "_cpu_analysis_s")


@dataclasses.dataclass
class Ctx:
    """What an experiment runs in, passed to it explicitly (no module state): where its
    figures go, quick or full, the parallel runner, the machine card every scenario runs on
    (`experiment --machine`; None: the default card, or a scenario file's own), the noise
    seed its scenarios take unless they set one (the registry runs a one-seed experiment once
    per seed) and the graph runner (`experiment --graph`: scenario -> SimResult through the
    ROS node graph, installed by the graph tools; None: in-process)."""

    out: Path = Path(".")
    quick: bool = False
    runner: Any = None  # fluxdrive.study.runner.Runner; None: in-process, in order
    name: str = ""
    echo: bool = True
    machine: Path | None = None
    graph_run: Callable[[Scenario], Any] | None = None
    bench: Path | None = None  # `experiment --bench`: this bench file replaces the paper bench
    seed: int = 1  # the noise seed of every scenario the context builds (unless one is given)
    turns: Turns | None = None  # experiments at once on the runner (None: this one alone)
    figures: bool = True  # False: figures drawn but not saved (a rerun on another seed)
    # what each run cost (`_job`'s figures with the experiment and seed), when kept: a list
    # every context of one command shares (`benchmark experiments`)
    ledger: list[dict] | None = None

    @functools.cached_property
    def card(self) -> MachineCard:
        """The card the experiment's own scenarios run on."""
        return _card(str(self.machine or DEFAULT_MACHINE))

    @functools.cached_property
    def cv(self) -> CardValues:
        """The card values every prediction uses."""
        return CardValues.of(self.card)

    def rpm(self, speed_pu: float) -> float:
        """A speed in per unit of the card's rated speed, in rpm."""
        return pu_rpm(speed_pu, self.machine)

    def build(self, machine_kw: dict | None = None, base: str | None = None, **raw) -> Scenario:
        """`build` on this context's card, with the context's seed unless `seed` is given."""
        raw.setdefault("seed", self.seed)
        return build(machine_kw, base, card=self.machine, **raw)

    def sensorless(self, speed_rpm: float, load_pu: float, **kw) -> Scenario:
        """`sensorless` on this context's card, with the context's seed unless given."""
        kw.setdefault("seed", self.seed)
        return sensorless(speed_rpm, load_pu, card=self.machine, **kw)

    def encoder_run(self, speed_rpm: float, load_pu: float, **kw) -> Scenario:
        """`encoder_run` on this context's card, with the context's seed unless given."""
        kw.setdefault("seed", self.seed)
        return encoder_run(speed_rpm, load_pu, card=self.machine, **kw)

    def log(self, msg: str) -> None:
        if self.echo:
            sys.stderr.write(f"[{self.name}] {msg}\n")
            sys.stderr.flush()

    def run(self, jobs: list[tuple[Scenario, Callable, dict | None]]) -> list[dict]:
        """Run (scenario, extractor, kwargs) jobs; results in order, progress on stderr."""
        return self.map(_job, [(sc, ex, kw, self.graph_run) for sc, ex, kw in jobs])

    def map(self, fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        """fn over items through the runner (in-process without one); results in order."""
        from fluxdrive.study.runner import Progress, Runner

        runner = self.runner or Runner("serial")
        items = [self._on_bench(x) for x in items]
        progress = Progress(len(items), label=self.name, echo=self.echo)
        if self.turns is None:
            out = runner.map(fn, items, progress)
        else:
            with self.turns.away():  # the other experiments' code runs meanwhile
                out = runner.map(fn, items, progress)
        if self.ledger is not None and fn is _job:
            self.ledger += [
                {"experiment": self.name, "seed": self.seed}
                | {k[1:]: v for k, v in o.items() if k in COST_KEYS}
                for o in out
            ]
        return out

    def _on_bench(self, item: Any) -> Any:
        """`item` (a scenario, or a job tuple holding some) with `--bench`'s file in place of
        the paper bench wherever a scenario runs on the paper bench (ideal runs stay ideal).
        The swapped file must keep the paper bench's observer model: the scenario's
        observers took their R^, L^, lambda^ from it when it was loaded."""
        if self.bench is None:
            return item
        if isinstance(item, tuple):
            return tuple(self._on_bench(x) for x in item)
        if not isinstance(item, Scenario):
            return item
        paper = load_bench_file(PAPER_BENCH, item.machine)
        if item.bench != paper:
            return item
        swap = load_bench_file(self.bench, item.machine)
        if swap.observer_model != paper.observer_model:
            raise ConfigError(
                f"{self.bench}: --bench must keep the paper bench's observer_model "
                f"(start the file with 'base: {PAPER_BENCH.name}')"
            )
        return dataclasses.replace(item, bench=swap)

    def fig(self, fig, name: str) -> str:
        """Save a figure as out/NAME.png; its file name.  Not saved when the context keeps no
        figures (laying out and rendering the PNG is most of a figure's cost)."""
        p = self.out / f"{name}.png"
        if not self.figures:
            import matplotlib.pyplot as plt

            plt.close(fig)
            return p.name
        self.out.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(p, dpi=100)
        import matplotlib.pyplot as plt

        plt.close(fig)
        return p.name


def observe(text: str, ours: str, note: str = "") -> dict:
    """A row that reports what was measured and makes no claim: no test, no verdict (a claim
    is a registered row judged by `claims.judge`; no experiment decides one itself)."""
    d = {"claim": text, "ours": ours}
    if note:
        d["note"] = note
    return d


def plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as p

    return p
