"""The padded multi-arm scene: one MuJoCo model with ``max_arms`` UR5 slots, a ground and,
optionally, static box obstacles (a bin, a table).

A task with k arms activates k slots; the others are masked out of every computation
(:mod:`mjx_multiarm.geometry.collision`), so one compiled function serves every team size. The
MuJoCo model is composed with ``MjSpec``: each slot attaches a copy of the arm MJCF under
the prefix ``arm{i}/``; its base is a mocap body placed at the arm's base pose.

Which geom pairs can collide is read off the compiled model with MuJoCo's own filtering
rules (contype/conaffinity, weld bodies, parent-child filter, ``<exclude>``), so the JAX
collision kernel and MuJoCo C (``mj_collision``) check exactly the same pairs. Obstacles are
world geoms like the ground: MuJoCo filters them alike, so each arm geom checked against the
ground is checked against every obstacle, and the kernels report both as one distance.
"""

from __future__ import annotations

import dataclasses
import functools

import mujoco
import numpy as np

from mjx_multiarm.geometry.robot import ARM_XML, ArmModel, geom_rotation, load_arm

#: Where MuJoCo-side models park inactive slots: far apart and far from every task.
PARKING_ORIGIN = np.array([1000.0, 0.0, 0.0])
PARKING_SPACING = 10.0


@dataclasses.dataclass(frozen=True, eq=False)
class CollisionPairs:
    """The geom pairs that count as collisions, in arm-local geom indices (``ArmModel.geom_names``:
    capsules first, then boxes).

    Attributes:
      between_arms: [ngeom, ngeom] bool; geom a of one arm vs geom b of another arm.
      self_pairs: [nself, 2] geom index pairs within one arm (non-adjacent links).
      ground: [nground] geoms checked against the ground plane (the base excepted).
    """

    between_arms: np.ndarray
    self_pairs: np.ndarray
    ground: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A compiled padded scene: the MuJoCo model plus the constants of the JAX kernels.

    Hashable by identity, so it can be a static argument of ``jax.jit``.
    """

    max_arms: int
    arm: ArmModel
    mj_model: mujoco.MjModel
    pairs: CollisionPairs
    geoms: np.ndarray  # [max_arms, ngeom] MuJoCo geom ids of each slot's collision geoms
    ground_geom: int
    obstacle_frames: np.ndarray  # [K, 4, 3] each static obstacle box's centre, then its unit x, y, z axes (world)
    obstacle_half: np.ndarray  # [K, 3] their half sizes
    mocap_ids: np.ndarray  # [max_arms] mocap index of each slot's base
    qpos_adr: np.ndarray  # [max_arms, 6] qpos address of each slot's joints


#: A static obstacle box: (centre [3], orientation wxyz [4], half sizes [3]), world frame, m.
Obstacle = tuple[tuple[float, float, float], tuple[float, float, float, float], tuple[float, float, float]]


def build_spec(max_arms: int = 10, arm_xml: str | None = None, obstacles: tuple[Obstacle, ...] = ()) -> mujoco.MjSpec:
    """Compose the padded scene: ground plane, light, the ``obstacles`` and ``max_arms`` arm slots."""
    if not 1 <= max_arms <= 64:
        raise ValueError(f"max_arms must be in [1, 64], got {max_arms}")
    spec = mujoco.MjSpec()
    spec.modelname = f"multiarm_{max_arms}"
    spec.worldbody.add_geom(
        name="ground", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], rgba=[0.9, 0.9, 0.9, 1]
    )
    spec.worldbody.add_light(pos=[0, 0, 4], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    for k, (pos, quat, half) in enumerate(obstacles):
        if min(half) <= 0:
            raise ValueError(f"obstacle {k}: half sizes must be positive, got {half}")
        spec.worldbody.add_geom(name=f"obstacle{k}", type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos, quat=quat, size=half,
                                rgba=[0.35, 0.55, 0.85, 1])
    exempt = load_arm(arm_xml).ground_exempt_bodies
    for i in range(max_arms):
        arm = mujoco.MjSpec.from_file(str(arm_xml or ARM_XML))  # a fresh copy per slot
        spec.attach(arm, prefix=f"arm{i}/", frame=spec.worldbody.add_frame())
        for body in exempt:  # bodies that stand on or cannot reach the ground
            spec.add_exclude(bodyname1="world", bodyname2=f"arm{i}/{body}")
    return spec


def _may_collide(m: mujoco.MjModel, excluded: set[int], g1: int, g2: int) -> bool:
    """MuJoCo's broad-phase filter for a geom pair (what ``mj_collision`` would test).

    ``excluded`` holds the model's ``exclude_signature`` values.
    """
    if not (m.geom_contype[g1] & m.geom_conaffinity[g2] or m.geom_contype[g2] & m.geom_conaffinity[g1]):
        return False
    b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
    w1, w2 = m.body_weldid[b1], m.body_weldid[b2]
    if w1 == w2:
        return False
    parent1, parent2 = m.body_weldid[m.body_parentid[w1]], m.body_weldid[m.body_parentid[w2]]
    filterparent = not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    if filterparent and w1 != 0 and w2 != 0 and (w1 == parent2 or w2 == parent1):
        return False
    return (min(b1, b2) << 16) + max(b1, b2) not in excluded


def _collision_pairs(m: mujoco.MjModel, geoms: np.ndarray, ground: int) -> CollisionPairs:
    """Read the pair sets off slot 0 (and slot 1 for pairs between arms)."""
    may_collide = functools.partial(_may_collide, m, set(m.exclude_signature.tolist()))
    ngeom = geoms.shape[1]
    slot0 = geoms[0]
    between = np.zeros((ngeom, ngeom), bool)
    if len(geoms) > 1:
        between = np.array([[may_collide(a, b) for b in geoms[1]] for a in slot0])
    self_pairs = [(a, b) for a in range(ngeom) for b in range(a + 1, ngeom) if may_collide(slot0[a], slot0[b])]
    return CollisionPairs(
        between_arms=between,
        self_pairs=np.array(self_pairs, dtype=np.int32).reshape(-1, 2),
        ground=np.array([c for c in range(ngeom) if may_collide(ground, slot0[c])], dtype=np.int32),
    )


@functools.cache
def build_scene(max_arms: int = 10, arm_xml: str | None = None, obstacles: tuple[Obstacle, ...] = ()) -> Scene:
    """Build (once per argument set) the padded scene with ``max_arms`` slots, the arm of
    ``arm_xml`` (default: the packaged UR5) and the static ``obstacles``."""
    arm = load_arm(arm_xml)
    m = build_spec(max_arms, arm_xml, obstacles).compile()
    boxes = [m.geom(f"obstacle{k}").id for k in range(len(obstacles))]
    geoms = np.array([[m.geom(f"arm{i}/{name}").id for name in arm.geom_names] for i in range(max_arms)])
    ground = m.geom("ground").id
    return Scene(
        max_arms=max_arms,
        arm=arm,
        mj_model=m,
        pairs=_collision_pairs(m, geoms, ground),
        geoms=geoms,
        ground_geom=ground,
        obstacle_frames=np.array([np.vstack([m.geom_pos[g], geom_rotation(m, g).T]) for g in boxes]).reshape(-1, 4, 3),
        obstacle_half=m.geom_size[boxes].reshape(-1, 3).copy(),
        mocap_ids=np.array([m.body_mocapid[m.body(f"arm{i}/base_link").id] for i in range(max_arms)]),
        qpos_adr=np.array(
            [[m.jnt_qposadr[m.joint(f"arm{i}/{j}").id] for j in arm.joint_names] for i in range(max_arms)]
        ),
    )


def set_mujoco_state(scene: Scene, data: mujoco.MjData, base_pos, base_quat, joints, active) -> None:
    """Write one padded scene into ``data`` (numpy; quaternions wxyz) and run ``mj_kinematics``.

    Inactive slots are parked far from the workspace at the home configuration, so MuJoCo C
    sees only the active arms' contacts.
    """
    for i in range(scene.max_arms):
        mocap = scene.mocap_ids[i]
        if active[i]:
            data.mocap_pos[mocap], data.mocap_quat[mocap] = base_pos[i], base_quat[i]
            data.qpos[scene.qpos_adr[i]] = joints[i]
        else:
            data.mocap_pos[mocap] = PARKING_ORIGIN + [PARKING_SPACING * i, 0.0, 0.0]
            data.mocap_quat[mocap] = [1.0, 0.0, 0.0, 0.0]
            data.qpos[scene.qpos_adr[i]] = scene.arm.home
    mujoco.mj_kinematics(scene.mj_model, data)
