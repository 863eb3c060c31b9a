"""Evaluation of policies and BiRRT.

- :mod:`.benchmark`: ``python -m eval.benchmark``, the paper's static and dynamic tables.
- :mod:`.latency`: pinned-thread inference latency.
- :mod:`.runtime`: policy vs. BiRRT trajectory computation time.
- :mod:`.physics`: reaching tasks kinematic vs. position-actuated under MuJoCo C.
- :mod:`.pickplace`: ``python -m eval.pickplace``, the pick-and-place application.
"""
