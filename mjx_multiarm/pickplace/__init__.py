"""The paper's application under MuJoCo physics: four arms with grippers pick objects into a bin.

- :mod:`.derive`: the pick-and-place assets derived from the original demo's meshes, bin and grasps.
- :mod:`.scene`: the MJCF: position-actuated arms, grippers, object slots, grasp welds, bin, floor.
- :mod:`.plans`: run plans: draws from a seed, placements, grasps, the configurations the phases head for.
- :mod:`.protocol`: the per-arm phase sequence as one JAX controller, and the collision rules.
- :mod:`.backends`: the physics backends driving the controller (MuJoCo C and MJX).
- :mod:`.render`: frames of runs.

``python -m eval.pickplace --help`` runs it.
"""
