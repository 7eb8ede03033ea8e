"""Every config field is declared once (`fluxdrive.core.schema`): its unit, range, text and
card rule live on the dataclass field, and the validation, the ROS parameter descriptors the
nodes declare and the parameter tables in the docs are read from there.

- every field of every block has a unit, a doc text and a range (or choices);
- validation takes exactly the schema's range: the ends accepted, just outside refused with
  one line naming the key;
- the descriptors the controller and observer nodes declare (started without a graph) carry
  the schema's text, unit, range -- narrowed on the card -- and live/read-only;
- docs/configuration.md holds the tables `schema.markdown_table` generates."""

from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path

import pytest
from fluxdrive.core import schema
from fluxdrive.core.machine import ConfigError
from fluxdrive.drive.config_blocks import BLOCKS, default_card, docs_tables, stale_tables
from fluxdrive.drive.control import ControllerConfig
from fluxdrive.drive.scenario import load_scenario, scenario_path
from ros_domains import domain

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = str(ROOT / "config" / "scenarios" / "paper_2pct_150load.yaml")


@pytest.mark.parametrize("key", sorted(BLOCKS))
def test_every_field_has_unit_doc_and_range(key):
    cls = BLOCKS[key].cls
    specs = schema.specs(cls)
    undeclared = {f.name for f in dataclasses.fields(cls)} - set(specs) - BLOCKS[key].free
    assert not undeclared, f"{key}: fields without a schema: {sorted(undeclared)}"
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    for name, s in specs.items():
        assert s.doc.strip(), f"{key}.{name}: no doc"
        if s.numeric:
            assert s.unit, f"{key}.{name}: no unit ('-' when dimensionless)"
            assert s.lo is not None and s.hi is not None and s.lo <= s.hi, f"{key}.{name}"
            v = defaults[name]
            for x in v if isinstance(v, tuple) else (v,):  # per phase: each
                assert x is None or s.lo <= x <= s.hi, f"{key}.{name}: default {v} off its range"
            assert v is not None or s.optional, f"{key}.{name}: None without a meaning"
        elif s.kind is str:
            assert s.choices or name in BLOCKS[key].free_text, f"{key}.{name}: no choices"


TIED_TO_OTHERS = {"stated_torque_nm"}
"""Keys a check ties to others besides their range (a card's torque must agree with
1.5 p lambda I_rated, tests/test_card_rig.py): their range's ends alone need not pass."""


@pytest.mark.parametrize("key", sorted(BLOCKS))
def test_validation_takes_exactly_the_schema_range(key):
    block = BLOCKS[key]
    card = default_card() if block.on_card else None
    for name, (lo, hi) in schema.ranges(block.cls, card).items():
        spec = schema.specs(block.cls)[name]
        for ok in (lo, hi):
            if name not in TIED_TO_OTHERS:
                block.check({name: ok})  # the ends are accepted
        step = 1 if spec.kind is int else max(abs(hi), abs(lo), 1.0) * 1e-6
        for bad in (lo - step, hi + step):
            with pytest.raises(ConfigError) as err:
                block.check({name: bad})
            text = str(err.value)
            assert name in text and "\n" not in text, text
            assert f"[{lo}, {hi}]" in text or f"[{lo:g}, {hi:g}]" in text, text


def test_study_spec_takes_exactly_the_schema_range():
    """A study spec's single-valued keys (study.spec.StudySettings, above the drive layer
    and so not among BLOCKS): what load_spec checks is the schema's range."""
    from fluxdrive.study.spec import StudySettings, study_settings

    for name, (lo, hi) in schema.ranges(StudySettings).items():
        kind = schema.specs(StudySettings)[name].kind
        for ok in (lo, hi):
            assert getattr(study_settings("s.yaml", {name: kind(ok)}), name) == kind(ok)
        step = 1 if kind is int else max(abs(hi), abs(lo), 1.0) * 1e-6
        for bad in (lo - step, hi + step):
            with pytest.raises(ConfigError, match=rf"s\.yaml: '{name}' must be .* in \["):
                study_settings("s.yaml", {name: kind(bad)})


def test_card_limits_narrow_the_range_and_check_holds_to_them():
    """current_bandwidth_hz at most a quarter of PWM, reference_timeout_s at least two host
    samples: the schema's ranges on the card are what `check` accepts."""
    sc = load_scenario(scenario_path("paper_2pct_150load"))
    card = sc.machine
    for d in (1, 4):
        rng = schema.ranges(ControllerConfig, card, d)
        assert rng["current_bandwidth_hz"][1] == 0.25 * card.pwm_hz
        assert rng["reference_timeout_s"][0] == pytest.approx(2 * d * card.ts_s)
        split = dataclasses.replace(sc.control, mode="split", decimation=d)
        for name, (lo, hi) in rng.items():
            for ok in (lo, hi):
                dataclasses.replace(split, **{name: ok}).validate()
        lo = rng["reference_timeout_s"][0]
        with pytest.raises(ConfigError, match="reference_timeout_s .* two samples"):
            dataclasses.replace(split, reference_timeout_s=lo * 0.99).check(card)
        hi = rng["current_bandwidth_hz"][1]
        dataclasses.replace(split, current_bandwidth_hz=hi).check(card)
        with pytest.raises(ConfigError, match="current_bandwidth_hz .* quarter of the PWM"):
            dataclasses.replace(split, current_bandwidth_hz=hi * 1.001).check(card)


def test_card_rules_fill_what_is_unset():
    """resolve() fills every None that has a rule, from the card; rules read the card only."""
    card = load_scenario(scenario_path("paper_2pct_150load")).machine
    r = ControllerConfig().resolved(card)
    for name, s in schema.specs(ControllerConfig).items():
        if s.rule is not None:
            assert getattr(r, name) == s.rule.value(card, r), name
    assert r.vdc_min_v == pytest.approx(0.28 * card.dc_bus_v)
    assert r.handback_rpm == pytest.approx(2 / 3 * r.handover_rpm)
    # an explicit value wins and moves no other field
    r2 = ControllerConfig(current_bandwidth_hz=500.0).resolved(card)
    assert r2.current_bandwidth_hz == 500.0 and r2.speed_bandwidth_hz == r.speed_bandwidth_hz


def test_deadtime_is_ranged_in_one_place():
    """The card's deadtime, a scenario's plant override and every feed-forward of it (controller,
    observers, split-mode drive) accept the one range of core.machine.DEADTIME_RANGE_S."""
    from fluxdrive.core.machine import DEADTIME_RANGE_S, MachineCard
    from fluxdrive.drive.control import DriveParams

    classes = [b.cls for b in BLOCKS.values()] + [MachineCard, DriveParams]
    seen = {
        f"{cls.__name__}.{name}": (s.lo, s.hi)
        for cls in classes
        for name, s in schema.specs(cls).items()
        if "deadtime" in name
    }
    assert len(seen) >= 4, seen
    assert all(r == DEADTIME_RANGE_S for r in seen.values()), seen
    over = {"plant": {"deadtime_s": DEADTIME_RANGE_S[1] * 1.01}}
    with pytest.raises(ConfigError, match=r"plant\.deadtime_s"):
        load_scenario(scenario_path("paper_2pct_150load"), overrides=over)


def test_docs_tables_are_generated_from_the_schema():
    """Every block has its table in the page, and it is the generated one (the staleness
    check of the whole page is in tests/test_docs.py)."""
    text = (ROOT / "docs" / "configuration.md").read_text()
    for key, table in docs_tables().items():
        assert f"<!-- params {key} -->\n{table}<!-- /params -->" in text, key
    assert stale_tables() == []


def test_an_option_takes_exactly_its_fields_range():
    """`schema.option`: a command-line option declared by a field -- its default, kind and
    range; the ends accepted, just outside refused with one line naming the option."""
    import argparse

    from fluxdrive.experiments.fronts import FrontWindow

    ap = argparse.ArgumentParser()
    for flag in ("--settle-s", "--window-s"):
        schema.option(ap, flag, FrontWindow)
    assert vars(ap.parse_args([])) == {"settle_s": 0.7, "window_s": 1.0}
    for name, (lo, hi) in schema.ranges(FrontWindow).items():
        flag = "--" + name.replace("_", "-")
        for ok in (lo, hi):
            assert getattr(ap.parse_args([f"{flag}={ok!r}"]), name) == ok
        for bad in (lo - 1e-6, hi + 1e-6):
            with pytest.raises(ConfigError) as err:
                ap.parse_args([f"{flag}={bad!r}"])
            assert str(err.value).startswith(f"{flag} must be a number in [{lo}, {hi}]"), err
    assert "[s]; range [0.05, 60]" in ap.format_help().replace("\n", " ").replace("  ", " ")


def test_shared_options_are_ranged_by_one_field_each():
    """--domain-id, the servers' --port/--scope-port and the CAN link's --decimation are
    declared through `schema.option` by one field each (GraphSettings.domain_id,
    ServeOptions.port, LinkOptions.decimation), never by a bare add_argument of their own."""
    import ast

    flags = {"--domain-id", "--port", "--scope-port", "--decimation"}
    own = []
    for path in [*(ROOT / "python").rglob("*.py"), *(ROOT / "src").rglob("*.py")]:
        if "/build/" in str(path) or "/install/" in str(path):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            if node.func.attr != "add_argument" or not node.args:
                continue
            first = node.args[0]
            if isinstance(first, ast.Constant) and first.value in flags:
                own.append(f"{path.relative_to(ROOT)} {first.value}")
    # the emulator's --port is a UDP multicast port of its bus (python-can checks it)
    assert own == ["python/fluxdrive/cli/canemulator.py --port"], own


# --------------------------------------------------------------- the nodes' descriptors
rclpy = pytest.importorskip("rclpy")


@pytest.fixture(scope="module")
def ctx():
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    c = rclpy.Context()
    rclpy.init(context=c, domain_id=domain(25))
    yield c
    rclpy.shutdown(context=c)


def _node(kind: str, ctx):
    from rclpy.parameter import Parameter

    ov = [Parameter("scenario", value=SCENARIO)]
    if kind == "controller":
        from foc_controller_node.node import ControllerNode

        return ControllerNode("controller", context=ctx, parameter_overrides=ov)
    from flux_observer_node.node import ObserverNode

    return ObserverNode("flux_measured", namespace="/obs", context=ctx, parameter_overrides=ov)


@pytest.mark.parametrize("kind", ["controller", "observer"])
def test_node_descriptors_are_the_schema(kind, ctx):
    """Every schema field a node declares: description starts with the field's doc and ends
    with its unit, range = the schema's range on the scenario's card, read-only = not live."""
    sc = load_scenario(scenario_path("paper_2pct_150load"))
    cfg = sc.control if kind == "controller" else sc.observers["flux_measured"]
    rng = schema.ranges(cfg, sc.machine, int(sc.control.decimation))
    node = _node(kind, ctx)
    try:
        seen = 0
        for name, s in schema.specs(cfg).items():
            if not node.has_parameter(name):
                continue
            seen += 1
            d = node.describe_parameter(name)
            assert d.description.startswith(s.doc), (name, d.description)
            if s.numeric:
                unit = "-" if s.unit == "-" else s.unit
                assert d.description.endswith(f"[{unit}]"), (name, d.description)
                r = (d.floating_point_range or d.integer_range)[0]
                lo, hi = rng[name]
                lo = 0.0 if s.none_is_zero else lo
                assert math.isclose(r.from_value, lo) and math.isclose(r.to_value, hi), name
            if s.choices:
                assert re.findall(r"[\w]+", d.additional_constraints)[2:] == list(s.choices)
            assert d.read_only == (not s.live), name
        assert seen >= 12
    finally:
        node.destroy_node()


def test_bridge_descriptors_are_the_schema(ctx):
    """The bench bridge in split mode: drive.<field> per DriveParams field and the supervisor's
    settings carry the schemas' ranges (what the drive and CanBridge accept) and text."""
    from bench_bridge.bridge_node import SUPERVISOR_FIELDS, BenchBridgeNode
    from fluxdrive.can.bridge import BridgeConfig
    from fluxdrive.can.loop import new_virtual_channel
    from fluxdrive.drive.control import DRIVE_PARAM_RANGES, DriveParams
    from rclpy.parameter import Parameter

    ov = [
        Parameter("channel", value=new_virtual_channel()),
        Parameter("control_split", value=True),
        Parameter("scenario", value=SCENARIO),
    ]
    node = BenchBridgeNode(context=ctx, parameter_overrides=ov)
    try:
        fields = [("drive." + n, n, s, DriveParams) for n, s in schema.specs(DriveParams).items()]
        fields += [(n, n, schema.specs(BridgeConfig)[n], BridgeConfig) for n in SUPERVISOR_FIELDS]
        for pname, name, s, cls in fields:
            d = node.describe_parameter(pname)
            assert d.description.startswith(s.doc), (pname, d.description)
            assert d.read_only == (not s.live), pname
            if s.numeric:
                r = (d.floating_point_range or d.integer_range)[0]
                assert (r.from_value, r.to_value) == schema.ranges(cls)[name], pname
        assert {n.upper() for n in schema.specs(DriveParams)} == set(DRIVE_PARAM_RANGES)
    finally:
        node.destroy_node()


# every node the graphs run, as paramdoc starts them: (class, node name, namespace, parameters)
NODES = {
    "plant": ("plant", "", {"scenario": SCENARIO}),
    "controller": ("controller", "", {"scenario": SCENARIO}),
    "observer": ("flux_measured", "/obs", {"scenario": SCENARIO}),
    "recorder": ("recorder", "", {}),  # bag_dir: under tmp_path
    "scope_tap": ("scope_tap", "", {"scenario": SCENARIO}),
}
ROS_OWN = {"use_sim_time", "start_type_description_service"}  # rclpy declares these itself


def _check_declared_from_schema(node) -> int:
    """Every parameter the node declared came from a schema field (`declare` keeps them in
    node.param_specs), and its descriptor is that field's: text, read-only = not live, a
    range inside the field's static range."""
    declared = set(node._parameters) - ROS_OWN
    specs = getattr(node, "param_specs", {})
    assert declared == set(specs), f"not from a schema: {sorted(declared - set(specs))}"
    for name, s in specs.items():
        d = node.describe_parameter(name)
        assert d.description.startswith(s.doc), (name, d.description)
        assert d.read_only == (not s.live), name
        r = (d.floating_point_range or d.integer_range or [None])[0]
        assert (r is not None) == (s.numeric and s.lo is not None), name
        if r is not None:
            lo = 0.0 if s.none_is_zero else s.lo
            assert lo <= r.from_value <= r.to_value <= s.hi, (name, r, s.lo, s.hi)
    return len(specs)


@pytest.mark.parametrize("kind", sorted(NODES))
def test_every_node_parameter_comes_from_a_schema(kind, ctx, tmp_path):
    from fluxdrive_ros.runner import load_class
    from rclpy.parameter import Parameter

    name, ns, values = NODES[kind]
    values = {**values, "bag_dir": str(tmp_path / "bag")} if kind == "recorder" else values
    ov = [Parameter(k, value=v) for k, v in values.items()]
    node = load_class(kind)(name, namespace=ns, context=ctx, parameter_overrides=ov)
    try:
        assert _check_declared_from_schema(node) >= 5
    finally:
        if hasattr(node, "proc"):  # the recorder's writer process
            node.close()
        node.destroy_node()


def test_bridge_parameters_come_from_a_schema(ctx):
    from bench_bridge.bridge_node import BenchBridgeNode
    from fluxdrive.can.loop import new_virtual_channel
    from rclpy.parameter import Parameter

    ov = [
        Parameter("channel", value=new_virtual_channel()),
        Parameter("control_split", value=True),
        Parameter("scenario", value=SCENARIO),
    ]
    node = BenchBridgeNode(context=ctx, parameter_overrides=ov)
    try:
        assert _check_declared_from_schema(node) >= 20
    finally:
        node.destroy_node()


def test_a_parameter_without_a_schema_is_refused(ctx):
    from fluxdrive_ros.params import P, declare
    from rclpy.node import Node

    node = Node("hand_written", context=ctx)
    try:
        with pytest.raises(TypeError, match="'gain' is not declared from a schema"):
            declare(node, [P("gain", 1.0, "a hand-written parameter", "-", 0.0, 2.0)])
    finally:
        node.destroy_node()


# --------------------------------------------------------------- the graph file's keys
def _graph(top: dict | None = None, node: dict | None = None) -> dict:
    return {
        **(top or {}),
        "nodes": [{"name": "plant", "node": "plant", **(node or {})}],
    }


@pytest.mark.parametrize("where", ["top", "node"])
def test_graph_file_keys_take_exactly_the_schema_range(where):
    """A graph file (`./fluxdrive launch`): its keys are the fields of
    fluxdrive.io.graphfile -- the ends of every range accepted, just outside
    refused in one line naming the file, the entry and the key; a choice outside its list
    likewise, and a key no field declares."""
    pytest.importorskip("fluxdrive_bringup")
    from fluxdrive.io import graphfile
    from fluxdrive_bringup.launch.launcher import parse_graph

    keys = graphfile.TOP_KEYS if where == "top" else graphfile.NODE_KEYS
    place = "g.yaml" if where == "top" else "g.yaml: nodes[0] (plant)"

    def parse(kw: dict):
        return parse_graph(_graph(kw) if where == "top" else _graph(node=kw), "g.yaml")

    numeric = {k: s for k, s in keys.items() if s.numeric}
    assert numeric and all(s.lo is not None and s.hi is not None for s in numeric.values())
    for name, s in numeric.items():
        for ok in (s.lo, s.hi):
            parse({name: s.kind(ok)})
        step = 1 if s.kind is int else max(abs(s.hi), abs(s.lo), 1.0) * 1e-6
        for bad in (s.lo - step, s.hi + step):
            with pytest.raises(ConfigError) as err:
                parse({name: s.kind(bad)})
            text = str(err.value)
            assert text.startswith(f"{place}: {name} must be ") and "\n" not in text, text
            assert f"[{s.lo}, {s.hi}]" in text, text
    for name, s in keys.items():
        if s.choices:
            parse({name: s.choices[-1]})
            with pytest.raises(ConfigError, match=rf"^{re.escape(place)}: {name} must be one of"):
                parse({name: "none_of_them"})
    with pytest.raises(ConfigError, match=rf"^{re.escape(place)}: unknown key\(s\) \['on_deth'\]"):
        parse({"on_deth": "stop"})
