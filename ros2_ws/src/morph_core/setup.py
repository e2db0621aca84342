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
    # What the nodes import: messages, protocol, the NumPy policy, the tree, weights, trust. A robot installs
    # this part only (and the sim node "[sim]"); no torch, no training stack.
    install_requires=[
        "numpy",
        "safetensors",
        "cryptography",  # Ed25519 signatures on pushed weights (protocol.trust)
    ],
    extras_require={
        # env: the MuJoCo bodies and the Gymnasium envs (what the sim node wraps). mujoco>=4.0: mujoco.batch
        # (the evaluation steps its swimmers in one call).
        "sim": ["mujoco>=4.0", "gymnasium"],
        # algo, the torch policy, theory: what the trainer runs (it requires this extra)
        "learn": ["morph_core[sim]", "torch", "torch-geometric", "tensorboard", "scipy", "tqdm"],
    },
    zip_safe=True,
    maintainer="morph-control developers",
    maintainer_email="dev@example.org",
    description=(
        "ROS-free core: variable-chain MuJoCo swimmer, joint graph, GNN actor-critic, "
        "PPO with trust-region compensation, theory."
    ),
    license="Apache-2.0",
)
