"""`./fluxdrive` command line.  Subcommands are loaded lazily so that the in-process tools
never import ROS; graph commands live in the fluxdrive_bringup package (src/)."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys

from fluxdrive.core.paths import ROOT
from fluxdrive.core.schema import Parser

REPO = ROOT

# subcommand -> (module, function, one-line help); each function takes argv (list[str])
COMMANDS: dict[str, tuple[str, str, str]] = {
    "sim": ("fluxdrive.cli.sim", "main_sim", "run a scenario in-process (no ROS) and report"),
    "benchmark": (
        "fluxdrive.cli.bench",
        "main",
        "benchmarks: engine | replay | graph | paced | can | study | firmware | plugin | "
        "experiments | setup | services",
    ),
    "demo": (
        "fluxdrive_bringup.cli",
        "main_demo",
        "the main job: 2 % / 150 % load scenario through the ROS graph, recorded",
    ),
    "run": ("fluxdrive_bringup.cli", "main_run", "run any scenario through the ROS graph"),
    "bench": (
        "fluxdrive_bringup.cli",
        "main_bench",
        "bench --interface socketcan --channel can0: a real drive on CAN under the ROS "
        "graph, after a pre-flight; bench --sil: the C drive in the loop",
    ),
    "tune": (
        "fluxdrive_bringup.cli",
        "main_tune",
        "hold a steady operating point (speed, load) paced until Ctrl-C, for live tuning",
    ),
    "launch": ("fluxdrive_bringup.cli", "main_launch", "start a graph described in YAML"),
    "topic": ("fluxdrive_bringup.cli", "main_topic", "topic list|echo|hz"),
    "node": ("fluxdrive_bringup.cli", "main_node", "node list"),
    "param": ("fluxdrive_bringup.cli", "main_param", "param get|set|dump"),
    "bag": (
        "fluxdrive.cli.bag",
        "main",
        "bag recover BAG_DIR [--out DIR]: a valid bag from an unfinalised one",
    ),
    "fault": ("fluxdrive_bringup.cli", "main_fault", "fault reset: clear a latched drive fault"),
    "scope": (
        "fluxdrive_bringup.cli",
        "main_scope",
        "live scope of a running graph in the browser (plots, parameters, fault reset)",
    ),
    "foxglove": (
        "fluxdrive_bringup.cli",
        "main_foxglove",
        "serve a running graph's topics and parameters to Foxglove / Lichtblick",
    ),
    "soak": (
        "fluxdrive_bringup.cli",
        "main_soak",
        "load check: long lockstep graph run + burst replay (memory, no loss)",
    ),
    "replay": ("fluxdrive.cli.replay", "main", "replay bags through observer variants"),
    "can-import": ("fluxdrive.cli.canimport", "main", "CAN capture (.log/.asc/.blf) -> bag"),
    "can-emulator": (
        "fluxdrive.cli.canemulator",
        "main",
        "the drive emulator (plant as the MCU) on a CAN bus, as a process",
    ),
    "fault-cases": (
        "fluxdrive.cli.faultcases",
        "main",
        "the drive's protections injected on each target (--write docs/firmware.md)",
    ),
    "fault-matrix": (
        "fluxdrive.cli.faultmatrix",
        "main",
        "fault-injection matrix of the control path (--write docs/safety.md)",
    ),
    "identify": (
        "fluxdrive.cli.identify",
        "main",
        "measure R, L, lambda, J, B, deadtime of a motor -> machine card (--check)",
    ),
    "experiment": ("fluxdrive.cli.experiment", "main", "reproduce the paper's figures"),
    "compare": (
        "fluxdrive.cli.compare",
        "main",
        "Pareto fronts of any observer variants (yours too): θ̃ vs allowed speed bandwidth",
    ),
    "study": (
        "fluxdrive.cli.study",
        "main",
        "sweeps and Monte-Carlo robustness maps on dask (local cores or a cluster)",
    ),
    "docs": (
        "fluxdrive.cli.docs",
        "main",
        "docs build | serve | quotes | params: the docs site (mkdocs), its figures and tables",
    ),
    "test": (
        "fluxdrive.cli.main",
        "main_test",
        "run the test suite (with ruff, mypy and the docs build)",
    ),
    "lint": ("fluxdrive.cli.main", "main_lint", "ruff over the project"),
}

# options that need the ROS graph: the same command, entered through the graph tools
LIVE_REPLAY = ("fluxdrive_bringup.replay.live_replay", "main")
EXPERIMENT_GRAPH = ("fluxdrive_bringup.launch.runs", "main_experiment_graph")


def suite_workers() -> int:
    """pytest-xdist workers of `./fluxdrive test`'s parallel part: one more than the
    cores, at most 4.  Most of its graph tests wait -- on lockstep answers over DDS, on
    process start-up -- so one test rarely keeps a core busy: on two cores a third worker
    took the parallel part from 450 s to 348 s.  At most 4: the workers share the domain
    ids 100-219 (tests/ros_domains.py), 30 each at 4."""
    return min(4, (os.cpu_count() or 1) + 1)


def main_test(argv: list[str]) -> int:
    """Run the suite with a ROS domain of its own and discovery on localhost: the given
    pytest arguments as one plain pytest, or (none given) the whole suite in two parts."""
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    env.setdefault("MPLBACKEND", "Agg")
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    if argv:
        return subprocess.call([*cmd, *argv], cwd=REPO, env=env)
    return _whole_suite(cmd, env)


def _whole_suite(cmd: list[str], env: dict[str, str]) -> int:
    """The parallel part, then the serial part (both always run, both print their
    summary); non-zero when either fails.  Closes with the two parts' wall times and one
    line of totals counted from their JUnit reports."""
    import tempfile
    import time
    import xml.etree.ElementTree as ET

    parts = [
        # worksteal: a worker that runs out takes pending tests from the other, so the part
        # does not end on one worker's queue of slow graph tests while the other idles
        ("parallel", ["-n", str(suite_workers()), "--dist", "worksteal", "-m", "not serial"]),
        ("serial", ["-m", "serial"]),
    ]
    codes, walls, counts = [], [], {"passed": 0, "failed": 0, "skipped": 0}
    with tempfile.TemporaryDirectory(prefix="fluxdrive-test-") as tmp:
        for name, args in parts:
            xml = os.path.join(tmp, f"{name}.xml")
            print(f"== fluxdrive test: {name} part (pytest {' '.join(args)})", flush=True)
            t0 = time.monotonic()
            run = [*cmd, *args, "--durations=15", f"--junitxml={xml}"]  # slowest: what to cut
            codes.append(subprocess.call(run, cwd=REPO, env=env))
            walls.append(time.monotonic() - t0)
            if os.path.exists(xml):
                for suite in ET.parse(xml).getroot().iter("testsuite"):
                    n, skip = int(suite.get("tests", 0)), int(suite.get("skipped", 0))
                    bad = int(suite.get("failures", 0)) + int(suite.get("errors", 0))
                    counts["passed"] += n - skip - bad
                    counts["failed"] += bad
                    counts["skipped"] += skip
    done = zip(parts, codes, walls, strict=True)
    print("== fluxdrive test: " + ", ".join(f"{n} exit {c} in {w:.0f} s" for (n, _), c, w in done))
    print("total: {passed} passed, {failed} failed, {skipped} skipped".format(**counts))
    return next((c for c in codes if c != 0), 0)


def main_lint(argv: list[str]) -> int:
    return subprocess.call([sys.executable, "-m", "ruff", "check", *(argv or ["."])], cwd=REPO)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        parser = Parser(prog="fluxdrive", description=__doc__)
        parser.print_usage()
        print("\ncommands:")
        for name, (_, _, text) in COMMANDS.items():
            print(f"  {name:12s} {text}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"fluxdrive: unknown command '{cmd}'; try ./fluxdrive help", file=sys.stderr)
        return 2
    mod, fn, _ = COMMANDS[cmd]
    if cmd == "replay" and "--live" in rest:
        mod, fn = LIVE_REPLAY  # the ROS publisher lives with the graph tools
    if cmd == "experiment" and "--graph" in rest:
        mod, fn = EXPERIMENT_GRAPH  # installs the graph runner, then the same experiments
    try:
        func = getattr(importlib.import_module(mod), fn)
    except (ImportError, AttributeError) as exc:
        if cmd != "demo":
            print(f"fluxdrive {cmd}: not available ({exc})", file=sys.stderr)
            return 2
        # until the graph package is built: the same scenario, in-process
        print(
            f"fluxdrive demo: the ROS graph is not available ({exc}); running the scenario "
            f"in-process instead",
            file=sys.stderr,
        )
        from fluxdrive.cli.sim import main_sim

        func = lambda argv: main_sim(["paper_2pct_150load", *argv])  # noqa: E731
    from fluxdrive.core.machine import ConfigError

    try:
        return int(func(rest) or 0)
    except ConfigError as exc:
        print(f"fluxdrive {cmd}: configuration error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
