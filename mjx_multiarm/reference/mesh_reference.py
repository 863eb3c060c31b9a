"""Exact distances between the UR5 collision meshes: the reference for the collision model.

The project's collision model (primitives in ``assets/ur5.xml``) must enclose the triangle
meshes of the UR5 description the original trained with, and should not be much larger.
This module measures both: it poses the meshes (the 7 link STLs and the gripper stand-in
box of ``ee_link``) with MuJoCo C's kinematics of the arm MJCF and computes exact
triangle-mesh distances with coal (the meshes themselves, not their convex hulls).

With ``hulls=True`` the links are their convex hulls instead: the original's PyBullet
collision model (convex hulls of the same meshes), for comparing the project's model with
the one the original's tasks were generated with.

The meshes are not part of the project; point :class:`MeshReference` at a directory that
holds them (``../shared/reference/ur5/collision`` beside a development checkout). Needs the
``coal`` package (``pip install ".[reference]"``).

Kinds follow the collision model: ``between_arms`` (every link of one arm against every
link of another), ``within_arm`` (the non-adjacent link pairs the model checks, by default
all of :data:`SELF_PAIRS`), ``ground`` (every link but the base against the plane z = 0)
and ``excluded`` (the non-adjacent pairs the model does not check). A mesh distance of 0 means
the surfaces touch or cross; a mesh entirely inside another is not detected (two solid
arm links cannot get there without crossing surfaces first).
"""

from __future__ import annotations

import dataclasses
import itertools
import pathlib

import mujoco
import numpy as np

from mjx_multiarm.geometry.robot import ARM_XML
from mjx_multiarm.reference import capsule_fit

#: Links in chain order (the arm MJCF's bodies 1..8); ``ee_link`` is the gripper box.
LINKS = (*capsule_fit.LINK_MESHES, "ee_link")
#: Non-adjacent link pairs of one arm (indices into :data:`LINKS`), as the original checked.
SELF_PAIRS = tuple((a, b) for a, b in itertools.combinations(range(len(LINKS)), 2) if b - a >= 2)
#: Links checked against the ground: all but the base, which stands on it.
GROUND_LINKS = tuple(range(1, len(LINKS)))
KINDS = ("between_arms", "within_arm", "ground", "excluded")


@dataclasses.dataclass
class SceneDistances:
    """Exact mesh distances of one scene (m); values at or above the cutoff are lower bounds.

    Attributes:
      between_arms / within_arm / ground / excluded: [n_arms] per arm, the smallest distance
        of the kind (``inf`` where the arm has no pair of that kind, e.g. a lone arm's
        ``between_arms``).
      nearest: per kind, the (arm, link, arm, link) pair that attains the scene's minimum
        (link -1 for the ground), or None.
    """

    between_arms: np.ndarray
    within_arm: np.ndarray
    ground: np.ndarray
    excluded: np.ndarray
    nearest: dict

    def scene_min(self, kind: str) -> float:
        return float(np.min(getattr(self, kind), initial=np.inf))


def _mesh_model(coal, vertices, triangles):
    """A coal BVH of a triangle mesh (its surface: exact mesh-mesh distances)."""
    model = coal.BVHModelOBBRSS()
    model.beginModel(len(triangles), len(vertices))
    model.addVertices(vertices)
    model.addTriangles(triangles.astype(np.int64))
    model.endModel()
    return model


def _convex_hull(coal, vertices):
    """The convex hull of points as a coal convex shape (solid: GJK/EPA distances)."""
    points = coal.StdVec_Vec3s()
    for v in vertices:
        points.append(v)
    return coal.ConvexBase.convexHull(points, True, "Qt")


class MeshReference:
    """The UR5 collision meshes posed by MuJoCo C kinematics, with exact distance queries.

    Args:
      mesh_dir: directory holding the STL files named in ``capsule_fit.LINK_MESHES``.
      cutoff: distances are exact below it; a pair whose bounding spheres are farther apart
        reports the (smaller than true) bounding-sphere gap, which is then >= cutoff.
      self_pairs: the link pairs of ``within_arm`` (default: all non-adjacent pairs); the
        other pairs of :data:`SELF_PAIRS` form the ``excluded`` kind.
      hulls: use each link's convex hull (the original's model) instead of its mesh.
    """

    def __init__(self, mesh_dir, cutoff: float = 0.1, self_pairs=SELF_PAIRS, hulls: bool = False):
        import coal  # the reference needs coal; nothing else in the project does

        self._coal = coal
        self.mesh_dir = mesh_dir = pathlib.Path(mesh_dir)
        self.cutoff = cutoff
        self.hulls = hulls
        self.self_pairs = {tuple(sorted(p)) for p in self_pairs}
        if not self.self_pairs <= set(SELF_PAIRS):
            raise ValueError(f"self_pairs: not non-adjacent link pairs: {sorted(self.self_pairs - set(SELF_PAIRS))}")
        triangles = [capsule_fit.read_stl(mesh_dir / file) for file in capsule_fit.LINK_MESHES.values()]
        triangles.append(capsule_fit.box_triangles(*capsule_fit.GRIPPER_BOX))
        self.vertices, self.models, self.sphere_centre, self.sphere_radius = [], [], [], []
        for tri in triangles:
            vertices, index = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
            model = _convex_hull(coal, vertices) if hulls else _mesh_model(coal, vertices, index.reshape(-1, 3))
            centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
            self.vertices.append(vertices)
            self.models.append(model)
            self.sphere_centre.append(centre)
            self.sphere_radius.append(np.linalg.norm(vertices - centre, axis=1).max())
        self._mj_model = mujoco.MjModel.from_xml_path(str(ARM_XML))
        self._mj_data = mujoco.MjData(self._mj_model)
        self._request = coal.DistanceRequest()
        self._result = coal.DistanceResult()

    def link_poses(self, base_pos, base_quat, joints) -> tuple[np.ndarray, np.ndarray]:
        """World rotations [8, 3, 3] and positions [8, 3] of the links of one arm (wxyz base)."""
        m, d = self._mj_model, self._mj_data
        d.mocap_pos[0], d.mocap_quat[0] = base_pos, base_quat
        d.qpos[:] = joints
        mujoco.mj_kinematics(m, d)
        return d.xmat[1:].reshape(-1, 3, 3).copy(), d.xpos[1:].copy()

    def pair_distance(self, pose_a, link_a: int, pose_b, link_b: int) -> float:
        """Mesh distance of links (indices into :data:`LINKS`) at poses (rotation, position).

        0 where the meshes touch or cross; with ``hulls``, signed (negative: penetration).
        """
        (rot_a, pos_a), (rot_b, pos_b) = pose_a, pose_b
        gap = np.linalg.norm(rot_a @ self.sphere_centre[link_a] + pos_a - rot_b @ self.sphere_centre[link_b] - pos_b)
        gap -= self.sphere_radius[link_a] + self.sphere_radius[link_b]
        if gap >= self.cutoff:
            return gap
        coal = self._coal
        self._result.clear()
        distance = coal.distance(self.models[link_a], coal.Transform3s(rot_a, pos_a),
                                 self.models[link_b], coal.Transform3s(rot_b, pos_b), self._request, self._result)
        return distance if self.hulls else max(0.0, distance)

    def scene(self, base_pos, base_quat, joints) -> SceneDistances:
        """Distances of one scene: base_pos [n, 3], base_quat [n, 4] (wxyz), joints [n, 6]."""
        n = len(joints)
        poses = []
        for i in range(n):
            rot, pos = self.link_poses(base_pos[i], base_quat[i], joints[i])
            poses.append([(rot[k], pos[k]) for k in range(len(LINKS))])
        out = {kind: np.full(n, np.inf) for kind in KINDS}
        nearest = dict.fromkeys(KINDS)
        best = dict.fromkeys(KINDS, np.inf)

        def record(kind, value, i, a, j, b):
            out[kind][i] = min(out[kind][i], value)
            if j >= 0 and kind == "between_arms":
                out[kind][j] = min(out[kind][j], value)
            if value < best[kind]:
                best[kind], nearest[kind] = value, (i, LINKS[a], j, LINKS[b] if b >= 0 else "ground")

        for i in range(n):
            for a, b in SELF_PAIRS:
                kind = "within_arm" if (a, b) in self.self_pairs else "excluded"
                record(kind, self.pair_distance(poses[i][a], a, poses[i][b], b), i, a, i, b)
            for a in GROUND_LINKS:
                rot, pos = poses[i][a]
                record("ground", float((self.vertices[a] @ rot[2] + pos[2]).min()), i, a, -1, -1)
            for j in range(i + 1, n):
                for a in range(len(LINKS)):
                    for b in range(len(LINKS)):
                        record("between_arms", self.pair_distance(poses[i][a], a, poses[j][b], b), i, a, j, b)
        return SceneDistances(**out, nearest=nearest)
