"""Trained policies deployed.

- :mod:`.policy_file`: standalone policy files (actor, optionally the critics, architecture,
  checksum, lineage), validated on load.
- :mod:`.policy`: :class:`~.policy.Planner`, a policy file as a closed-loop planner (numpy and
  batched JAX; ``safe=True`` shields every step).
- :mod:`.handover`: the hybrid planner: what the policy leaves unfinished goes to BiRRT.
"""
