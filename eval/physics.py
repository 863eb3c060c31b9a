"""Physics fidelity of the reaching policy: the same tasks run kinematically (the training
environment) and with the arms position-actuated under MuJoCo's dynamics.

    python -m eval.physics --tasks held512.npz --arms 4 --json

Under physics every arm is servoed (the pick-and-place scene's gains, torque limits and
gravity compensation; :func:`mjx_multiarm.pickplace.scene.build_reaching_spec`) toward the
joint waypoint the policy outputs each control step (50 ms, 12 physics steps of 1/240 s,
the servo target interpolated); the policy observes the measured joints. A task succeeds
when every arm is within 2 cm / 0.1 rad at one control step before ``--episode-steps``,
with no collision of the measured configuration (the collision model, checked at the end of
every control step; the kinematic environment also sweeps the motion between steps). The kinematic column is :mod:`eval.benchmark`'s evaluation of the same tasks.
Tracking error: the joint distance between the servo target and the measured joints at the
end of each control step.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjx_multiarm.env.reaching import EVAL_TOLERANCE
from mjx_multiarm.geometry.collision import CONTACTS_ONLY, scene_contacts
from mjx_multiarm.geometry.kinematics import forward_kinematics
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.geometry.transforms import quat_angle
from mjx_multiarm.pickplace.protocol import SUBSTEPS
from mjx_multiarm.pickplace.scene import build_reaching_spec
from mjx_multiarm.tasks.dataset import load_tasks
from mjx_multiarm.tasks.types import Tasks


def _measure(num_arms: int):
    scene = build_scene(num_arms)

    @jax.jit
    def measure(base_pos, base_quat, joints, target_pos, target_quat):
        frames = forward_kinematics(scene.arm, base_pos, base_quat, joints)
        reached = ((jnp.linalg.norm(frames.ee_pos - target_pos, axis=-1) < EVAL_TOLERANCE[0])
                   & (quat_angle(frames.ee_quat, target_quat) < EVAL_TOLERANCE[1])).all(-1)
        active = jnp.ones(joints.shape[:-1], bool)
        return reached, scene_contacts(scene, base_pos, base_quat, joints, active, CONTACTS_ONLY).collided.any(-1)

    return measure


def physics_outcomes(planner, tasks: Tasks, episode_steps: int = 500) -> dict:
    """Success, collision and timeout rates and servo tracking of ``tasks`` (one team size,
    every slot active) under MuJoCo C dynamics, all tasks in lockstep."""
    n, arms = tasks.active.shape
    if not tasks.active.all():
        raise ValueError("physics_outcomes needs tasks whose every slot is active (select one team size)")
    model = build_reaching_spec(arms).compile()
    joint_ids = np.array([[model.joint(f"arm{i}/{j}").id for j in load_arm().joint_names] for i in range(arms)])
    qpos, act = model.jnt_qposadr[joint_ids], np.array([[model.actuator(f"arm{i}/{j}").id for j in load_arm().joint_names]
                                                        for i in range(arms)])
    mocap = np.array([model.body_mocapid[model.body(f"arm{i}/base_link").id] for i in range(arms)])
    datas = []
    for t in range(n):
        d = mujoco.MjData(model)
        d.mocap_pos[mocap], d.mocap_quat[mocap] = tasks.base_pos[t], tasks.base_quat[t]
        d.qpos[qpos] = d.ctrl[act] = tasks.start_joints[t]
        mujoco.mj_forward(model, d)
        datas.append(d)
    step = planner.batched(arms)
    measure = _measure(arms)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    base_pos, base_quat, target_pos, target_quat = map(f32, (tasks.base_pos, tasks.base_quat, tasks.target_pos,
                                                              tasks.target_quat))
    joints = np.stack([d.qpos[qpos] for d in datas])
    prev = joints.copy()
    command = joints.copy()
    done = np.zeros(n, bool)
    success, collided = np.zeros(n, bool), np.zeros(n, bool)
    steps = np.full(n, episode_steps)
    tracking = []
    for k in range(episode_steps):
        target = np.asarray(step(base_pos, base_quat, f32(prev), f32(joints), target_pos, target_quat, target_pos,
                                 target_quat), np.float64)
        for t in np.flatnonzero(~done):
            d = datas[t]
            for s in range(SUBSTEPS):
                d.ctrl[act] = command[t] + (target[t] - command[t]) * ((s + 1) / SUBSTEPS)
                mujoco.mj_step(model, d)
        prev, command = joints, np.where(done[:, None, None], command, target)
        joints = np.stack([d.qpos[qpos] for d in datas])
        tracking.append(np.abs(joints - command)[~done].reshape(-1, 6))
        reached, collision = (np.asarray(x) for x in measure(base_pos, base_quat, f32(joints), target_pos, target_quat))
        ending = ~done & (collision | reached)
        collided |= ending & collision
        success |= ending & reached & ~collision
        steps[ending] = k + 1
        done |= ending
        if done.all():
            break
    tracking = np.concatenate(tracking)
    return {"tasks": n, "success_rate": float(success.mean()), "collision_rate": float(collided.mean()),
            "timeout_rate": float((~done).mean()), "steps_to_success": float(steps[success].mean()) if success.any() else None,
            "tracking_error_rad": {"mean": float(tracking.mean()), "p99": float(np.percentile(tracking, 99)),
                                   "max": float(tracking.max())}}


def main(argv=None) -> None:
    from eval.benchmark import policy_outcomes
    from mjx_multiarm.planner.policy import Planner

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", type=pathlib.Path, required=True, help="task dataset .npz")
    parser.add_argument("--arms", type=int, default=4, help="team size to run (default 4)")
    parser.add_argument("--checkpoint", type=pathlib.Path, help="policy file or run directory (default: the shipped policy)")
    parser.add_argument("--episode-steps", type=int, default=500)
    parser.add_argument("--json", action="store_true", help="end with one JSON line")
    args = parser.parse_args(argv)
    tasks, _ = load_tasks(args.tasks)
    rows = np.flatnonzero(tasks.num_arms == args.arms)
    if not len(rows):
        parser.error(f"--tasks {args.tasks} has no {args.arms}-arm tasks")
    team = jax.tree.map(lambda x: np.asarray(x)[rows][:, : args.arms] if np.ndim(x) >= 2 else np.asarray(x)[rows], tasks)
    planner = Planner.load(args.checkpoint)
    start = time.perf_counter()
    physics = physics_outcomes(planner, team, args.episode_steps)
    physics["seconds"] = time.perf_counter() - start
    kinematic, _ = policy_outcomes(planner, team, dynamic=False, episode_steps=args.episode_steps)
    kin = {"tasks": len(rows), "success_rate": float(np.mean(kinematic.success)),
           "collision_rate": float(np.mean(kinematic.collision)), "timeout_rate": float(np.mean(kinematic.timeout))}
    print(f"{args.arms}-arm tasks ({len(rows)}): kinematic success {kin['success_rate']:.1%} (collisions "
          f"{kin['collision_rate']:.1%}); physics success {physics['success_rate']:.1%} (collisions "
          f"{physics['collision_rate']:.1%}, timeouts {physics['timeout_rate']:.1%}); servo tracking error mean "
          f"{physics['tracking_error_rad']['mean']:.4f} rad, p99 {physics['tracking_error_rad']['p99']:.4f}")
    if args.json:
        print(json.dumps({"arms": args.arms, "kinematic": kin, "physics": physics}))


if __name__ == "__main__":
    main()
