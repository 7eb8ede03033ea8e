"""Markdown tables of every declared parameter of the graph's nodes, read from the nodes
themselves (descriptions, units, ranges, defaults for the demo scenario, live or not):

    python -m fluxdrive_bringup.inspect.paramdoc > /tmp/params.md   (the tables in docs/graph.md)
"""

from __future__ import annotations

import os
import sys

from fluxdrive.drive.scenario import CONFIG_DIR

# node class -> (config block, anchor in docs/configuration.md): the block's fields, which the
# node declares from their schema, are documented there, once
SCHEMA_BLOCKS = {
    "observer": ("observer", "observers-the-flux-observers"),
    "controller": ("control", "control-the-controller"),
}


def _schema_fields(cls: str) -> set[str]:
    from fluxdrive.core import schema
    from fluxdrive.drive.config_blocks import BLOCKS

    return set(schema.specs(BLOCKS[SCHEMA_BLOCKS[cls][0]].cls)) if cls in SCHEMA_BLOCKS else set()


def _schema_note(cls: str) -> list[str]:
    if cls not in SCHEMA_BLOCKS:
        return []
    key, anchor = SCHEMA_BLOCKS[cls]
    return [
        f"Plus every field of the `{key}` block, default the scenario's: "
        f"[configuration.md](configuration.md#{anchor}).",
        "",
    ]


def tables() -> str:
    import rclpy
    from rcl_interfaces.msg import ParameterType

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from fluxdrive_ros.runner import load_class
    from rclpy.parameter import Parameter

    sc = str(CONFIG_DIR / "scenarios" / "paper_2pct_150load.yaml")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0") or 0))
    out = []
    specs = [
        ("spm_plant_sim (/plant)", "plant", "plant", "", {"scenario": sc}),
        ("flux_observer_node (/obs/<name>)", "observer", "flux_measured", "/obs", {"scenario": sc}),
        ("foc_controller_node (/controller)", "controller", "controller", "", {"scenario": sc}),
        (
            "recorder (/recorder)",
            "recorder",
            "recorder",
            "",
            {"bag_dir": "/tmp/fluxdrive-paramdoc-never-written/bag"},
        ),
    ]
    skip = {"use_sim_time", "start_type_description_service"}
    try:
        for title, cls, name, ns, params in specs:
            node = load_class(cls)(
                name,
                namespace=ns,
                context=ctx,
                parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
            )
            try:
                out.append(f"#### {title}\n")
                out.append("| parameter | default (demo) | range / choices | live | description |")
                out.append("|---|---|---|---|---|")
                for pname in sorted(set(node._parameters) - _schema_fields(cls)):
                    if pname in skip:
                        continue
                    d = node.describe_parameter(pname)
                    v = node.get_parameter(pname).value
                    if d.type == ParameterType.PARAMETER_STRING and len(str(v)) > 40:
                        v = "…/" + str(v).rsplit("/", 1)[-1]
                    rng = ""
                    if d.floating_point_range:
                        r = d.floating_point_range[0]
                        rng = f"[{r.from_value:g}, {r.to_value:g}]"
                    elif d.integer_range:
                        r = d.integer_range[0]
                        rng = f"[{r.from_value}, {r.to_value}]"
                    elif d.additional_constraints:
                        rng = d.additional_constraints.replace("one of: ", "")
                    live = "no" if d.read_only else "yes"
                    desc = d.description.replace(" (live)", "").replace("|", "\\|")
                    val = (
                        f"{v:g}"
                        if isinstance(v, float)
                        else repr(v)
                        if isinstance(v, (list, bool))
                        else str(v)
                    )
                    out.append(f"| `{pname}` | {val} | {rng} | {live} | {desc} |")
                out += ["", *_schema_note(cls)]
            finally:
                if hasattr(node, "proc"):  # the recorder's writer process
                    node.close()
                node.destroy_node()
    finally:
        ctx.try_shutdown()
    import shutil

    shutil.rmtree("/tmp/fluxdrive-paramdoc-never-written", ignore_errors=True)
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(tables() + "\n")
