"""Collision verdicts of the JAX kernel on many random scenes: differences from a recorded
reference and from the expert's compiled (numba, float64) checker.

Scenes: ``--scenes`` random padded scenes in 10 slots, 1-10 active arms (team size
``1 + k % 10`` for scene k), bases scattered so that arms often reach each other (uniform in a
square of side ``sqrt(n)`` m), random yaws, joints home + N(0, 1 rad) within the limits; the
same scenes for the same ``--seed``.

- **Reference**: ``--record FILE`` stores every arm's verdict (``scene_contacts(...).collided``)
  with the seed; a later run with ``--reference FILE`` regenerates the scenes and counts the
  arms whose verdict differs. A kernel change that keeps the model must count 0.
- **Numba checker** (:class:`mjx_multiarm.geometry.checker.CollisionChecker`, an independent
  float64 implementation): per scene, whether any arm collides. Scenes whose smallest
  kernel distance is within ``1e-5`` m of contact are left out (float32 rounding) and counted.
- ``--max-distance 0`` asks the kernel for contacts only (``CONTACTS_ONLY``, what the
  environment's step asks); its verdicts must match the reference too (no checker
  comparison: clear arms read 0, so near-contact scenes cannot be told apart).

    python benchmarks/collision_verdicts.py --scenes 100000 --record benchmarks/collision_verdicts_100k.npz
    python benchmarks/collision_verdicts.py --scenes 100000 --reference benchmarks/collision_verdicts_100k.npz
    python benchmarks/collision_verdicts.py --scenes 100000 --reference benchmarks/collision_verdicts_100k.npz \
        --max-distance 0 --no-checker
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import cpu_name

from mjx_multiarm.files import atomic_write
from mjx_multiarm.geometry.checker import CollisionChecker
from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.geometry.transforms import yaw_quat

SLOTS = 10
#: Kernel distances closer to 0 than this (m) are within float32 rounding of contact.
ROUNDING = 1e-5


def random_scenes(seed: int, count: int, block: int = 1000):
    """(base_pos [N, 10, 3], base_quat [N, 10, 4], joints [N, 10, 6], active [N, 10]), drawn
    in blocks of ``block`` scenes with generators seeded (seed, block index): the first k
    scenes are the same whatever ``count``."""
    arm = load_arm()
    parts = []
    for b in range(-(-count // block)):
        rng = np.random.default_rng([seed, b])
        xy, yaw = rng.uniform(-0.5, 0.5, (block, SLOTS, 2)), rng.uniform(-np.pi, np.pi, (block, SLOTS))
        parts.append((xy, yaw, rng.normal(0.0, 1.0, (block, SLOTS, 6))))
    xy, yaw, noise = (np.concatenate(x)[:count] for x in zip(*parts))
    arms = 1 + np.arange(count) % SLOTS
    pos = np.concatenate([xy * np.sqrt(arms)[:, None, None], np.zeros((count, SLOTS, 1))], axis=-1)
    quat = np.asarray(yaw_quat(yaw), np.float64)
    joints = np.clip(arm.home + noise, *arm.joint_range.T)
    return pos, quat, joints, np.arange(SLOTS) < arms[:, None]


def kernel_results(pos, quat, joints, active, chunk: int = 4096, max_distance: float = math.inf):
    """Per-arm verdicts [N, 10] and smallest distances [N, 10] of the JAX kernel."""
    scene = build_scene(SLOTS)

    @jax.jit
    def check(*inputs):
        contacts = scene_contacts(scene, *inputs, max_distance=max_distance)
        return contacts.collided, contacts.min_distance

    verdicts, distances = [], []
    for start in range(0, len(pos), chunk):
        part = slice(start, start + chunk)
        out = check(*(jnp.asarray(x[part], jnp.float32) for x in (pos, quat, joints)), jnp.asarray(active[part]))
        verdicts.append(np.asarray(out[0]))
        distances.append(np.asarray(out[1]))
    return np.concatenate(verdicts), np.concatenate(distances)


def checker_verdicts(pos, quat, joints, active) -> np.ndarray:
    """Per scene, whether the numba checker finds any collision [N]."""
    arm = load_arm()
    return np.array([CollisionChecker(p[a], q[a], arm.joint_range, 0.05).collided(j[a].reshape(1, -1))[0]
                     for p, q, j, a in zip(pos, quat, joints, active)])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=2026)
    out = parser.add_mutually_exclusive_group()
    out.add_argument("--record", type=pathlib.Path, help="store the kernel's verdicts as the reference")
    out.add_argument("--reference", type=pathlib.Path, help="count the verdicts that differ from this recording")
    parser.add_argument("--no-checker", action="store_true", help="skip the numba checker comparison")
    parser.add_argument("--max-distance", type=float, default=math.inf,
                        help="the kernel's max_distance (0: contacts only; needs --no-checker)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.max_distance <= ROUNDING and not args.no_checker:
        parser.error("--max-distance at or below contact hides the distances the checker comparison needs: add --no-checker")

    print(f"# {cpu_name()}, {jax.devices()[0].device_kind}, jax {jax.__version__}")
    scenes = random_scenes(args.seed, args.scenes)
    start = time.perf_counter()
    verdicts, distances = kernel_results(*scenes, max_distance=args.max_distance)
    result = {"scenes": args.scenes, "seed": args.seed, "max_distance": args.max_distance, "arms": int(scenes[3].sum()),
              "collided_arms": int(verdicts.sum()), "kernel_seconds": time.perf_counter() - start}
    if args.record:
        atomic_write(args.record, lambda f: np.savez_compressed(f, seed=args.seed, verdicts=np.packbits(verdicts, axis=-1)))
        print(f"recorded {args.scenes} scenes' verdicts to {args.record}")
    if args.reference:
        stored = np.load(args.reference)
        if int(stored["seed"]) != args.seed:
            raise SystemExit(f"error: {args.reference} was recorded with --seed {int(stored['seed'])}, not {args.seed}")
        reference = np.unpackbits(stored["verdicts"], axis=-1, count=SLOTS).astype(bool)
        if len(reference) < args.scenes:
            raise SystemExit(f"error: {args.reference} holds {len(reference)} scenes, fewer than --scenes {args.scenes}")
        result["differ_from_reference"] = int((reference[: args.scenes] != verdicts).sum())
    if not args.no_checker:
        start = time.perf_counter()
        theirs = checker_verdicts(*scenes)
        clear = np.abs(np.where(scenes[3], distances, np.inf)).min(axis=-1) > ROUNDING
        result.update(differ_from_checker=int((theirs != verdicts.any(axis=-1))[clear].sum()),
                      near_contact_scenes=int((~clear).sum()), checker_seconds=time.perf_counter() - start)
    for key, value in result.items():
        print(f"{key:>22}: {value:,.1f}" if isinstance(value, float) else f"{key:>22}: {value:,}")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
