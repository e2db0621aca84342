"""``morph-record``'s own command line, without DDS: ``--help`` prints the parameters and exits; a stray
argument is refused. Neither starts a recorder nor leaves a bag behind."""

import subprocess
import sys

CLI = [sys.executable, "-m", "trainer.bags.record"]


def test_help_prints_the_parameters_and_creates_nothing(tmp_path):
    done = subprocess.run([*CLI, "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "usage: morph-record" in done.stdout
    for name in ("output", "max_episodes", "storage", "topics"):
        assert f"\n  {name} " in done.stdout, name
    assert "(default: 'mcap')" in done.stdout
    assert list(tmp_path.iterdir()) == []  # no bag (rosbag2_<date>) in the folder it ran in


def test_an_argument_outside_ros_args_is_refused_and_creates_nothing(tmp_path):
    done = subprocess.run([*CLI, "--out", "bag"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "morph-record: error: unrecognized arguments: --out bag" in done.stderr
    assert list(tmp_path.iterdir()) == []
