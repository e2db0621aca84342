from setuptools import find_packages, setup

package_name = "swimmer_sim_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["morph_core[sim]"],
    zip_safe=True,
    maintainer="morph-control developers",
    maintainer_email="dev@example.org",
    description=(
        "ROS 2 node: MuJoCo swimmer with a configurable chain and episodes, "
        "publishing JointState, Odometry, Clock and episode announcements."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "swimmer_sim_node = swimmer_sim_node.sim_node:main",
        ],
    },
)
