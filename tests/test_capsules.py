"""The MJCF capsules enclose the UR5 collision meshes; the gripper is the original's box."""

from __future__ import annotations

import numpy as np
import pytest

from mjx_multiarm.geometry.robot import load_arm
from mjx_multiarm.reference import capsule_fit


def _link_capsules(link: str):
    arm = load_arm()
    body = arm.body_names.index(link)
    return [(ends[0], ends[1], r) for ends, r, b in zip(arm.capsule_ends, arm.capsule_radius, arm.capsule_body) if b == body]


@pytest.mark.parametrize("link", sorted(capsule_fit.LINK_MESHES))
def test_capsules_enclose_the_link_mesh(reference_dir, link):
    triangles = capsule_fit.read_stl(reference_dir / "collision" / capsule_fit.LINK_MESHES[link])
    capsules = _link_capsules(link)
    vertices = triangles.reshape(-1, 3)
    assert capsule_fit.outside_distance(vertices, capsules).max() < 5e-3  # spec: within 5 mm
    assert capsule_fit.outside_distance(vertices, capsules).max() <= 1e-4  # as fitted: inside
    surface = capsule_fit.sample_surface(triangles, 2e-3)
    assert capsule_fit.outside_distance(surface, capsules).max() <= 1e-3


def test_gripper_is_the_original_box():
    """ee_link's one collision geom is the URDF's gripper stand-in box, exactly."""
    arm = load_arm()
    (box,) = [b for b, body in enumerate(arm.box_body) if arm.body_names[body] == "ee_link"]
    centre, size = capsule_fit.GRIPPER_BOX
    np.testing.assert_allclose(arm.box_frame[box, 0], centre)
    np.testing.assert_allclose(arm.box_frame[box, 1:], np.eye(3))
    np.testing.assert_allclose(arm.box_half[box], size / 2)
    assert arm.body_names.index("ee_link") not in arm.capsule_body


def test_volume_overhead_stays_tight(reference_dir):
    """Union-of-capsules volume over mesh volume, all capsule links (fitted: 1.7)."""
    mesh = union = 0.0
    for link, file in capsule_fit.LINK_MESHES.items():
        mesh += capsule_fit.mesh_volume(capsule_fit.read_stl(reference_dir / "collision" / file))
        union += capsule_fit.union_volume(_link_capsules(link), 200_000)
    assert union / mesh < 1.8, union / mesh


def test_read_stl_rejects_malformed_files(tmp_path):
    bad = tmp_path / "truncated.stl"
    bad.write_bytes(b"\0" * 80 + (5).to_bytes(4, "little") + b"\0" * 60)
    with pytest.raises(ValueError, match="truncated.stl"):
        capsule_fit.read_stl(bad)
