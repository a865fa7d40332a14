from setuptools import find_packages, setup

package_name = "stabilizer_gate_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", ["config/stabilizer_gate_node.yaml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    description="Stabilizer gate over ROS 2: coplanarity of the active stance, ramped switch.",
    license="Apache-2.0",
    entry_points={"console_scripts": ["stabilizer_gate_node = stabilizer_gate_node.node:main"]},
)
