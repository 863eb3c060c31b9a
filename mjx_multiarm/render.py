"""Offscreen renders of episodes: arms, targets and end-effector trails, as PNG frames or MP4.

    frames = render_episode(env, task, trajectory)      # [T, H, W, 3] uint8
    save_frames(frames, "out/episode0")                 # out/episode0/frame_0000.png ...
    save_video(frames, "out/episode0.mp4")              # needs imageio + imageio-ffmpeg

MuJoCo's renderer needs an OpenGL context. Without a display it works through EGL (GPU or
Mesa) or OSMesa (CPU): with ``MUJOCO_GL`` unset this module tries EGL, then OSMesa; with
``MUJOCO_GL`` set it uses that backend only. When none works, :class:`RenderingUnavailable`
says what to install.
"""

from __future__ import annotations

import importlib
import os
import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from mjx_multiarm.env.reaching import ReachingEnv
from mjx_multiarm.geometry.scene import set_mujoco_state
from mjx_multiarm.geometry.transforms import quat_to_mat
from mjx_multiarm.tasks.types import Tasks

#: Arm colours (RGBA), cycled over the arms of a team.
COLOURS = np.array([[0.90, 0.30, 0.25, 1], [0.25, 0.55, 0.90, 1], [0.30, 0.75, 0.35, 1], [0.95, 0.65, 0.20, 1],
                    [0.60, 0.40, 0.80, 1], [0.20, 0.75, 0.75, 1], [0.85, 0.45, 0.65, 1], [0.55, 0.55, 0.55, 1],
                    [0.70, 0.70, 0.20, 1], [0.40, 0.30, 0.20, 1]], np.float32)


class RenderingUnavailable(RuntimeError):
    """No OpenGL backend for offscreen rendering."""


@struct.dataclass
class Trajectory:
    """One recorded episode (numpy): joints [T, A, 6], end-effector and target positions
    [T, A, 3], target orientations [T, A, 4] (wxyz), and the outcome."""

    joints: np.ndarray
    ee_pos: np.ndarray
    target_pos: np.ndarray
    target_quat: np.ndarray
    success: bool
    collided: bool


def record_episode(env: ReachingEnv, policy, params, task: Tasks, steps: int | None = None) -> Trajectory:
    """Run one task (a device task row, e.g. ``bank.take(i)`` unbatched) with
    ``policy(states, params)`` (as :func:`mjx_multiarm.env.wrappers.make_episodes`) and keep
    every step until the episode ends."""
    steps = env.config.max_steps if steps is None else steps

    @jax.jit
    def run(task, params):
        start = env.reset(None, task)

        def step(state, _):
            batched = jax.tree.map(lambda x: x[None], state)
            following = env.step(state, policy(batched, params)[0])
            return following, following

        _, states = jax.lax.scan(step, start, None, steps)
        return jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), start, states)

    states = jax.device_get(run(task, params))
    last = int(np.argmax(states.done)) if states.done.any() else steps
    keep = slice(0, last + 1)
    return Trajectory(states.joints[keep], states.arms.ee_pos[keep], states.arms.target_pos[keep], states.arms.target_quat[keep],
                      bool(states.success[last]), bool(states.collided[last].any()))


def make_renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """A renderer on the first OpenGL backend that works (see the module docstring)."""
    configured = os.environ.get("MUJOCO_GL")
    backends = [None] if configured else ["egl", "osmesa"]
    errors = []
    for name in backends:
        try:
            if name is not None:
                from mujoco.rendering.classic import gl_context

                gl_context.GLContext = importlib.import_module(f"mujoco.{name}").GLContext
            return mujoco.Renderer(model, height, width)
        except Exception as error:  # noqa: BLE001 - every backend failure is reported below
            errors.append(f"{name or configured}: {type(error).__name__}: {error}")
    raise RenderingUnavailable("offscreen rendering needs OpenGL through EGL or OSMesa; tried " + "; ".join(errors)
                               + ". Install libegl1 (or libosmesa6) or set MUJOCO_GL to a working backend.")


def _add_geom(scene: mujoco.MjvScene, kind, size, pos, mat, rgba) -> None:
    if scene.ngeom >= scene.maxgeom:
        return
    mujoco.mjv_initGeom(scene.geoms[scene.ngeom], kind, np.asarray(size, np.float64), np.asarray(pos, np.float64),
                        np.asarray(mat, np.float64).ravel(), np.asarray(rgba, np.float32))
    scene.ngeom += 1


def _geom_slots(model: mujoco.MjModel) -> np.ndarray:
    """Arm slot of every geom (-1 for the ground and other non-arm geoms)."""
    slots = np.full(model.ngeom, -1)
    for g in range(model.ngeom):
        name = model.body(model.geom_bodyid[g]).name
        if name.startswith("arm") and "/" in name:
            slots[g] = int(name[3 : name.index("/")])
    return slots


def _camera(base_pos: np.ndarray) -> mujoco.MjvCamera:
    camera = mujoco.MjvCamera()
    centre = base_pos.mean(axis=0)
    spread = np.max(np.linalg.norm(base_pos[:, :2] - centre[:2], axis=-1)) if len(base_pos) > 1 else 0.0
    camera.lookat[:] = centre + [0, 0, 0.3]
    camera.distance = 1.8 + 1.3 * spread
    camera.azimuth, camera.elevation = 135.0, -30.0
    return camera


def render_episode(env: ReachingEnv, task: Tasks, trajectory: Trajectory, height: int = 480, width: int = 640,
                   renderer: mujoco.Renderer | None = None) -> np.ndarray:
    """Frames [T, H, W, 3] (uint8) of ``trajectory`` of ``task`` (one numpy task row):
    the arms, each arm's target (a coloured sphere with a short approach axis) and its
    end-effector trail so far."""
    scene = env.scene
    renderer = renderer or make_renderer(scene.mj_model, height, width)
    data = mujoco.MjData(scene.mj_model)
    active = np.asarray(task.active, bool)
    base_pos, base_quat = np.asarray(task.base_pos), np.asarray(task.base_quat)
    camera = _camera(base_pos[active])
    options = mujoco.MjvOption()
    options.geomgroup[3] = 1  # the arms' collision geoms (capsules and the gripper box) are what we draw
    slots = _geom_slots(scene.mj_model)
    frames = []
    for t in range(len(trajectory.joints)):
        set_mujoco_state(scene, data, base_pos, base_quat, trajectory.joints[t], active)
        renderer.update_scene(data, camera, options)
        for geom in renderer.scene.geoms[: renderer.scene.ngeom]:
            if geom.objtype == mujoco.mjtObj.mjOBJ_GEOM and slots[geom.objid] >= 0:
                geom.rgba[:3] = 0.55 + 0.45 * COLOURS[slots[geom.objid] % len(COLOURS), :3]
        for arm in np.flatnonzero(active):
            colour = COLOURS[arm % len(COLOURS)]
            target_mat = np.asarray(quat_to_mat(jnp.asarray(trajectory.target_quat[t, arm])))
            _add_geom(renderer.scene, mujoco.mjtGeom.mjGEOM_SPHERE, [0.03, 0, 0], trajectory.target_pos[t, arm], np.eye(3),
                      [*colour[:3], 0.6])
            _add_geom(renderer.scene, mujoco.mjtGeom.mjGEOM_CYLINDER, [0.006, 0.05, 0],
                      trajectory.target_pos[t, arm] + target_mat[:, 2] * 0.05, target_mat, colour)
            for point in trajectory.ee_pos[max(0, t - 200) : t + 1 : 2, arm]:
                _add_geom(renderer.scene, mujoco.mjtGeom.mjGEOM_SPHERE, [0.006, 0, 0], point, np.eye(3), [*colour[:3], 0.8])
        frames.append(renderer.render().copy())
    return np.stack(frames)


def save_frames(frames: np.ndarray, directory: str | os.PathLike) -> list[pathlib.Path]:
    """Write ``frames`` as ``frame_0000.png`` ... into ``directory`` (created)."""
    import matplotlib.image

    directory = pathlib.Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / f"frame_{i:04d}.png" for i in range(len(frames))]
    for frame, path in zip(frames, paths):
        matplotlib.image.imsave(path, frame)
    return paths


def save_video(frames: np.ndarray, path: str | os.PathLike, fps: int = 20) -> pathlib.Path:
    """Write ``frames`` as an MP4 (imageio with its ffmpeg plugin must be installed:
    ``pip install imageio imageio-ffmpeg``); raises ImportError naming them otherwise."""
    try:
        import imageio.v3 as iio
    except ImportError as error:
        raise ImportError("MP4 output needs imageio and imageio-ffmpeg (pip install imageio imageio-ffmpeg); "
                          "save_frames writes PNG frames without them") from error
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, frames, fps=fps, codec="libx264")
    return path
