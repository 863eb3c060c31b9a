"""The pick-and-place scene: four position-actuated UR5 arms with parallel grippers, a bin,
one object slot per arm, a floor; one MJCF model for MuJoCo C and MJX.

Written with ``MjSpec`` from the project's UR5 MJCF and the derived assets
(``assets/pickplace.json``, :mod:`mjx_multiarm.pickplace.derive`). Layout as the original
demo: bases on a 1.2 m square at z = 0.01 (arms 2 and 3 turned by pi), the bin at the centre,
each arm's object 1 m from the centre in front of it.

Every arm has one object slot: a free body (0.5 kg, the original's inertia) carrying the
convex pieces of every object; a run selects one object per slot and parks the other pieces
100 m overhead (:meth:`PickPlaceScene.geom_pos`), so one compiled model serves every draw.
Grasping is a weld between ``ee_link`` and the slot body, off until the grasp; its relative
pose is written at activation (``eq_data``).

Contacts (contype/conaffinity, :func:`arm_bits`): objects collide with the floor, the bin and
each other; arm geoms (the collision capsules, the gripper box, the fingers and their pads)
collide with the floor, the bin, objects and every other arm's geoms, not with their own
arm's. Every collision a run counts comes from these contacts, at every physics step
(:mod:`mjx_multiarm.pickplace.protocol`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib

import mujoco
import numpy as np

from mjx_multiarm.files import atomic_write
from mjx_multiarm.geometry.robot import ARM_XML, load_arm

ASSETS = pathlib.Path(__file__).resolve().parents[1] / "assets" / "pickplace.json"
GRIPPER_ARM_XML = ASSETS.parent / "ur5_gripper.xml"
NUM_ARMS = 4
#: (x, y, yaw) of each base (the original demo's ``robot_base_poses``), at z = BASE_HEIGHT.
ARM_BASES = np.array([[0.6, 0.6, 0.0], [0.6, -0.6, 0.0], [-0.6, 0.6, np.pi], [-0.6, -0.6, np.pi]])
BASE_HEIGHT = 0.01
BASE_POS = np.concatenate([ARM_BASES[:, :2], np.full((NUM_ARMS, 1), BASE_HEIGHT)], axis=1)
BASE_QUAT = np.stack([np.cos(ARM_BASES[:, 2] / 2), 0 * ARM_BASES[:, 2], 0 * ARM_BASES[:, 2], np.sin(ARM_BASES[:, 2] / 2)], 1)
#: Where each arm's object stands (x, y) and where it drops it (ee_link position).
OBJECT_XY = np.array([[1.0, 0.0], [0.0, -1.0], [0.0, 1.0], [-1.0, 0.0]])
DUMP_POSITIONS = np.array([[0.2, 0.2, 0.5], [0.2, -0.2, 0.5], [-0.2, 0.2, 0.5], [-0.2, -0.2, 0.5]])
TIMESTEP = 1.0 / 240.0  # the original's physics rate
PARKED_OFFSET = np.array([0.0, 0.0, 100.0])  # unused object pieces, relative to their slot
FLOOR_HALF = np.array([3.0, 3.0, 0.05])  # the floor's top face is z = 0
OBJECT_MASS = 0.5
OBJECT_INERTIA = 1e-4

#: Arm joint servos: stiffness (N m/rad), damping (N m s/rad) and torque limits (UR5: 150 N m
#: at the base, shoulder and elbow, 28 N m at the wrists). Gravity is compensated.
ARM_KP = np.array([4000.0, 4000.0, 3000.0, 600.0, 600.0, 300.0])
ARM_KV = np.array([250.0, 250.0, 150.0, 25.0, 25.0, 10.0])
ARM_TORQUE = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])
ARM_ARMATURE = 0.05

#: The parallel gripper (Robotiq 2F-85 numbers): each finger travels half the 85 mm stroke
#: along ee_link z, toward the approach axis ee_link x; pads 37.5 x 22 mm, centred 0.13 m
#: out along the approach axis.
GRIPPER_STROKE = 0.085
PAD_CENTRE_X = 0.13
PAD_HALF = np.array([0.01875, 0.011, 0.004])
FINGER_KP = 200.0
FINGER_FORCE = 60.0

#: contype / conaffinity bits (MuJoCo makes a contact when one geom's contype shares a bit
#: with the other's conaffinity): floor, bin and objects have contype 1 and conaffinity 3.
STATIC_BITS = (1, 3)
OBJECT_BITS = (1, 3)
#: Bit 2 in an arm's contype meets the static scene's and the objects' conaffinity; bit
#: 4 << i marks arm i, in the conaffinity of every other arm (:func:`arm_bits`).
ARM_STATIC_BIT, ARM_FIRST_BIT = 2, 4

#: MJX (XLA) collision sizes: each collision function's candidate pairs are culled to the
#: ``MJX_MAX_GEOM_PAIRS`` nearest by bounding sphere, and the run's contacts to the
#: ``MJX_MAX_CONTACTS`` deepest (the constraint rows follow); the MJX backend raises where a
#: run needs more (:mod:`mjx_multiarm.pickplace.backends`). MuJoCo C and MuJoCo Warp ignore both.
MJX_MAX_GEOM_PAIRS = 128
MJX_MAX_CONTACTS = 64

# Kinds of geom owners, for classifying contacts.
FLOOR, BIN, ARM, OBJECT = 0, 1, 2, 3


def arm_bits(arm: int) -> tuple[int, int]:
    """(contype, conaffinity) of arm ``arm``'s geoms: they touch the floor, the bin, the
    objects and the other arms, never their own arm."""
    others = sum(ARM_FIRST_BIT << j for j in range(NUM_ARMS) if j != arm)
    return ARM_STATIC_BIT | ARM_FIRST_BIT << arm, others


@dataclasses.dataclass(frozen=True)
class ObjectAsset:
    """One object: its convex pieces (object frame, m), its lowest point and its grasps
    (ee_link pose in the object frame, [N, 7] position + wxyz)."""

    name: str
    hulls: tuple[np.ndarray, ...]
    bottom: float
    grasps: np.ndarray


@dataclasses.dataclass(frozen=True)
class PickPlaceAssets:
    objects: dict[str, ObjectAsset]
    bin_boxes: tuple[dict, ...]


@functools.cache
def load_assets(path: str | None = None) -> PickPlaceAssets:
    """Read the derived assets (``assets/pickplace.json`` by default)."""
    path = pathlib.Path(path or ASSETS)
    if not path.is_file():
        raise FileNotFoundError(f"pick-and-place assets not found: {path} "
                                "(derive them with python -m mjx_multiarm.pickplace.derive)")
    raw = json.loads(path.read_text())
    objects = {}
    for name, obj in raw["objects"].items():
        grasps = np.asarray(obj["grasps"], float)
        if grasps.ndim != 2 or grasps.shape[1] != 7 or not len(grasps):
            raise ValueError(f"{path}: object {name!r} needs grasps of shape [N, 7], got {grasps.shape}")
        objects[name] = ObjectAsset(name, tuple(np.asarray(h, float) for h in obj["hulls"]), float(obj["bottom"]), grasps)
    return PickPlaceAssets(objects, tuple(raw["bin"]["boxes"]))


@dataclasses.dataclass(frozen=True, eq=False)
class PickPlaceScene:
    """The compiled scene and the indices the protocol and the backends use.

    Hashable by identity (a static argument of ``jax.jit``).
    """

    model: mujoco.MjModel
    assets: PickPlaceAssets
    object_names: tuple[str, ...]
    arm_qpos: np.ndarray  # [4, 6] qpos address of each arm's joints
    arm_dof: np.ndarray  # [4, 6]
    finger_qpos: np.ndarray  # [4, 2]
    arm_actuators: np.ndarray  # [4, 6]
    finger_actuators: np.ndarray  # [4, 2]
    object_qpos: np.ndarray  # [4] qpos address of each slot's free joint (7 numbers)
    object_dof: np.ndarray  # [4] its dof address (6 numbers)
    object_body: np.ndarray  # [4]
    ee_body: np.ndarray  # [4]
    welds: np.ndarray  # [4] equality id of each arm's grasp weld
    piece_geoms: dict[str, np.ndarray]  # object name -> [4, pieces] geom ids in each slot
    geom_kind: np.ndarray  # [ngeom] FLOOR / BIN / ARM / OBJECT
    geom_slot: np.ndarray  # [ngeom] arm or object slot (-1 for floor and bin)

    def object_index(self, name: str) -> int:
        if name not in self.object_names:
            raise ValueError(f"unknown object {name!r}; choose from {', '.join(self.object_names)}")
        return self.object_names.index(name)

    def geom_pos(self, objects) -> np.ndarray:
        """``model.geom_pos`` [ngeom, 3] with, in each slot i, the pieces of ``objects[i]``
        (a name or an index) at home and every other piece parked."""
        if len(objects) != NUM_ARMS:
            raise ValueError(f"the pick-and-place layout needs one object per arm ({NUM_ARMS}), got {len(objects)}")
        pos = self.model.geom_pos.copy()
        for name, geoms in self.piece_geoms.items():
            for slot in range(NUM_ARMS):
                chosen = objects[slot]
                chosen = self.object_names[chosen] if isinstance(chosen, (int, np.integer)) else chosen
                if chosen not in self.object_names:
                    raise ValueError(f"unknown object {chosen!r}; choose from {', '.join(self.object_names)}")
                if name != chosen:
                    pos[geoms[slot]] += PARKED_OFFSET
        return pos


def _add_gripper(ee: mujoco.MjsBody) -> None:
    """Two fingers on slide joints along ee_link z, each with a pad, and their servos' bodies."""
    half_stroke = GRIPPER_STROKE / 2
    for side, sign in (("left", 1.0), ("right", -1.0)):
        finger = ee.add_body(name=f"finger_{side}", pos=[0.0, 0.0, sign * half_stroke])
        finger.add_joint(name=f"finger_{side}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0.0, 0.0, -sign],
                         range=[0.0, half_stroke], armature=0.01, damping=5.0)
        finger.mass = 0.05
        finger.inertia = [1e-5, 1e-5, 1e-5]
        finger.explicitinertial = True
        kw = {"type": mujoco.mjtGeom.mjGEOM_BOX, "group": 1, "rgba": [0.15, 0.15, 0.15, 1.0],
              "friction": [1.0, 0.005, 0.0001]}
        finger.add_geom(name=f"pad_{side}", pos=[PAD_CENTRE_X, 0.0, sign * PAD_HALF[2]], size=PAD_HALF, **kw)
        finger.add_geom(name=f"finger_{side}", pos=[0.10, 0.0, sign * (2 * PAD_HALF[2] + 0.006)],
                        size=[0.035, PAD_HALF[1], 0.006], **kw)


def actuated_arm(gripper: bool = True, bits: tuple[int, int] = (0, 0)) -> mujoco.MjSpec:
    """The project's UR5 with gravity compensation and joint armature (for its servos), and
    optionally the gripper; every geom gets the contact ``bits`` (contype, conaffinity;
    the default switches its contacts off: pure dynamics)."""
    arm = mujoco.MjSpec.from_file(str(ARM_XML))
    for geom in arm.geoms:
        geom.group = 1  # visible in renders
        geom.rgba = [0.55, 0.6, 0.7, 1.0] if geom.name != "ee_link_0" else [0.2, 0.2, 0.2, 1.0]
    for joint in arm.joints:
        joint.armature = ARM_ARMATURE
        joint.actgravcomp = False
    if gripper:
        _add_gripper(arm.body("ee_link"))
    for geom in arm.geoms:
        geom.contype, geom.conaffinity = bits
    for body in arm.bodies:
        body.gravcomp = 1.0
    return arm


def add_arm_servos(spec: mujoco.MjSpec, prefix: str) -> None:
    """Position servos (:data:`ARM_KP`, :data:`ARM_KV`, torque limits) on an attached arm's joints."""
    for j, joint in enumerate(load_arm().joint_names):
        spec.add_actuator(name=f"{prefix}{joint}", target=f"{prefix}{joint}", trntype=mujoco.mjtTrn.mjTRN_JOINT,
                          gaintype=mujoco.mjtGain.mjGAIN_FIXED, biastype=mujoco.mjtBias.mjBIAS_AFFINE,
                          gainprm=[ARM_KP[j]] + [0] * 9, biasprm=[0, -ARM_KP[j], -ARM_KV[j]] + [0] * 7,
                          ctrlrange=[-2 * np.pi, 2 * np.pi], forcerange=[-ARM_TORQUE[j], ARM_TORQUE[j]])


def build_reaching_spec(num_arms: int) -> mujoco.MjSpec:
    """Reaching teams under dynamics: ``num_arms`` servoed arms on mocap bases (placed per
    task), no gripper and no contacts (collisions are the collision model's), 240 Hz."""
    spec = mujoco.MjSpec()
    spec.modelname = f"reaching_physics_{num_arms}"
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for i in range(num_arms):
        spec.attach(actuated_arm(gripper=False), prefix=f"arm{i}/", frame=spec.worldbody.add_frame())
        add_arm_servos(spec, f"arm{i}/")
    return spec


def build_spec(assets: PickPlaceAssets) -> mujoco.MjSpec:
    """The scene as an ``MjSpec`` (see the module docstring)."""
    spec = mujoco.MjSpec()
    spec.modelname = "pickplace"
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    # MJX (XLA) collision sizes, first: MJX reads a numeric at index = its id in numeric_data.
    spec.add_numeric(name="max_geom_pairs", data=[MJX_MAX_GEOM_PAIRS])
    spec.add_numeric(name="max_contact_points", data=[MJX_MAX_CONTACTS])
    world = spec.worldbody
    # A box, not a plane: parked object pieces (far away in their slot's frame) never reach it.
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[0.0, 0.0, -FLOOR_HALF[2]], size=FLOOR_HALF,
                   rgba=[0.85, 0.85, 0.82, 1],
                   contype=STATIC_BITS[0], conaffinity=STATIC_BITS[1], friction=[1.0, 0.005, 0.0001])
    world.add_light(pos=[0, 0, 4], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    bin_body = world.add_body(name="bin")
    for box in assets.bin_boxes:
        bin_body.add_geom(name=f"bin_{box['name']}", type=mujoco.mjtGeom.mjGEOM_BOX, pos=box["pos"], size=box["size"],
                          euler=box["euler"], contype=STATIC_BITS[0], conaffinity=STATIC_BITS[1], group=1,
                          rgba=[0.35, 0.55, 0.85, 1.0], friction=[1.0, 0.005, 0.0001])
    for name, obj in assets.objects.items():
        for k, hull in enumerate(obj.hulls):
            spec.add_mesh(name=f"{name}_{k}", uservert=hull.reshape(-1).tolist())
    for i in range(NUM_ARMS):
        frame = world.add_frame(pos=BASE_POS[i], quat=BASE_QUAT[i])
        arm = actuated_arm(bits=arm_bits(i))
        arm.body("base_link").mocap = False  # welded to the world at the frame
        spec.attach(arm, prefix=f"arm{i}/", frame=frame)
        add_arm_servos(spec, f"arm{i}/")
        for side in ("left", "right"):
            spec.add_actuator(name=f"arm{i}/finger_{side}", target=f"arm{i}/finger_{side}",
                              trntype=mujoco.mjtTrn.mjTRN_JOINT, gaintype=mujoco.mjtGain.mjGAIN_FIXED,
                              biastype=mujoco.mjtBias.mjBIAS_AFFINE, gainprm=[FINGER_KP] + [0] * 9,
                              biasprm=[0, -FINGER_KP, -10.0] + [0] * 7, ctrlrange=[0.0, GRIPPER_STROKE / 2],
                              forcerange=[-FINGER_FORCE, FINGER_FORCE])
        slot = world.add_body(name=f"object{i}", pos=[*OBJECT_XY[i], 0.5])
        slot.add_freejoint(name=f"object{i}")
        slot.mass, slot.inertia, slot.explicitinertial = OBJECT_MASS, [OBJECT_INERTIA] * 3, True
        slot.ipos, slot.iquat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]  # at the object frame's origin
        for name, obj in assets.objects.items():
            for k in range(len(obj.hulls)):
                slot.add_geom(name=f"object{i}/{name}_{k}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_{k}",
                              contype=OBJECT_BITS[0], conaffinity=OBJECT_BITS[1], group=1, density=0,
                              rgba=[0.9, 0.45, 0.15, 1.0], friction=[1.0, 0.005, 0.0001])
        spec.add_equality(name=f"grasp{i}", type=mujoco.mjtEq.mjEQ_WELD, name1=f"arm{i}/ee_link", name2=f"object{i}",
                          objtype=mujoco.mjtObj.mjOBJ_BODY, active=False,
                          data=[0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0])
    return spec


def write_scene(path, assets_path: str | None = None) -> None:
    """Write the scene's MJCF to ``path`` (self-contained: the object pieces' vertices
    inline), for MuJoCo's viewer or any MJCF tool."""
    spec = build_spec(load_assets(assets_path))
    m = spec.compile()  # MjSpec.to_xml needs a compiled spec
    for body in spec.bodies:  # an explicit inertial whose frame the compiler chose: write that frame
        if body.explicitinertial and np.isnan(body.ipos).any():
            body.ipos, body.iquat = m.body(body.name).ipos, m.body(body.name).iquat
    xml = spec.to_xml()
    atomic_write(pathlib.Path(path), lambda f: f.write(xml.encode()))


def finger_envelope() -> tuple[np.ndarray, np.ndarray]:
    """(centre, half sizes) [3] in the ee_link frame of the box that encloses both simulated
    fingers and their pads at every opening: the union of their boxes' bounds, open and
    closed (the fingers slide in a straight line, so every opening lies between the two)."""
    m = actuated_arm().compile()
    data = mujoco.MjData(m)
    ee = m.body("ee_link").id
    geoms = [g for g in range(m.ngeom) if m.geom(g).name.startswith(("pad_", "finger_"))]
    slides = [m.jnt_qposadr[m.joint(f"finger_{side}").id] for side in ("left", "right")]
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T  # [8, 3]
    corners = []
    for travel in (0.0, GRIPPER_STROKE / 2):
        data.qpos[slides] = travel
        mujoco.mj_kinematics(m, data)
        for g in geoms:
            world = data.geom_xpos[g] + (signs * m.geom_size[g]) @ data.geom_xmat[g].reshape(3, 3).T
            corners.append((world - data.xpos[ee]) @ data.xmat[ee].reshape(3, 3))
    corners = np.concatenate(corners)
    low, high = corners.min(axis=0), corners.max(axis=0)
    return (low + high) / 2, (high - low) / 2


def gripper_arm_xml() -> str:
    """The arm MJCF of the pick-and-place collision model: the project's UR5 (its capsules and
    the original's gripper stand-in box) plus ``ee_link_1``, the box of :func:`finger_envelope`
    rounded out to 0.1 mm, inserted after the stand-in box (the rest of the file unchanged).
    ``assets/ur5_gripper.xml`` holds it (written by :func:`write_gripper_arm`; the tests check
    it is current)."""
    centre, half = finger_envelope()
    low, high = np.floor((centre - half) * 1e4) / 1e4, np.ceil((centre + half) * 1e4) / 1e4
    numbers = lambda x: " ".join(f"{v:.5f}".rstrip("0").rstrip(".") for v in x)  # noqa: E731
    lines = ARM_XML.read_text().splitlines(keepends=True)
    stand_in = [k for k, line in enumerate(lines) if 'name="ee_link_0"' in line]
    if len(stand_in) != 1:
        raise ValueError(f"{ARM_XML}: expected one ee_link_0 geom line, found {len(stand_in)}")
    indent = lines[stand_in[0]][: len(lines[stand_in[0]]) - len(lines[stand_in[0]].lstrip())]
    box = (f"{indent}<!-- Both simulated fingers and pads at every opening (pickplace.scene.finger_envelope). -->\n"
           f'{indent}<geom class="collision" type="box" name="ee_link_1" pos="{numbers((low + high) / 2)}" '
           f'size="{numbers((high - low) / 2)}"/>\n')
    return "".join(lines[: stand_in[0] + 1]) + box + "".join(lines[stand_in[0] + 1:])


def write_gripper_arm(path=GRIPPER_ARM_XML) -> None:
    """Write :func:`gripper_arm_xml` to ``path`` (default: the packaged asset)."""
    xml = gripper_arm_xml()
    atomic_write(pathlib.Path(path), lambda f: f.write(xml.encode()))


@functools.cache
def collision_model(assets_path: str | None = None) -> tuple[str, tuple]:
    """``(arm_xml, obstacles)`` of the pick-and-place scene for :class:`mjx_multiarm.planner.Planner`
    and :class:`mjx_multiarm.env.reaching.ReachingEnv`: the arm with the gripper as simulated
    (:func:`gripper_arm_xml`) and the bin's boxes as static obstacles; the floor (top face at
    z = 0) is the collision model's ground. The objects are not in it: neither the one an
    arm carries nor those on the floor."""
    m = build_scene(assets_path).model
    bins = np.flatnonzero(_geom_owners(m)[0] == BIN)
    if np.any(m.body_pos[m.body("bin").id]) or not np.array_equal(m.body_quat[m.body("bin").id], [1.0, 0.0, 0.0, 0.0]):
        raise AssertionError("the bin body must sit at the world origin")
    obstacles = tuple((tuple(m.geom_pos[g].tolist()), tuple(m.geom_quat[g].tolist()), tuple(m.geom_size[g].tolist()))
                      for g in bins)
    return str(GRIPPER_ARM_XML), obstacles


def _geom_owners(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    kind = np.full(m.ngeom, -1)
    slot = np.full(m.ngeom, -1)
    for g in range(m.ngeom):
        name = m.geom(g).name
        if name == "floor":
            kind[g] = FLOOR
        elif name.startswith("bin_"):
            kind[g] = BIN
        elif name.startswith("arm"):
            kind[g], slot[g] = ARM, int(name[3])
        elif name.startswith("object"):
            kind[g], slot[g] = OBJECT, int(name[6])
    if (kind < 0).any():
        raise AssertionError(f"unclassified geoms: {[m.geom(g).name for g in np.flatnonzero(kind < 0)]}")
    return kind, slot


@functools.cache
def build_scene(assets_path: str | None = None) -> PickPlaceScene:
    """Compile (once per assets file) the pick-and-place scene."""
    assets = load_assets(assets_path)
    m = build_spec(assets).compile()
    joints = load_arm().joint_names
    kind, slot = _geom_owners(m)

    def ids(fn, names):
        return np.array([[fn(f"arm{i}/{n}").id for n in names] for i in range(NUM_ARMS)])

    arm_joint_ids = ids(m.joint, joints)
    finger_joint_ids = ids(m.joint, ("finger_left", "finger_right"))
    object_joints = np.array([m.joint(f"object{i}").id for i in range(NUM_ARMS)])
    return PickPlaceScene(
        model=m,
        assets=assets,
        object_names=tuple(assets.objects),
        arm_qpos=m.jnt_qposadr[arm_joint_ids],
        arm_dof=m.jnt_dofadr[arm_joint_ids],
        finger_qpos=m.jnt_qposadr[finger_joint_ids],
        arm_actuators=ids(m.actuator, joints),
        finger_actuators=ids(m.actuator, ("finger_left", "finger_right")),
        object_qpos=m.jnt_qposadr[object_joints],
        object_dof=m.jnt_dofadr[object_joints],
        object_body=np.array([m.body(f"object{i}").id for i in range(NUM_ARMS)]),
        ee_body=np.array([m.body(f"arm{i}/ee_link").id for i in range(NUM_ARMS)]),
        welds=np.array([m.equality(f"grasp{i}").id for i in range(NUM_ARMS)]),
        piece_geoms={name: np.array([[m.geom(f"object{i}/{name}_{k}").id for k in range(len(obj.hulls))]
                                     for i in range(NUM_ARMS)]) for name, obj in assets.objects.items()},
        geom_kind=kind,
        geom_slot=slot,
    )
