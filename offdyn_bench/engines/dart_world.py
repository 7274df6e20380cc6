"""A DART world built from the same MJCF file that MuJoCo compiles.

DART's MJCF parser (``dartpy.utils.MjcfParser``) reads the file; the compiled MuJoCo model of the
same file is the reference for what the file *means*. Where the parser leaves a quantity unread or
reads it differently, the value is copied from the compiled model, so the two engines start from one
set of physical parameters and differ only in how they simulate them:

- joint ranges: the parser keeps ``compiler angle="degree"`` values as radians and does not enforce
  them; they are set from ``jnt_range`` and enforced as DART joint-limit constraints;
- inertia: the parser leaves every moment of inertia at the identity (``inertiafromgeom``); it is
  set from ``body_inertia``/``body_iquat``;
- damping, stiffness, Coulomb friction (``frictionloss``), gravity and timestep come from the
  compiled model;
- the floor: MuJoCo's plane is an infinite half-space; the parser makes it a 1 cm box centred at
  z = 0 (its top 5 mm above MuJoCo's floor). It becomes a 1 m thick, 400 m wide box whose top is
  at z = 0;
- friction: MuJoCo uses the larger friction of the two geoms in contact, DART the smaller; each robot
  shape carries the value MuJoCo would use against the floor, the floor the largest of them;
- armature: DART has none; it is emulated exactly within DART's step (:meth:`DartWorld.step`);
- the collision detector: the parser's default (FCL) replaces capsules by 0.1 m spheres; ODE's and
  Bullet's detectors support capsules (ODE is the default here: it is stateless between steps and
  about twice as fast in this suite's benchmark).

A kinematic check runs at construction: the world pose of every body must match MuJoCo's at a
random configuration, so a parser change cannot silently move a limb.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile
from collections.abc import Iterator

import mujoco
import numpy as np

from offdyn_bench.errors import OffdynError

COLLISION_DETECTORS = ("ode", "bullet")
FLOOR_HALF_WIDTH = 200.0  # m; MuJoCo's plane is infinite, a locomotion episode covers < 50 m
FLOOR_THICKNESS = 1.0  # m; thick enough that no contact tunnels through it
KINEMATIC_TOLERANCE = 1e-9  # m (and rotation-matrix entries)
GROUND_PREFIX = "__geom_skel__"


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Collect what C++ code writes to file descriptor 2 while parsing. DART's parser warns about
    the massless frames it inserts between a body's joints and about FCL's missing capsule support;
    both are replaced here, so the warnings would only mislead. They are kept for error messages."""
    lines: list[str] = []
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines.extend(sink.read().decode("utf-8", "replace").splitlines())


def _detector(name: str):
    import dartpy

    if name == "ode":
        return dartpy.collision.OdeCollisionDetector()
    if name == "bullet":
        return dartpy.collision.BulletCollisionDetector()
    raise OffdynError(f"unknown DART collision detector {name!r}; expected one of {', '.join(COLLISION_DETECTORS)} "
                      "(FCL and DART's own detector do not support capsules)")


@dataclasses.dataclass
class DartWorld:
    """A DART world of one MJCF robot and its floor, with the map between MuJoCo and DART coordinates.

    DART's generalized positions and velocities are MuJoCo's ``qpos`` and ``qvel`` (the same
    numbers, no offset: a state read and written back is bit for bit the same); ``dof_indices`` maps
    MuJoCo's joint order to DART's dof order.
    """

    world: object  # dartpy.simulation.World
    robot: object  # dartpy.dynamics.Skeleton
    dof_indices: np.ndarray  # DART dof index of each MuJoCo joint, in MuJoCo order
    actuator_dofs: np.ndarray  # DART dof index each actuator drives
    gear: np.ndarray
    ctrl_range: np.ndarray  # (nu, 2); rows of +-inf where the actuator is not ctrllimited
    collision_detector: str
    armature_damping: np.ndarray  # per DART dof: armature / timestep (zeros when not emulated)

    @property
    def time(self) -> float:
        return float(self.world.getTime())

    def set_qpos_qvel(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        positions = np.zeros(self.robot.getNumDofs())
        velocities = np.zeros(self.robot.getNumDofs())
        positions[self.dof_indices] = qpos
        velocities[self.dof_indices] = qvel
        self.robot.setPositions(positions)
        self.robot.setVelocities(velocities)

    def qpos(self) -> np.ndarray:
        return np.asarray(self.robot.getPositions())[self.dof_indices]

    def qvel(self) -> np.ndarray:
        return np.asarray(self.robot.getVelocities())[self.dof_indices]

    def torques(self, ctrl: np.ndarray) -> np.ndarray:
        """Generalized forces of MuJoCo's ``motor`` actuators: gear x control, the control clipped
        to its range first (MuJoCo clamps ``ctrllimited`` controls before applying them)."""
        clipped = np.clip(ctrl, self.ctrl_range[:, 0], self.ctrl_range[:, 1])
        forces = np.zeros(self.robot.getNumDofs())
        np.add.at(forces, self.actuator_dofs, self.gear * clipped)
        return forces

    def step(self, ctrl: np.ndarray, n_frames: int) -> None:
        forces = self.torques(ctrl)
        robot, world = self.robot, self.world
        if not self.armature_damping.any():
            for _ in range(n_frames):
                robot.setForces(forces)  # DART clears generalized forces after every step
                world.step()
            return
        for _ in range(n_frames):
            # Armature, emulated: DART damps implicitly, -d * qvel(next); with d raised by
            # armature/h and +armature/h * qvel(now) added, the two terms are -armature * qacc.
            robot.setForces(forces + self.armature_damping * np.asarray(robot.getVelocities()))
            world.step()


def _check_supported(model: mujoco.MjModel, xml_path: str) -> None:
    hinge_or_slide = {int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)}
    for j in range(model.njnt):
        if int(model.jnt_type[j]) not in hinge_or_slide:
            raise OffdynError(f"{xml_path}: joint {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)!r} is "
                              "not a hinge or slide joint; the DART backend supports planar chains of those only")
    for a in range(model.nu):
        if (int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT)
                or int(model.actuator_gaintype[a]) != int(mujoco.mjtGain.mjGAIN_FIXED)
                or int(model.actuator_biastype[a]) != int(mujoco.mjtBias.mjBIAS_NONE)
                or int(model.actuator_dyntype[a]) != int(mujoco.mjtDyn.mjDYN_NONE)):
            raise OffdynError(f"{xml_path}: actuator {a} is not a joint motor; the DART backend supports "
                              "<motor joint=...> actuators only")


def build_dart_world(xml_path: str, model: mujoco.MjModel, collision_detector: str = "ode",
                     emulate_armature: bool = True) -> DartWorld:
    """Parse ``xml_path`` with DART's MJCF parser and align it with ``model`` (the same file
    compiled by MuJoCo); see the module docstring for every correction."""
    import dartpy

    _check_supported(model, xml_path)
    detector = _detector(collision_detector)
    with _captured_stderr() as messages:
        try:
            world = dartpy.utils.MjcfParser.readWorld(dartpy.common.Uri.createFromPath(os.path.abspath(xml_path)))
        except Exception as exc:  # pybind raises RuntimeError subclasses; say which file and why
            raise OffdynError(f"DART's MJCF parser could not read {xml_path}: {exc}") from exc
    if world is None:
        raise OffdynError(f"DART's MJCF parser could not read {xml_path}: " + " | ".join(messages[-3:]))

    skeletons = [world.getSkeleton(i) for i in range(world.getNumSkeletons())]
    robots = [s for s in skeletons if s.getNumDofs() > 0]
    floors = [s for s in skeletons if s.getName().startswith(GROUND_PREFIX)]
    if len(robots) != 1 or len(floors) != 1:
        raise OffdynError(f"{xml_path}: expected one articulated robot and one floor geom in the DART world, got "
                          f"{[s.getName() for s in skeletons]}")
    robot, floor = robots[0], floors[0]

    joint_names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
    dart_names = [robot.getDof(i).getName() for i in range(robot.getNumDofs())]
    missing = [n for n in joint_names if n not in dart_names]
    if missing or len(dart_names) != model.nv:
        raise OffdynError(f"{xml_path}: DART's parser produced dofs {dart_names}, MuJoCo joints {joint_names}")
    dof_indices = np.array([dart_names.index(n) for n in joint_names])

    world.setTimeStep(float(model.opt.timestep))
    world.setGravity(np.array(model.opt.gravity))
    world.getConstraintSolver().setCollisionDetector(detector)

    armature_damping = np.zeros(robot.getNumDofs())
    if emulate_armature:
        armature_damping[dof_indices] = model.dof_armature / model.opt.timestep
    _absorb_reference_positions(model, robot, joint_names)
    for j, name in enumerate(joint_names):
        dof = robot.getDof(int(dof_indices[j]))
        dof.setDampingCoefficient(float(model.dof_damping[j]) + float(armature_damping[dof_indices[j]]))
        dof.setCoulombFriction(float(model.dof_frictionloss[j]))
        dof.setSpringStiffness(float(model.jnt_stiffness[j]))
        dof.setRestPosition(float(model.qpos_spring[model.jnt_qposadr[j]]))
        if model.jnt_limited[j]:
            low, high = model.jnt_range[j]
            dof.setPositionLimits((float(low), float(high)))
            robot.getJoint(name).setLimitEnforcement(True)  # the parser names 1-dof joints as their dof
        else:
            dof.setPositionLimits((-np.inf, np.inf))

    for b in range(1, model.nbody):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
        node = robot.getBodyNode(name)
        if node is None:
            raise OffdynError(f"{xml_path}: body {name!r} is missing from DART's world")
        rotation = np.empty(9)
        mujoco.mju_quat2Mat(rotation, model.body_iquat[b])
        rotation = rotation.reshape(3, 3)
        node.setMass(float(model.body_mass[b]))
        node.setLocalCOM(np.array(model.body_ipos[b]))
        node.setMomentOfInertia(*_moment_entries(rotation @ np.diag(model.body_inertia[b]) @ rotation.T))

    _align_contacts(model, robot, floor, xml_path)
    _check_kinematics(model, robot, dof_indices, xml_path)

    actuator_dofs = np.array([dof_indices[model.actuator_trnid[a, 0]] for a in range(model.nu)], dtype=int)
    ctrl_range = np.where(model.actuator_ctrllimited[:, None].astype(bool), model.actuator_ctrlrange,
                          np.array([-np.inf, np.inf]))
    return DartWorld(world=world, robot=robot, dof_indices=dof_indices,
                     actuator_dofs=actuator_dofs, gear=np.array(model.actuator_gear[:, 0]), ctrl_range=ctrl_range,
                     collision_detector=collision_detector, armature_damping=armature_damping)


def _absorb_reference_positions(model: mujoco.MjModel, robot, joint_names: list[str]) -> None:
    """The parser measures a joint from its MJCF ``ref`` (Hopper's ``rootz`` starts at 0 in DART,
    1.25 in MuJoCo). Moving ``ref`` into the joint's parent frame makes DART's coordinates MuJoCo's,
    so states convert without a rounding step."""
    import dartpy

    for j, name in enumerate(joint_names):
        ref = float(model.qpos0[model.jnt_qposadr[j]])
        if ref == 0.0:
            continue
        joint = robot.getJoint(name)
        axis = np.asarray(joint.getAxis(), dtype=float)
        offset = dartpy.math.Isometry3()
        if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_SLIDE):
            offset.set_translation(-ref * axis)
        else:
            offset.set_rotation(dartpy.math.AngleAxis(-ref, axis).to_rotation_matrix())
        joint.setTransformFromParentBodyNode(joint.getTransformFromParentBodyNode().multiply(offset))


def _moment_entries(inertia: np.ndarray) -> tuple[float, ...]:
    """DART's ``setMomentOfInertia(Ixx, Iyy, Izz, Ixy, Ixz, Iyz)`` from a symmetric matrix."""
    return (float(inertia[0, 0]), float(inertia[1, 1]), float(inertia[2, 2]),
            float(inertia[0, 1]), float(inertia[0, 2]), float(inertia[1, 2]))


def _align_contacts(model: mujoco.MjModel, robot, floor, xml_path: str) -> None:
    import dartpy

    floor_geoms = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    if len(floor_geoms) != 1:
        raise OffdynError(f"{xml_path}: expected one plane geom as the floor, found {len(floor_geoms)}")
    floor_geom = floor_geoms[0]
    floor_friction = float(model.geom_friction[floor_geom, 0])

    contact_frictions = []
    self_collision = False
    for g in range(model.ngeom):
        if g == floor_geom:
            continue
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g)
        node = robot.getBodyNode(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g]))
        shapes = {s.getName(): s for s in node.getShapeNodes()}
        if name not in shapes:
            raise OffdynError(f"{xml_path}: geom {name!r} is missing from DART's world")
        friction = max(float(model.geom_friction[g, 0]), floor_friction)  # MuJoCo's rule: the larger one
        shapes[name].getDynamicsAspect().setFrictionCoeff(friction)
        contact_frictions.append(friction)
        for other in range(g + 1, model.ngeom):
            if other != floor_geom and model.geom_bodyid[other] != model.geom_bodyid[g] and (
                    model.geom_contype[g] & model.geom_conaffinity[other]
                    or model.geom_contype[other] & model.geom_conaffinity[g]):
                self_collision = True
    if self_collision:
        robot.enableSelfCollisionCheck()
        robot.disableAdjacentBodyCheck()  # MuJoCo filters parent-child contacts the same way

    floor_node = floor.getBodyNode(0)
    floor_node.removeAllShapeNodes()
    box = dartpy.dynamics.BoxShape(np.array([2 * FLOOR_HALF_WIDTH, 2 * FLOOR_HALF_WIDTH, FLOOR_THICKNESS]))
    transform = dartpy.math.Isometry3()
    transform.set_translation(np.array([0.0, 0.0, -FLOOR_THICKNESS / 2]))
    shape_node = floor_node.createShapeNode(box, "floor")
    shape_node.setRelativeTransform(transform)
    shape_node.createCollisionAspect()
    shape_node.createDynamicsAspect().setFrictionCoeff(max(contact_frictions, default=floor_friction))


def _check_kinematics(model: mujoco.MjModel, robot, dof_indices: np.ndarray, xml_path: str) -> None:
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    data.qpos[:] = model.qpos0 + rng.uniform(-0.3, 0.3, model.nq)
    mujoco.mj_kinematics(model, data)
    positions = np.zeros(robot.getNumDofs())
    positions[dof_indices] = data.qpos
    saved = np.asarray(robot.getPositions()).copy()
    robot.setPositions(positions)
    try:
        for b in range(1, model.nbody):
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
            transform = robot.getBodyNode(name).getWorldTransform()
            offset = max(np.abs(transform.translation() - data.xpos[b]).max(),
                         np.abs(transform.rotation() - data.xmat[b].reshape(3, 3)).max())
            if offset > KINEMATIC_TOLERANCE:
                raise OffdynError(f"{xml_path}: DART places body {name!r} {offset:.3g} away from MuJoCo's pose; "
                                  "the two engines would not simulate the same robot")
    finally:
        robot.setPositions(saved)
