"""Graph commands of `./fluxdrive` (dispatched from fluxdrive.cli): launch, run, demo,
topic, node, param, ...  Everything here may import ROS; the in-process tools never do."""

from __future__ import annotations


def main_launch(argv: list[str]) -> int:
    from fluxdrive_bringup.launch.launcher import main

    return main(argv)


def main_run(argv: list[str]) -> int:
    from fluxdrive_bringup.launch.runs import main_run as run

    return run(argv)


def main_bench(argv: list[str]) -> int:
    if "--sil" in argv or "--pil" in argv:  # simulated drive: host build or board image
        from fluxdrive_bringup.measure.sil import main
    else:  # the real bench: a drive on a CAN bus
        from fluxdrive_bringup.measure.realbench import main

    return main(argv)


def main_demo(argv: list[str]) -> int:
    from fluxdrive_bringup.launch.runs import main_demo as demo

    return demo(argv)


def main_tune(argv: list[str]) -> int:
    from fluxdrive_bringup.launch.tune import main

    return main(argv)


def main_topic(argv: list[str]) -> int:
    from fluxdrive_bringup.inspect.commands import main_topic as f

    return f(argv)


def main_node(argv: list[str]) -> int:
    from fluxdrive_bringup.inspect.commands import main_node as f

    return f(argv)


def main_param(argv: list[str]) -> int:
    from fluxdrive_bringup.inspect.commands import main_param as f

    return f(argv)


def main_soak(argv: list[str]) -> int:
    from fluxdrive_bringup.measure.soak import main

    return main(argv)


def main_fault(argv: list[str]) -> int:
    from fluxdrive_bringup.inspect.commands import main_fault as f

    return f(argv)


def main_scope(argv: list[str]) -> int:
    from fluxdrive_bringup.view.scope import main

    return main(argv)


def main_foxglove(argv: list[str]) -> int:
    from fluxdrive_bringup.view.foxglove_bridge import main

    return main(argv)
