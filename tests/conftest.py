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
    warm_for_graph(["paper_2pct_150load"], lambda text: print(text, file=sys.stderr))
