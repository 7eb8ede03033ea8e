"""Markdown tables of every declared parameter of the graph's nodes, read from the nodes
themselves (descriptions, units, ranges, defaults for the demo scenario, live or not), between
the markers of docs/graph.md:

    python -m fluxdrive_bringup.inspect.paramdoc [--write | --check]   (./fluxdrive docs params)

Every parameter a node declares comes from a schema field (`fluxdrive_ros.params.declare`);
the fields of the controller's and observers' config blocks are in docs/configuration.md.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from fluxdrive.core import schema
from fluxdrive.core.schema import Parser
from fluxdrive.drive.config_blocks import BLOCKS
from fluxdrive.drive.scenario import CONFIG_DIR, REPO_ROOT

PAGE = REPO_ROOT / "docs" / "graph.md"
BEGIN, END = "<!-- node-params -->\n", "<!-- /node-params -->"
# node class -> (config block, anchor in docs/configuration.md): the block's fields, which the
# node declares from their schema, are documented there, once
SCHEMA_BLOCKS = {
    "observer": ("observer", "observers-the-flux-observers"),
    "controller": ("control", "control-the-controller"),
}
ROS_OWN = {"use_sim_time", "start_type_description_service"}  # rclpy declares these


def _nodes(scratch: str) -> list[tuple[str, str, str, str, dict[str, Any]]]:
    """(title, node class, name, namespace, parameters) of each table; graph_id 0: the value
    outside a launched graph (a launch sets its own); the recorder's bag in `scratch`."""
    sc = str(CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml")
    demo = {"scenario": sc, "graph_id": 0}
    return [
        ("spm_plant_sim (/plant)", "plant", "plant", "", demo),
        ("flux_observer_node (/obs/<name>)", "observer", "flux_measured", "/obs", demo),
        ("foc_controller_node (/controller)", "controller", "controller", "", demo),
        ("recorder (/recorder)", "recorder", "recorder", "", {"bag_dir": scratch + "/bag"}),
        (
            "scope tap (/scope_tap, started by `./fluxdrive scope`)",
            "scope_tap",
            "scope_tap",
            "",
            demo,
        ),
    ]


def _schema_fields(cls: str) -> set[str]:
    return set(schema.specs(BLOCKS[SCHEMA_BLOCKS[cls][0]].cls)) if cls in SCHEMA_BLOCKS else set()


def _value_text(v: Any) -> str:
    if isinstance(v, str) and v.startswith(f"{REPO_ROOT}/"):  # the same in every checkout
        v = v[len(f"{REPO_ROOT}/") :]
    if isinstance(v, str) and (len(v) > 40 or v.startswith("/")):  # elsewhere: a temp dir
        return "…/" + v.rsplit("/", 1)[-1]
    if isinstance(v, float):
        return f"{v:g}"
    return repr(v) if isinstance(v, (list, bool)) else str(v)


def _range_text(d) -> str:
    if d.floating_point_range:
        r = d.floating_point_range[0]
        return f"[{r.from_value:g}, {r.to_value:g}]"
    if d.integer_range:
        r = d.integer_range[0]
        return f"[{r.from_value}, {r.to_value}]"
    return d.additional_constraints.replace("one of: ", "")


def _row(name: str, value: Any, d) -> str:
    live = "no" if d.read_only else "yes"
    desc = d.description.replace(" (live)", "").replace("|", "\\|")
    return f"| `{name}` | {_value_text(value)} | {_range_text(d)} | {live} | {desc} |"


def _plugin_row(node_cls) -> list[str]:
    """A user variant declares `plugin_kwargs` (and only its model fields): not on the demo."""
    from fluxdrive_ros.params import config_params

    p = config_params(node_cls.PLUGIN_SETTINGS())[0]
    d = p.descriptor()
    only = "user variants only, which declare this and their model: `r_hat_ohm`, `l_hat_h`, "
    d.description = f"({only}`lambda_hat_vs`) {d.description}"
    return [_row(p.name, p.default, d)]


def _table(cls: str, node) -> list[str]:
    out = [
        "| parameter | default (demo) | range / choices | live | description |",
        "|---|---|---|---|---|",
    ]
    for pname in sorted(set(node._parameters) - _schema_fields(cls) - ROS_OWN):
        out.append(_row(pname, node.get_parameter(pname).value, node.describe_parameter(pname)))
    if cls == "observer":
        out += _plugin_row(type(node))
    out.append("")
    if cls in SCHEMA_BLOCKS:
        key, anchor = SCHEMA_BLOCKS[cls]
        out += [
            f"Plus every field of the `{key}` block, default the scenario's: "
            f"[configuration.md](configuration.md#{anchor}).",
            "",
        ]
    return out


def tables() -> str:
    """The tables, one per node, as docs/graph.md holds them between its markers."""
    import rclpy
    from fluxdrive_ros.runner import load_class
    from rclpy.parameter import Parameter

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0") or 0))
    out = []
    scratch = tempfile.mkdtemp(prefix="fluxdrive-paramdoc-")  # its own: tables run in parallel
    try:
        for title, cls, name, ns, params in _nodes(scratch):
            ov = [Parameter(k, value=v) for k, v in params.items()]
            node = load_class(cls)(name, namespace=ns, context=ctx, parameter_overrides=ov)
            try:
                out += [f"#### {title}", "", *_table(cls, node)]
            finally:
                if hasattr(node, "proc"):  # the recorder's writer process
                    node.close()
                node.destroy_node()
    finally:
        ctx.try_shutdown()
        shutil.rmtree(scratch, ignore_errors=True)
    return "\n".join(out)


def fill(text: str, page: Path = PAGE) -> str:
    """`text` with the tables between its markers regenerated."""
    if BEGIN not in text or END not in text:
        raise ValueError(f"{page}: no {BEGIN.strip()} ... {END} markers")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return head + BEGIN + tables() + END + tail


def main(argv: list[str] | None = None) -> int:
    ap = Parser(prog="paramdoc", description=__doc__.split("\n\n")[0])
    how = ap.add_mutually_exclusive_group()
    how.add_argument("--write", action="store_true", help=f"rewrite the tables in {PAGE.name}")
    how.add_argument("--check", action="store_true", help="exit 1 when they are stale")
    args = ap.parse_args(argv)
    if not (args.write or args.check):
        sys.stdout.write(tables() + "\n")
        return 0
    text = PAGE.read_text()
    try:
        new = fill(text)
    except ValueError as exc:
        print(f"docs params: {exc}", file=sys.stderr)
        return 1
    page = PAGE.relative_to(REPO_ROOT)
    if args.check:
        if new != text:
            print(f"{page}: node parameter tables are stale (./fluxdrive docs params)")
        return int(new != text)
    if new != text:
        PAGE.write_text(new)
    print(f"{page}: node parameter tables {'updated' if new != text else 'current'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
