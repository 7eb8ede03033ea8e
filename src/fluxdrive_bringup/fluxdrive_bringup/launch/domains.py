"""Which ROS domain a graph runs on: the nodes alive on a domain, a free domain for a run,
and the refusal that names them when the chosen one is in use (two graphs on one domain hear
each other's samples)."""

from __future__ import annotations

import os
import random


def domain_users(domain_id: int, wait_s: float | None = None) -> list[str]:
    """Nodes alive on a ROS domain (discovery on localhost), after up to wait_s (default:
    one discovery announcement period, inspect_cli.SETTLE_MIN_S): another graph there would
    hear this one's topics and this one its."""
    from fluxdrive_bringup.inspect.commands import SETTLE_MIN_S, Session

    wait_s = SETTLE_MIN_S if wait_s is None else wait_s
    s = Session(domain_id=domain_id, wait_s=wait_s, node_name=f"fluxdrive_probe_{os.getpid()}")
    try:
        me = s.node.get_name()

        def others() -> list[str]:
            return sorted(
                {
                    f"{ns.rstrip('/')}/{n}"
                    for n, ns in s.node.get_node_names_and_namespaces()
                    if n != me
                }
            )

        s.discover(lambda: bool(others()))
        return others()
    finally:
        s.close()


def choose_domain(domain_id: int | None, what: str) -> tuple[int | None, str]:
    """A domain no live node uses: the given one (--domain-id, else ROS_DOMAIN_ID) if it is
    free -- else (None, one line naming the clash); without either, a random free one."""
    given = (
        domain_id
        if domain_id is not None
        else (int(os.environ["ROS_DOMAIN_ID"]) if os.environ.get("ROS_DOMAIN_ID") else None)
    )
    if given is not None:
        users = domain_users(given)
        if users:
            shown = ", ".join(users[:6]) + (f" and {len(users) - 6} more" if len(users) > 6 else "")
            return None, (
                f"ROS_DOMAIN_ID={given} is in use by {shown} (another graph?): two "
                f"graphs on one domain hear each other's samples; choose another "
                f"(--domain-id) or unset ROS_DOMAIN_ID for a free one, or "
                f"--shared-domain to {what} there anyway"
            )
        return given, ""
    for _ in range(8):
        dom = random.randint(110, 219)
        if not domain_users(dom, wait_s=0.5):
            return dom, ""
    return None, "no free ROS domain found among 8 random ones in 110-219"


def pick_domain_id() -> int:
    """The environment's ROS_DOMAIN_ID, else a random one (a run must not meet another)."""
    env = os.environ.get("ROS_DOMAIN_ID")
    if env:
        return int(env)
    return random.randint(110, 219)
