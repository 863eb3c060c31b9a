"""Training: ``python -m train.sac`` and :func:`train.run.train`.

- :mod:`.config`: ``RunConfig`` and the presets.
- :mod:`.run`: the host loop, checkpoints, signals, held-out evaluations, summary.
- :mod:`.sac`: the command line.
- :mod:`.data`: a run's tasks, experts, environments and task banks.
- :mod:`.trainer`: the jitted training iteration.
- :mod:`.agent`: SAC and behaviour-cloning updates.
- :mod:`.replay`: the on-device replay buffer.
- :mod:`.curriculum`: the tolerance curriculum.
- :mod:`.relabel`: expert relabelling of collisions.
- :mod:`.checkpoint`: Orbax checkpoints with fallback past damaged ones.
- :mod:`.finetune`: fine-tuning from a policy file and its lineage.
- :mod:`.evaluation`: deterministic evaluation on a task bank.
- :mod:`.plots`: the learning curve.
"""
