"""The paced tuning graph: the simulated drive paced to the wall clock until Ctrl-C, one process
per node, for live parameter changes (`./fluxdrive param set ...` from another shell).

    ros2 launch fluxdrive_bringup tune.launch.py [namespace:=/bench_a] [domain_id:=N]

The graph is the project's graph file config/graphs/sim_paced.yaml, read at launch time
(fluxdrive_bringup.launch.rosgraph): the same graph `./fluxdrive launch sim_paced.yaml` starts.
"""

GRAPH = "sim_paced.yaml"


def generate_launch_description():
    from fluxdrive_bringup.launch.rosgraph import generate

    return generate(GRAPH)
