"""Derive the pick-and-place assets from the original demo's reference data.

``python -m mjx_multiarm.pickplace.derive --reference ../shared/reference/pickplace`` reads
the object meshes, the bin's collision proxy and the GraspIt grasps of the original demo and
writes ``mjx_multiarm/assets/pickplace.json``: small numbers the scene is built from, so
that the feature runs on a fresh clone without the reference folder.

- Objects: the convex hull of each mesh, reduced to at most ``--hull-vertices`` vertices
  (greedy: the hull vertex farthest outside the reduced hull is added until none is more than
  ``--hull-tolerance`` outside or the budget is spent). Where one hull is far from the mesh
  (hull volume > ``--decompose-above`` x mesh volume: the drill), the mesh's surface samples
  are clustered (k-means, k = 2..4) and each cluster gets its own reduced hull; the smallest
  k whose union is within the bound wins, else the tightest.
- The bin: the proxy's tapered floor and four walls as boxes (its URDF scale applied).
- Grasps: the ``ee_link`` pose in the object frame per GraspIt grasp (palm pose times the
  90-degree rotation about x that maps the palm frame to ``ee_link``), position + wxyz.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

from mjx_multiarm.files import atomic_write

#: The objects the original demo draws from (potted_meat_can has grasps but was not used).
OBJECTS = ("bleach_cleanser", "cube", "mustard_bottle", "power_drill", "sugar_box", "tomato_soup_can")
#: ``tote.urdf``'s mesh scale.
BIN_SCALE = np.array([1.7, 1.4, 0.6])
#: Palm frame -> ee_link frame: 90 degrees about x (wxyz).
PALM_TO_EE = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0])
OUTPUT = pathlib.Path(__file__).resolve().parents[1] / "assets" / "pickplace.json"


def _hull(points: np.ndarray):
    from scipy.spatial import ConvexHull

    return ConvexHull(points)


def outside_distance(points: np.ndarray, hull_vertices: np.ndarray) -> np.ndarray:
    """How far each point lies outside the convex hull of ``hull_vertices`` (a lower bound
    of the Euclidean distance: the largest face-plane excess; <= 0 inside)."""
    eq = _hull(hull_vertices).equations  # [f, 4]: n . x + d <= 0 inside
    return (points @ eq[:, :3].T + eq[:, 3]).max(axis=1)


def reduced_hull(points: np.ndarray, max_vertices: int, tolerance: float) -> np.ndarray:
    """At most ``max_vertices`` of the hull's vertices whose hull leaves no vertex more than
    ``tolerance`` outside (or the best the budget allows); [k, 3]."""
    vertices = points[_hull(points).vertices]
    centre = vertices.mean(axis=0)
    chosen = list({int(np.argmax(vertices[:, a] * s)) for a in range(3) for s in (-1, 1)})
    while True:
        if len(chosen) >= 4:
            outside = outside_distance(vertices, vertices[chosen])
        else:
            outside = np.linalg.norm(vertices - centre, axis=1)
        worst = int(np.argmax(outside))
        if len(chosen) >= max_vertices or (len(chosen) >= 4 and outside[worst] <= tolerance):
            return vertices[sorted(chosen)]
        chosen.append(worst)


def _inside_union(samples: np.ndarray, hulls: list[np.ndarray]) -> np.ndarray:
    inside = np.zeros(len(samples), bool)
    for vertices in hulls:
        inside |= outside_distance(samples, vertices) <= 0
    return inside


def union_volume(hulls: list[np.ndarray], samples: int = 200_000, seed: int = 0) -> float:
    """Monte Carlo volume of a union of convex hulls (m^3)."""
    allv = np.concatenate(hulls)
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    points = np.random.default_rng(seed).uniform(lo, hi, size=(samples, 3))
    return float(np.prod(hi - lo) * _inside_union(points, hulls).mean())


def _kmeans(points: np.ndarray, k: int, seed: int = 0, rounds: int = 50) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = points[rng.choice(len(points), k, replace=False)]
    for _ in range(rounds):
        labels = np.argmin(((points[:, None] - centres[None]) ** 2).sum(-1), axis=1)
        centres = np.stack([points[labels == j].mean(axis=0) if np.any(labels == j) else centres[j] for j in range(k)])
    return labels


def object_hulls(mesh, max_vertices: int, tolerance: float, decompose_above: float) -> tuple[list[np.ndarray], dict]:
    """The reduced convex piece(s) of one object mesh, and their statistics."""
    mesh_volume = abs(float(mesh.volume))
    vertices = np.asarray(mesh.vertices)
    single = [reduced_hull(vertices, max_vertices, tolerance)]
    best = (union_volume(single), single, [vertices])
    stats = {"mesh_volume_cm3": mesh_volume * 1e6, "full_hull_volume_cm3": float(mesh.convex_hull.volume) * 1e6}
    if best[0] > decompose_above * mesh_volume:
        samples = np.concatenate([vertices, np.asarray(mesh.sample(20_000, seed=0))])
        for k in (2, 3, 4):
            labels = _kmeans(samples, k)
            clusters = [samples[labels == j] for j in range(k)]
            pieces = [reduced_hull(c, max_vertices, tolerance) for c in clusters]
            volume = union_volume(pieces)
            if volume < best[0]:
                best = (volume, pieces, clusters)
            if volume <= decompose_above * mesh_volume:
                break
    volume, hulls, covered = best
    outside = max(float(outside_distance(c, h).max()) for c, h in zip(covered, hulls))
    stats.update(pieces=len(hulls), vertices=[len(h) for h in hulls], union_volume_cm3=volume * 1e6,
                 union_over_mesh=volume / mesh_volume, max_outside_mm=outside * 1e3)
    return hulls, stats


def bin_boxes(proxy_vertices: np.ndarray, wall: float = 0.01) -> tuple[list[dict], dict]:
    """The bin as five boxes (floor + four tapered walls), from its scaled proxy's vertices."""
    v = proxy_vertices * BIN_SCALE
    z_floor, z_rim = float(v[:, 2].min()), float(v[:, 2].max())
    low = v[v[:, 2] < z_floor + 0.2 * (z_rim - z_floor)]
    high = v[v[:, 2] > z_rim - 0.2 * (z_rim - z_floor)]
    floor_half = np.abs(low[:, :2]).max(axis=0)  # outer half-extents at the bottom and the rim
    rim_half = np.abs(high[:, :2]).max(axis=0)
    height = z_rim - z_floor
    boxes = [{"name": "floor", "pos": [0.0, 0.0, z_floor + wall / 2], "euler": [0.0, 0.0, 0.0],
              "size": [float(floor_half[0]), float(floor_half[1]), wall / 2]}]
    for axis, name in ((0, "x"), (1, "y")):
        lean = float(rim_half[axis] - floor_half[axis])  # outward lean over the height
        tilt = float(np.arctan2(lean, height))
        slant = float(np.hypot(lean, height))
        other = 1 - axis
        for sign in (1.0, -1.0):
            centre = np.zeros(3)
            centre[axis] = sign * ((floor_half[axis] + rim_half[axis]) / 2 - wall / 2 * np.cos(tilt))
            centre[2] = z_floor + height / 2
            half = [0.0, 0.0, slant / 2]
            half[axis] = wall / 2
            half[other] = float(max(floor_half[other], rim_half[other]))
            euler = [0.0, 0.0, 0.0]
            euler[other] = float(sign * tilt if axis == 0 else -sign * tilt)  # tops lean outward
            boxes.append({"name": f"wall_{'+' if sign > 0 else '-'}{name}", "pos": centre.tolist(), "euler": euler,
                          "size": half})
    stats = {"floor_cm": (2 * floor_half * 100).round(1).tolist(), "rim_cm": (2 * rim_half * 100).round(1).tolist(),
             "z_floor": z_floor, "z_rim": z_rim}
    return boxes, stats


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def ee_grasps(graspit: np.ndarray) -> np.ndarray:
    """GraspIt palm poses [N, 7] (position, xyzw) -> ee_link poses in the object frame
    [N, 7] (position, wxyz)."""
    palm = np.concatenate([graspit[:, 6:7], graspit[:, 3:6]], axis=1)
    ee = _quat_mul(palm, np.broadcast_to(PALM_TO_EE, palm.shape))
    ee *= np.where(ee[:, :1] < 0, -1.0, 1.0)
    return np.concatenate([graspit[:, :3], ee / np.linalg.norm(ee, axis=1, keepdims=True)], axis=1)


def derive(reference: pathlib.Path, max_vertices: int = 24, tolerance: float = 0.002,
           decompose_above: float = 1.5) -> dict:
    """Every asset number of the pick-and-place scene, with the statistics of the fit."""
    import trimesh

    missing = [p for p in (reference / "objects", reference / "tote", reference / "grasps") if not p.is_dir()]
    if missing:
        raise FileNotFoundError(f"not a pick-and-place reference folder: missing {', '.join(map(str, missing))}")
    objects = {}
    for name in OBJECTS:
        mesh = trimesh.load(reference / "objects" / name / f"{name}.ply", force="mesh", process=True)
        hulls, stats = object_hulls(mesh, max_vertices, tolerance, decompose_above)
        grasps = ee_grasps(np.load(reference / "grasps" / name / "graspit_grasps.npy"))
        objects[name] = {
            "hulls": [np.round(h, 5).tolist() for h in hulls],
            "bottom": float(np.asarray(mesh.vertices)[:, 2].min()),
            "grasps": np.round(grasps, 6).tolist(),
            "stats": stats,
        }
    proxy = trimesh.load(reference / "tote" / "ToteA.L.Proxy.obj", force="mesh", process=False)
    boxes, bin_stats = bin_boxes(np.asarray(proxy.vertices))
    return {
        "source": "derived by mjx_multiarm.pickplace.derive from the original demo's meshes, bin proxy and GraspIt grasps",
        "settings": {"hull_vertices": max_vertices, "hull_tolerance_m": tolerance, "decompose_above": decompose_above},
        "objects": objects,
        "bin": {"boxes": boxes, "stats": bin_stats},
    }


def main(argv=None) -> None:
    """Command line: derive the assets and write them (atomically) with a summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", required=True, help="the reference folder (../shared/reference/pickplace)")
    parser.add_argument("--out", default=str(OUTPUT), help="output JSON (default: the packaged asset)")
    parser.add_argument("--hull-vertices", type=int, default=24, help="most vertices per convex piece")
    parser.add_argument("--hull-tolerance", type=float, default=0.002, help="metres a hull vertex may lie outside")
    parser.add_argument("--decompose-above", type=float, default=1.5, help="hull/mesh volume that triggers decomposition")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    assets = derive(pathlib.Path(args.reference), args.hull_vertices, args.hull_tolerance, args.decompose_above)
    text = json.dumps(assets, indent=1)
    atomic_write(args.out, lambda f: f.write(text.encode()))
    for name, obj in assets["objects"].items():
        s = obj["stats"]
        print(f"{name:16s} mesh {s['mesh_volume_cm3']:6.0f} cm^3  full hull {s['full_hull_volume_cm3']:6.0f}  "
              f"reduced: {s['pieces']} piece(s), {s['vertices']} vertices, union {s['union_volume_cm3']:6.0f} "
              f"({s['union_over_mesh']:.2f} x mesh), mesh up to {s['max_outside_mm']:.1f} mm outside  grasps {len(obj['grasps'])}")
    b = assets["bin"]["stats"]
    print(f"bin: floor {b['floor_cm']} cm at z {b['z_floor']:.3f}, rim {b['rim_cm']} cm at z {b['z_rim']:.3f}")
    print(f"wrote {args.out} ({len(text) / 1e3:.0f} kB) in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
