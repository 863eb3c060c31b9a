"""Tight enclosing capsules for the UR5 collision meshes.

Each link's collision mesh is replaced by a small union of capsules that
encloses the whole mesh surface while keeping the union volume low.  Vertices
alone are not enough: the UR5 tubes have vertices only at their ends, so the
surface is sampled densely (``sample_surface``).

For a fixed axis line the minimum-volume enclosing capsule is almost closed
form: with axial coordinates t_i and perpendicular distances d_i of the points
and a radius r >= max d_i, the shortest enclosing segment is
``[min(t_i + h_i), max(t_i - h_i)]`` with ``h_i = sqrt(r^2 - d_i^2)``.  The
radius is found by a 1-D search and the axis line (4 dof) by Nelder-Mead.

Several capsules are fitted by clustering the points (slabs along the
principal axes, k-means restarts), fitting one capsule per cluster, and then
shrinking: each capsule in turn is refitted to only the points that no other
capsule encloses, until the summed volume stops improving.  The candidate
with the smallest union volume wins.

Run ``python -m mjx_multiarm.reference.capsule_fit --meshes DIR`` to fit all links
(``--sweep`` first compares 1, 2 and 3 capsules per link). The gripper stand-in box of
``ee_link`` is not fitted: the collision model keeps it as the exact box.
"""

import argparse
import math
import os
import time

import numpy as np

LINK_MESHES = {
    "base_link": "base.stl",
    "shoulder_link": "shoulder.stl",
    "upper_arm_link": "upperarm.stl",
    "forearm_link": "forearm.stl",
    "wrist_1_link": "wrist1.stl",
    "wrist_2_link": "wrist2.stl",
    "wrist_3_link": "wrist3.stl",
}
# Gripper stand-in of ee_link: (centre, size) of the URDF collision box.
GRIPPER_BOX = (np.array([0.02, 0.0, 0.0]), np.array([0.14, 0.12, 0.08]))
DEFAULT_COUNTS = {
    "base_link": 1,
    "shoulder_link": 1,
    "upper_arm_link": 3,
    "forearm_link": 4,
    "wrist_1_link": 1,
    "wrist_2_link": 1,
    "wrist_3_link": 1,
}
MIN_LENGTH = 1.2e-3  # shortest fitted segment [m]; stays >= 1 mm after rounding
FIT_SPACING = 5e-3  # surface sample spacing used for fitting [m]
CHECK_SPACING = 1e-3  # surface sample spacing used for verification [m]
DECIMALS = 4  # precision of reported endpoints and radii (0.1 mm)

_STL_RECORD = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attr", "<u2")])


def read_stl(path):
    """Read a binary STL file into a float64 array of shape [n_triangles, 3, 3]."""
    with open(path, "rb") as f:
        data = f.read()
    name = os.path.basename(path)
    if len(data) < 84:
        raise ValueError(f"{name}: too short for a binary STL header ({len(data)} bytes)")
    n = int(np.frombuffer(data, "<u4", 1, 80)[0])
    if n == 0 or len(data) != 84 + 50 * n:
        raise ValueError(f"{name}: malformed binary STL ({n} triangles declared, {len(data)} bytes)")
    triangles = np.frombuffer(data, _STL_RECORD, n, 84)["vertices"].astype(np.float64)
    if not np.isfinite(triangles).all():
        raise ValueError(f"{name}: non-finite vertex coordinates")
    return triangles


def mesh_volume(triangles):
    """Enclosed volume of a closed triangle mesh (sum of signed tetrahedra, absolute)."""
    return abs(np.linalg.det(triangles).sum()) / 6.0


def box_triangles(center, size):
    """Closed, outward-oriented triangle mesh [12, 3, 3] of an axis-aligned box."""
    corners = np.asarray(center) + (np.array(np.unravel_index(np.arange(8), (2, 2, 2))).T - 0.5) * size
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    quads = corners[np.array(faces)]
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def sample_surface(triangles, spacing):
    """Vertices plus points on every triangle, so that the whole surface lies near a sample.

    Each triangle is covered by rows parallel to its longest edge, at most
    spacing apart and sampled at most spacing apart; the two other edges are
    sampled explicitly.  Returns unique points [n, 3].
    """
    out = []
    for tri in triangles:
        k = np.argmax(np.linalg.norm(tri - np.roll(tri, -1, axis=0), axis=1))
        a, b, c = np.roll(tri, -k, axis=0)
        ab, ac = b - a, c - a
        length = np.linalg.norm(ab)
        height = np.linalg.norm(np.cross(ab, ac)) / length
        s, t = np.meshgrid(np.linspace(0, 1, math.ceil(length / spacing) + 1),
                           np.linspace(0, 1, math.ceil(height / spacing) + 1))
        keep = s + t <= 1 + 1e-9
        out.append(a + s[keep, None] * ab + t[keep, None] * ac)
        for p, q in ((a, c), (b, c)):
            n = math.ceil(np.linalg.norm(q - p) / spacing)
            out.append(p + np.linspace(0, 1, n + 1)[:, None] * (q - p))
    return np.unique(np.concatenate(out).round(12), axis=0)


def point_capsule_distance(points, p0, p1, radius):
    """Signed distance [n] from points [n, 3] to a capsule surface (negative inside)."""
    points, p0, p1 = np.asarray(points, float), np.asarray(p0, float), np.asarray(p1, float)
    seg = p1 - p0
    length2 = seg @ seg
    t = np.zeros(len(points)) if length2 == 0 else np.clip((points - p0) @ seg / length2, 0.0, 1.0)
    return np.linalg.norm(points - p0 - t[:, None] * seg, axis=1) - radius


def outside_distance(points, capsules):
    """Per point, the smallest signed distance to any capsule (<= 0 means enclosed)."""
    return np.min([point_capsule_distance(points, *c) for c in capsules], axis=0)


def union_volume(capsules, n_samples=400_000, seed=0):
    """Monte Carlo volume of a union of capsules, sampled in its bounding box."""
    lo = np.min([np.minimum(p0, p1) - r for p0, p1, r in capsules], axis=0)
    hi = np.max([np.maximum(p0, p1) + r for p0, p1, r in capsules], axis=0)
    samples = np.random.default_rng(seed).uniform(lo, hi, (n_samples, 3))
    inside = np.count_nonzero(outside_distance(samples, capsules) <= 0.0)
    return float(np.prod(hi - lo) * inside / n_samples)


def _capsule_volume(p0, p1, radius):
    return math.pi * radius**2 * np.linalg.norm(np.subtract(p1, p0)) + 4.0 / 3.0 * math.pi * radius**3


def _best_capsule_on_line(points, origin, direction, n_radii=48):
    """Minimum-volume enclosing capsule whose axis is the given line.

    Returns (volume, p0, p1, radius); the radius is the best of a grid between
    the largest perpendicular distance and the all-enclosing sphere radius.
    """
    direction = direction / np.linalg.norm(direction)
    rel = points - origin
    t = rel @ direction
    d2 = np.maximum(np.einsum("ij,ij->i", rel, rel) - t**2, 0.0)
    radii = math.sqrt(d2.max()) + 0.5 * (t.max() - t.min()) * np.linspace(0.0, 1.0, n_radii) ** 2
    h = np.sqrt(np.maximum(radii[:, None] ** 2 - d2, 0.0))
    t0, t1 = (t + h).min(axis=1), (t - h).max(axis=1)
    length = np.maximum(t1 - t0, MIN_LENGTH)
    volume = np.pi * radii**2 * length + 4.0 / 3.0 * np.pi * radii**3
    k = int(np.argmin(volume))
    ends = 0.5 * (t0[k] + t1[k]) + np.array([-0.5, 0.5]) * length[k]
    return volume[k], origin + ends[0] * direction, origin + ends[1] * direction, radii[k]


def _fit_capsule(points, hint=None, n_starts=2):
    """Minimum-volume capsule enclosing points: returns (volume, p0, p1, radius).

    Candidate axis lines (principal and coordinate axes through the centroid,
    plus the axis of an optional hint capsule) are screened, and Nelder-Mead
    refines the tilt and offset of the best n_starts of them.
    """
    from scipy.optimize import minimize
    from scipy.spatial import ConvexHull, QhullError

    try:
        points = points[ConvexHull(points).vertices]
    except QhullError:  # flat or tiny point sets: keep every point
        pass
    center = points.mean(axis=0)
    _, _, pca = np.linalg.svd(points - center, full_matrices=False)
    lines = [(center, axis) for axis in np.vstack([pca, np.eye(3)])]
    if hint is not None:
        lines.append((0.5 * (hint[0] + hint[1]), hint[1] - hint[0]))
    screen = [_best_capsule_on_line(points, *line)[0] for line in lines]
    best = None
    for k in np.argsort(screen)[:n_starts]:
        origin, axis = lines[k][0], lines[k][1] / np.linalg.norm(lines[k][1])
        e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)

        def line(x):
            return origin + x[2] * e1 + x[3] * e2, axis + x[0] * e1 + x[1] * e2

        res = minimize(
            lambda x: _best_capsule_on_line(points, *line(x))[0],
            np.zeros(4),
            method="Nelder-Mead",
            options={
                "initial_simplex": np.vstack([np.zeros(4), np.diag([0.2, 0.2, 0.01, 0.01])]),
                "xatol": 1e-5,
                "fatol": 1e-10,
                "maxiter": 1000,
            },
        )
        fit = _best_capsule_on_line(points, *line(res.x), n_radii=400)
        if best is None or fit[0] < best[0]:
            best = fit
    return best


def _shrink(points, capsules, max_rounds=20, rtol=1e-4):
    """Refit each capsule to the points no other capsule encloses, until no capsule shrinks.

    The union keeps enclosing every point; capsules left with nothing to
    enclose are dropped.
    """
    capsules = list(capsules)
    for _ in range(max_rounds):
        improved = False
        for j in reversed(range(len(capsules))):
            others = capsules[:j] + capsules[j + 1:]
            needed = points[outside_distance(points, others) > 0.0] if others else points
            if len(needed) == 0:
                del capsules[j]
                improved = True
                continue
            fit = _fit_capsule(needed, hint=capsules[j])
            if fit[0] < _capsule_volume(*capsules[j]) * (1.0 - rtol):
                capsules[j] = fit[1:]
                improved = True
        if not improved:
            break
    return capsules


def fit_link(points, n_capsules, n_kmeans=4, seed=0):
    """Fit up to n_capsules capsules whose union encloses all points with small volume.

    Fewer capsules are returned when that gives a smaller union (the single
    capsule fit is always a candidate).  Deterministic for a given seed.
    Returns a list of (p0, p1, radius).
    """
    from scipy.cluster.vq import kmeans2

    points = np.asarray(points, float)
    candidates = [[_fit_capsule(points)[1:]]]
    if n_capsules == 1:
        return candidates[0]
    center = points.mean(axis=0)
    _, _, pca = np.linalg.svd(points - center, full_matrices=False)
    inits = []
    for axis in pca:
        s = (points - center) @ axis
        inits.append(np.searchsorted(np.quantile(s, np.linspace(0, 1, n_capsules + 1)[1:-1]), s))
    inits += [kmeans2(points, n_capsules, minit="++", seed=seed + i)[1] for i in range(n_kmeans)]
    candidates += [
        _shrink(points, [_fit_capsule(points[labels == j])[1:] for j in np.unique(labels)])
        for labels in inits
    ]
    volumes = [union_volume(c, 100_000, seed) for c in candidates]
    return candidates[int(np.argmin(volumes))]


def round_outward(capsules, points, decimals=DECIMALS):
    """Round endpoints to the given decimals and grow radii (rounded up) until all points are enclosed."""
    step = 10.0**-decimals
    rounded = [[np.round(p0, decimals) + 0.0, np.round(p1, decimals) + 0.0, math.ceil(r / step - 1e-6) * step]
               for p0, p1, r in capsules]
    while (gap := outside_distance(points, rounded)).max() > 1e-9:
        worst = int(np.argmax(gap))
        owner = np.argmin([point_capsule_distance(points[worst:worst + 1], *c)[0] for c in rounded])
        rounded[owner][2] += math.ceil(gap[worst] / step - 1e-6) * step
    return [(p0, p1, round(r, decimals)) for p0, p1, r in rounded]


def fit_mesh(triangles, n_capsules):
    """Fit and outward-round capsules for a triangle mesh; return (capsules, statistics).

    The fit uses surface samples FIT_SPACING apart; rounding then enforces
    enclosure of samples CHECK_SPACING apart, so no surface point lies more
    than CHECK_SPACING outside the union.
    """
    capsules = fit_link(sample_surface(triangles, FIT_SPACING), n_capsules)
    dense = sample_surface(triangles, CHECK_SPACING)
    capsules = round_outward(capsules, dense)
    stats = {
        "vertex_outside": outside_distance(triangles.reshape(-1, 3), capsules).max(),
        "surface_outside": outside_distance(dense, capsules).max(),
        "mesh_volume": mesh_volume(triangles),
        "union_volume": union_volume(capsules),
    }
    return capsules, stats


def _fmt(p):
    return " ".join(f"{x:.{DECIMALS}f}" for x in p)


def _load(meshes):
    """Triangle meshes of every link, keyed by link name."""
    return {name: read_stl(os.path.join(meshes, file)) for name, file in LINK_MESHES.items()}


def main(argv=None):
    """Command line entry point: fit, verify and print capsules for every link."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", required=True, help="directory of the UR5 collision STLs")
    parser.add_argument("--counts", default="", help="per-link capsule counts, e.g. base_link=2,wrist_1_link=2")
    parser.add_argument("--sweep", action="store_true", help="first compare 1, 2 and 3 capsules per link")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    counts = dict(DEFAULT_COUNTS)
    for item in filter(None, args.counts.split(",")):
        name, n = item.split("=")
        if name not in counts:
            parser.error(f"unknown link {name!r}; choose from {', '.join(counts)}")
        counts[name] = int(n)
    links = _load(args.meshes)
    fits = {}
    if args.sweep:
        print("sweep: union volume cm^3 (overhead = union / mesh volume) by capsule count")
        for name, triangles in links.items():
            cells = []
            for n in (1, 2, 3):
                fits[name, n] = fit_mesh(triangles, n)
                capsules, stats = fits[name, n]
                used = "" if len(capsules) == n else f" [{len(capsules)} used]"
                union = stats["union_volume"]
                cells.append(f"{n}: {union * 1e6:7.1f} ({union / stats['mesh_volume']:.2f}){used}")
            print(f"  {name:15s} mesh {fits[name, 1][1]['mesh_volume'] * 1e6:6.1f}  " + "  ".join(cells))
        print()
    total = {"count": 0, "mesh_volume": 0.0, "union_volume": 0.0}
    mjcf = []
    for name, triangles in links.items():
        capsules, stats = fits.get((name, counts[name])) or fit_mesh(triangles, counts[name])
        print(f"{name}: {len(capsules)} capsule(s)")
        for p0, p1, r in capsules:
            print(f"  p0=({_fmt(p0)})  p1=({_fmt(p1)})  r={r:.{DECIMALS}f}")
        print(f"  max outside: vertices {stats['vertex_outside'] * 1e3:+.3f} mm, "
              f"surface ({CHECK_SPACING * 1e3:g} mm grid) {stats['surface_outside'] * 1e3:+.3f} mm")
        print(f"  mesh volume {stats['mesh_volume'] * 1e6:.1f} cm^3  "
              f"union volume {stats['union_volume'] * 1e6:.1f} cm^3  "
              f"overhead {stats['union_volume'] / stats['mesh_volume']:.2f}")
        total["count"] += len(capsules)
        total["mesh_volume"] += stats["mesh_volume"]
        total["union_volume"] += stats["union_volume"]
        mjcf.append(f"<!-- {name} -->")
        mjcf += [f'<geom type="capsule" fromto="{_fmt(p0)} {_fmt(p1)}" size="{r:.{DECIMALS}f}"/>'
                 for p0, p1, r in capsules]
    print(f"total: {total['count']} capsules  mesh volume {total['mesh_volume'] * 1e6:.1f} cm^3  "
          f"union volume {total['union_volume'] * 1e6:.1f} cm^3  "
          f"overhead {total['union_volume'] / total['mesh_volume']:.2f}")
    centre, size = GRIPPER_BOX  # the original's gripper stand-in: a box, kept exact
    mjcf += ["<!-- ee_link -->", f'<geom type="box" pos="{_fmt(centre)}" size="{_fmt(size / 2)}"/>']
    print("\n".join(mjcf))
    print(f"runtime {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
