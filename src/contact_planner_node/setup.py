from setuptools import find_packages, setup

package_name = "contact_planner_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", ["config/contact_planner_node.yaml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    description="Contact-before-motion planner node over ROS 2.",
    license="Apache-2.0",
    entry_points={"console_scripts": ["contact_planner_node = contact_planner_node.node:main"]},
)
