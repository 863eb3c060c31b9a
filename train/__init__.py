"""Training: `python -m train.sac`, replay buffer, presets, checkpoints (issue 6)."""
