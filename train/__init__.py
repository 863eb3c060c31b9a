"""Training: `python -m train.sac` and `train.run.train()`: the run configuration and presets, data, SAC with expert demonstrations, curriculum, replay, checkpoints."""
