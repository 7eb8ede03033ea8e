"""The ROS domain of every test that starts nodes: a slice of domain ids per pytest process,
so the pytest-xdist workers of `./fluxdrive test` never share one.

- the main pytest process (a plain `pytest`, the suite's serial part): 40-99;
- xdist workers (PYTEST_XDIST_WORKER gw0, gw1, ...) split 100-219 evenly: with two
  workers gw0 has 100-159 and gw1 160-219.

All below 233, the highest domain id DDS maps to UDP ports.  Inside its slice a test's
domain is its `offset` (distinct per test, so a straggler of one test never meets the next)
shifted by the ROS_DOMAIN_ID the run started with, so that two checkouts' suites on one
machine rarely pick the same ids.  `pin_process_domain` (tests/conftest.py) sets
ROS_DOMAIN_ID to the slice's first pick for whatever reads the environment.
"""

from __future__ import annotations

import os

MAIN = (40, 100)  # the main process: [lo, hi)
WORKERS = (100, 220)  # shared out among the xdist workers
SEED_VAR = "FLUXDRIVE_TEST_DOMAIN_SEED"  # the ROS_DOMAIN_ID the run started with


def domain_slice() -> tuple[int, int]:
    """[lo, hi) of this pytest process's domain ids."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw"):
        return MAIN
    n = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "2"))
    i = int(worker[2:])
    width = (WORKERS[1] - WORKERS[0]) // max(n, 1)
    if width < 1 or i >= n:
        raise RuntimeError(f"tests/ros_domains.py: no ROS domains left for xdist worker {worker}")
    return WORKERS[0] + i * width, WORKERS[0] + (i + 1) * width


def _seed() -> int:
    try:
        return int(os.environ.get(SEED_VAR) or os.environ.get("ROS_DOMAIN_ID") or 0)
    except ValueError:
        return 0


def domain(offset: int = 0) -> int:
    """This process's ROS domain for the test that uses `offset`."""
    lo, hi = domain_slice()
    return lo + (offset + _seed()) % (hi - lo)


def pin_process_domain() -> None:
    """Remember the run's ROS_DOMAIN_ID as the seed (once, inherited by xdist workers) and
    point ROS_DOMAIN_ID at this process's slice."""
    os.environ.setdefault(SEED_VAR, str(_seed()))
    os.environ["ROS_DOMAIN_ID"] = str(domain(0))
