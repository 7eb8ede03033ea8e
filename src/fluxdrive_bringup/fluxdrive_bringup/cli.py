"""Graph commands of `./fluxdrive` (dispatched from fluxdrive.cli): launch, run, demo,
topic, node, param, ...  Everything here may import ROS; the in-process tools never do."""

from __future__ import annotations


def main_launch(argv: list[str]) -> int:
    from .launch import main

    return main(argv)


def main_run(argv: list[str]) -> int:
    from .runs import main_run as run

    return run(argv)


def main_bench(argv: list[str]) -> int:
    from .sil import main

    return main(argv)


def main_demo(argv: list[str]) -> int:
    from .runs import main_demo as demo

    return demo(argv)


def main_tune(argv: list[str]) -> int:
    from .tune import main

    return main(argv)


def main_topic(argv: list[str]) -> int:
    from .inspect_cli import main_topic as f

    return f(argv)


def main_node(argv: list[str]) -> int:
    from .inspect_cli import main_node as f

    return f(argv)


def main_param(argv: list[str]) -> int:
    from .inspect_cli import main_param as f

    return f(argv)


def main_soak(argv: list[str]) -> int:
    from .soak import main

    return main(argv)


def main_fault(argv: list[str]) -> int:
    from .inspect_cli import main_fault as f

    return f(argv)


def main_scope(argv: list[str]) -> int:
    from .scope import main

    return main(argv)


def main_foxglove(argv: list[str]) -> int:
    from .foxglove_bridge import main

    return main(argv)
