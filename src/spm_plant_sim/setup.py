from setuptools import find_packages, setup

package_name = "spm_plant_sim"

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
        "Switching-level SPM machine, inverter and sensor simulator node "
        "(publishes PhaseFrame, PlantTruth, /clock)."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": ["plant = spm_plant_sim.node:main"],
    },
)
