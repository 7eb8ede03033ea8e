"""The real-bench graph: the drive on a CAN bus (bench_bridge in split mode at D = 4), the
observers, the controller and the recorder.  Run `./fluxdrive bench --check` (the pre-flight)
first: this launch arms the drive once its parameters are acknowledged, like `./fluxdrive bench`
after its pre-flight.

    ros2 launch fluxdrive_bringup bench.launch.py [namespace:=/bench_a] [domain_id:=N]

The graph is the project's graph file config/graphs/bench_real.yaml, read at launch time
(fluxdrive_bringup.launch.rosgraph): the same graph `./fluxdrive launch bench_real.yaml` starts.
"""

GRAPH = "bench_real.yaml"


def generate_launch_description():
    from fluxdrive_bringup.launch.rosgraph import generate

    return generate(GRAPH)
