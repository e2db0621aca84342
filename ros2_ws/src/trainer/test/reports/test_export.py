"""morph-export: the ONNX graph computes the torch policy (1..64 joints, ONNX Runtime; chains and, with --tree,
kinematic trees), bad input is refused."""

import copy
import json
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

import morph_core.env.registration  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch, chain_batch
from morph_core.policy.config import PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.onnx_export import (
    FORMAT,
    TREE_FORMAT,
    ExportError,
    SingleChainPolicy,
    SingleTreePolicy,
    check_against_policy,
    export_checkpoint,
    export_model,
    random_parents,
    scaled_difference,
)
from morph_core.policy.weights import CheckpointError, load_checkpoint
from trainer.cli import export as export_cli
from trainer.cli.keys import main as keys_main

pytestmark = pytest.mark.slow  # its fixtures train and export policies

SHIPPED = Path(__file__).resolve().parents[3] / "morph_policy_node/morph_policy_node/models/swimmer_gnn.safetensors"
CLI = [sys.executable, "-m", "trainer.cli.export"]


def trained_shaped(config: PolicyConfig, seed: int) -> GraphActorCritic:
    """A policy whose outputs are of a trained one's size: the init's 0.01-gain action layer would give
    means ~1e-3, where an absolute 1e-5 tolerance tests little. Every parameter gets noise of its own scale."""
    torch.manual_seed(seed)
    policy = GraphActorCritic(config)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(torch.randn_like(p) * max(float(p.std()) if p.numel() > 1 else 0.0, 0.3))
    return policy.eval()


def _save(policy: GraphActorCritic, path: Path) -> Path:
    policy.save(path, metadata={"global_step": 1234})
    return path


def _session(path: Path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # one summation order: the same rounding on every run
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def _chain(rng: np.random.Generator, n: int):
    return (rng.uniform(-1.7, 1.7, n).astype(np.float32), rng.normal(0, 3, n).astype(np.float32),
            np.array([rng.uniform(-6, 6), *rng.normal(0, 1, 3)], np.float32))  # fmt: skip


POLICIES = {
    "shipped": lambda: GraphActorCritic.load(SHIPPED).eval(),
    "trained-shaped": lambda: trained_shaped(PolicyConfig(), seed=3),
    "unidirectional": lambda: trained_shaped(PolicyConfig(bidirectional=False, conv1_channels=8), seed=4),
}


@pytest.fixture(scope="module", params=list(POLICIES))
def exported(request, tmp_path_factory):
    """(torch policy, its checkpoint, its exported graph with the value output)."""
    tmp = tmp_path_factory.mktemp(request.param)
    policy = POLICIES[request.param]()
    ckpt = SHIPPED if request.param == "shipped" else _save(policy, tmp / "policy.safetensors")
    result = export_checkpoint(ckpt, tmp / "policy.onnx", with_value=True)
    return policy, ckpt, result


@pytest.fixture(scope="module")
def swimmer_states():
    """n -> states of a real n-joint swimmer (MuJoCo) driven by random efforts, for n = 1..64."""
    rng = np.random.default_rng(0)
    states = {}
    for n in range(1, 65):
        env = gymnasium.make("MorphSwimmer-v0", num_joints=n)
        obs, _ = env.reset(seed=n)
        states[n] = [obs]
        for _ in range(4):
            for _ in range(3):
                obs, *_ = env.step(rng.uniform(-1, 1, n))
            states[n].append(obs)
        env.close()
    return states


def test_onnx_graph_equals_the_torch_policy_at_every_length_1_to_64(exported, swimmer_states):
    policy, ckpt, result = exported
    session = _session(result.path)
    assert [i.name for i in session.get_inputs()] == ["joint_pos", "joint_vel", "global"]
    assert [o.name for o in session.get_outputs()] == ["action", "value"]
    numpy_policy = NumpyPolicy(policy)
    scale = worst = 0.0
    for n, states in swimmer_states.items():
        for obs in states:
            pos, vel, glob = (np.asarray(obs[k], np.float32) for k in ("joint_pos", "joint_vel", "global"))
            action, value = session.run(None, {"joint_pos": pos, "joint_vel": vel, "global": glob})
            with torch.no_grad():
                mean, _, v = policy(chain_batch(pos, vel, glob))
            assert action.shape == (n,) and action.dtype == np.float32 and value.shape == (1,)
            # 1e-5 on every effort the motors get (|mean| <= 1), relative beyond: a trained policy's unclipped
            # means reach ~5 and its values tens, where float32 rounding alone moves them by more.
            worst = max(worst, scaled_difference(action, mean[0].numpy()).max())
            worst = max(worst, scaled_difference(value, v.numpy()).max())
            np.testing.assert_allclose(np.clip(action, -1, 1), np.clip(mean[0].numpy(), -1, 1), rtol=0, atol=1e-5)
            # The controllers' NumPy path computes the same: the three implementations agree.
            worst = max(worst, scaled_difference(action, numpy_policy.mean(pos, vel, glob)).max())
            scale = max(scale, float(np.abs(action).max()))
    assert worst <= 1e-5
    assert scale > 0.5, "outputs too small for an absolute tolerance to mean anything"
    # The export's own check, on random states with extremes no swimmer reaches, is looser (TOLERANCE).
    assert result.max_error <= 1e-4 and result.lengths_checked[0] == 1 and result.lengths_checked[-1] == 64


def test_random_states_match_within_float32_rounding(exported):
    """Beyond the states a swimmer visits (every joint at a random angle, fast): 1e-5 within the motors'
    range [-1, 1] and relative beyond it, or float32's own error where that is larger (the shipped
    policy's float32 torch vs its float64 evaluation)."""
    policy, ckpt, result = exported
    session = _session(result.path)
    single = SingleChainPolicy(policy, with_value=False)
    exact = copy.deepcopy(single).double()
    rng = np.random.default_rng(11)
    for n in (1, 2, 7, 20, 33, 64):
        for _ in range(4):
            pos, vel, glob = _chain(rng, n)
            action, _ = session.run(None, {"joint_pos": pos, "joint_vel": vel, "global": glob})
            with torch.no_grad():
                want = policy(chain_batch(pos, vel, glob))[0][0].numpy()
                truth = exact(*(torch.from_numpy(x).double() for x in (pos, vel, glob))).numpy()
            float32_error = scaled_difference(want, truth).max()
            assert scaled_difference(action, want).max() <= max(1e-5, 2 * float32_error), f"{n} joints"


def test_exported_graph_carries_its_format_and_checkpoint_metadata(exported):
    policy, ckpt, result = exported
    model = onnx.load(str(result.path))
    onnx.checker.check_model(model, full_check=True)
    props = {p.key: p.value for p in model.metadata_props}
    assert props["format"] == FORMAT
    assert props["checkpoint"] == str(ckpt)
    written = PolicyConfig.from_dict(json.loads(Path(ckpt).with_suffix(".json").read_text())["policy"])
    assert PolicyConfig(**json.loads(props["policy_config"])) == written
    assert float(props["log_std"]) == pytest.approx(float(policy.log_std.detach()))
    dims = [d.dim_param for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims == ["num_joints"]  # one symbolic length, shared by the inputs and the action


def test_the_check_detects_a_graph_of_other_weights():
    a, b = trained_shaped(PolicyConfig(), seed=1), trained_shaped(PolicyConfig(), seed=2)
    graph = export_model(a).SerializeToString()
    assert check_against_policy(graph, a) <= 1e-5
    assert check_against_policy(graph, b) > 1e-2


def test_cli_exports_the_actor_alone_by_default(tmp_path):
    ckpt = _save(trained_shaped(PolicyConfig(), seed=5), tmp_path / "p.safetensors")
    out = tmp_path / "sub" / "actor.onnx"
    run = subprocess.run([*CLI, str(ckpt), str(out)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "wrote" in run.stdout and "1, 2, 3, 7, 10, 20, 64 joints" in run.stdout
    assert "deprecated" not in run.stderr
    session = _session(out)
    assert [o.name for o in session.get_outputs()] == ["action"]
    pos, vel, glob = _chain(np.random.default_rng(0), 9)
    (action,) = session.run(None, {"joint_pos": pos, "joint_vel": vel, "global": glob})
    np.testing.assert_allclose(action, NumpyPolicy(GraphActorCritic.load(ckpt)).mean(pos, vel, glob), atol=1e-5)
    assert [p.name for p in out.parent.iterdir()] == ["actor.onnx"]  # atomic: no temp file left


def test_a_signed_checkpoint_s_signature_goes_into_the_graph_s_metadata(tmp_path):
    ckpt = _save(trained_shaped(PolicyConfig(), seed=6), tmp_path / "p.safetensors")
    props = lambda: {p.key: p.value for p in onnx.load(str(tmp_path / "a.onnx")).metadata_props}  # noqa: E731
    export_checkpoint(ckpt, tmp_path / "a.onnx", lengths=(3,))
    assert "signed_weights" not in props()
    assert keys_main(["new", str(tmp_path / "key")]) == 0
    assert keys_main(["sign", str(ckpt), "--key", str(tmp_path / "key")]) == 0
    export_checkpoint(ckpt, tmp_path / "a.onnx", lengths=(3,))
    signed = load_checkpoint(ckpt).signed
    assert json.loads(props()["signed_weights"]) == {"header": signed.header, "signature": signed.signature}
    assert props()["checkpoint_sha256"] == load_checkpoint(ckpt).data_sha256


@pytest.fixture(scope="module", params=list(POLICIES))
def tree_exported(request, tmp_path_factory):
    """(torch policy, its exported tree graph with the value output)."""
    tmp = tmp_path_factory.mktemp(f"tree-{request.param}")
    policy = POLICIES[request.param]()
    ckpt = SHIPPED if request.param == "shipped" else _save(policy, tmp / "policy.safetensors")
    return policy, export_checkpoint(ckpt, tmp / "tree.onnx", with_value=True, tree=True)


def test_tree_graph_equals_the_torch_and_numpy_policies_on_trees(tree_exported):
    # Random trees, stars (every joint on the torso: up to 64 messages summed there) and forks, 1..64 joints:
    # 1e-5 within the motors' range and relative beyond, or twice float32's own error where that is larger
    # (torch in float32 vs the same modules in float64), as for chains.
    policy, result = tree_exported
    assert result.tree and result.max_error <= 1e-4
    session = _session(result.path)
    assert [i.name for i in session.get_inputs()] == ["joint_pos", "joint_vel", "global", "parents"]
    assert [o.name for o in session.get_outputs()] == ["action", "value"]
    exact = copy.deepcopy(SingleTreePolicy(policy, with_value=True)).double()
    numpy_policy = NumpyPolicy(policy)
    rng = np.random.default_rng(12)
    scale = 0.0
    for n in (1, 2, 3, 6, 11, 25, 40, 64):
        for shape in ("random", "random", "star", "fork"):
            pos, vel, glob = _chain(rng, n)
            parents = random_parents(rng, n, shape) if shape != "fork" else np.minimum(np.arange(n) - 1, 1)
            action, value = session.run(None, {"joint_pos": pos, "joint_vel": vel, "global": glob, "parents": parents})
            with torch.no_grad():
                mean, _, v = policy(
                    ChainBatch.from_padded(pos[None], vel[None], glob[None], [n], parents=parents[None])
                )
                want = mean[0].numpy()
                truth = exact(*(torch.from_numpy(x).double() for x in (pos, vel, glob)), torch.from_numpy(parents))
            bound = max(1e-5, 2 * float(scaled_difference(want, truth[0].numpy()).max()))
            assert action.shape == (n,) and value.shape == (1,)
            assert scaled_difference(action, want).max() <= bound, f"{shape} of {n} joints"
            assert scaled_difference(value, v.numpy()).max() <= max(
                1e-5, 2 * scaled_difference(v.numpy(), truth[1].numpy()).max()
            )
            numpy_mean = numpy_policy.mean(pos, vel, glob, parents)
            assert scaled_difference(numpy_mean, want).max() <= bound, f"NumPy: {shape} of {n} joints"
            scale = max(scale, float(np.abs(action).max()))
    assert scale > 0.5, "outputs too small for an absolute tolerance to mean anything"


def test_tree_graph_on_chains_equals_the_torch_chain_path(tree_exported):
    # Given a chain's parents, the tree graph (gather and scatter-add) computes what torch's chain path
    # (shifted adds, the default export's form) does.
    policy, result = tree_exported
    session = _session(result.path)
    rng = np.random.default_rng(13)
    for n in (1, 4, 30, 64):
        pos, vel, glob = _chain(rng, n)
        action, _ = session.run(None, {"joint_pos": pos, "joint_vel": vel, "global": glob, "parents": np.arange(n) - 1})
        with torch.no_grad():
            want = policy(chain_batch(pos, vel, glob))[0][0].numpy()
        assert scaled_difference(action, want).max() <= 1e-5, f"{n} joints"


def test_tree_graph_carries_its_format_and_the_check_detects_other_weights(tree_exported):
    policy, result = tree_exported
    model = onnx.load(str(result.path))
    onnx.checker.check_model(model, full_check=True)
    props = {p.key: p.value for p in model.metadata_props}
    assert props["format"] == TREE_FORMAT != FORMAT
    for i in range(4):  # one symbolic length, shared by all joint inputs
        dims = [d.dim_param or d.dim_value for d in model.graph.input[i].type.tensor_type.shape.dim]
        assert dims == ([4] if i == 2 else ["num_joints"])
    assert model.graph.input[3].type.tensor_type.elem_type == onnx.TensorProto.INT64
    other = trained_shaped(PolicyConfig(), seed=2)
    assert check_against_policy(result.path.read_bytes(), other, tree=True) > 1e-2


def test_cli_exports_the_tree_graph(tmp_path):
    ckpt = _save(trained_shaped(PolicyConfig(), seed=5), tmp_path / "p.safetensors")
    out = tmp_path / "tree.onnx"
    run = subprocess.run([*CLI, str(ckpt), str(out), "--tree"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "parents [N]" in run.stdout and "star and chain trees" in run.stdout
    session = _session(out)
    assert [i.name for i in session.get_inputs()] == ["joint_pos", "joint_vel", "global", "parents"]
    pos, vel, glob = _chain(np.random.default_rng(0), 9)
    parents = np.array([-1, 0, 0, -1, 3, 3, 5, 1, 2])
    (action,) = session.run(None, {"joint_pos": pos, "joint_vel": vel, "global": glob, "parents": parents})
    want = NumpyPolicy(GraphActorCritic.load(ckpt)).mean(pos, vel, glob, parents)
    np.testing.assert_allclose(action, want, atol=1e-5)


def _bad_checkpoints(tmp: Path) -> dict[str, Path]:
    good = _save(trained_shaped(PolicyConfig(), seed=6), tmp / "good.safetensors")
    bad: dict[str, Path] = {"missing file": tmp / "absent.safetensors"}
    pickled = tmp / "pickled.safetensors"
    torch.save(GraphActorCritic().state_dict(), pickled)
    pickled.with_suffix(".json").write_text(good.with_suffix(".json").read_text())
    bad["torch pickle"] = pickled
    no_config = tmp / "noconfig.safetensors"
    no_config.write_bytes(good.read_bytes())
    bad["config missing"] = no_config
    other = tmp / "other.safetensors"
    other.write_bytes(good.read_bytes())
    meta = json.loads(good.with_suffix(".json").read_text())
    meta["policy"]["conv1_channels"] = 7  # tensors of the wrong shape for this config
    other.with_suffix(".json").write_text(json.dumps(meta))
    bad["shape mismatch"] = other
    truncated = tmp / "truncated.safetensors"
    truncated.write_bytes(good.read_bytes()[:500])
    truncated.with_suffix(".json").write_text(good.with_suffix(".json").read_text())
    bad["truncated"] = truncated
    return bad


def test_bad_checkpoints_are_refused_with_the_reason_and_nothing_is_written(tmp_path, capsys):
    out = tmp_path / "out.onnx"
    for what, ckpt in _bad_checkpoints(tmp_path).items():
        with pytest.raises(CheckpointError) as err:
            export_checkpoint(ckpt, out)
        assert str(ckpt) in str(err.value), what
        assert not out.exists(), what
        assert export_cli.main([str(ckpt), str(out)]) == 1, what
        stderr = capsys.readouterr().err
        assert stderr.startswith("morph-export: error: ") and str(ckpt) in stderr, what
        assert not out.exists(), what


def test_output_must_be_an_onnx_file(tmp_path, capsys):
    ckpt = _save(trained_shaped(PolicyConfig(), seed=7), tmp_path / "p.safetensors")
    with pytest.raises(ExportError, match=r"\.onnx"):
        export_checkpoint(ckpt, tmp_path / "p.safetensors.out")
    assert export_cli.main([str(ckpt), str(tmp_path / "p.out")]) == 1
    assert "must be a .onnx file" in capsys.readouterr().err
    for argv in ([str(ckpt)], ["--onnx", str(ckpt)]):  # two paths needed
        with pytest.raises(SystemExit) as exit_:
            export_cli.main(argv)
        assert exit_.value.code == 2 and "morph-export: error:" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.json", "p.safetensors"]


def test_the_deprecated_onnx_option_still_exports_and_says_so_once(tmp_path, capsys):
    ckpt = _save(trained_shaped(PolicyConfig(), seed=8), tmp_path / "p.safetensors")
    assert export_cli.main(["--onnx", str(ckpt), str(tmp_path / "p.onnx")]) == 0
    err = capsys.readouterr().err
    assert err.count("--onnx is deprecated: write morph-export CHECKPOINT OUT") == 1
    assert (tmp_path / "p.onnx").is_file()
    with pytest.raises(SystemExit) as exit_:  # both forms at once: which paths were meant?
        export_cli.main(["--onnx", str(ckpt), str(tmp_path / "q.onnx"), str(ckpt), str(tmp_path / "r.onnx")])
    assert exit_.value.code == 2 and "not both" in capsys.readouterr().err
    assert not (tmp_path / "q.onnx").exists() and not (tmp_path / "r.onnx").exists()


SHIPPED_POLICIES = sorted(SHIPPED.parent.glob("*.safetensors"))


def _body_states(weights_config: PolicyConfig):
    """(states, parents, descriptions) of the body a shipped policy drives, from real MuJoCo: swimmer chains for a
    4-feature policy, centipedes (2..6 leg pairs, trees) for a 12-feature one, with each joint's description for a
    policy that reads them (else None); random efforts, a few steps apart."""
    from morph_core.env.centipede import MorphCentipedeEnv
    from morph_core.env.vec_env import model_descriptions

    rng = np.random.default_rng(1)
    if weights_config.global_features == 12:
        envs = [MorphCentipedeEnv(leg_pairs=n) for n in (2, 3, 4, 6)]
    else:
        envs = [gymnasium.make("MorphSwimmer-v0", num_joints=n) for n in (1, 3, 6, 12)]
    states = []
    for k, env in enumerate(envs):
        obs, _ = env.reset(seed=k)
        for _ in range(4):
            for _ in range(3):
                obs, *_ = env.step(rng.uniform(-1, 1, env.action_space.shape[0]))
            parents = np.asarray(obs["parents"]) if "parents" in obs else np.arange(len(obs["joint_pos"])) - 1
            desc = model_descriptions(env.unwrapped.model) if weights_config.joint_features else None
            states.append((*(np.asarray(obs[k], np.float32) for k in ("joint_pos", "joint_vel", "global")), parents,
                           desc))  # fmt: skip
        env.close()
    return states


@pytest.mark.parametrize("tree", [False, True], ids=["chain", "tree"])
@pytest.mark.parametrize("shipped", SHIPPED_POLICIES, ids=lambda p: p.stem)
def test_every_shipped_policy_exports_and_onnx_runtime_equals_the_numpy_policy(shipped, tree, tmp_path):
    """morph-export on each model the nodes ship (the centipede's reads 12 global features, not 4): the CLI
    writes the graph, and ONNX Runtime on the body's own states equals the NumPy and torch policies."""
    assert {p.stem for p in SHIPPED_POLICIES} >= {"swimmer_gnn", "centipede_gnn"}
    out = tmp_path / f"{shipped.stem}.onnx"
    run = subprocess.run([*CLI, str(shipped), str(out), *(["--tree"] if tree else [])],
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stderr
    weights = load_checkpoint(shipped)
    width = weights.config.global_features
    assert f"global [{width}]" in run.stdout
    session = _session(out)
    assert session.get_inputs()[2].shape == [width]
    policy, numpy_policy = GraphActorCritic.load(shipped).eval(), NumpyPolicy(GraphActorCritic.load(shipped))
    worst, scale = 0.0, 0.0
    for pos, vel, glob, parents, desc in _body_states(weights.config):  # without --tree, a centipede is a chain
        feed = {"joint_pos": pos, "joint_vel": vel, "global": glob}
        if tree:
            feed["parents"] = parents.astype(np.int64)
        if desc is not None:  # the legged generalist reads each joint's description
            feed["joint_desc"] = desc
        (action,) = session.run(None, feed)
        want = numpy_policy.mean(pos, vel, glob, parents.astype(np.int64) if tree else None, joint_desc=desc)
        with torch.no_grad():
            batch = ChainBatch.from_padded(pos[None], vel[None], glob[None], [len(pos)],
                                           parents=parents.astype(np.int64)[None] if tree else None,
                                           joint_desc=None if desc is None else desc[None])  # fmt: skip
            mean = policy(batch)[0][0].numpy()
        worst = max(worst, scaled_difference(action, want).max(), scaled_difference(action, mean).max())
        scale = max(scale, float(np.abs(action).max()))
    assert worst <= 1e-4
    assert scale > 0.1, "outputs too small for the tolerance to mean anything"
