from setuptools import find_packages, setup

package_name = "stance_tools"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["data/*.yaml", "paths/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", ["launch/stance.launch.py"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    description="The stance command line: teleop, record, plot, demo, bench, graph.",
    license="Apache-2.0",
    entry_points={"console_scripts": ["stance = stance_tools.cli:main"]},
)
