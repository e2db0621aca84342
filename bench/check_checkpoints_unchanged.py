"""Do the shipped checkpoints answer bit for bit as they did? This code against another commit's, in one process.

Each shipped policy (``morph_policy_node/models/*.safetensors``) is loaded by both versions of ``morph_core``
(this tree's, and ``--ref``'s taken out with ``git archive``), one after the other in this process, and
asked the same questions: the torch policy's mean and value on a batch of chains and one of trees, the
NumPy actor's batch forward, its one-chain and one-tree means, and, with ``--onnx``, the exported
graph's answers in ONNX Runtime. Every answer must be equal bit for bit (same process, same machine).

    python bench/check_checkpoints_unchanged.py              # against main
    python bench/check_checkpoints_unchanged.py --ref HEAD~3 --onnx
"""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "ros2_ws" / "src" / "morph_core"
MODELS = ROOT / "ros2_ws" / "src" / "morph_policy_node" / "morph_policy_node" / "models"


def _questions(global_width: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    b, j = 6, 12
    n = np.array([1, 2, 5, 12, 7, 3])
    mask = np.arange(j) < n[:, None]
    pos = (rng.uniform(-1.5, 1.5, (b, j)) * mask).astype(np.float32)
    vel = (rng.normal(0, 2, (b, j)) * mask).astype(np.float32)
    glob = rng.normal(0, 1, (b, global_width)).astype(np.float32)
    parents = np.full((b, j), -1, np.int64)
    for row in range(b):
        for k in range(n[row]):
            parents[row, k] = rng.integers(-1, k)
    return {"pos": pos, "vel": vel, "glob": glob, "n": n, "parents": parents}


def _core_modules() -> dict:
    return {k: v for k, v in sys.modules.items() if k == "morph_core" or k.startswith("morph_core.")}


def answers(core: Path, onnx: bool, models: list[Path]) -> dict[str, np.ndarray]:
    """Every answer of the checkpoints ``models``, computed by the ``morph_core`` package under ``core``. The
    process's own ``morph_core`` modules are put back afterwards (a test process goes on with its classes)."""
    saved = _core_modules()
    for name in saved:
        del sys.modules[name]
    sys.path.insert(0, str(core))
    try:
        import torch

        chains = importlib.import_module("morph_core.policy.chains")
        numpy_actor = importlib.import_module("morph_core.policy.numpy_actor")
        export = importlib.import_module("morph_core.policy.onnx_export")
        assert Path(chains.__file__).is_relative_to(core), chains.__file__
        out: dict[str, np.ndarray] = {}
        for checkpoint in models:
            policy, weights = export.policy_from_checkpoint(checkpoint)
            q = _questions(weights.config.global_features)
            actor = numpy_actor.NumpyPolicy(weights)
            key = checkpoint.stem
            with torch.no_grad():
                for kind, parents in (("chains", None), ("trees", q["parents"])):
                    batch = chains.ChainBatch.from_padded(q["pos"], q["vel"], q["glob"], q["n"], parents=parents)
                    mean, _, value = policy(batch)
                    out[f"{key}/torch/{kind}/mean"], out[f"{key}/torch/{kind}/value"] = mean.numpy(), value.numpy()
                    m, v = actor.forward(q["pos"], q["vel"], q["glob"], q["n"], parents)
                    out[f"{key}/numpy/{kind}/mean"], out[f"{key}/numpy/{kind}/value"] = m, v
            k = int(q["n"][3])
            out[f"{key}/numpy/one chain"] = actor.mean(q["pos"][3, :k], q["vel"][3, :k], q["glob"][3])
            out[f"{key}/numpy/one tree"] = actor.mean(
                q["pos"][3, :k], q["vel"][3, :k], q["glob"][3], q["parents"][3, :k]
            )
            if onnx:
                import onnxruntime as ort

                for tree in (False, True):
                    model = export.export_model(policy, with_value=True, tree=tree).SerializeToString()
                    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
                    feeds = {"joint_pos": q["pos"][3, :k], "joint_vel": q["vel"][3, :k], "global": q["glob"][3]}
                    if tree:
                        feeds["parents"] = q["parents"][3, :k]
                    for name, value in zip(("action", "value"), session.run(None, feeds), strict=True):
                        out[f"{key}/onnx/{'tree' if tree else 'chain'}/{name}"] = value
        return out
    finally:
        sys.path.remove(str(core))
        for name in _core_modules():
            del sys.modules[name]
        sys.modules.update(saved)


def reference_core(ref: str, into: Path) -> Path:
    """``ref``'s ``morph_core`` package, taken out of git into ``into``; its parent directory is returned."""
    data = subprocess.run(
        ["git", "-C", str(ROOT), "archive", ref, "ros2_ws/src/morph_core/morph_core"],
        check=True, capture_output=True,
    ).stdout  # fmt: skip
    archive = into / "ref.tar"
    archive.write_bytes(data)
    with tarfile.open(archive) as tar:
        tar.extractall(into, filter="data")
    return into / "ros2_ws" / "src" / "morph_core"


def shipped_at(ref: str) -> list[Path]:
    """The shipped checkpoints that ``ref`` shipped too: a policy shipped since (the legged generalist, which
    reads joint descriptions) has no earlier answers to keep, and an older ``morph_core`` may not read it."""

    def at_ref(path: Path) -> bool:
        spec = f"{ref}:{path.relative_to(ROOT).as_posix()}"
        return subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", spec], capture_output=True).returncode == 0

    return [p for p in sorted(MODELS.glob("*.safetensors")) if at_ref(p)]


def compare(ref: str = "main", onnx: bool = False) -> list[str]:
    """Names of the answers that differ between this tree and ``ref`` on the checkpoints both ship (empty: bit
    for bit the same)."""
    models = shipped_at(ref)
    with tempfile.TemporaryDirectory() as tmp:
        theirs = answers(reference_core(ref, Path(tmp)), onnx, models)
    ours = answers(CORE, onnx, models)
    if set(ours) != set(theirs):
        return sorted(set(ours) ^ set(theirs))
    return [k for k in ours if ours[k].dtype != theirs[k].dtype or not np.array_equal(ours[k], theirs[k])]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ref", default="main", help="the commit to compare with (default: main)")
    parser.add_argument("--onnx", action="store_true", help="also the exported graphs' answers in ONNX Runtime")
    args = parser.parse_args(argv)
    differ = compare(args.ref, args.onnx)
    models = ", ".join(p.stem for p in shipped_at(args.ref))
    if differ:
        print(f"differ from {args.ref}: {', '.join(differ)}")
        return 1
    print(f"{models}: every answer bit for bit as at {args.ref}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
