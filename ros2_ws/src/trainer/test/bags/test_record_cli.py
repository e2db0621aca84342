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
    assert "(default: 'mcap'; read-only)" in done.stdout
    assert list(tmp_path.iterdir()) == []  # no bag (rosbag2_<date>) in the folder it ran in


def test_an_argument_outside_ros_args_is_refused_and_creates_nothing(tmp_path):
    done = subprocess.run([*CLI, "--output", "bag"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "morph-record: error: unrecognized arguments: --output bag" in done.stderr
    assert list(tmp_path.iterdir()) == []


def test_out_is_the_output_parameter_and_not_given_twice(tmp_path):
    """--out, as every tool names the folder it writes; -p output:= still works; both at once are refused."""
    from trainer.bags.record import with_out

    assert with_out(["morph-record"], "my bag") == ["morph-record", "--ros-args", "-p", 'output:="my bag"']
    assert with_out(["morph-record", "--ros-args", "-p", "output:=b"], None)[-1] == "output:=b"
    cmd = [*CLI, "--out", "a", "--ros-args", "-p", "output:=b"]
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--out and -p output:= name the bag twice" in done.stderr
    assert list(tmp_path.iterdir()) == []
