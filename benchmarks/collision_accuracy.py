"""The collision model against exact mesh distances: missed contacts and false flags.

Random scenes (one arm: random yaw; two arms: bases 0.3-1.3 m apart, random yaws; joints
home + N(0, 1 rad) within the limits) are checked by the project's collision model and by
the exact triangle-mesh reference (:mod:`mjx_multiarm.reference.mesh_reference`, meshes of
``../shared/reference``). Per kind (between arms, within an arm, ground), a scene is

- a **miss** when the meshes touch (distance 0, or a link below the ground) and the model
  reports no contact;
- a **false flag** when the model reports a contact and the meshes are apart, binned by
  the mesh distance (0-5, 5-20, 20-50, > 50 mm).

Self pairs are the non-adjacent link pairs the model checks; mesh contacts in the pairs it
excludes (``excluded``) are reported with how many of those scenes the model flags anyway
(by another kind). Also reported: the mesh-minus-model distance at near contact (meshes apart
by less than 50 mm; positive = the model is larger than the meshes), and the mesh link pairs
nearest in false-flagged scenes.

The original's collision model, the convex hull of each link mesh (PyBullet), is measured
the same way on the same scenes (``original_hulls``), and the project's model against it
(``against_hulls``): per kind, the scenes the project's model flags where the hulls are
apart (it rejects what the original accepts), also where they are >= 5 mm apart, and the
scenes the hulls flag where the project's model is free (``--no-hulls`` skips all this).

    python benchmarks/collision_accuracy.py --two-arm 20000 --one-arm 5000 --json
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib
import time

import jax
import numpy as np
from common import cpu_name

from mjx_multiarm.geometry.collision import scene_contacts
from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.geometry.transforms import yaw_quat
from mjx_multiarm.reference.mesh_reference import KINDS, LINKS, MeshReference

MESHES = pathlib.Path(__file__).resolve().parents[2] / "shared" / "reference" / "ur5" / "collision"
BINS_MM = (0.0, 5.0, 20.0, 50.0, np.inf)
NEAR = 0.05  # near contact: meshes apart by less than this (m)


def random_scenes(rng: np.random.Generator, count: int, num_arms: int):
    """Base positions [count, n, 3], quaternions [count, n, 4] (wxyz), joints [count, n, 6]."""
    arm = load_arm()
    pos = np.zeros((count, num_arms, 3))
    if num_arms == 2:
        angle = rng.uniform(-np.pi, np.pi, count)
        pos[:, 1, :2] = rng.uniform(0.3, 1.3, count)[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
    elif num_arms != 1:
        raise ValueError(f"num_arms must be 1 or 2, got {num_arms}")
    quat = np.asarray(yaw_quat(rng.uniform(-np.pi, np.pi, (count, num_arms))), np.float64)
    joints = np.clip(arm.home + rng.normal(0.0, 1.0, (count, num_arms, 6)), *arm.joint_range.T)
    return pos, quat, joints


def checked_self_links(scene) -> list[tuple[int, int]]:
    """The link (body) pairs of the model's self pairs, as indices into ``LINKS``."""
    arm = scene.arm
    if arm.body_names != LINKS:
        raise ValueError(f"arm bodies {arm.body_names} are not the reference links {LINKS}")
    body = np.concatenate([arm.capsule_body, arm.box_body])
    return sorted({tuple(sorted((int(body[a]), int(body[b])))) for a, b in scene.pairs.self_pairs})


def model_distances(pos, quat, joints, batch: int = 1024) -> dict:
    """The collision model's per-scene smallest signed distance per kind [count]."""
    scene = build_scene(pos.shape[1])
    active = np.ones(pos.shape[:2], bool)
    evaluate = jax.jit(lambda *a: scene_contacts(scene, *a))
    out = collections.defaultdict(list)
    for s in range(0, len(pos), batch):
        part = slice(s, s + batch)
        contacts = evaluate(pos[part].astype(np.float32), quat[part].astype(np.float32),
                            joints[part].astype(np.float32), active[part])
        for kind, value in zip(KINDS[:3], (contacts.between_arms, contacts.within_arm, contacts.ground)):
            out[kind].append(np.asarray(value).min(axis=-1))
    return {kind: np.concatenate(v) for kind, v in out.items()}


def mesh_distances(reference: MeshReference, pos, quat, joints):
    """The reference's per-scene smallest distance per kind [count] and the nearest link pairs."""
    out = {kind: np.empty(len(pos)) for kind in KINDS}
    nearest = {kind: [] for kind in KINDS}
    for k in range(len(pos)):
        d = reference.scene(pos[k], quat[k], joints[k])
        for kind in KINDS:
            out[kind][k] = d.scene_min(kind)
            nearest[kind].append(d.nearest[kind])
    return out, nearest


def summarize(model: dict, mesh: dict, nearest: dict) -> dict:
    """Per kind: misses, false flags by mesh-distance bin, near-contact gap, worst link pairs."""
    summary = {}
    flagged_any = np.min([model[kind] for kind in KINDS if kind in model], axis=0) < 0.0
    for kind in KINDS:
        r = mesh[kind]
        checked = np.isfinite(r)
        if not checked.any():
            continue
        if kind not in model:  # pairs the model does not check
            touching = checked & (r <= 0.0)
            summary[kind] = {"scenes": int(checked.sum()), "mesh_contacts": int(touching.sum()),
                             "flagged_by_other_kinds": int((touching & flagged_any).sum())}
            continue
        m = model[kind]
        touching = checked & (r <= 0.0)
        flagged = checked & (m < 0.0)
        false = flagged & ~touching
        counts = np.histogram(r[false] * 1e3, bins=BINS_MM)[0]
        near = checked & (r > 0.0) & (r < NEAR)
        gap = (r - m)[near] * 1e3  # how much larger the model is than the meshes
        pairs = collections.Counter(
            f"{a}-{b}" for a, b in ((nearest[kind][k][1], nearest[kind][k][3]) for k in np.flatnonzero(false & (r >= 5e-3)))
        )
        n = int(checked.sum())
        summary[kind] = {
            "scenes": n,
            "mesh_contacts": int(touching.sum()),
            "model_flags": int(flagged.sum()),
            "missed": int((touching & (m >= 0.0)).sum()),
            "false_flags_by_mesh_mm": dict(zip(("0-5", "5-20", "20-50", ">50"), counts.tolist())),
            "false_flag_rate_5mm": float(counts[1:].sum() / n),
            "near_excess_mm_median": float(np.median(gap)) if gap.size else None,
            "near_excess_mm_p90": float(np.percentile(gap, 90)) if gap.size else None,
            "worst_link_pairs_5mm": dict(pairs.most_common(5)),
        }
    return summary


def against_hulls(model: dict, hulls: dict) -> dict:
    """Per kind: scenes the model flags where the convex hulls are apart (also >= 5 mm apart),
    and scenes the hulls flag where the model is free."""
    out = {}
    for kind in model:
        m, h = model[kind], hulls[kind]
        checked = np.isfinite(h)
        out[kind] = {"scenes": int(checked.sum()),
                     "model_flags_hulls_apart": int((checked & (m < 0) & (h > 0)).sum()),
                     "model_flags_hulls_apart_5mm": int((checked & (m < 0) & (h >= 5e-3)).sum()),
                     "hull_flags_model_free": int((checked & (h <= 0) & (m >= 0)).sum())}
    return out


def _print_summary(summary: dict) -> None:
    for kind, s in summary.items():
        if "model_flags" not in s:
            print(f"  {kind:12s} mesh contacts {s['mesh_contacts']:6d}, flagged by other kinds "
                  f"{s['flagged_by_other_kinds']}")
            continue
        print(f"  {kind:12s} mesh contacts {s['mesh_contacts']:6d}  model flags {s['model_flags']:6d}  "
              f"missed {s['missed']}  false flags by mesh mm {s['false_flags_by_mesh_mm']}  "
              f">=5 mm: {s['false_flag_rate_5mm']:.2%}  near contact, mesh minus model: median "
              f"{s['near_excess_mm_median']:.1f} mm, p90 {s['near_excess_mm_p90']:.1f} mm  "
              f"worst pairs {s['worst_link_pairs_5mm']}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--two-arm", type=int, default=20_000, help="random 2-arm scenes")
    parser.add_argument("--one-arm", type=int, default=5_000, help="random 1-arm scenes")
    parser.add_argument("--meshes", type=pathlib.Path, default=MESHES, help="directory of the UR5 collision STLs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-hulls", action="store_true", help="skip the original's model (convex hulls)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON line")
    args = parser.parse_args(argv)
    if not args.meshes.is_dir():
        parser.error(f"--meshes: no directory {args.meshes}")
    self_pairs = checked_self_links(build_scene(1))
    reference = MeshReference(args.meshes, self_pairs=self_pairs)
    hulls = None if args.no_hulls else MeshReference(args.meshes, self_pairs=self_pairs, hulls=True)
    rng = np.random.default_rng(args.seed)
    result = {"cpu": cpu_name(), "seed": args.seed}
    for label, arms, count in (("one_arm", 1, args.one_arm), ("two_arm", 2, args.two_arm)):
        if count <= 0:
            continue
        start = time.perf_counter()
        pos, quat, joints = random_scenes(rng, count, arms)
        model = model_distances(pos, quat, joints)
        mesh, nearest = mesh_distances(reference, pos, quat, joints)
        result[label] = summarize(model, mesh, nearest)
        print(f"{label}: {count} scenes in {time.perf_counter() - start:.0f} s")
        _print_summary(result[label])
        if hulls is not None:
            hull, hull_nearest = mesh_distances(hulls, pos, quat, joints)
            hull_model = {kind: hull[kind] for kind in model}
            result[label + "_original_hulls"] = summarize(hull_model, mesh, hull_nearest)
            result[label + "_against_hulls"] = against_hulls(model, hull)
            print(f"{label}, the original's model (per-link convex hulls) on the same scenes:")
            _print_summary(result[label + "_original_hulls"])
            print(f"{label}, this model against the convex hulls: {result[label + '_against_hulls']}")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
