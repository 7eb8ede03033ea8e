from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

package_name = "fluxdrive_bringup"
# the project's config/ (graph files, ROS parameter files, scenarios, machine cards, benches,
# the DBC) lives at the repository root: installed to share/fluxdrive_bringup/config, where
# the launch files read the graph files (fluxdrive_bringup.launch.rosgraph)
CONFIG = "../../config"


def config_files() -> list[tuple[str, list[str]]]:
    """(share/<package>/config/<dir>, [files]) for every directory under config/."""
    here = Path(__file__).resolve().parent
    out: dict[str, list[str]] = {}
    for f in sorted((here / CONFIG).resolve().rglob("*")):
        if f.is_file():
            rel = f.relative_to((here / CONFIG).resolve())
            dest = str(Path("share", package_name, "config", rel.parent))
            out.setdefault(dest, []).append(str(Path(CONFIG, rel)))
    return sorted(out.items())


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", sorted(glob("launch/*.launch.py"))),
        *config_files(),
    ],
    # the scope's page and its vendored JavaScript (served from the package directory)
    package_data={package_name: ["view/scope_web/*.*", "view/scope_web/vendor/*"]},
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="fluxdrive",
    maintainer_email="fluxdrive@example.com",
    description="Scripts and configuration to start the fluxdrive node graph.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "recorder = fluxdrive_bringup.record.recorder:main",
            "container = fluxdrive_ros.runner:container_main",
            "scope = fluxdrive_bringup.view.scope:main",
            "scope_tap = fluxdrive_bringup.view.scope_tap:main",
            "foxglove_bridge = fluxdrive_bringup.view.foxglove_bridge:main",
        ],
    },
)
