"""PPO on recorded transitions (algo.train_from_data): data from an in-process lockstep recording of a
sampling policy (protocol.loopback), real MuJoCo and real PyTorch; GAE against a direct sum, the decoupled
weighting on data of an older policy, resume equal to an uninterrupted run, refusals of unusable data."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.ppo import compute_gae
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig
from morph_core.algo.train_from_data import (
    DataMismatchError,
    EpisodeReturns,
    Samples,
    data_digest,
    run_state,
    train_from_data,
)
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.protocol.loopback import MeanController, SamplingController, record_episodes
from morph_core.protocol.transition_batch import MissingPolicyInfoError, TransitionBatch
from morph_core.protocol.transitions import assemble

# batch_size 32 < the 100 recorded steps: one pass is 4 updates on random quarters of the data
SMALL = small(num_envs=1, num_steps=32, minibatch_size=16, checkpoint_interval=32)
EPISODES = ((3, 40), (6, 30), (9, 30))


def record(controller, episodes=EPISODES, seed=0) -> TransitionBatch:
    return assemble(record_episodes(controller, episodes, seed)).batch


@pytest.fixture(scope="module")
def behaviour(tmp_path_factory):
    """The policy that recorded the data, as a checkpoint, and the data (three chain lengths)."""
    torch.set_num_threads(1)
    torch.manual_seed(7)
    policy = GraphActorCritic().eval()
    path = tmp_path_factory.mktemp("behaviour") / "policy.safetensors"
    policy.save(path)
    data = record(SamplingController(policy, seed=1))
    assert len(data) == 100 and data.ppo_ready and sorted(set(data.num_joints.tolist())) == [3, 6, 9]
    return path, data


def _rows(run):
    with RunDir(run).progress.open() as f:
        return list(csv.DictReader(f))


def _state(run):
    return load_training_state(RunDir(run).state)


def test_ppo_from_data_changes_the_policy_and_logs_per_dimension(tmp_path, behaviour):
    init, data = behaviour
    run = train_from_data(TrainConfig(seed=2, **SMALL), data, tmp_path / "run", iterations=2, init=init)
    before = GraphActorCritic.load(init).state_dict()
    after = GraphActorCritic.load(RunDir(run).checkpoints / "policy_00000050.safetensors").state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before), "the policy did not change"
    rows = _rows(run)
    assert [r["global_step"] for r in rows] == ["25", "50"]  # 100 steps in 4 parts of 25
    for r in rows:
        for k in ("policy_loss", "value_loss", "approx_kl", "clip_frac", "explained_variance"):
            assert np.isfinite(float(r[k])), k
        for d in (3, 6, 9):
            assert 0.0 <= float(r[f"clip_frac_d{d}"]) <= 1.0 or r[f"clip_frac_d{d}"] == ""
        assert all(r[f"clip_frac_d{d}"] == "" for d in (2, 4, 5, 7, 8, 10))  # not in the data
    seen = {d for r in rows for d in (3, 6, 9) if r[f"clip_frac_d{d}"] != ""}
    assert len(seen) >= 2
    # The recorded episodes' returns per chain length, as the data say.
    returns = EpisodeReturns.of(data)
    assert float(rows[0]["return_d6"]) == pytest.approx(float(data.reward[40:70].sum()))
    assert float(rows[0]["return_mean"]) == pytest.approx(float(returns.returns.mean()))
    assert int(rows[0]["episodes"]) == 3

    # The first update starts from the recording policy: on-policy, weights 1 (float rounding only).
    first, second = rows
    assert float(first["stale_frac"]) == 0.0
    assert float(first["is_weight_mean"]) == pytest.approx(1.0, abs=1e-5)
    # The second one starts from the updated policy: every sample is stale, the decoupled weight engages.
    assert float(second["stale_frac"]) == 1.0
    assert float(second["is_weight_mean"]) < 1.0
    assert float(second["behaviour_logr_mean"]) != 0.0


def test_resume_continues_exactly_as_an_uninterrupted_run(tmp_path, behaviour):
    init, data = behaviour
    cfg = TrainConfig(seed=3, **SMALL)
    straight = train_from_data(cfg, data, tmp_path / "a", iterations=7, init=init)
    # 5 updates end mid-way through the second pass (parts of 25 samples): its order is in the state.
    part = train_from_data(cfg, data, tmp_path / "b", iterations=5, init=init)
    assert run_state(part)["done"] == 5
    train_from_data(cfg, data, part, iterations=7, resume=True)
    (ta, ma), (tb, mb) = _state(straight), _state(part)
    assert ta.keys() == tb.keys() and "section.data.order" in ta
    for k in ta:
        assert torch.equal(ta[k], tb[k]), k  # weights, Adam moments, generator, pass order: bit for bit
    assert ma["counters"] == mb["counters"]
    ra, rb = _rows(straight), _rows(part)
    assert [r["global_step"] for r in ra] == [r["global_step"] for r in rb] == [str(25 * i) for i in range(1, 8)]
    skip = {"wall_time", "sps", "prepare_s", "update_s"}
    assert [{k: v for k, v in r.items() if k not in skip} for r in ra] == [
        {k: v for k, v in r.items() if k not in skip} for r in rb
    ]


def test_rounds_on_new_data_carry_the_state_and_resume_on_other_data_is_refused(tmp_path, behaviour):
    init, data = behaviour
    cfg = TrainConfig(seed=4, **SMALL)
    run = train_from_data(cfg, data, tmp_path / "run", init=init)
    assert run_state(run)["done"] == run_state(run)["iterations"] == 4  # default: one pass
    more = record(SamplingController(GraphActorCritic.load(init), seed=9), ((4, 20), (2, 30)), seed=3)
    with pytest.raises(DataMismatchError, match="trains on other data"):
        train_from_data(cfg, more, run, resume=True)
    with pytest.raises(DataMismatchError, match="trains on these data already"):
        train_from_data(cfg, data, run, resume=True, new_data=True)
    tensors_before, _ = _state(run)
    train_from_data(cfg, more, run, resume=True, new_data=True, iterations=1, source=["more"])
    state = run_state(run)
    assert state["data_round"] == 2 and state["env_steps"] == 150 and state["source"] == ["more"]
    assert state["digest"] == data_digest(more) and state["iteration"] == 5
    tensors_after, _ = _state(run)
    assert not torch.equal(tensors_before["optim.0.step"], tensors_after["optim.0.step"])
    # one update on half of the 50 new steps: 2 epochs of 2 minibatches (16 + 9 samples)
    assert float(tensors_after["optim.0.step"]) == float(tensors_before["optim.0.step"]) + 2 * 2
    rows = _rows(run)
    assert [r["data_round"] for r in rows] == ["1"] * 4 + ["2"]
    assert rows[-1]["env_steps"] == "150" and rows[-1]["data_steps"] == "50"
    # Back to the first data: a third round (the data set the run trains on is the latest one).
    train_from_data(cfg, data, run, resume=True, new_data=True, iterations=3)
    state = run_state(run)
    assert state["done"] == 3 and state["data_round"] == 3


def test_data_without_policy_info_or_outside_the_chain_range_are_refused(tmp_path, behaviour):
    init, data = behaviour
    deterministic = record(MeanController(GraphActorCritic.load(init)), ((3, 10),))
    with pytest.raises(MissingPolicyInfoError, match="10 of 10 steps have no policy_info"):
        train_from_data(TrainConfig(**SMALL), deterministic, tmp_path / "a")
    assert not (tmp_path / "a").exists()  # nothing written
    with pytest.raises(DataMismatchError, match="chains of 3..9 joints, outside"):
        train_from_data(TrainConfig(min_joints=4, **SMALL), data, tmp_path / "b")
    with pytest.raises(ValueError, match="no transitions"):
        train_from_data(TrainConfig(**SMALL), TransitionBatch.empty(), tmp_path / "c")
    with pytest.raises(ValueError, match="anneal_lr"):
        train_from_data(TrainConfig(anneal_lr=True, **SMALL), data, tmp_path / "d")


def test_advantages_are_gae_over_each_episode_bootstrapped_at_its_truncation(behaviour):
    init, data = behaviour
    policy = GraphActorCritic.load(init)
    samples = Samples(data, 10)
    gamma, lam = 0.9, 0.8
    values, adv, ret = samples.advantages(policy, gamma, lam)
    v_states, v_finals = samples.values(policy)
    torch.testing.assert_close(values, v_states)
    torch.testing.assert_close(ret, adv + values)
    # Direct sums over each episode: A_t = sum_k (gamma lam)^k delta_{t+k}, the last delta bootstrapped on
    # V of the episode's final next state.
    starts = [0, 40, 70]
    ends = [40, 70, 100]
    assert np.flatnonzero(data.truncated).tolist() == [39, 69, 99]
    v = v_states.double().numpy()
    r = data.reward
    for e, (s, t) in enumerate(zip(starts, ends, strict=True)):
        v_next = np.r_[v[s + 1 : t], float(v_finals[e])]
        delta = r[s:t] + gamma * v_next - v[s:t]
        expected = [sum((gamma * lam) ** k * delta[i + k] for k in range(t - s - i)) for i in range(t - s)]
        np.testing.assert_allclose(adv[s:t].numpy(), expected, rtol=1e-4, atol=1e-4)
    # The episode grid gives what the flat [N, 1] recursion gives.
    final = torch.zeros(len(data))
    final[samples.truncated_rows] = v_finals
    flat_adv, _ = compute_gae(
        samples.rewards[:, None], v_states[:, None], samples.terminated[:, None], samples.truncated[:, None],
        final[:, None], torch.zeros(1), gamma, lam,
    )  # fmt: skip
    torch.testing.assert_close(adv, flat_adv[:, 0], rtol=0, atol=1e-6)


def test_digest_tells_data_apart(behaviour):
    _, data = behaviour
    assert data_digest(data) == data_digest(TransitionBatch.from_arrays(data.arrays()))
    changed = data.arrays()
    changed["reward"] = changed["reward"].copy()
    changed["reward"][5] += 1e-9
    assert data_digest(TransitionBatch.from_arrays(changed)) != data_digest(data)


def test_steps_without_policy_info_feed_the_advantages_but_never_an_update(tmp_path, behaviour):
    init, data = behaviour
    arrays = data.arrays()
    lost = [5, 41, 42]  # a policy_info lost in recording, or another controller acting for a moment
    arrays["has_policy_info"] = arrays["has_policy_info"].copy()
    arrays["log_prob"] = arrays["log_prob"].copy()
    arrays["has_policy_info"][lost], arrays["log_prob"][lost] = False, np.nan
    partial = TransitionBatch.from_arrays(arrays)
    cfg = TrainConfig(**{**SMALL, "num_steps": 128})  # one batch holds every usable step
    run = train_from_data(cfg, partial, tmp_path / "run", init=init)
    (row,) = _rows(run)
    # 97 = 6 x 16 + 1: the update leaves the last one out rather than normalise a lone advantage
    assert (row["data_steps"], row["usable_steps"], row["batch_size"]) == ("100", "97", "96")
    # Their rewards still reach the steps before them: the advantages are those of the whole data.
    policy = GraphActorCritic.load(init)
    _, adv_partial, _ = Samples(partial, 10).advantages(policy, 0.98, 0.98)
    _, adv_whole, _ = Samples(data, 10).advantages(policy, 0.98, 0.98)
    torch.testing.assert_close(adv_partial, adv_whole, rtol=0, atol=0)


def test_a_batch_never_leaves_one_sample_for_its_last_minibatch(tmp_path, behaviour):
    # 33 steps in minibatches of 16: a last minibatch of one sample would normalise its advantage to 0/0
    # and turn every weight NaN; the update takes 32.
    init, _ = behaviour
    data = record(SamplingController(GraphActorCritic.load(init), seed=4), ((3, 33),))
    assert len(data) == 33
    run = train_from_data(TrainConfig(**{**SMALL, "num_steps": 64}), data, tmp_path / "run", init=init)
    (row,) = _rows(run)
    assert row["batch_size"] == "32" and np.isfinite(float(row["policy_loss"]))
    tensors, _ = _state(run)
    assert all(torch.isfinite(v).all() for k, v in tensors.items() if k.startswith(("policy.", "optim.")))
    single = record(SamplingController(GraphActorCritic.load(init), seed=4), ((3, 1),))
    with pytest.raises(ValueError, match="too few"):
        train_from_data(TrainConfig(**SMALL), single, tmp_path / "one")


# -- trees ------------------------------------------------------------------------------------


def _old_digest(data: TransitionBatch) -> str:
    """data_digest as it was before ``parents`` existed: every other array, in layout order."""
    import hashlib

    h = hashlib.sha256()
    for key, a in data.arrays().items():
        if key != "parents":
            a = np.ascontiguousarray(a)
            h.update(f"{key}:{a.dtype.str}:{a.shape};".encode())
            h.update(a.tobytes())
    return h.hexdigest()


def test_an_npz_written_before_parents_trains_exactly_as_the_chains_it_holds(tmp_path, behaviour):
    init, data = behaviour
    np.savez(tmp_path / "old.npz", **{k: v for k, v in data.arrays().items() if k != "parents"})
    old = TransitionBatch.from_npz(tmp_path / "old.npz")
    assert old.is_chains and Samples(old, 10).parents is None  # the policy's chain path
    # Its digest is the one it had: runs started on it resume on it.
    assert data_digest(old) == data_digest(data) == _old_digest(data)
    cfg = TrainConfig(seed=5, **SMALL)
    a = train_from_data(cfg, data, tmp_path / "a", iterations=2, init=init)
    b = train_from_data(cfg, old, tmp_path / "b", iterations=2, init=init)
    (ta, _), (tb, _) = _state(a), _state(b)
    assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)


def test_a_tree_dataset_reads_every_state_with_its_tree(behaviour, random_trees):
    init, data = behaviour
    trees = random_trees(data)
    policy = GraphActorCritic.load(init)
    samples, chains = Samples(trees, 10), Samples(data, 10)
    padded = np.pad(trees.parents, ((0, 0), (0, 10 - trees.max_joints)), constant_values=-1)
    np.testing.assert_array_equal(samples.parents.numpy(), padded)

    # The states' values and the truncated steps' next-state values, each with the row's own tree.
    states, finals = samples.values(policy)
    with torch.no_grad():
        direct = policy(ChainBatch.from_padded(samples.joint_pos, samples.joint_vel, samples.global_feats,
                                               samples.num_joints, parents=padded))[2]  # fmt: skip
        rows = samples.truncated_rows
        direct_finals = policy(ChainBatch.from_padded(*samples.next_obs, samples.num_joints[rows],
                                                      parents=padded[rows.numpy()]))[2]  # fmt: skip
    torch.testing.assert_close(states, direct, rtol=0, atol=1e-6)
    torch.testing.assert_close(finals, direct_finals, rtol=0, atol=1e-6)
    chain_states, chain_finals = chains.values(policy)
    assert not torch.allclose(states, chain_states) and not torch.allclose(finals, chain_finals)

    # Every batch and minibatch an update takes carries the data's trees.
    values, advantages, returns = samples.advantages(policy, 0.98, 0.95)
    index = torch.tensor([0, 45, 80, 99, 41])
    batch = samples.batch(index, values, advantages, returns)
    np.testing.assert_array_equal(batch.parents.numpy(), padded[index.numpy()])
    minibatch, _ = batch.minibatch(torch.arange(len(index)))
    width = int(trees.num_joints[index.numpy()].max())
    np.testing.assert_array_equal(minibatch.parents.numpy(), padded[index.numpy(), :width])
    assert chains.batch(index, values, advantages, returns).parents is None


def test_a_tree_dataset_trains_otherwise_than_its_chains_and_is_other_data(tmp_path, behaviour, random_trees):
    init, data = behaviour
    trees = random_trees(data)
    assert data_digest(trees) != data_digest(data)
    assert data_digest(trees) != data_digest(random_trees(data, seed=1))  # only the trees differ
    assert data_digest(trees) == data_digest(TransitionBatch.from_arrays(trees.arrays()))
    cfg = TrainConfig(seed=6, **SMALL)
    a = train_from_data(cfg, data, tmp_path / "chains", iterations=1, init=init)
    b = train_from_data(cfg, trees, tmp_path / "trees", iterations=1, init=init)
    (ta, _), (tb, _) = _state(a), _state(b)
    assert any(not torch.equal(ta[k], tb[k]) for k in ta if k.startswith("policy."))
    rows = _rows(b)
    assert np.isfinite(float(rows[0]["policy_loss"])) and rows[0]["clip_frac_d6"] != ""  # per dimension still
    with pytest.raises(DataMismatchError, match="trains on other data"):
        train_from_data(cfg, data, b, resume=True)
    train_from_data(cfg, trees, b, resume=True, iterations=2)
    assert run_state(b)["done"] == 2
