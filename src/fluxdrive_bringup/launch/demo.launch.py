"""The demo graph: the simulated drive in lockstep on the 2 % speed / 150 % load scenario,
sensorless, recorded; it ends by itself after the scenario.

    ros2 launch fluxdrive_bringup demo.launch.py [namespace:=/bench_a] [domain_id:=N]

The graph is the project's graph file config/graphs/sim_lockstep.yaml, read at launch time
(fluxdrive_bringup.launch.rosgraph): the same graph `./fluxdrive launch sim_lockstep.yaml` starts.
"""

GRAPH = "sim_lockstep.yaml"


def generate_launch_description():
    from fluxdrive_bringup.launch.rosgraph import generate

    return generate(GRAPH)
