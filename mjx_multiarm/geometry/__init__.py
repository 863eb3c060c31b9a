"""The arm and its scene.

- :mod:`.robot`: the UR5 MJCF compiled once, the constants the kernels use.
- :mod:`.transforms`: the one quaternion convention.
- :mod:`.kinematics`: batched forward kinematics.
- :mod:`.scene`: the padded multi-arm scene and which geom pairs count.
- :mod:`.collision`: the batched exact distances (between arms, self, ground) and swept motions.
- :mod:`.certified`: the certified motion check (no configuration along a motion touches).
- :mod:`.compiled`: the same kinematics and distances as numba-compiled scalar code (the CPU kernel).
- :mod:`.checker`: the compiled collision checker of one team (BiRRT, detour tasks, replay checks).
- :mod:`.ik`: batched damped-least-squares IK.
- :mod:`.evaluate`: the numpy entry point :func:`~.evaluate.evaluate_arms`.
"""
