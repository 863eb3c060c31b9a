"""mjx-multiarm: multi-arm UR5 scenes, kinematics and collision on JAX / MuJoCo MJX.

Public entry points:

- :func:`evaluate_arms`: numpy in/out end-effector poses and collision flags.
- :func:`build_scene`: the padded multi-arm MuJoCo scene and its JAX kernel constants.
- :func:`forward_kinematics`, :func:`scene_contacts`, :func:`swept_contacts`: the batched
  JAX functions (jit/vmap-able) behind it.
- :class:`Planner`: a trained policy as a closed-loop planner (numpy in/out, or batched JAX).
- :class:`ReachingEnv`, :class:`EnvConfig`: the multi-arm reaching environment
  (``reset``/``step``); batching helpers in :mod:`mjx_multiarm.wrappers`.
"""

from mjx_multiarm.api import ArmEvaluation, evaluate_arms
from mjx_multiarm.collision import Contacts, num_substeps, scene_contacts, swept_contacts
from mjx_multiarm.env import EnvConfig, ReachingEnv
from mjx_multiarm.kinematics import ArmFrames, forward_kinematics
from mjx_multiarm.scene import Scene, build_scene

__all__ = [
    "ArmEvaluation",
    "ArmFrames",
    "Contacts",
    "EnvConfig",
    "PlannedPath",
    "Planner",
    "ReachingEnv",
    "Scene",
    "build_scene",
    "evaluate_arms",
    "forward_kinematics",
    "num_substeps",
    "scene_contacts",
    "swept_contacts",
]


def __getattr__(name: str):
    # The planner needs the networks (models/), which import this package's modules:
    # load it on first use to keep the import graph acyclic.
    if name in ("Planner", "PlannedPath"):
        from mjx_multiarm import policy

        return getattr(policy, name)
    raise AttributeError(f"module 'mjx_multiarm' has no attribute {name!r}")
