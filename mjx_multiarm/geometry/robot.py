"""The UR5 arm: its MJCF and the kinematic/collision constants read from the compiled model.

The MJCF in ``assets/ur5.xml`` is the single source of truth; :func:`load_arm` compiles it
once and extracts everything the JAX kernels need as numpy constants (:class:`ArmModel`).
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib

import mujoco
import numpy as np

ARM_XML = pathlib.Path(__file__).resolve().parents[1] / "assets" / "ur5.xml"
NUM_JOINTS = 6
NUM_POINTS = 10
#: Reach of the arm: the radius of its workspace hemisphere (m).
REACH = 0.85


@dataclasses.dataclass(frozen=True, eq=False)
class ArmModel:
    """Constants of one arm, in its own frames (numpy; quaternions wxyz).

    Bodies form a chain (``body_parent[b] == b - 1``); body 0 is the base, placed by the
    scene. ``body_joint[b]`` is the index of the hinge joint at the origin of body ``b``
    (or -1 for a fixed body).
    """

    body_names: tuple[str, ...]
    body_pos: np.ndarray  # [nbody, 3] position in the parent body frame
    body_quat: np.ndarray  # [nbody, 4] orientation in the parent body frame
    body_joint: tuple[int, ...]
    joint_names: tuple[str, ...]
    joint_axis: np.ndarray  # [6, 3] hinge axis in its body frame
    joint_range: np.ndarray  # [6, 2] (lower, upper), rad
    velocity_limit: np.ndarray  # [6] rad/s
    home: np.ndarray  # [6] home configuration
    ground_exempt_bodies: tuple[str, ...]  # never checked against the ground
    capsule_names: tuple[str, ...]
    capsule_body: np.ndarray  # [ncap] body of each capsule
    capsule_ends: np.ndarray  # [ncap, 2, 3] segment end points in the body frame
    capsule_radius: np.ndarray  # [ncap]
    box_names: tuple[str, ...]
    box_body: np.ndarray  # [nbox] body of each box
    box_frame: np.ndarray  # [nbox, 4, 3] centre, then the unit x, y, z axes, in the body frame
    box_half: np.ndarray  # [nbox, 3] half sizes along the box's axes
    ee_body: int
    ee_pos: np.ndarray  # [3] ee_link site in its body frame
    ee_quat: np.ndarray  # [4]
    point_body: np.ndarray  # [10] body of each observed link point
    point_pos: np.ndarray  # [10, 3] link points in their body frames

    @property
    def num_capsules(self) -> int:
        return len(self.capsule_names)

    @property
    def num_boxes(self) -> int:
        return len(self.box_names)

    @property
    def geom_names(self) -> tuple[str, ...]:
        """Every collision geom: the capsules, then the boxes (the kernel's geom order)."""
        return self.capsule_names + self.box_names


def _custom_text(m: mujoco.MjModel, name: str) -> str:
    """The data of a ``<custom><text>`` element."""
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TEXT, name)
    if i < 0:
        raise ValueError(f"arm MJCF: missing <custom><text name='{name}'>")
    start = m.text_adr[i]
    return bytes(m.text_data[start : start + m.text_size[i]]).rstrip(b"\0").decode()


def geom_rotation(m: mujoco.MjModel, g: int) -> np.ndarray:
    """Rotation [3, 3] of geom ``g`` in its body frame (columns: the geom's axes)."""
    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, m.geom_quat[g])
    return rot.reshape(3, 3)


def _capsule_ends(m: mujoco.MjModel, g: int) -> np.ndarray:
    """Segment end points of capsule ``g`` in its body frame."""
    axis = geom_rotation(m, g)[:, 2] * m.geom_size[g, 1]
    return np.stack([m.geom_pos[g] - axis, m.geom_pos[g] + axis])


@functools.cache
def load_arm(xml_path: str | None = None) -> ArmModel:
    """Compile the arm MJCF (default: the packaged UR5) and extract its constants."""
    m = mujoco.MjModel.from_xml_path(str(xml_path or ARM_XML))
    bodies = range(1, m.nbody)  # skip the world body
    if any(m.body_parentid[b] != b - 1 for b in bodies if b > 1):
        raise ValueError(f"{xml_path or ARM_XML}: arm bodies must form a single chain")
    if m.njnt != NUM_JOINTS or any(m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE for j in range(m.njnt)):
        raise ValueError(f"{xml_path or ARM_XML}: expected {NUM_JOINTS} hinge joints")
    body_joint = tuple(int(m.body_jntadr[b]) if m.body_jntnum[b] else -1 for b in bodies)
    colliding = [g for g in range(m.ngeom) if m.geom_contype[g] or m.geom_conaffinity[g]]
    geoms = [g for g in colliding if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE]
    boxes = [g for g in colliding if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
    if len(geoms) + len(boxes) != len(colliding):
        raise ValueError(f"{xml_path or ARM_XML}: collision geoms must be capsules or boxes")
    sites = {m.site(s).name: s for s in range(m.nsite)}
    points = [sites[f"point_{i}"] for i in range(NUM_POINTS)]
    ee = sites["ee_link"]
    return ArmModel(
        body_names=tuple(m.body(b).name for b in bodies),
        body_pos=m.body_pos[1:].copy(),
        body_quat=m.body_quat[1:].copy(),
        body_joint=body_joint,
        joint_names=tuple(m.joint(j).name for j in range(m.njnt)),
        joint_axis=m.jnt_axis.copy(),
        joint_range=m.jnt_range.copy(),
        velocity_limit=m.numeric("joint_velocity_limit").data.copy(),
        home=m.key("home").qpos.copy(),
        ground_exempt_bodies=tuple(_custom_text(m, "ground_exempt_bodies").split()),
        capsule_names=tuple(m.geom(g).name for g in geoms),
        capsule_body=np.array([m.geom_bodyid[g] - 1 for g in geoms]),
        capsule_ends=np.stack([_capsule_ends(m, g) for g in geoms]),
        capsule_radius=m.geom_size[geoms, 0].copy(),
        box_names=tuple(m.geom(g).name for g in boxes),
        box_body=np.array([m.geom_bodyid[g] - 1 for g in boxes], dtype=int),
        box_frame=np.array([np.vstack([m.geom_pos[g], geom_rotation(m, g).T]) for g in boxes]).reshape(-1, 4, 3),
        box_half=m.geom_size[boxes].reshape(-1, 3).copy(),
        ee_body=int(m.site_bodyid[ee] - 1),
        ee_pos=m.site_pos[ee].copy(),
        ee_quat=m.site_quat[ee].copy(),
        point_body=np.array([m.site_bodyid[s] - 1 for s in points]),
        point_pos=m.site_pos[points].copy(),
    )
