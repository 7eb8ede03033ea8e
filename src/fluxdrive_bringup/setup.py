from setuptools import find_packages, setup

package_name = "fluxdrive_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
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
