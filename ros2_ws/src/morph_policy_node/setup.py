from glob import glob

from setuptools import find_packages, setup

package_name = "morph_policy_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    # The shipped policy lives beside the node module, so the default checkpoint
    # resolves the same way in a source checkout, a venv and a colcon install.
    package_data={
        package_name: [
            "models/*.safetensors",
            "models/*.json",
            "models/README.md",
            "fastdds_profile.xml",
            "fastdds_profile_loopback_only.xml",
        ]
    },
    include_package_data=True,
    install_requires=["morph_core"],
    zip_safe=False,  # the shipped model is read from beside the module
    maintainer="morph-control developers",
    maintainer_email="dev@example.org",
    description="ROS 2 node: morphology-agnostic GNN policy, joint graph built from each JointState message.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "morph_policy_node = morph_policy_node.policy_node:main",
        ],
    },
)
