"""LiveLearner without DDS: episodes of a real in-process lockstep loop (MuJoCo + the sampling policy), stale
and unusable steps dropped from an episode's start, PPO updates making versions, weights that rebuild the
policy exactly, resume continuing the run."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small_config
from morph_core.algo.train import TrainConfig
from morph_core.env.bodies import comb_parents, star_parents, swimmer_tree
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.policy_weights import unpack_policy_weights
from morph_core.msgs.records import DescriptionRecord, JointStateRecord
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.weights import load_checkpoint
from morph_core.protocol.loopback import LoopbackRecording, SamplingController, record_episodes
from morph_core.protocol.policy_updates import PolicyUpdates, checkpoint_trust
from morph_core.protocol.transitions import SkipCounts, TransitionAssembler, TransitionConfig
from morph_core.protocol.trust import TrustedKeys, load_public_key, write_key_pair
from trainer.live.learner import EpisodeCutter, LiveLearner, LiveOptions, NonFiniteUpdate

SMALL = small_config(num_envs=1, checkpoint_interval=64)


@pytest.fixture(scope="module")
def episodes():
    """Three episodes (3, 6, 9 joints; 40 steps each) sampled by a fresh policy, as the node would see them."""
    torch.set_num_threads(1)
    torch.manual_seed(3)
    loop = LoopbackRecording(SwimmerSim(3, seed=0, effort_timeout=None), SamplingController(GraphActorCritic(), 1))
    for i, n in enumerate((3, 6, 9)):
        if i:
            loop.new_episode(n)
        loop.run(40)
    loop.finish()
    out: dict[int, list] = {}
    asm = TransitionAssembler()
    for t in asm.push_many(loop.records) + asm.flush():
        out.setdefault(t.episode, []).append(t)
    eps = list(out.values())
    assert [len(e) for e in eps] == [40, 40, 40] and all(e[-1].truncated for e in eps)
    return eps


def test_update_needs_a_batch_then_makes_the_next_version(tmp_path, episodes):
    learner = LiveLearner(SMALL, tmp_path, max_staleness=1)
    assert learner.version == 0 and RunDir(tmp_path).state.exists()
    assert learner.add_episode(episodes[0], [0] * 40) == 40
    assert not learner.ready()
    learner.add_episode(episodes[1], [None] * 40)  # a node that does not say its version: kept
    assert learner.ready() and learner.pool_size == 80
    before = [p.detach().clone() for p in learner.policy.parameters()]
    row = learner.update(pairs=2)
    assert learner.version == 1 and row["version"] == 1 and row["batch_size"] == 80 and row["pairs"] == 2
    assert row["version_lag_mean"] == 0.0 and row["pool_episodes"] == 2
    assert any(not torch.equal(a, b) for a, b in zip(before, learner.policy.parameters(), strict=True))
    assert learner.pool_size == 0
    rows = list(csv.DictReader(open(RunDir(tmp_path).progress)))
    assert len(rows) == 1 and int(rows[0]["version"]) == 1 and float(rows[0]["return_d3"]) == row["return_d3"]
    assert sorted(p.name for p in RunDir(tmp_path).checkpoints.iterdir()) == [
        "policy_00000080.json", "policy_00000080.safetensors"]  # fmt: skip


def test_an_update_takes_one_batch_of_the_oldest_episodes_and_leaves_the_rest(tmp_path, episodes):
    learner = LiveLearner(SMALL, tmp_path, max_staleness=1)  # batch_size 64: two 40-step episodes
    for ep in episodes:
        learner.add_episode(ep, [0] * 40)
    assert learner.pool_size == 120
    pool, versions = learner.take_pool()
    assert [len(b) for b in pool] == [40, 40] and len(versions) == 80
    np.testing.assert_array_equal(pool[0].joint_pos[:, :3], np.array([t.joint_pos for t in episodes[0]]))
    assert learner.pool_size == 40 and not learner.ready()  # the third waits for the next batch
    learner.add_episode(episodes[0], [0] * 40)
    assert learner.ready()
    row = learner.update()
    assert row["batch_size"] == 80 and row["pool_episodes"] == 2 and learner.pool_size == 0


def test_stale_and_unusable_steps_are_cut_from_the_episode_start(tmp_path, episodes):
    learner = LiveLearner(SMALL, tmp_path, max_staleness=1)
    learner.counters["version"] = 5
    versions = [2] * 10 + [3] * 10 + [4] * 20  # versions 2 and 3 are more than 1 behind 5
    assert learner.add_episode(episodes[0], versions) == 20
    assert learner.dropped_stale == 20
    bad = list(episodes[1])
    bad[4] = type(bad[4])(**{**bad[4].__dict__, "has_policy_info": False, "log_prob": float("nan")})
    assert learner.add_episode(bad, [5] * 40) == 35 and learner.dropped_no_info == 5
    with pytest.raises(ValueError, match="truncated"):
        learner.add_episode(episodes[2][:-1], [5] * 39)
    with pytest.raises(ValueError, match="versions"):
        learner.add_episode(episodes[2], [5])
    learner.cfg = TrainConfig(**{**SMALL.to_dict(), "max_joints": 8})  # 9 joints: outside the run's chains
    assert learner.add_episode(episodes[2], [5] * 40) == 0


def test_weights_rebuild_the_policy_and_resume_continues(tmp_path, episodes):
    learner = LiveLearner(SMALL, tmp_path)
    for e in episodes[:2]:
        learner.add_episode(e, [0] * 40)
    learner.update()
    dims, data = learner.weights_message()
    w = unpack_policy_weights([d[0] for d in dims], [d[1] for d in dims], data)
    assert w.version == 1 and w.metadata["run"] == learner.run_id
    rebuilt = GraphActorCritic(PolicyConfig.from_dict(w.config))
    rebuilt.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in w.tensors.items()})
    for (k, a), b in zip(learner.policy.state_dict().items(), rebuilt.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    run_id, step = learner.run_id, learner.counters["global_step"]
    learner.close()
    again = LiveLearner(SMALL, tmp_path, resume=True)
    assert (again.version, again.run_id, again.counters["global_step"]) == (1, run_id, step)
    for a, b in zip(again.policy.parameters(), learner.policy.parameters(), strict=True):
        assert torch.equal(a, b)
    again.add_episode(episodes[2], [1] * 40)
    again.add_episode(episodes[0], [1] * 40)
    again.update()
    steps = [int(r["global_step"]) for r in csv.DictReader(open(RunDir(tmp_path).progress))]
    assert steps == [80, 160] and again.version == 2
    fresh = LiveLearner(SMALL, tmp_path / "other")
    assert fresh.run_id != run_id


def test_signed_weights_and_checkpoints_stay_in_order_across_resume_and_a_new_run(tmp_path, episodes):
    signer = write_key_pair(tmp_path / "key")
    node = PolicyUpdates(lambda w: w.version, None, TrustedKeys([load_public_key(tmp_path / "key.pub")]))

    def offer(learner):
        dims, data = learner.weights_message()
        return node.offer([d[0] for d in dims], [d[1] for d in dims], data)

    def train(learner, version):
        learner.add_episode(episodes[0], [version] * 40)
        learner.add_episode(episodes[1], [version] * 40)
        learner.update()

    first = LiveLearner(SMALL, tmp_path / "run", signer=signer)
    assert offer(first).outcome == "pending"
    train(first, 0)
    assert (offer(first).outcome, node.current()) == ("pending", 1)
    # the checkpoint of version 1 carries the message's signature, over the same bytes
    checkpoint = load_checkpoint(RunDir(tmp_path / "run").checkpoints / "policy_00000080.safetensors")
    trust = checkpoint_trust(checkpoint, node.keys)
    assert (trust.signer, trust.order) == (signer.fingerprint, (first.epoch, 1))
    old_message = first.weights_message()
    first.close()
    resumed = LiveLearner(SMALL, tmp_path / "run", resume=True, signer=signer)
    assert resumed.epoch == first.epoch and offer(resumed).code == "not_newer"
    train(resumed, 1)
    assert offer(resumed).outcome == "pending" and node.current() == 2
    replay = node.offer([d[0] for d in old_message[0]], [d[1] for d in old_message[0]], old_message[1])
    assert replay.code == "replayed"
    fresh = LiveLearner(SMALL, tmp_path / "fresh", signer=signer)  # a trainer started afresh: after the old run
    assert fresh.epoch > resumed.epoch and offer(fresh).outcome == "pending" and node.current() == 0
    assert offer(resumed).code == "replayed"
    unsigned = LiveLearner(SMALL, tmp_path / "unsigned")
    assert offer(unsigned).code == "unsigned"


def test_options_refuse_nonsense(tmp_path):
    with pytest.raises(ValueError, match="at least one"):
        LiveOptions((), tmp_path)
    with pytest.raises(ValueError, match="twice"):
        LiveOptions(("/a", "/a"), tmp_path)
    with pytest.raises(ValueError, match="silence_timeout"):
        LiveOptions(("/a",), tmp_path, silence_timeout=0)
    for nice in (-1, 20):
        with pytest.raises(ValueError, match="nice"):
            LiveOptions(("/a",), tmp_path, nice=nice)
    with pytest.raises(ValueError, match="anneal_lr"):
        LiveLearner(TrainConfig(**{**SMALL.to_dict(), "anneal_lr": True}), tmp_path)
    assert np.isfinite(SMALL.batch_size)


def test_live_updates_log_the_log_ratio_histograms(tmp_path, episodes):
    from dataclasses import replace

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    learner = LiveLearner(replace(SMALL, tensorboard=True), tmp_path, max_staleness=1)
    learner.add_episode(episodes[0], [0] * 40)
    learner.add_episode(episodes[1], [0] * 40)
    learner.update()
    learner.close()
    acc = EventAccumulator(str(RunDir(tmp_path).tensorboard), size_guidance={"histograms": 0})
    acc.Reload()
    tags = acc.Tags()["histograms"]
    assert {"log_ratio/d3", "log_ratio/d6"} <= set(tags), tags
    assert acc.Histograms("log_ratio/d3")[0].step == 80


def test_resume_skips_a_damaged_state_for_the_previous_one(tmp_path, episodes):
    learner = LiveLearner(SMALL, tmp_path, max_staleness=1)
    learner.add_episode(episodes[0], [0] * 40)
    learner.add_episode(episodes[1], [0] * 40)
    learner.update()
    learner.close()
    state = RunDir(tmp_path).state
    state.write_bytes(state.read_bytes()[: state.stat().st_size // 2])  # truncated on disk
    resumed = LiveLearner(SMALL, tmp_path, resume=True, max_staleness=1)
    assert resumed.resumed and resumed.version == 0  # the state before the update, whole
    assert resumed.run_id == learner.run_id


def test_a_diverged_update_is_refused_and_the_learner_kept_as_it_was(tmp_path, episodes):
    """An update that leaves the parameters non-finite (here: a step size no float32 survives) is refused; the
    learner is then exactly the one before it: the same next update as a learner that never saw it."""
    blown, fresh = LiveLearner(SMALL, tmp_path / "a"), LiveLearner(SMALL, tmp_path / "b")
    pool = ([], np.zeros(0))
    for learner in (blown, fresh):
        learner.add_episode(episodes[0], [0] * 40)
        learner.add_episode(episodes[1], [0] * 40)
        pool = learner.take_pool()
    before = blown.learner.params.theta.detach().clone()
    blown.learner.optimizer.param_groups[0]["lr"] = 1e38
    with pytest.raises(NonFiniteUpdate, match="non-finite; refused"):
        blown.update(pool)
    assert blown.rejected_updates == 1 and blown.version == 0
    assert torch.equal(blown.learner.params.theta, before)
    blown.learner.optimizer.param_groups[0]["lr"] = SMALL.learning_rate
    a, b = blown.update(pool), fresh.update(pool)
    assert a["version"] == b["version"] == 1 and a["approx_kl"] == b["approx_kl"]
    assert torch.equal(blown.learner.params.theta, fresh.learner.params.theta)
    assert len(list(csv.DictReader(open(RunDir(tmp_path / "a").progress)))) == 1  # the refused update not logged


@pytest.mark.slow
def test_the_update_compiled_ahead_is_the_graph_the_first_update_runs(tmp_path, episodes):
    """compile_update traces the minibatch gradient on made-up chains before any data: the first real update
    then finds its graph (none traced anew, no fallback), and nothing the update reads has changed."""
    from dataclasses import replace

    from morph_core.algo.trust_region import get_rule

    learner = LiveLearner(replace(SMALL, compile=True), tmp_path, max_staleness=1)
    gradient = learner.learner.minibatch_gradient(get_rule(learner.cfg.update_config().rule))
    theta, gen = learner.learner.params.theta.detach().clone(), learner.gen.get_state()
    assert learner.compile_update() > 0
    assert len(gradient.graphs) == 1 and not gradient.fell_back
    assert torch.equal(learner.learner.params.theta, theta) and torch.equal(learner.gen.get_state(), gen)
    assert not learner.learner.optimizer.state and learner.version == 0
    learner.add_episode(episodes[0], [0] * 40)
    learner.add_episode(episodes[1], [0] * 40)
    row = learner.update()
    assert len(gradient.graphs) == 1 and not gradient.fell_back
    assert row["version"] == 1 and np.isfinite(row["approx_kl"])


def test_steps_carry_their_tree_into_the_update_and_an_episode_is_one_tree(tmp_path):
    torch.set_num_threads(1)
    torch.manual_seed(3)
    loop = LoopbackRecording(SwimmerSim(6, seed=0, effort_timeout=None), SamplingController(GraphActorCritic(), 2))
    loop.run(70)
    loop.finish()
    tree = np.array([-1, 0, 1, 1, 0, 4])  # in pre-order, as a URDF lists it

    def episode(description=()):
        asm = TransitionAssembler()
        steps = asm.push_many([*description, *loop.records]) + asm.flush()
        assert len(steps) == 70 and steps[-1].truncated
        return steps

    # The same states read on the chain of their message order, and on a tree their description names.
    chains, trees = episode(), episode([DescriptionRecord(0, swimmer_urdf(tree))])
    assert all(np.array_equal(t.parents, np.arange(6) - 1) for t in chains)  # message order: a chain
    assert all(np.array_equal(t.parents, tree) for t in trees)

    params = {}
    for name, steps in (("chains", chains), ("trees", trees)):
        learner = LiveLearner(SMALL, tmp_path / name)
        assert learner.add_episode(steps, [0] * 70) == 70
        pool, versions = learner.take_pool()
        assert pool[0].is_chains == (name == "chains")
        np.testing.assert_array_equal(pool[0].parents, np.tile(tree if name == "trees" else np.arange(6) - 1, (70, 1)))
        learner.update((pool, versions))
        params[name] = learner.learner.params.theta.detach().clone()
    assert not torch.equal(params["chains"], params["trees"])  # the same steps, read as another robot

    # Two trees in one episode (its steps disagree on the robot): not one episode, dropped.
    learner = LiveLearner(SMALL, tmp_path / "mixed")
    assert learner.add_episode(chains[:35] + trees[35:], [0] * 70) == 0 and learner.dropped_no_info == 70


def test_the_learner_learns_on_branched_swimmers_as_the_trainer_assembles_them(tmp_path):
    """Real tree swimmers: the sim's robot_description, the joints in another order at every state, efforts naming
    theirs; the assembler reads each step on its tree and the update takes them with it."""
    torch.set_num_threads(1)
    torch.manual_seed(4)
    trees = (swimmer_tree(star_parents(2, 2)), swimmer_tree(comb_parents(3)))
    policy = GraphActorCritic()
    records = record_episodes(SamplingController(policy, 6), ((trees[0], 40), (trees[1], 40)), describe=True,
                              shuffle_seed=1, name_efforts=True)  # fmt: skip
    asm = TransitionAssembler()
    steps = asm.push_many(records) + asm.flush()
    assert asm.skips == SkipCounts() and [sum(t.episode == e for t in steps) for e in (0, 1)] == [40, 40]
    learner = LiveLearner(SMALL, tmp_path)
    learner.policy.load_state_dict(policy.state_dict())  # the policy that sampled: on-policy
    for e, tree in enumerate(trees):
        episode = [t for t in steps if t.episode == e]
        assert all(t.parents.tolist() == tree.parents.tolist() and t.names == tree.names for t in episode)
        assert learner.add_episode(episode, [0] * 40) == 40
    pool, versions = learner.take_pool()  # one batch per episode, each on its tree
    assert [len(b) for b in pool] == [40, 40] and not any(b.is_chains for b in pool)
    for batch, tree in zip(pool, trees, strict=True):
        np.testing.assert_array_equal(batch.parents, np.tile(tree.parents, (40, 1)))
    before = [p.detach().clone() for p in learner.policy.parameters()]
    row = learner.update((pool, versions))
    assert row["version"] == 1 and row["batch_size"] == 80 and np.isfinite(row["approx_kl"])
    assert row["is_weight_mean"] == pytest.approx(1.0, abs=1e-5)  # each step's log-prob on its own tree
    assert any(not torch.equal(a, b) for a, b in zip(before, learner.policy.parameters(), strict=True))


def test_a_live_run_starts_from_init_as_a_simulator_run_does(tmp_path):
    # --init fine-tunes live too: the first weights are the checkpoint's, its architecture the run's.
    torch.manual_seed(8)
    start = GraphActorCritic(PolicyConfig(bidirectional=False))
    start.save(tmp_path / "start.safetensors")
    learner = LiveLearner(SMALL, tmp_path / "run", init=tmp_path / "start.safetensors")
    assert learner.cfg.policy == start.config and learner.cfg.policy != SMALL.policy
    mine, theirs = learner.policy.state_dict(), start.state_dict()
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
    assert RunDir(tmp_path / "run").init.exists()
    with pytest.raises(ValueError, match="init starts a new run"):
        LiveLearner(SMALL, tmp_path / "run", resume=True, init=tmp_path / "start.safetensors")
    fresh = LiveLearner(SMALL, tmp_path / "fresh")  # without it: the seed's fresh policy, as before
    assert fresh.cfg.policy == SMALL.policy and not RunDir(tmp_path / "fresh").init.exists()


@pytest.mark.parametrize("silent", ["mid-episode", "at a new body"])
def test_a_silent_pair_loses_only_the_episode_it_cut_not_the_complete_ones_its_assembler_held(tmp_path, silent):
    """The live node's assembler judges a state only once 500 later states came (``SETTLE_STATES``): with short
    episodes it holds several whole ones, of several bodies. A pair falling silent then loses only the episode the
    silence cut off (none when it fell silent at a new body's first state, as a policy stalled at a body swap);
    the complete ones all reach the pool."""
    torch.set_num_threads(1)
    torch.manual_seed(5)
    last = 30 if silent == "mid-episode" else 1
    bodies = ((3, 60), (5, 60), (4, 60), (6, 60), (3, 60), (5, last))
    records = record_episodes(SamplingController(GraphActorCritic(), 7), bodies, seed=2, describe=True)
    if silent == "at a new body":  # the stream ends with the new body's first state: its second never comes
        records = records[: max(i for i, r in enumerate(records) if isinstance(r, JointStateRecord))]
    asm = TransitionAssembler(TransitionConfig(settle_states=500))
    learner = LiveLearner(SMALL, tmp_path)
    cutter = EpisodeCutter(learner, lambda stamp: 0)
    cutter.take(asm.push_many(records))
    assert learner.pool_size == 0 and asm.stats.transitions == 0  # all still unjudged, as live
    lost = cutter.drop(asm)
    assert asm.skips.steps_skipped == 0 and asm.stats.boundaries == 5  # (the cut: an orphan odometry at most)
    assert lost == (30 if silent == "mid-episode" else 0) and (asm.cut_off is None) == (silent == "at a new body")
    assert learner.pool_size == 5 * 60 and learner.dropped_no_info == 0
    pooled = []
    while learner.pool_size:
        pooled += [(len(b), b.joint_pos.shape[1]) for b in learner.take_pool()[0]]
    assert pooled == [(60, 3), (60, 5), (60, 4), (60, 6), (60, 3)]  # each episode whole, on its body

    # Released as the stream goes on, the same episodes reach the pool one by one, each as it ends.
    asm, learner = TransitionAssembler(TransitionConfig(settle_states=10)), LiveLearner(SMALL, tmp_path / "stream")
    cutter = EpisodeCutter(learner, lambda stamp: 0)
    sizes = []
    for r in records:
        cutter.take(asm.push(r))
        sizes.append(learner.pool_size)
    # (the last complete one waits for 10 states after it: the body after it gives 30, or only its first)
    assert sorted(set(sizes)) == [0, 60, 120, 180, 240] + ([300] if silent == "mid-episode" else [])
    assert cutter.drop(asm) == lost and learner.pool_size == 300
