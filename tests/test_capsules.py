"""The MJCF capsules enclose the UR5 collision meshes and the gripper stand-in box."""

from __future__ import annotations

import numpy as np
import pytest

from mjx_multiarm import capsule_fit
from mjx_multiarm.robot import load_arm
from mjx_multiarm.transforms import quat_to_mat

# The gripper box is rigidly attached to wrist_3 (ee_link has no joint): it is enclosed by
# the capsules of wrist_3_link, in whose frame it is checked.
EE_IN_WRIST_3 = (np.array([0.0, 0.13, 0.0]), np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))


def _link_capsules(link: str):
    arm = load_arm()
    body = arm.body_names.index(link)
    return [(ends[0], ends[1], r) for ends, r, b in zip(arm.capsule_ends, arm.capsule_radius, arm.capsule_body) if b == body]


def _gripper_box_in_wrist_3():
    offset, quat = EE_IN_WRIST_3
    box = capsule_fit.box_triangles(*capsule_fit.GRIPPER_BOX)
    return box @ np.asarray(quat_to_mat(quat)).T + offset


@pytest.mark.parametrize("link", sorted(capsule_fit.LINK_MESHES))
def test_capsules_enclose_the_link_mesh(reference_dir, link):
    triangles = capsule_fit.read_stl(reference_dir / "collision" / capsule_fit.LINK_MESHES[link])
    capsules = _link_capsules(link)
    vertices = triangles.reshape(-1, 3)
    assert capsule_fit.outside_distance(vertices, capsules).max() < 5e-3  # spec: within 5 mm
    assert capsule_fit.outside_distance(vertices, capsules).max() <= 1e-4  # as fitted: inside
    surface = capsule_fit.sample_surface(triangles, 2e-3)
    assert capsule_fit.outside_distance(surface, capsules).max() <= 1e-3


def test_capsules_enclose_the_gripper_box():
    box = _gripper_box_in_wrist_3()
    surface = capsule_fit.sample_surface(box, 2e-3)
    assert capsule_fit.outside_distance(surface, _link_capsules("wrist_3_link")).max() <= 0.0


def test_volume_overhead_stays_tight(reference_dir):
    """Union-of-capsules volume over mesh volume, all links + gripper (fitted: 1.8)."""
    mesh = union = 0.0
    for link, file in capsule_fit.LINK_MESHES.items():
        mesh += capsule_fit.mesh_volume(capsule_fit.read_stl(reference_dir / "collision" / file))
        if link != "wrist_3_link":
            union += capsule_fit.union_volume(_link_capsules(link), 200_000)
    mesh += capsule_fit.mesh_volume(_gripper_box_in_wrist_3())
    union += capsule_fit.union_volume(_link_capsules("wrist_3_link"), 200_000)
    assert union / mesh < 2.0, union / mesh


def test_read_stl_rejects_malformed_files(tmp_path):
    bad = tmp_path / "truncated.stl"
    bad.write_bytes(b"\0" * 80 + (5).to_bytes(4, "little") + b"\0" * 60)
    with pytest.raises(ValueError, match="truncated.stl"):
        capsule_fit.read_stl(bad)
