from setuptools import find_packages, setup

package_name = "morph_ros_util"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["morph_core"],  # protocol.input_counts (diagnostics)
    zip_safe=True,
    maintainer="morph-control developers",
    maintainer_email="dev@example.org",
    description="ROS 2 helpers shared by the project's nodes: a node runner that always ends on SIGINT/SIGTERM.",
    license="Apache-2.0",
)
