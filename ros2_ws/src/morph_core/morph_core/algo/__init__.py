"""PPO on mixed action dimensions: trust-region rules, the update, the simulator loop, evaluation, checkpoints."""
