"""Any graph file of the project: graph:=NAME (a file under config/graphs, or a path).

    ros2 launch fluxdrive_bringup graph.launch.py graph:=sim_separate [namespace:=/a] [domain_id:=N]

Read at launch time (fluxdrive_bringup.launch.rosgraph): the same graph `./fluxdrive launch
NAME` starts.  Without graph:=, the demo graph (config/graphs/sim_lockstep.yaml).
"""

GRAPH = "sim_lockstep.yaml"


def generate_launch_description():
    from fluxdrive_bringup.launch.rosgraph import generate

    return generate(GRAPH)
