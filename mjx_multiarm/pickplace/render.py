"""Renders of pick-and-place runs: arms, grippers, objects, the bin and the policy's targets."""

from __future__ import annotations

import jax
import mujoco
import numpy as np

from mjx_multiarm.pickplace.protocol import (
    REACH_ABOVE,
    REACH_DUMP,
    REACH_PREGRASP,
    policy_target,
)
from mjx_multiarm.render import COLOURS, _add_geom, make_renderer


def _camera() -> mujoco.MjvCamera:
    camera = mujoco.MjvCamera()
    camera.lookat[:] = [0.0, 0.0, 0.25]
    camera.distance, camera.azimuth, camera.elevation = 3.2, 135.0, -35.0
    return camera


class RunRecorder:
    """Collects frames of some runs of a MuJoCo C batch every ``every`` control steps; use
    its :meth:`on_step` as :func:`~mjx_multiarm.pickplace.backends.run_mujoco`'s ``on_step``."""

    def __init__(self, model: mujoco.MjModel, runs, plans, every: int = 2, height: int = 360, width: int = 480):
        self.runs, self.plans, self.every = list(runs), plans, every
        self.renderer = make_renderer(model, height, width)
        self.frames = {r: [] for r in self.runs}
        self.options = mujoco.MjvOption()

    def on_step(self, step: int, datas, state) -> None:
        if step % self.every:
            return
        for r in self.runs:
            if bool(np.asarray(state.ended)[r]) and self.frames[r]:
                continue
            self.renderer.update_scene(datas[r], _camera(), self.options)
            phases = np.asarray(state.phase)[r]
            targets = np.asarray(policy_target(jax.tree.map(lambda x, r=r: x[r], self.plans), phases)[0])
            for arm, phase in enumerate(phases):
                if phase not in (REACH_ABOVE, REACH_PREGRASP, REACH_DUMP):
                    continue
                target = targets[arm]
                _add_geom(self.renderer.scene, mujoco.mjtGeom.mjGEOM_SPHERE, [0.03, 0, 0], target, np.eye(3),
                          [*COLOURS[arm][:3], 0.6])
            self.frames[r].append(self.renderer.render().copy())

    def close(self) -> None:
        self.renderer.close()
