"""scripts/bit_for_bit.py compares two outputs exactly only when one machine made both: across CPUs the
kernels round differently, and a difference would say nothing about the code (issue 49)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "bit_for_bit.py"
sys.path.insert(0, str(SCRIPT.parent))
import bit_for_bit  # noqa: E402

from morph_core.algo.run_dir import RunDir  # noqa: E402

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)


def _out(path: Path, machine: dict | None, returns: list[str]) -> Path:
    (path / "sim-p1").mkdir(parents=True)
    rows = ["global_step,return_mean,wall_time", *(f"{i},{r},{i * 0.5}" for i, r in enumerate(returns))]
    RunDir(path / "sim-p1").progress.write_text("\n".join(rows) + "\n")
    if machine is not None:
        (path / bit_for_bit.MACHINE).write_text(json.dumps(machine))
    return path


def _compare(a: Path, b: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "compare", str(a), str(b)], capture_output=True, text=True)


def test_the_fingerprint_names_this_machine():
    here = bit_for_bit._machine(ROOT)
    assert here["cpu"] and here["torch_cpu_capability"] and here["cores"] >= 1
    assert here == bit_for_bit._machine(ROOT)  # the same machine twice is the same machine


def test_outputs_of_one_machine_are_compared_to_the_bit(tmp_path):
    here = bit_for_bit._machine(ROOT)
    a = _out(tmp_path / "a", here, ["1.5", "2.25"])
    same = _compare(a, _out(tmp_path / "b", here, ["1.5", "2.25"]))
    assert same.returncode == 0 and "identical" in same.stdout
    off = _compare(a, _out(tmp_path / "c", here, ["1.5", "2.2500001"]))  # one digit in the last place
    assert off.returncode == 1 and "DIFFERENT" in off.stdout


def test_outputs_of_two_machines_are_refused_in_one_line(tmp_path):
    here = bit_for_bit._machine(ROOT)
    a = _out(tmp_path / "a", here, ["1.5"])
    amd = _out(tmp_path / "b", {**here, "cpu": "AMD EPYC 9B14", "simd": ["avx2", "fma"]}, ["1.5"])
    refused = _compare(a, amd)
    assert refused.returncode == 2 and refused.stdout == ""
    assert refused.stderr.count("\n") == 1 and "made on different machines (cpu, simd differ)" in refused.stderr
    half = _compare(a, _out(tmp_path / "c", None, ["1.5"]))  # one side does not say where it was made
    assert half.returncode == 2 and "only one of" in half.stderr
    old = _compare(_out(tmp_path / "d", None, ["1.5"]), _out(tmp_path / "e", None, ["1.5"]))  # both older
    assert old.returncode == 0
