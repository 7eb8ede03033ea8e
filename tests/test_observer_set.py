"""The project's observer set is declared once, in the demo scenario's `observers` block; the
graph files (`observers_of:`), the observer nodes' parameters (from the scenario) and the
experiments (OBS6, beyond.VARIANTS) derive it from there."""

from __future__ import annotations

import pytest
from fluxdrive.core import yamlio
from fluxdrive.drive.scenario import (
    CONFIG_DIR,
    OBSERVER_SET_SCENARIO,
    load_scenario,
    observer_set,
    scenario_path,
)

SET = observer_set()


def test_the_set_is_the_demo_scenarios_observers():
    raw = yamlio.load_file(scenario_path(OBSERVER_SET_SCENARIO))
    assert SET == raw["observers"] and len(SET) == 6
    sc = load_scenario(scenario_path(OBSERVER_SET_SCENARIO))
    for name, spec in SET.items():
        assert sc.observers[name].variant == spec["variant"]
        assert sc.observers[name].voltage_source == spec["voltage_source"]


@pytest.mark.parametrize("graph", ["sim_lockstep", "sim_separate"])
def test_graph_files_expand_the_set(graph):
    pytest.importorskip("rclpy")
    from fluxdrive_bringup.launch.launcher import load_graph

    g = load_graph(CONFIG_DIR / "graphs" / f"{graph}.yaml")
    obs = [n for n in g.nodes if n.node == "observer"]
    assert [n.name for n in obs] == list(SET)
    assert all(n.namespace == "/obs" for n in obs)


def test_node_parameters_and_experiments_read_the_set():
    # the observer nodes' parameter file names the scenario and declares no observer itself
    ros = yamlio.load_file(CONFIG_DIR / "ros" / "observers.yaml")
    assert list(ros) == ["/obs/**"]
    assert ros["/obs/**"]["ros__parameters"]["scenario"].endswith(f"{OBSERVER_SET_SCENARIO}.yaml")
    from fluxdrive.experiments.beyond_common import VARIANTS
    from fluxdrive.experiments.common import LITERAL, OBS4, OBS6

    assert OBS6 == SET and {**OBS4, **LITERAL} == SET
    assert all(VARIANTS[k] == v for k, v in OBS4.items())
