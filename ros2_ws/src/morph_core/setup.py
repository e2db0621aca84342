from setuptools import find_packages, setup

package_name = "morph_core"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=[
        "numpy",
        "mujoco>=4.0",  # mujoco.batch (the evaluation steps its swimmers in one call)
        "gymnasium",
        "torch",
        "torch-geometric",
        "safetensors",
        "matplotlib",
        "scipy",
        "tqdm",
        "tensorboard",
        "cryptography",  # Ed25519 signatures on pushed weights (protocol.trust)
    ],
    zip_safe=True,
    maintainer="morph-control developers",
    maintainer_email="dev@example.org",
    description=(
        "ROS-free core: variable-chain MuJoCo swimmer, joint graph, GNN actor-critic, "
        "PPO with trust-region compensation, theory."
    ),
    license="Apache-2.0",
)
