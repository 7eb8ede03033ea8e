"""Every config loader against hostile files: the cases a probe found (each reproduced) and a
property-based fuzz (hypothesis, derandomized) over scenario, machine card, bench, graph,
ros__parameters file and study spec.  The property: a loader returns a valid object or
raises its one refusal (ConfigError; ValueError for a parameter file) with one line naming
the file -- never another exception -- and with the process's peak memory grown by less than
MEMORY_BUDGET_MB over the whole fuzz.  Time is printed per loader (worst document), not
asserted: how fast this machine is decides no outcome; HANG_GUARD_S only ends a hung one."""

from __future__ import annotations

import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from fluxdrive.core import yamlio
from fluxdrive.core.machine import ConfigError, load_machine
from fluxdrive.drive.scenario import CONFIG_DIR, load_scenario
from fluxdrive.study.spec import load_spec
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
# not a speed bound: a document still loading after this long is hung (the runaways the probe
# found -- alias bomb, huge profile -- took minutes and gigabytes; the budget that holds them
# is MEMORY_BUDGET_MB and the refusals' texts)
HANG_GUARD_S = 120.0
MEMORY_BUDGET_MB = 300.0  # peak RSS growth over one loader's whole fuzz
MUTATED, TEXTS = 150, 250  # documents per loader: 400, 2400 over the six loaders

FUZZ = dict(
    derandomize=True,  # the same documents on every run (seeded by the test)
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _alias_bomb(levels: int = 9) -> str:
    """The classic "billion laughs": 9 lists of 9 aliases of the level below."""
    out = "lol0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
    for i in range(1, levels):
        out += f"lol{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 9) + "]\n"
    return out


# ----------------------------------------------------------------- the probe's cases
def _scenario_raw() -> dict[str, Any]:
    """The 2 % / 150 % scenario with two of its observers, its machine and bench as absolute
    paths (so a copy anywhere loads; the bench file has a fuzz of its own)."""
    raw = yamlio.load_file(CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml")
    raw["machine"] = str(CONFIG_DIR / "machines" / "default_spm.yaml")
    raw["bench"] = str(CONFIG_DIR / "benches" / "paper_lab.yaml")
    raw["observers"] = {k: raw["observers"][k] for k in ("flux_measured", "emf_commanded")}
    raw["driving"] = "flux_measured"
    return raw


PROBE_CASES: dict[str, tuple[dict[str, Any], str]] = {
    "steady_window_s": ({"steady_window_s": ["a", "b"]}, "steady_window_s"),
    "machine_int": ({"machine": 42}, "'machine'"),
    "huge_int": ({"duration_s": 10**400}, "64-bit"),
    "observer_list": ({"observers": {"flux_measured": [1, 2]}}, "observers.flux_measured"),
    "plant_int": ({"plant": 5}, "'plant'"),
    "angle_inf": ({"initial_angle_deg": float("inf")}, "initial_angle_deg"),
    "offset_inf": ({"faults": {"current_offset_pu": [float("inf"), 0, 0]}}, "current_offset_pu"),
    "alias_bomb": ({}, "alias"),
}


@pytest.mark.parametrize("case", sorted(PROBE_CASES))
def test_probe_scenario_cases_are_one_line_exit_2(tmp_path, case):
    """Each bad scenario of the probe through `./fluxdrive sim`: exit 2, one line naming the
    file and the key, no traceback (they were ValueError/TypeError/OverflowError tracebacks,
    a NaN deep in the run, or 6.8 GB for the alias bomb)."""
    patch, words = PROBE_CASES[case]
    text = yamlio.dumps({**_scenario_raw(), **patch}, sort_keys=False)
    if case == "alias_bomb":  # the bomb under `extra:`, which the loader keeps as given
        text += "extra:\n" + "".join("  " + ln + "\n" for ln in _alias_bomb().splitlines())
    p = tmp_path / f"{case}.yaml"
    p.write_text(text)
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "fluxdrive.cli", "sim", str(p), "--no-plots"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    err = r.stderr.strip()
    print(case, f"{time.perf_counter() - t0:.1f} s:", err)
    assert r.returncode == 2, (r.returncode, err)
    assert "Traceback" not in r.stderr and len(err.splitlines()) == 1, err
    assert str(p) in err and words in err


def test_alias_bomb_in_a_graph_env_is_one_line(tmp_path):
    """The probe's graph file with a bomb under `env:` took 6.8 GB and 71 s, then
    `OSError: Argument list too long`; now the loader refuses it at once."""
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive_bringup.launch.launcher import load_graph

    p = tmp_path / "bomb_graph.yaml"
    body = "".join("  " + ln + "\n" for ln in _alias_bomb().splitlines())
    p.write_text(f"name: g\nenv:\n{body}nodes:\n  - {{name: plant, node: plant}}\n")
    with pytest.raises(ConfigError) as ei:
        load_graph(p)
    # refused for its aliases, before expanding them (which took the 6.8 GB)
    assert str(p) in str(ei.value) and "alias" in str(ei.value)
    # an env value that is a collection, or too long for exec, is refused as well
    p.write_text("name: g\nenv: {X: [1, 2]}\nnodes:\n  - {name: plant, node: plant}\n")
    with pytest.raises(ConfigError, match="env.X"):
        load_graph(p)
    p.write_text(f"name: g\nenv: {{X: {'y' * 40000}}}\nnodes:\n  - {{name: plant, node: plant}}\n")
    with pytest.raises(ConfigError, match="env.X"):
        load_graph(p)


def test_yamlio_limits():
    """The reader's own limits, each one YAMLError with a line: depth, recursion, int64,
    size, a date that is none, text that is not UTF-8; aliases within the budget load."""
    for text, words in (
        ("[" * 100 + "]" * 100, "nested deeper"),
        ("&a [*a]", "recursive alias"),
        ("x: 9223372036854775808", "64-bit"),
        ("x: 2001-13-45", "month must be"),
        ("x: " + "y" * (yamlio.MAX_DOCUMENT_CHARS + 1), "characters"),
    ):
        with pytest.raises(yamlio.YAMLError) as ei:
            yamlio.loads(text)
        assert words in yamlio.describe(ei.value)
        assert "\n" not in yamlio.describe(ei.value)
    assert yamlio.loads("x: 9223372036854775807")["x"] == (1 << 63) - 1
    doc = yamlio.loads("a: &a {b: [1, 2]}\nc: *a\nd: {<<: *a, e: 3}\n")
    assert doc["c"] == {"b": [1, 2]} and doc["d"] == {"b": [1, 2], "e": 3}


def test_not_utf8_file(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes(b"name: caf\xe9\n")
    with pytest.raises(ConfigError) as ei:
        load_machine(p)
    assert str(p) in str(ei.value) and "UTF-8" in str(ei.value)


# --------------------------------------------------------------------------- the fuzz
_LEAF = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(1 << 70), 1 << 70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["paper", "measured", "brake", "encoder", "plant", "", "0", "1e400"]),
)
_VALUE = st.recursive(
    _LEAF,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.one_of(st.text(max_size=8), st.integers(-3, 3)), inner, max_size=4)
    ),
    max_leaves=10,
)


def _mutate(data: st.DataObject, doc: Any, depth: int = 0) -> Any:
    """`doc` with one place (chosen by hypothesis) replaced, removed or added to."""
    if isinstance(doc, dict) and doc and depth < 4 and data.draw(st.integers(0, 3)) > 0:
        key = data.draw(st.sampled_from(sorted(doc, key=str)))
        out = dict(doc)
        op = data.draw(st.integers(0, 5))
        if op == 0:
            del out[key]
        elif op == 1:
            out[data.draw(st.text(max_size=8))] = data.draw(_VALUE)
        else:
            out[key] = _mutate(data, doc[key], depth + 1)
        return out
    if isinstance(doc, list) and doc and depth < 4 and data.draw(st.integers(0, 3)) > 0:
        i = data.draw(st.integers(0, len(doc) - 1))
        out = list(doc)
        out[i] = _mutate(data, doc[i], depth + 1)
        return out
    return data.draw(_VALUE)


# YAML text with its syntax in it: anchors, aliases, tags, merges, flow and block collections
_YAML_TOKENS = [
    *"ab:-[]{},'\"#?|>\t",
    ": ", "- ", ", ", "\n", "\n  ", "\n    ", "&x ", "*x", "&y ", "*y", "<<: ", "!!str ",
    "!!int ", "!!float ", "!!binary ", "!!map ", "!!seq ", "!!set ", "!!omap ", "!!timestamp ",
    "1", "-1", "1e9", "0x1F", "0o17", ".inf", "-.inf", ".nan", "9" * 30, "~", "null", "true",
    "2001-12-14", "2001-13-45", "%YAML 1.1\n", "---\n", "...\n", "duration_s", "nodes",
    "ros__parameters", "machine", "observers", "variant",
]  # fmt: skip
_YAML_TEXT = st.lists(st.sampled_from(_YAML_TOKENS), max_size=40).map("".join)


class _Budget:
    """Time per document and peak-RSS growth over the fuzz."""

    def __init__(self) -> None:
        self.rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        self.worst_s = 0.0
        self.n = 0

    def run(self, fn, *args) -> None:
        t0 = time.perf_counter()
        try:
            fn(*args)
        finally:
            dt = time.perf_counter() - t0
            self.worst_s = max(self.worst_s, dt)
            self.n += 1
            assert dt < HANG_GUARD_S, f"{dt:.1f} s for one document: hung"

    def check(self, what: str) -> None:
        grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - self.rss0) / 1024
        print(
            f"{what}: {self.n} documents, worst {self.worst_s:.3f} s, peak RSS +{grown_mb:.0f} MB"
        )
        assert grown_mb < MEMORY_BUDGET_MB


def _expect_refusal_or_ok(load, path: Path, errors=(ConfigError,)) -> None:
    try:
        load(path)
    except errors as exc:
        msg = str(exc)
        assert "\n" not in msg, msg
        assert str(path) in msg or path.name in msg, msg


def _fuzz(tmp_path: Path, what: str, base: Any, load, errors=(ConfigError,)) -> None:
    budget = _Budget()
    path = tmp_path / f"{what}.yaml"

    @settings(max_examples=MUTATED, **FUZZ)
    @given(data=st.data())
    def structured(data: st.DataObject) -> None:
        doc = _mutate(data, base)
        path.write_text(yamlio.dumps(doc, sort_keys=False, allow_unicode=True))
        budget.run(_expect_refusal_or_ok, load, path, errors)

    @settings(max_examples=TEXTS, **FUZZ)
    @given(text=_YAML_TEXT)
    def text(text: str) -> None:
        path.write_text(text)
        budget.run(_expect_refusal_or_ok, load, path, errors)

    structured()
    text()
    budget.check(what)


def test_fuzz_scenario(tmp_path):
    _fuzz(tmp_path, "scenario", _scenario_raw(), load_scenario)


def test_fuzz_machine_card(tmp_path):
    base = yamlio.load_file(CONFIG_DIR / "machines" / "default_spm.yaml")
    _fuzz(tmp_path, "machine", base, load_machine)


def test_fuzz_bench(tmp_path):
    """A bench file named by a scenario (its own errors name both files)."""
    bench = tmp_path / "bench.yaml"
    sc = tmp_path / "sc.yaml"
    raw = _scenario_raw()
    raw["bench"] = str(bench)
    sc.write_text(yamlio.dumps(raw))
    base = yamlio.load_file(CONFIG_DIR / "benches" / "paper_lab.yaml")

    def load(p: Path) -> None:
        assert p == bench
        load_scenario(sc)

    _fuzz(tmp_path, "bench", base, load)


def test_fuzz_study_spec(tmp_path):
    base = yamlio.load_file(CONFIG_DIR / "studies" / "lowest_speed_map.yaml")
    _fuzz(tmp_path, "study", base, load_spec)


def test_fuzz_graph(tmp_path):
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive_bringup.launch.launcher import load_graph

    base = yamlio.load_file(CONFIG_DIR / "graphs" / "sim_separate.yaml")
    for nd in base["nodes"]:
        nd["params"] = [str(ROOT / p) for p in nd.get("params", [])]
    _fuzz(tmp_path, "graph", base, load_graph)


def test_fuzz_ros_params_file(tmp_path):
    pytest.importorskip("fluxdrive_ros")
    from fluxdrive_ros.params import check_params_file

    base = yamlio.load_file(CONFIG_DIR / "ros" / "controller.yaml")
    _fuzz(tmp_path, "params", base, check_params_file, errors=(ValueError,))
