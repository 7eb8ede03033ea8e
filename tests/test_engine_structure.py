"""Structure of the engine package: no ROS import, kernel array layouts counted, not typed."""

from __future__ import annotations

import ast
from pathlib import Path

import fluxdrive
import pytest
from fluxdrive.core.layout import Layout
from fluxdrive.drive import observers, plant
from fluxdrive.drive.control import kernel as control

ENGINE = Path(fluxdrive.__file__).resolve().parent


def test_engine_has_no_ros_import():
    """No module under python/fluxdrive imports rclpy (or any ROS client package), at any
    depth of the file (a function-level import counts too): the engine runs without ROS."""
    ros = ("rclpy", "rosidl_runtime_py", "flux_drive_msgs", "fluxdrive_ros", "fluxdrive_bringup")
    offenders = []
    files = sorted(ENGINE.rglob("*.py"))
    assert len(files) > 20
    for f in files:
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif (
                isinstance(node, ast.Call)
                and getattr(node.func, "attr", getattr(node.func, "id", ""))
                in ("import_module", "__import__")
                and node.args
                and isinstance(node.args[0], ast.Constant)
                and isinstance(node.args[0].value, str)
            ):
                names = [node.args[0].value]  # importlib.import_module("rclpy")
            else:
                continue
            for n in names:
                if n.split(".")[0] in ros:
                    offenders.append(f"{f.relative_to(ENGINE)}:{node.lineno} imports {n}")
    assert not offenders, offenders


@pytest.mark.parametrize(
    "mod, prefix",
    [
        (plant, "MP"),
        (plant, "PS"),
        (plant, "FR"),
        (plant, "TR"),
        (plant, "LD"),
        (observers, "OP"),
        (observers, "OS"),
        (observers, "ES"),
        (control, "CP"),
        (control, "CS"),
        (control, "CO"),
    ],
)
def test_kernel_layouts_are_dense(mod, prefix):
    """Every kernel array's constants are 0..N-1, each once, and N is the count."""
    ns = vars(mod)
    idx = sorted(
        v
        for k, v in ns.items()
        if k.startswith(prefix + "_") and k != prefix + "_N" and isinstance(v, int)
    )
    assert idx == list(range(ns[prefix + "_N"]))
    assert len(ns["_" + prefix].names) == ns[prefix + "_N"]


def test_layout_refuses_a_hand_typed_index():
    ns: dict[str, object] = {}
    lay = Layout("XX")
    ns["XX_A"] = lay.index()
    ns["XX_B"], ns["XX_C"] = lay.indices(2)
    assert lay.close(ns) == 3 and lay.names == ("a", "b", "c")
    bad = Layout("YY")
    ns2 = {"YY_A": bad.index(), "YY_B": 5}
    with pytest.raises(RuntimeError, match="YY"):
        bad.close(ns2)


def test_layout_names_given_with_the_indices():
    """A name handed out with an index is the column's name; the rest are the constants'."""
    lay = Layout("ZZ")
    ns: dict[str, object] = {"ZZ_IA": lay.index("i_a")}
    ns["ZZ_X"], ns["ZZ_Y"] = lay.indices(2, "x_pos y_pos")
    ns["ZZ_K"] = lay.index()
    assert lay.close(ns) == 4 and lay.names == ("i_a", "x_pos", "y_pos", "k")
    with pytest.raises(ValueError, match="ZZ2"):
        Layout("ZZ2").indices(2, "one")
