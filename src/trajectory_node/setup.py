from setuptools import find_packages, setup

package_name = "trajectory_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", ["config/trajectory_node.yaml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    description="Stance plans interpolated, timed and executed through pik_node.",
    license="Apache-2.0",
    entry_points={"console_scripts": ["trajectory_node = trajectory_node.node:main"]},
)
