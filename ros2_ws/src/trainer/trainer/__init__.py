"""Trainer: PPO command-line tools around morph_core (training, evaluation)."""
