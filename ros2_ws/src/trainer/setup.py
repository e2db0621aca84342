from glob import glob

from setuptools import find_packages, setup

package_name = "trainer"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    # morph_core[learn]: the core's learning part (algo, the torch policy, theory), which the nodes never install.
    install_requires=[
        "morph_core[learn]",
        "matplotlib",
        "numpy",
        "rosbags",
        "pillow",
        "imageio-ffmpeg",
        "threadpoolctl",
    ],
    # morph-export: torch's ONNX exporter (onnxscript) and ONNX Runtime to check the graph it writes.
    # morph-sweep and --rollout-workers: Ray Tune trials and Ray actors (Ray is never a node's dependency).
    extras_require={"onnx": ["onnx", "onnxruntime", "onnxscript"], "ray": ["ray[tune]"]},
    zip_safe=True,
    maintainer="morph-control developers",
    maintainer_email="dev@example.org",
    description=(
        "PPO trainer (fixed or dimension-compensated clipping) from simulation, "
        "recorded rosbag2 topics and live rollouts."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "morph-train = trainer.cli.train:main",
            "morph-eval = trainer.cli.eval:main",
            "morph-theory = trainer.cli.theory:main",
            "morph-gait = trainer.cli.gait:main",
            "morph-record = trainer.bags.record:main",
            "morph-bag = trainer.bags.cli:main",
            "morph-render = trainer.cli.render:main",
            "morph-export = trainer.cli.export:main",
            "morph-keys = trainer.cli.keys:main",
            "morph-sweep = trainer.sweep.cli:main",
        ],
    },
)
