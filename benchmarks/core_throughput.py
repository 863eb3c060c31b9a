"""Throughput of batched kinematics + full collision (between arms, self, ground).

Counts arm-evaluations per second: one arm's forward kinematics and every collision check
it takes part in, at one configuration. Each measured call runs ``--steps`` random joint
motions of a batch of scenes inside one ``jit``-compiled ``lax.scan`` (compile excluded).
``--impl ours`` asks for every arm's exact smallest distances; ``ours-contacts`` for the
contacts only (``max_distance=CONTACTS_ONLY``: the verdicts, as the environment's step asks).

    python benchmarks/core_throughput.py --arms 1,4,10 --batch 1,64,1024
    python benchmarks/core_throughput.py --arms 4 --batch 1024 --json
    python benchmarks/core_throughput.py --arms 4 --batch 1024 --impl ours-contacts
    python benchmarks/core_throughput.py --arms 4 --batch 1024 --impl mjx-kinematics
    python benchmarks/core_throughput.py --arms 4 --batch 256 --impl mjx-collision

With ``--json`` every measurement also prints one JSON line (arms, batch, device,
arm_evals_per_s, ...); a single measurement's JSON line is the last line of the output.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import add_timing_arguments, cpu_name, selected_device

from mjx_multiarm import build_scene, scene_contacts
from mjx_multiarm.geometry.collision import CONTACTS_ONLY
from mjx_multiarm.geometry.transforms import yaw_quat


def _inputs(rng, num_arms, batch):
    """Arms on a line 0.6 m apart (a dense, often-colliding layout) near home."""
    scene = build_scene(num_arms)
    base_pos = np.zeros((batch, num_arms, 3), np.float32)
    base_pos[..., 0] = 0.6 * np.arange(num_arms)
    base_quat = np.asarray(yaw_quat(rng.uniform(-np.pi, np.pi, (batch, num_arms))), np.float32)
    joints = (scene.arm.home + rng.normal(0.0, 1.0, (batch, num_arms, 6))).astype(np.float32)
    return scene, base_pos, base_quat, joints, np.ones((batch, num_arms), bool)


def _ours(scene, max_distance=math.inf):
    def evaluate(base_pos, base_quat, joints, active):
        return scene_contacts(scene, base_pos, base_quat, joints, active, max_distance).collided

    return evaluate


def _mjx(scene, collide: bool):
    """MJX's generic pipeline on the same padded model (for comparison): kinematics only,
    or kinematics + ``mjx.collision`` over the same filtered capsule pairs."""
    from mujoco import mjx

    model = mjx.put_model(scene.mj_model)
    qpos_adr = jnp.asarray(scene.qpos_adr.ravel())
    mocap = jnp.asarray(scene.mocap_ids)

    def one(base_pos, base_quat, joints):
        data = mjx.make_data(model)
        data = data.replace(
            qpos=data.qpos.at[qpos_adr].set(joints.ravel()),
            mocap_pos=data.mocap_pos.at[mocap].set(base_pos),
            mocap_quat=data.mocap_quat.at[mocap].set(base_quat),
        )
        data = mjx.kinematics(model, data)
        if collide:
            return jnp.any(mjx.collision(model, data)._impl.contact.dist < 0)
        return jnp.any(data.geom_xpos[:, 2] < 0)

    def evaluate(base_pos, base_quat, joints, active):
        return jax.vmap(one)(base_pos, base_quat, joints)

    return evaluate


IMPLEMENTATIONS = {
    "ours": _ours,  # exact distances, as the benchmark has always measured
    "ours-contacts": lambda scene: _ours(scene, CONTACTS_ONLY),  # verdicts only, as the environment asks
    "mjx-kinematics": lambda scene: _mjx(scene, collide=False),
    "mjx-collision": lambda scene: _mjx(scene, collide=True),
}


def measure(num_arms, batch, device, impl="ours", steps=20, min_seconds=2.0, seed=0):
    """Median arm-evaluations/s over repeated jitted rollouts of ``steps`` motions."""
    rng = np.random.default_rng(seed)
    scene, base_pos, base_quat, joints, active = _inputs(rng, num_arms, batch)
    evaluate = IMPLEMENTATIONS[impl](scene)
    motions = rng.normal(0.0, 0.05, (steps, batch, num_arms, 6)).astype(np.float32)
    args = jax.device_put((base_pos, base_quat, joints, active, motions), device)

    @jax.jit
    def rollout(base_pos, base_quat, joints, active, motions):
        def step(q, dq):
            q = q + dq
            return q, jnp.sum(evaluate(base_pos, base_quat, q, active))

        return jax.lax.scan(step, joints, motions)[1].sum()

    rollout(*args).block_until_ready()  # compile
    times, start = [], time.perf_counter()
    while time.perf_counter() - start < min_seconds or len(times) < 3:
        t = time.perf_counter()
        rollout(*args).block_until_ready()
        times.append(time.perf_counter() - t)
    per_call = statistics.median(times)
    return {
        "arms": num_arms,
        "batch": batch,
        "device": device.platform,
        "device_kind": device.device_kind,
        "impl": impl,
        "arm_evals_per_s": num_arms * batch * steps / per_call,
        "scenes_per_s": batch * steps / per_call,
        "capsules_per_arm": scene.arm.num_capsules,
        "repeats": len(times),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arms", default="1,4,10", help="comma-separated team sizes (slots = arms)")
    parser.add_argument("--batch", default="1,64,1024", help="comma-separated batch sizes (scenes)")
    parser.add_argument("--impl", choices=sorted(IMPLEMENTATIONS), default="ours")
    add_timing_arguments(parser, 20, "motions per jitted rollout")
    args = parser.parse_args(argv)

    device = selected_device(args)
    print(f"# {cpu_name()}, {device.device_kind}, jax {jax.__version__}")
    print(f"{'arms':>4} {'batch':>6} {'arm-evals/s':>14} {'scenes/s':>12}")
    for num_arms in (int(a) for a in args.arms.split(",")):
        for batch in (int(b) for b in args.batch.split(",")):
            result = measure(num_arms, batch, device, args.impl, args.steps, args.seconds)
            print(f"{num_arms:>4} {batch:>6} {result['arm_evals_per_s']:>14,.0f} {result['scenes_per_s']:>12,.0f}")
            if args.json:
                print(json.dumps(result))


if __name__ == "__main__":
    main()
