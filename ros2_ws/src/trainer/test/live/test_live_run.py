"""The live learner as a loop around ``algo.run.Run``: an old state (its run id under ``env``) resumed, with the
learning rate given, and the row hook heard after every update (whose state is always saved)."""

import dataclasses
import json

import torch
from safetensors.torch import save as safetensors_bytes

from morph_core.algo.checkpoint import _digest, load_training_state, previous_state_path
from morph_core.algo.config import TrainerConfig
from morph_core.algo.run_dir import RunDir
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.protocol.loopback import SamplingController, record_episodes
from morph_core.protocol.transitions import TransitionAssembler
from trainer.live.learner import LiveLearner


def test_the_live_learner_resumes_an_old_state_with_a_new_learning_rate_and_hears_rows(tmp_path):
    cfg = TrainerConfig(batch_size=64, minibatch_size=32, update_epochs=1, min_joints=3, max_joints=3, compile=False,
                    progress_bar=False, tensorboard=False)  # fmt: skip
    first = LiveLearner(cfg, tmp_path)
    run_id, epoch = first.run_id, first.epoch
    first.close()
    # The state as the live learner wrote it before sections: the run id and epoch under env.
    path = RunDir(tmp_path).state
    tensors, meta = load_training_state(path)
    live = meta.pop("sections")["live"]
    assert live.pop("version") == 1
    meta["env"] = live
    path.write_bytes(safetensors_bytes(tensors, metadata={"state": json.dumps(meta), "sha256": _digest(tensors)}))
    previous_state_path(path).unlink(missing_ok=True)

    heard = []
    again = LiveLearner(dataclasses.replace(cfg, learning_rate=0.002), tmp_path, resume=True,
                        on_row=lambda row, saved: heard.append((row["version"], saved)))  # fmt: skip
    assert again.resumed and (again.run_id, again.epoch) == (run_id, epoch)
    assert [g["lr"] for g in again.learner.optimizer.param_groups] == [0.002]
    torch.manual_seed(5)
    asm = TransitionAssembler()
    steps = asm.push_many(record_episodes(SamplingController(GraphActorCritic(), seed=2), ((3, 80),), 0)) + asm.flush()
    assert again.add_episode(steps, [0] * len(steps)) == len(steps) >= 64
    row = again.update()
    again.close()
    assert heard == [(1, True)] and row["learning_rate"] == 0.002
    assert load_training_state(path)[1]["sections"]["live"] == {"version": 1, "run": run_id, "epoch": epoch}
