import sys
from pathlib import Path

# helpers importable from tests; fluxdrive from the repo even without an editable install
sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))


def pytest_configure(config):
    """ROS_DOMAIN_ID of this pytest process's slice (tests/ros_domains.py): the xdist
    workers of `./fluxdrive test` never share a domain, whatever reads the environment."""
    from ros_domains import pin_process_domain

    pin_process_domain()


def pytest_collection_finish(session):
    """Graph tests start launchers and time their start-up; after an engine change the
    launcher first compiles the nodes' kernels (fluxdrive_bringup.launch.kernels), which on
    a loaded machine takes minutes. Do it once here, before any test's clock runs; a no-op
    while numba's cache holds them."""
    import re

    starts = re.compile(r"Launcher\(|run_graph\(")
    files = {Path(item.path) for item in session.items}
    if not any(f.name.startswith("test_graph_") or starts.search(f.read_text()) for f in files):
        return
    try:
        from fluxdrive_bringup.launch.kernels import warm_for_graph
    except ImportError:  # no ROS packages built: the graph tests skip themselves
        return
    _compile_this_workers_share("paper_2pct_150load")
    warm_for_graph(["paper_2pct_150load"], lambda text: print(text, file=sys.stderr))


def _compile_this_workers_share(scenario: str) -> None:
    """With a cold cache and two xdist workers, warm_for_graph compiles in one worker while
    the other waits on the cache lock (about 45 s of a quiet machine, one core idle).  Each
    worker first compiles its own share instead, both at once: gw0 the plant's kernels
    (about 27 s) holding the cache lock, the others the observers' and the controller's
    (about 17 s) without it.  warm_for_graph then takes the lock in each worker -- after
    gw0's share, so nothing is compiled twice -- loads every kernel from the cache and
    writes its marker."""
    import os
    from contextlib import nullcontext

    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw") or int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) < 2:
        return
    cache = os.environ.get("NUMBA_CACHE_DIR")
    from fluxdrive_bringup.launch.kernels import MARKER

    if not cache or (Path(cache) / MARKER).exists():
        return
    from fluxdrive.drive.scenario import load_scenario, scenario_path
    from fluxdrive.drive.warm import cache_lock, graph_kernel_calls

    plant = worker == "gw0"
    with cache_lock() if plant else nullcontext():
        for kernel, args in graph_kernel_calls(load_scenario(scenario_path(scenario))):
            if kernel.__name__.startswith("plant_") == plant:  # type: ignore[attr-defined]
                kernel(*args)  # type: ignore[operator]
