from setuptools import find_packages, setup

package_name = "foc_controller_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="fluxdrive",
    maintainer_email="fluxdrive@example.com",
    description=(
        "Field-oriented controller node with sensorless start-up (PhaseFrame "
        "and RotorEstimate in, DutyCommand out)."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": ["controller = foc_controller_node.node:main"],
    },
)
