"""Atomic writes that keep the previous file: a writer killed at any moment leaves the newest complete file
under its name (a killed live trainer's state was found missing once, between the two renames)."""

import os
import random
import signal
import subprocess
import sys
import time

import pytest

from morph_core.util.atomic import atomic_write_bytes

WRITER = """
import sys
from morph_core.util.atomic import atomic_write_bytes
path, previous = sys.argv[1], sys.argv[2]
i = 0
print("ready", flush=True)
while True:
    i += 1
    atomic_write_bytes(path, str(i).encode() * 64, previous=previous)
"""


def test_the_previous_file_is_kept_and_the_new_one_replaces_it(tmp_path):
    path, previous = tmp_path / "state.bin", tmp_path / "state.prev.bin"
    atomic_write_bytes(path, b"one", previous=previous)
    assert path.read_bytes() == b"one" and not previous.exists()
    atomic_write_bytes(path, b"two", previous=previous)
    atomic_write_bytes(path, b"three", previous=previous)
    assert path.read_bytes() == b"three" and previous.read_bytes() == b"two"


@pytest.mark.slow
def test_a_writer_killed_at_any_moment_leaves_a_complete_file_under_the_name(tmp_path):
    # A real process rewriting the file in a loop, SIGKILLed at random moments: each time, the name must
    # hold a complete file (it did not when the kill fell between moving the old file away and moving the
    # new one in).
    rng = random.Random(0)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    for kill in range(40):
        path, previous = tmp_path / f"s{kill}.bin", tmp_path / f"s{kill}.prev.bin"
        atomic_write_bytes(path, b"0" * 64)
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path), str(previous)], env=env,
                                stdout=subprocess.PIPE, text=True)  # fmt: skip
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.01, 0.05))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        assert path.exists(), f"kill {kill}: {path.name} missing ({sorted(p.name for p in tmp_path.iterdir())})"
        data = path.read_bytes()
        assert len(data) % 64 == 0 and data == data[: len(data) // 64] * 64, f"kill {kill}: a partial file"
