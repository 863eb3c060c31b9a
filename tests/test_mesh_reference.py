"""The collision model against exact mesh distances (needs ../shared/reference and coal).

The reference poses the UR5 collision meshes with MuJoCo C and measures exact triangle-mesh
distances (``mjx_multiarm.reference.mesh_reference``). The model must enclose the meshes (no mesh
contact unflagged in the pairs it checks), and every non-adjacent pair it leaves out must be
one the meshes never touch, or touch only where the model flags the arm anyway.
"""

from __future__ import annotations

import itertools
import pathlib
import sys

import numpy as np
import pytest

from mjx_multiarm.geometry.scene import build_scene
from mjx_multiarm.reference.mesh_reference import LINKS, SELF_PAIRS, MeshReference

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
from collision_accuracy import (  # noqa: E402
    checked_self_links,
    mesh_distances,
    model_distances,
    random_scenes,
    summarize,
)

pytest.importorskip("coal")
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def reference(request):
    root = pathlib.Path(__file__).resolve().parents[2] / "shared" / "reference" / "ur5" / "collision"
    if not root.is_dir():
        pytest.skip(f"reference meshes not found at {root}")
    return MeshReference(root, self_pairs=checked_self_links(build_scene(1)))


@pytest.mark.parametrize("num_arms", [1, 2])
def test_no_mesh_contact_is_missed(reference, num_arms):
    """400 random scenes: every mesh contact in a checked pair is flagged, and contacts in the
    excluded pairs are flagged by another kind; false flags stay rare."""
    pos, quat, joints = random_scenes(np.random.default_rng(11 + num_arms), 400, num_arms)
    mesh, nearest = mesh_distances(reference, pos, quat, joints)
    summary = summarize(model_distances(pos, quat, joints), mesh, nearest)
    for kind, s in summary.items():
        if kind == "excluded":
            assert s["flagged_by_other_kinds"] == s["mesh_contacts"], s
            continue
        assert s["missed"] == 0, (kind, s)
        assert s["mesh_contacts"] > 0, (kind, s)  # the scenes do exercise contacts
        assert s["false_flag_rate_5mm"] <= 0.06, (kind, s)  # measured at scale: <= 3 %


def _grid_minimum(reference, link_a, link_b, joints, step_deg, base=None):
    """Smallest mesh distance of two links of one arm over a joint grid (the other joints 0)."""
    a, b = LINKS.index(link_a), LINKS.index(link_b)
    best = np.inf
    for angles in itertools.product(np.radians(np.arange(-180.0, 180.0, step_deg)), repeat=len(joints)):
        q = np.zeros(6)
        q[list(joints)] = angles
        rot, pos = reference.link_poses(np.zeros(3), IDENTITY, q)
        best = min(best, reference.pair_distance((rot[a], pos[a]), a, (rot[b], pos[b]), b))
    return best


def _reach(reference, link: str, offset: float) -> float:
    """A bound on how far a link's mesh points lie from a joint axis ``offset`` m up the chain."""
    return offset + np.linalg.norm(reference.vertices[LINKS.index(link)], axis=1).max()


@pytest.mark.parametrize("link, floor_mm", [("wrist_3_link", 13.0), ("ee_link", 24.0)])
def test_wrist_1_never_touches_wrist_3_or_the_gripper(reference, link, floor_mm):
    """Only the wrist_2 and wrist_3 angles move these links relative to wrist_1. On a 3-degree
    grid the meshes stay floor_mm apart; between grid points a joint turns at most 1.5
    degrees, moving the mesh by at most reach * 1.5 degrees per joint."""
    step = 3.0
    minimum = _grid_minimum(reference, "wrist_1_link", link, (4, 5), step)
    ee_offset = 0.13 if link == "ee_link" else 0.0  # ee_link's origin in wrist_3's frame
    reach_w3 = _reach(reference, link, ee_offset)
    slack = np.radians(step / 2) * (0.09465 + reach_w3 + reach_w3)  # wrist_2, then wrist_3
    assert minimum * 1e3 >= floor_mm, minimum
    assert minimum - slack > 0.0, (minimum, slack)


def test_wrist_2_never_touches_the_gripper(reference):
    minimum = _grid_minimum(reference, "wrist_2_link", "ee_link", (5,), 1.0)
    slack = np.radians(0.5) * _reach(reference, "ee_link", 0.13)
    assert minimum * 1e3 >= 32.0 and minimum - slack > 0.0, (minimum, slack)


def test_base_touches_the_upper_arm_only_with_the_upper_arm_below_the_ground(reference):
    """Wherever the base and upper arm meshes come within 10 mm (5-degree grid of pan and
    lift), the upper arm reaches at least 10 cm below the ground: the ground check flags
    the arm there, so the base-upper arm pair is not checked."""
    base, upper = LINKS.index("base_link"), LINKS.index("upper_arm_link")
    near, lowest = 0, -np.inf
    for pan, lift in itertools.product(np.radians(np.arange(-180.0, 180.0, 5.0)), repeat=2):
        rot, pos = reference.link_poses(np.zeros(3), IDENTITY, np.array([pan, lift, 0, 0, 0, 0]))
        if reference.pair_distance((rot[base], pos[base]), base, (rot[upper], pos[upper]), upper) < 0.01:
            near += 1
            lowest = max(lowest, (reference.vertices[upper] @ rot[upper][2] + pos[upper][2]).min())
    assert near > 0  # the meshes do touch there
    assert lowest < -0.1, lowest


def test_reference_rejects_adjacent_self_pairs(reference):
    with pytest.raises(ValueError, match="self_pairs"):
        MeshReference(reference.mesh_dir, self_pairs=[(0, 1)])
    assert set(SELF_PAIRS) >= reference.self_pairs


def test_convex_hulls_enclose_the_meshes(reference):
    """The original's model (per-link convex hulls) is never farther apart than the meshes,
    is exactly as far where the closest points are on the hull, and reports penetration
    (negative) where the meshes cross."""
    hulls = MeshReference(reference.mesh_dir, self_pairs=reference.self_pairs, hulls=True)
    pos, quat, joints = random_scenes(np.random.default_rng(5), 100, 2)
    mesh, _ = mesh_distances(reference, pos, quat, joints)
    hull, _ = mesh_distances(hulls, pos, quat, joints)
    for kind in ("between_arms", "within_arm", "ground"):
        near = mesh[kind] < reference.cutoff
        assert (hull[kind][near] <= mesh[kind][near] + 1e-6).all(), kind
    assert (hull["ground"] == mesh["ground"]).all()  # the lowest point is a mesh vertex either way
    touching = mesh["between_arms"] <= 0.0
    assert touching.any() and (hull["between_arms"][touching] < 0.0).all()
