"""Installed sizes of a robot's venv and a developer's, for two revisions side by side in one run.

    python bench/bench_install.py --before REV [--after REV] [--no-developer]

Each revision is unpacked with ``git archive`` (``--after`` defaults to the working tree as it is). For each:

- a robot's venv: ``python -m venv``, then ROS (the PyPI wheels that the revision's requirements-dev.txt names,
  with its constraints.txt: what a robot has as its ROS), then the policy node alone, then the sim node beside
  it, both through this checkout's ``scripts/install_nodes.sh --from`` the revision (the same pip command for
  every revision: its package directories, its constraints, not editable);
- a developer's venv: the revision's own ``scripts/setup.sh`` in its unpacked copy.

After each step: ``du -sm`` of the venv's site-packages, and which of torch, torch-geometric, tensorboard,
matplotlib, mujoco and gymnasium are installed (``importlib.metadata``). pip's cache serves the wheels.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WATCHED = ("torch", "torch-geometric", "tensorboard", "matplotlib", "mujoco", "gymnasium")


def _run(cmd: list[str], cwd: Path | None = None) -> None:
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")


def unpack(rev: str, dest: Path) -> Path:
    """The revision's tree at ``dest`` (``.``: this checkout's tracked and untracked, not ignored, files as
    they are, uncommitted changes included)."""
    dest.mkdir(parents=True)
    tar = dest / "tree.tar"
    if rev == ".":
        listed = subprocess.run(
            ["git", "-C", str(ROOT), "ls-files", "-co", "--exclude-standard", "-z"], capture_output=True, check=True
        ).stdout
        files = b"\0".join(f for f in listed.split(b"\0") if f and (ROOT / f.decode()).exists())
        subprocess.run(["tar", "-C", str(ROOT), "-cf", str(tar), "--null", "-T", "-"], input=files, check=True)
    else:
        _run(["git", "-C", str(ROOT), "archive", "--format=tar", "-o", str(tar), rev])
    _run(["tar", "-C", str(dest), "-xf", str(tar)])
    tar.unlink()
    return dest


def site_packages(venv: Path) -> Path:
    return venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"


def measure(venv: Path) -> tuple[int, list[str]]:
    """(MB that du counts in the venv's site-packages, which WATCHED distributions are installed)."""
    mb = int(subprocess.run(["du", "-sm", str(site_packages(venv))], capture_output=True, text=True).stdout.split()[0])
    code = "import importlib.metadata as m, json; print(json.dumps([d.metadata['Name'] for d in m.distributions()]))"
    python = str(venv / "bin" / "python")
    names = json.loads(subprocess.run([python, "-c", code], capture_output=True, text=True, check=True).stdout)
    installed = {re.sub(r"[-_.]+", "-", n).lower() for n in names}
    return mb, [w for w in WATCHED if w in installed]


def robot(tree: Path, work: Path) -> list[tuple[str, int, list[str]]]:
    venv = work / "robot"
    _run([sys.executable, "-m", "venv", str(venv)])
    python = str(venv / "bin" / "python")
    ros = [r for r in (tree / "requirements-dev.txt").read_text().splitlines() if r.startswith("ros-")]
    _run([python, "-m", "pip", "install", "--quiet", "-c", str(tree / "constraints.txt"), *ros])
    rows = [("ROS wheels", *measure(venv))]
    install = ["bash", str(ROOT / "scripts" / "install_nodes.sh"), python, "--from", str(tree)]
    _run([*install, "--policy-only"])
    rows.append(("+ policy node", *measure(venv)))
    _run(install)
    rows.append(("+ sim node", *measure(venv)))
    return rows


def developer(tree: Path) -> tuple[str, int, list[str]]:
    _run(["bash", str(tree / "scripts" / "setup.sh")], cwd=tree)
    return ("developer (setup.sh)", *measure(tree / ".venv"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", required=True, help="a git revision")
    parser.add_argument("--after", default=".", help="a git revision; '.': the working tree as it is")
    parser.add_argument("--no-developer", action="store_true", help="the robot's venv only")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_install_") as tmp:
        for name, rev in (("before", args.before), ("after", args.after)):
            tree = unpack(rev, Path(tmp) / name / "tree")
            rows = robot(tree, Path(tmp) / name)
            if not args.no_developer:
                rows.append(developer(tree))
            for what, mb, watched in rows:
                print(f"{name:6s} {rev:10s} | {what:22s} | {mb:6,d} MB | {', '.join(watched) or '-'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
