"""mjx-multiarm: multi-arm UR5 scenes, kinematics and collision on JAX / MuJoCo MJX.

Public entry points:

- :func:`evaluate_arms`: numpy in/out end-effector poses and collision flags.
- :func:`build_scene`: the padded multi-arm MuJoCo scene and its JAX kernel constants.
- :func:`forward_kinematics`, :func:`scene_contacts`, :func:`swept_contacts`: the batched
  JAX functions (jit/vmap-able) behind it.
- :class:`Planner`: a trained policy as a closed-loop planner (numpy in/out, or batched JAX).
- :class:`ReachingEnv`, :class:`EnvConfig`: the multi-arm reaching environment
  (``reset``/``step``); batching helpers in :mod:`mjx_multiarm.env.wrappers`.
"""

from mjx_multiarm.env.reaching import EnvConfig, ReachingEnv
from mjx_multiarm.geometry.collision import (
    Contacts,
    num_substeps,
    scene_contacts,
    swept_contacts,
)
from mjx_multiarm.geometry.evaluate import ArmEvaluation, evaluate_arms
from mjx_multiarm.geometry.kinematics import ArmFrames, forward_kinematics
from mjx_multiarm.geometry.scene import Scene, build_scene
from mjx_multiarm.planner.policy import PlannedPath, Planner

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
