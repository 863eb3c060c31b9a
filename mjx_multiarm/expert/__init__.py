"""The BiRRT expert: centralized RRT-Connect plans, decimated into environment actions.

- :mod:`.planner`: RRT-Connect (OMPL) on the collision model (the compiled checker of
  :mod:`mjx_multiarm.geometry.checker`).
- :mod:`.decimate`: dense joint path -> delta-joint environment steps.
- :mod:`.solve`: a task's expert: plan, decimate, certify as the environment executes, re-plan.
- :mod:`.store`: memory-mapped, checksummed expert files.
- :mod:`.precompute`: resumable chunked precompute on local processes or Ray.
- :mod:`.replan`: the re-planning BiRRT baseline for moving targets.

``python -m mjx_multiarm.expert --help`` runs the batched precompute.
"""
