"""Target data from an independently written model: DeepMind Control Suite's ``cheetah`` as the
target of Gymnasium's ``HalfCheetah-v5``.

Every other diagnosis test measures a target that is the source plus declared effects, so the
vocabulary can always explain it. dm-control's cheetah was written separately from Gymnasium's
half_cheetah.xml: the same robot (joints, root coordinates and actuators map one to one, which
:func:`check_mapping` asserts), with parameters that nobody chose to match an effect.

- :func:`dm_cheetah_model`: dm-control's cheetah compiled with ``mujoco`` directly;
- :func:`record_target`: transitions of a target model under HalfCheetah-v5's reset distribution,
  control interval and observation, as the diagnosis ``.npz`` arrays;
- :func:`non_geometric_copy`: HalfCheetah-v5 with dm's non-geometric parameters copied in;
- :func:`model_differences`: every parameter difference between two compiled models;
- :func:`true_difference_effects`: those differences set by hand in the effect vocabulary, and
  :func:`account_for_differences`: what each difference is (an effect, or why there is none);
- :func:`hand_set_errors`: the diagnosis evaluator's errors for the stock source, the hand-set
  hypothesis and the exact target model.

Ground truth: ``model_differences()`` with MuJoCo 3.17.0 and dm-control 1.0.50, "HalfCheetah-v5
value -> dm cheetah value", names as in HalfCheetah-v5 (dm calls the floor ``ground``), angles in
rad, quaternions with a non-negative first component. Derived constants the compiler computes
from these (``body_subtreemass``, ``*_invweight0``, ``dof_M0``, ``actuator_acc0``, ``stat``, ...)
are left out; ``model_differences(include_derived=True)`` lists them too. The tests compare the
function with this list line by line::

    # begin ground truth
    ncam: 1 -> 2
    nmat: 2 -> 13
    ntex: 3 -> 2
    nsensor: 0 -> 1
    nuser_geom: 1 -> 0
    narena: 6291456 -> 13631488
    body_inertia[torso]: [0.897118 0.885655 0.0179609] -> [0.897118 0.885697 0.0179193]
    body_iquat[torso]: [0.52243 0.476516 0.476516 0.52243] -> [0.522426 0.47652 0.47652 0.522426]
    body_iquat[bthigh]: [0.32329 0 0.9463 0] -> [0.325568 0 0.945519 0]
    body_iquat[bshin]: [0.52762 0 -0.849481 0] -> [0.529919 0 -0.848048 0]
    body_iquat[bfoot]: [0.990901 0 -0.13459 0] -> [0.991445 0 -0.130526 0]
    body_iquat[fthigh]: [0.96639 0 0.257081 0] -> [0.965926 0 0.258819 0]
    body_iquat[fshin]: [0.955336 0 -0.29552 0] -> [0.956305 0 -0.292372 0]
    body_iquat[ffoot]: [0.955336 0 -0.29552 0] -> [0.956305 0 -0.292372 0]
    jnt_range[bthigh]: [-0.52 1.05] -> [-0.523599 1.0472]
    jnt_range[bshin]: [-0.785 0.785] -> [-0.872665 0.872665]
    jnt_range[bfoot]: [-0.4 0.785] -> [-4.01426 0.872665]
    jnt_range[fthigh]: [-1 0.7] -> [-0.994838 0.00698132]
    jnt_range[fshin]: [-1.2 0.87] -> [-1.22173 0.872665]
    jnt_range[ffoot]: [-0.5 0.5] -> [-0.488692 0.488692]
    jnt_solimp[rootx]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[rootz]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[rooty]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[bthigh]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[bshin]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[bfoot]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[fthigh]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[fshin]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    jnt_solimp[ffoot]: [0 0.8 0.03 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_conaffinity[torso]: 0 -> 1
    geom_conaffinity[head]: 0 -> 1
    geom_conaffinity[bthigh]: 0 -> 1
    geom_conaffinity[bshin]: 0 -> 1
    geom_conaffinity[bfoot]: 0 -> 1
    geom_conaffinity[fthigh]: 0 -> 1
    geom_conaffinity[fshin]: 0 -> 1
    geom_conaffinity[ffoot]: 0 -> 1
    geom_friction[floor]: [0.4 0.1 0.1] -> [1 0.005 0.0001]
    geom_pos[floor]: [0 0 0] -> [98 0 0]
    geom_quat[head]: [0.90687 0 0.42141 0] -> [0.906308 0 0.422618 0]
    geom_quat[bthigh]: [0.32329 0 0.9463 0] -> [0.325568 0 0.945519 0]
    geom_quat[bshin]: [0.52762 0 -0.849481 0] -> [0.529919 0 -0.848048 0]
    geom_quat[bfoot]: [0.990901 0 -0.13459 0] -> [0.991445 0 -0.130526 0]
    geom_quat[fthigh]: [0.96639 0 0.257081 0] -> [0.965926 0 0.258819 0]
    geom_quat[fshin]: [0.955336 0 -0.29552 0] -> [0.956305 0 -0.292372 0]
    geom_quat[ffoot]: [0.955336 0 -0.29552 0] -> [0.956305 0 -0.292372 0]
    geom_size[floor]: [40 40 40] -> [100 0.8 0.5]
    geom_solimp[floor]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[torso]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[head]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[bthigh]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[bshin]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[bfoot]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[fthigh]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[fshin]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_solimp[ffoot]: [0 0.8 0.01 0.5 2] -> [0.9 0.95 0.001 0.5 2]
    geom_user: shape (9, 1) -> (9, 0)
    actuator_gear[fthigh]: [120 0 0 0 0 0] -> [90 0 0 0 0 0]
    # end ground truth

What the lines mean for the dynamics (:func:`account_for_differences` says it per line):

- the floor's sliding friction is 1.0 in dm (its ``ground`` lies outside the ``cheetah`` default
  class and takes MuJoCo's default friction ``1 0.005 0.0001``), 0.4 in Gymnasium: a contact
  takes the larger of its two geoms' frictions, so every foot contact slides 2.5 times harder.
  The torsional and rolling parts differ too but no contact uses them (condim 3 everywhere);
- the front thigh's gear is 90 in dm, 120 in Gymnasium;
- contacts: Gymnasium sets ``solimp="0 .8 .01"`` on every geom, dm keeps MuJoCo's default
  ``0.9 0.95 0.001``: far stiffer contacts;
- joint limits: dm gives ranges in degrees (bfoot's lower limit is -230 deg: practically none;
  fthigh's upper limit is 0.4 deg instead of 0.7 rad), and keeps MuJoCo's default limit impedance
  ``0.9 0.95 0.001`` where Gymnasium sets the very soft ``0 .8 .03``;
- dm sets ``conaffinity=1`` on every body geom, so the legs and the torso collide with each other;
  Gymnasium's body geoms only collide with the floor;
- geom orientations: dm writes the capsules' angles in whole degrees (``euler="0 -218 0"``),
  Gymnasium in rounded radians (``axisangle="0 1 0 -3.8"``): up to 0.01 rad apart, which moves
  where a foot touches the floor. The bodies' principal inertia axes (``body_iquat``) and the
  torso's principal moments (through the head) follow, but no body's moment about y changes, and
  that is the only one a planar robot feels;
- the floor's position and size, cameras, lights, the sensor, materials, ``nuser_geom`` and the
  ``nstack`` memory size change nothing in the dynamics (a plane is infinite for collision).

Masses, joint damping, armature, stiffness, body positions, geom sizes, the timestep (0.01 s),
integrator (Euler), solver and every other ``opt`` field are the same.

What the gap is made of, measured with :func:`hand_set_errors` on ``record_target(dm, 2000,
seed=0)`` (held-out one-step normalized RMSE): stock source 0.466; with the hand-set effects
0.0745; adding dm's joint-limit solimp as well 0.036, dm's geom angles instead 0.067, both
7e-16 (the exact model). dm's self-collisions change nothing in this data: the robot's own geoms
never touch under this behaviour policy.
"""

from __future__ import annotations

import copy
import math
import numbers
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium.utils import seeding

from offdyn_bench.diagnose import DiagnosisSettings, Transitions
from offdyn_bench.diagnose.residual import Hypothesis, ResidualEvaluator
from offdyn_bench.diagnose.source import FULL_PHYSICS, SourceSimulator
from offdyn_bench.effects import Effect
from offdyn_bench.effects.model import ModelEffect
from offdyn_bench.errors import OffdynError

ENV_ID = "HalfCheetah-v5"
CONTROL_INTERVAL = 0.05
"""Seconds per control step: HalfCheetah-v5's timestep 0.01 s x frame_skip 5."""
EPISODE_STEPS = 200
RESET_NOISE_SCALE = 0.1
"""HalfCheetah-v5's ``reset_noise_scale``: qpos = qpos0 + U(-0.1, 0.1), qvel ~ N(0, 0.1)."""

# The one object whose name differs between the two files (Gymnasium's name -> dm's).
_DM_NAME = {"floor": "ground"}


class CrossModelError(OffdynError):
    """A model that cannot stand in for HalfCheetah-v5, or bad arguments to this module."""


def ground_truth() -> tuple[str, ...]:
    """The differences this module's docstring lists: what :func:`model_differences` must return."""
    text = __doc__ or ""
    start, end = "# begin ground truth", "# end ground truth"
    block = text[text.index(start) + len(start):text.index(end)]
    return tuple(line.strip() for line in block.strip().splitlines())


# --- the two models ---------------------------------------------------------------------------

def _quiet_compile(build: Any) -> mujoco.MjModel:
    # Both files use the deprecated ``settotalmass``; the warning is theirs to fix.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*settotalmass.*")
        return build()


def gymnasium_model() -> mujoco.MjModel:
    """A copy of the model HalfCheetah-v5 builds (the source of every test here)."""
    env = gymnasium.make(ENV_ID)
    try:
        return copy.copy(env.unwrapped.model)
    finally:
        env.close()


def dm_cheetah_model() -> mujoco.MjModel:
    """dm-control's cheetah (``dm_control.suite.cheetah.get_model_and_assets()``) compiled with
    ``mujoco`` directly; raises :class:`CrossModelError` if it does not map onto HalfCheetah-v5."""
    from dm_control.suite import cheetah

    xml, assets = cheetah.get_model_and_assets()
    model = _quiet_compile(lambda: mujoco.MjModel.from_xml_string(xml.decode(), assets))
    check_mapping(model)
    return model


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int) -> str:
    return mujoco.mj_id2name(model, kind, index) or ""


def frame_skip(model: mujoco.MjModel) -> int:
    """Physics steps per control step that give ``model`` the 0.05 s control interval."""
    timestep = float(model.opt.timestep)
    skip = round(CONTROL_INTERVAL / timestep)
    if skip < 1 or abs(skip * timestep - CONTROL_INTERVAL) > 1e-12:
        raise CrossModelError(f"timestep {timestep:g} s does not divide HalfCheetah-v5's control interval of "
                              f"{CONTROL_INTERVAL} s; expected a timestep of 0.05 s / n for a whole n")
    return skip


def check_mapping(model: mujoco.MjModel, reference: mujoco.MjModel | None = None) -> int:
    """Assert that ``model`` has HalfCheetah-v5's state and action layout: the same joints (name,
    type, axis with its sign, anchor) at the same qpos/qvel addresses on the same bodies, the root
    coordinates rootx/rootz/rooty measured from the same torso frame, the same reset pose, and the
    same actuators (name, joint, control range, a motor whose torque has the gear's sign) in the
    same order. Returns the frame skip of the 0.05 s control interval. Gears may differ: that is a
    parameter, not a mapping."""
    ref = gymnasium_model() if reference is None else reference

    def mismatch(what: str, got: object, expected: object) -> CrossModelError:
        return CrossModelError(f"the model does not map onto {ENV_ID}: {what} is {got}, expected {expected}")

    for count in ("nq", "nv", "nu", "njnt", "nbody"):
        if getattr(model, count) != getattr(ref, count):
            raise mismatch(count, getattr(model, count), getattr(ref, count))
    for b in range(ref.nbody):
        name, expected = _name(model, mujoco.mjtObj.mjOBJ_BODY, b), _name(ref, mujoco.mjtObj.mjOBJ_BODY, b)
        if b and name != expected:
            raise mismatch(f"body {b}", repr(name), repr(expected))
        if model.body_parentid[b] != ref.body_parentid[b]:
            raise mismatch(f"the parent of body {expected!r}", model.body_parentid[b], ref.body_parentid[b])
    for j in range(ref.njnt):
        joint = _name(ref, mujoco.mjtObj.mjOBJ_JOINT, j)
        if _name(model, mujoco.mjtObj.mjOBJ_JOINT, j) != joint:
            raise mismatch(f"joint {j}", repr(_name(model, mujoco.mjtObj.mjOBJ_JOINT, j)), repr(joint))
        for field in ("jnt_type", "jnt_qposadr", "jnt_dofadr", "jnt_bodyid", "jnt_axis", "jnt_pos"):
            if not np.array_equal(getattr(model, field)[j], getattr(ref, field)[j]):
                raise mismatch(f"{field} of joint {joint!r}", getattr(model, field)[j], getattr(ref, field)[j])
    # The root joints' qpos is measured from the torso's frame: the same frame means the same meaning.
    for b in ref.jnt_bodyid[ref.jnt_limited == 0]:
        for field in ("body_pos", "body_quat"):
            if not np.array_equal(getattr(model, field)[b], getattr(ref, field)[b]):
                raise mismatch(f"{field} of the root body", getattr(model, field)[b], getattr(ref, field)[b])
    if not np.array_equal(model.qpos0, ref.qpos0):
        raise mismatch("qpos0 (the reset pose)", model.qpos0, ref.qpos0)
    for a in range(ref.nu):
        actuator = _name(ref, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
        if _name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) != actuator:
            raise mismatch(f"actuator {a}", repr(_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)), repr(actuator))
        for field in ("actuator_trntype", "actuator_trnid", "actuator_ctrllimited", "actuator_ctrlrange",
                      "actuator_gaintype", "actuator_biastype", "actuator_dyntype"):
            if not np.array_equal(getattr(model, field)[a], getattr(ref, field)[a]):
                raise mismatch(f"{field} of actuator {actuator!r}", getattr(model, field)[a], getattr(ref, field)[a])
        if not np.array_equal(np.sign(model.actuator_gear[a]), np.sign(ref.actuator_gear[a])):
            raise mismatch(f"the gear's sign of actuator {actuator!r}", model.actuator_gear[a], ref.actuator_gear[a])
    return frame_skip(model)


# --- recording ----------------------------------------------------------------------------------

def observation(data: mujoco.MjData) -> np.ndarray:
    """HalfCheetah-v5's observation with its defaults (``exclude_current_positions_from_observation``):
    qpos without rootx, then qvel."""
    return np.concatenate([data.qpos[1:], data.qvel])


def _whole(value: object, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        raise CrossModelError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def record_target(model: mujoco.MjModel, steps: int, seed: int,
                  episode_steps: int = EPISODE_STEPS) -> dict[str, np.ndarray]:
    """Roll ``model`` (any model with HalfCheetah-v5's layout) for ``steps`` control steps in
    episodes of ``episode_steps``; return the arrays of the diagnosis ``.npz`` contract.

    As HalfCheetah-v5 does: episode ``k`` resets with Gymnasium's generator seeded
    ``seed * 10_000 + k`` (the state ``env.reset(seed=seed * 10_000 + k)`` draws), each action is
    held for :func:`frame_skip` ``mujoco.mj_step`` calls (clipped to the control range), and the
    observation is qpos[1:] and qvel. The behaviour policy adds uniform jumps to a slow sine per
    actuator, so every actuator sweeps its whole range. No noise; the same seed gives the same
    arrays. ``qpos``/``qvel`` are the state before each step; nothing terminates.
    """
    steps = _whole(steps, "steps", 1)
    seed = _whole(seed, "seed", 0)
    episode_steps = _whole(episode_steps, "episode_steps", 1)
    skip = check_mapping(model)
    data = mujoco.MjData(model)
    policy = np.random.default_rng(seed)
    low, high = model.actuator_ctrlrange.T
    columns: dict[str, list[Any]] = {k: [] for k in ("observations", "actions", "next_observations",
                                                    "terminations", "truncations", "qpos", "qvel")}
    episode = 0
    while len(columns["actions"]) < steps:
        reset, _ = seeding.np_random(seed * 10_000 + episode)
        mujoco.mj_resetData(model, data)
        data.qpos[:] = model.qpos0 + reset.uniform(-RESET_NOISE_SCALE, RESET_NOISE_SCALE, model.nq)
        data.qvel[:] = RESET_NOISE_SCALE * reset.standard_normal(model.nv)
        mujoco.mj_forward(model, data)
        phase = policy.uniform(0, 2 * np.pi, model.nu)
        frequency = policy.uniform(0.05, 0.3, model.nu)
        for t in range(episode_steps):
            action = np.clip(0.6 * np.sin(frequency * t + phase) + policy.uniform(-0.7, 0.7, model.nu), low, high)
            columns["qpos"].append(data.qpos.copy())
            columns["qvel"].append(data.qvel.copy())
            columns["observations"].append(observation(data))
            data.ctrl[:] = action
            mujoco.mj_step(model, data, nstep=skip)
            columns["actions"].append(action)
            columns["next_observations"].append(observation(data))
            last = t == episode_steps - 1 or len(columns["actions"]) >= steps
            columns["terminations"].append(False)
            columns["truncations"].append(last)
            if last:
                break
        episode += 1
    return {k: np.asarray(v, dtype=bool if k in ("terminations", "truncations") else float)
            for k, v in columns.items()}


# --- the second target: only non-geometric parameters differ -----------------------------------

NON_GEOMETRIC_FIELDS = ("body_mass", "body_inertia", "actuator_gear", "geom_friction", "dof_damping", "dof_armature")


def non_geometric_copy() -> mujoco.MjModel:
    """HalfCheetah-v5's model with dm cheetah's body masses and (principal) inertias, actuator
    gears, geom frictions, dof damping and armature copied in, object by object by name.

    Of these only three differ (see the module's ground truth): the front thigh's gear (120 ->
    90), the floor's friction (0.4 0.1 0.1 -> 1 0.005 0.0001: sliding x2.5) and the torso's
    principal moments about x and z (by under 0.3%, from dm's head angle; its moment about y, the
    only one the planar robot feels, is the same). Masses, damping and armature are equal.
    Geometry, contact and joint-limit parameters stay Gymnasium's, so ``gear`` and ``friction``
    reproduce this target exactly.
    """
    target = dm_cheetah_model()
    model = gymnasium_model()
    for field in NON_GEOMETRIC_FIELDS:
        kind = field.split("_")[0]
        mine, theirs = getattr(model, field), getattr(target, field)
        for i, j in _matched(model, target, kind):
            mine[i] = theirs[j]
    mujoco.mj_setConst(model, mujoco.MjData(model))
    return model


# --- every difference -------------------------------------------------------------------------

_OBJECT_TYPES = {"body": mujoco.mjtObj.mjOBJ_BODY, "jnt": mujoco.mjtObj.mjOBJ_JOINT,
                 "geom": mujoco.mjtObj.mjOBJ_GEOM, "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR}
_COUNTS = {"body": "nbody", "jnt": "njnt", "dof": "nv", "geom": "ngeom", "actuator": "nu"}
_QUATERNIONS = ("body_quat", "body_iquat", "geom_quat")

# Addresses, ids and sizes of the model's own tables: they say where a value is stored, not what it is.
BOOKKEEPING = frozenset({
    "body_bvhadr", "body_bvhnum", "body_dofadr", "body_dofnum", "body_geomadr", "body_geomnum", "body_jntadr",
    "body_jntnum", "body_mocapid", "body_parentid", "body_plugin", "body_rootid", "body_treeid", "body_weldid",
    "jnt_actuatorid", "jnt_bodyid", "jnt_dofadr", "jnt_qposadr", "dof_Madr", "dof_bodyid", "dof_jntid",
    "dof_parentid", "dof_treeid", "geom_bodyid", "geom_dataid", "geom_matid", "geom_plugin", "actuator_actadr",
    "actuator_actnum", "actuator_ctrladr", "actuator_ctrlnum", "actuator_historyadr", "actuator_outadr",
    "actuator_outnum", "actuator_plugin", "actuator_trnid",
})
# Constants the compiler (and mj_setConst) computes from the parameters.
DERIVED = frozenset({
    "body_subtreemass", "body_invweight0", "body_sameframe", "body_simple", "body_margin", "body_contype",
    "body_conaffinity", "dof_M0", "dof_invweight0", "dof_simplenum", "dof_length", "geom_aabb", "geom_rbound",
    "geom_sameframe", "actuator_acc0", "actuator_length0",
})
# Colours and visibility groups: what a renderer draws, never what the physics does.
RENDERING = frozenset({"geom_rgba", "geom_group", "jnt_group", "actuator_group"})
_COUNT_FIELDS = ("nq", "nv", "nu", "na", "nbody", "njnt", "ngeom", "nsite", "ncam", "nlight", "nmesh", "nhfield",
                 "nmat", "ntex", "npair", "nexclude", "neq", "ntendon", "nsensor", "nkey", "nflex", "nskin", "nnumeric",
                 "ntext", "ntuple", "nplugin", "nmocap", "nuserdata", "nuser_body", "nuser_jnt", "nuser_geom",
                 "nuser_site", "nuser_cam", "nuser_tendon", "nuser_actuator", "nuser_sensor", "nconmax", "njmax",
                 "narena")


def model_fields(model: mujoco.MjModel) -> dict[str, list[str]]:
    """Every per-object field of bodies, joints, dofs, geoms and actuators, by object kind."""
    names = [n for n in dir(model) if not n.startswith("_")]
    return {kind: sorted(n for n in names if n.startswith(kind + "_")) for kind in _COUNTS}


def _matched(model: mujoco.MjModel, other: mujoco.MjModel, kind: str) -> list[tuple[int, int]]:
    """Index pairs of the same object in both models, matched by name (dofs by their joint)."""
    if kind == "dof":
        return [(d, d) for d in range(model.nv)]  # check_mapping pins the dof layout
    matched = []
    for i in range(getattr(model, _COUNTS[kind])):
        name = _name(model, _OBJECT_TYPES[kind], i)
        j = mujoco.mj_name2id(other, _OBJECT_TYPES[kind], name)
        if j < 0 and name in _DM_NAME:
            j = mujoco.mj_name2id(other, _OBJECT_TYPES[kind], _DM_NAME[name])
        if j < 0:
            raise CrossModelError(f"{kind} {name!r} of {ENV_ID} has no counterpart in the other model")
        matched.append((i, j))
    return matched


def _label(model: mujoco.MjModel, kind: str, index: int) -> str:
    if kind == "dof":
        return _name(model, mujoco.mjtObj.mjOBJ_JOINT, int(model.dof_jntid[index]))
    return _name(model, _OBJECT_TYPES[kind], index)


def _canonical(field: str, value: np.ndarray) -> np.ndarray:
    value = np.asarray(value, dtype=float).ravel()
    if field in _QUATERNIONS:  # q and -q are the same rotation
        nonzero = value[np.abs(value) > 1e-12]
        if nonzero.size and nonzero[0] < 0:
            value = -value
    return value + 0.0  # no "-0"


def _shown(value: object) -> str:
    if isinstance(value, np.ndarray) and value.size != 1:
        return "[" + " ".join(f"{v:.6g}" for v in value.ravel()) + "]"
    number = np.asarray(value).item()
    return f"{number:.6g}" if isinstance(number, float) else str(number)


def _differs(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape != b.shape or not np.allclose(a, b, rtol=1e-9, atol=1e-12)


def model_differences(target: mujoco.MjModel | None = None, *, source: mujoco.MjModel | None = None,
                      include_derived: bool = False) -> list[str]:
    """Every parameter difference between ``source`` (HalfCheetah-v5 by default) and ``target``
    (dm cheetah by default), one readable line each: ``field[object]: source value -> target value``.

    Compared: every per-object field of bodies, joints, dofs, geoms and actuators (objects matched
    by name) except table addresses (:data:`BOOKKEEPING`), derived constants (:data:`DERIVED`,
    listed with ``include_derived``) and colours (:data:`RENDERING`); every ``opt`` field;
    ``qpos0``/``qpos_spring``; and the number of each kind of object.
    """
    source = gymnasium_model() if source is None else source
    target = dm_cheetah_model() if target is None else target
    check_mapping(target, source)
    lines: list[str] = []
    for count in _COUNT_FIELDS:
        if getattr(source, count) != getattr(target, count):
            lines.append(f"{count}: {getattr(source, count)} -> {getattr(target, count)}")
    for field in sorted(f for f in dir(source.opt) if not f.startswith("_")):
        a, b = getattr(source.opt, field), getattr(target.opt, field)
        if callable(a):
            continue
        if _differs(np.atleast_1d(np.asarray(a, dtype=float)), np.atleast_1d(np.asarray(b, dtype=float))):
            lines.append(f"opt.{field}: {_shown(np.asarray(a))} -> {_shown(np.asarray(b))}")
    for field in ("qpos0", "qpos_spring"):
        if _differs(getattr(source, field), getattr(target, field)):
            lines.append(f"{field}: {_shown(getattr(source, field))} -> {_shown(getattr(target, field))}")
    skipped = BOOKKEEPING | RENDERING | (frozenset() if include_derived else DERIVED)
    for kind, fields in model_fields(source).items():
        pairs = _matched(source, target, kind)
        for field in fields:
            if field in skipped:
                continue
            mine, theirs = getattr(source, field), getattr(target, field)
            if mine.shape[1:] != theirs.shape[1:]:
                lines.append(f"{field}: shape {mine.shape} -> {theirs.shape}")
                continue
            for i, j in pairs:
                a, b = _canonical(field, mine[i]), _canonical(field, theirs[j])
                if _differs(a, b):
                    lines.append(f"{field}[{_label(source, kind, i)}]: {_shown(a)} -> {_shown(b)}")
    if include_derived:
        for field in ("meaninertia", "meanmass", "meansize", "extent", "center"):
            a, b = np.atleast_1d(getattr(source.stat, field)), np.atleast_1d(getattr(target.stat, field))
            if _differs(a, b):
                lines.append(f"stat.{field}: {_shown(a)} -> {_shown(b)}")
    return lines


# --- the differences set by hand ----------------------------------------------------------------

def _joint_limit_effects(source: mujoco.MjModel, target: mujoco.MjModel) -> list[dict[str, Any]]:
    """Effects that move each joint limit of ``source`` to ``target``'s: one ``joint_range``
    where both limits scale alike about the reference position, else a ``joint_limit`` shift
    per side that moves."""
    effects: list[dict[str, Any]] = []
    for j in np.flatnonzero(source.jnt_limited):
        joint = _name(source, mujoco.mjtObj.mjOBJ_JOINT, j)
        (low, high), (new_low, new_high) = source.jnt_range[j], target.jnt_range[j]
        if not _differs(source.jnt_range[j], target.jnt_range[j]):
            continue
        ref = float(np.clip(source.qpos0[source.jnt_qposadr[j]], low, high))
        scales = [(new - ref) / (old - ref) if old != ref else math.nan for old, new in ((low, new_low), (high, new_high))]
        if math.isclose(scales[0], scales[1], rel_tol=1e-9):
            effects.append({"kind": "joint_range", "target": joint, "scale": float(scales[0])})
            continue
        for side, old, new in (("lower", low, new_low), ("upper", high, new_high)):
            if not math.isclose(old, new, rel_tol=1e-9, abs_tol=1e-12):
                effects.append({"kind": "joint_limit", "target": joint, "side": side, "shift": float(new - old)})
    return effects


def true_difference_effects(target: mujoco.MjModel | None = None) -> list[dict[str, Any]]:
    """Effect dicts that, applied to HalfCheetah-v5, reproduce ``target`` (dm cheetah by default)
    as closely as the effect vocabulary allows: the true differences set by hand.

    Computed from the two models: a ``gear`` scale per actuator whose gear differs, a ``friction``
    scale per geom whose sliding friction differs (only sliding counts: every geom has condim 3),
    one ``contact_solimp`` when the target's geoms share one impedance that differs from the
    source's, and per joint whose range differs a ``joint_range`` scale (both limits scale alike
    about the reference pose) or a ``joint_limit`` shift per side. For dm cheetah: gear fthigh
    x0.75, friction floor x2.5, contact_solimp (0.9, 0.95, 0.001, 0.5, 2), joint_range on bshin
    and ffoot, joint_limit on both sides of bthigh, bfoot, fthigh and fshin. What no effect
    expresses is in :func:`account_for_differences`: the joint limits' solimp, the geoms'
    angles and the self-collisions.
    """
    source = gymnasium_model()
    target = dm_cheetah_model() if target is None else target
    check_mapping(target, source)
    effects: list[dict[str, Any]] = []
    for a, b in _matched(source, target, "actuator"):
        old, new = float(source.actuator_gear[a, 0]), float(target.actuator_gear[b, 0])
        if not math.isclose(old, new, rel_tol=1e-12):
            effects.append({"kind": "gear", "target": _name(source, mujoco.mjtObj.mjOBJ_ACTUATOR, a), "scale": new / old})
    if np.any(source.geom_condim != 3) or np.any(target.geom_condim != 3):
        raise CrossModelError("expected condim 3 (sliding friction only) on every geom of both models")
    for g, h in _matched(source, target, "geom"):
        old, new = float(source.geom_friction[g, 0]), float(target.geom_friction[h, 0])
        if not math.isclose(old, new, rel_tol=1e-12):
            effects.append({"kind": "friction", "target": _name(source, mujoco.mjtObj.mjOBJ_GEOM, g), "scale": new / old})
    solimp = np.unique(target.geom_solimp, axis=0)
    if len(solimp) == 1 and _differs(source.geom_solimp, np.repeat(solimp, source.ngeom, axis=0)):
        dmin, dmax, width, midpoint, power = (float(x) for x in solimp[0])
        effects.append({"kind": "contact_solimp", "target": None, "dmin": dmin, "dmax": dmax, "width": width,
                        "midpoint": midpoint, "power": power})
    effects.extend(_joint_limit_effects(source, target))
    for effect in effects:  # each one must be valid in the vocabulary
        Effect.from_dict(effect)
    return effects


# Why a difference has no effect, by field (or "field[object]" where the object matters).
_NO_DYNAMICS = {
    "geom_pos[floor]": "no effect on the dynamics: a plane is infinite for collision",
    "geom_size[floor]": "no effect on the dynamics: a plane's size only sets how it is drawn",
    "ncam": "no effect on the dynamics: cameras are for rendering",
    "nlight": "no effect on the dynamics: lights are for rendering",
    "nmat": "no effect on the dynamics: materials are for rendering",
    "ntex": "no effect on the dynamics: textures are for rendering",
    "nsensor": "no effect on the dynamics: dm's torso_subtreelinvel sensor only reads the state",
    "nuser_geom": "no effect on the dynamics: user data MuJoCo never reads",
    "geom_user": "no effect on the dynamics: user data MuJoCo never reads",
    "narena": "no effect on the dynamics: Gymnasium's nstack memory size",
}
_NOT_EXPRESSIBLE = {
    "geom_quat": "not expressible: no effect kind turns a geom (dm's angles differ by up to 0.01 rad)",
    "body_iquat": "not expressible: no effect kind turns a body's principal inertia axes",
    "body_inertia": "not expressible: 'mass' scales mass and inertia together, not one moment",
    "geom_conaffinity": "not expressible: no effect kind turns on collisions between the robot's own geoms",
    "jnt_solimp": "not expressible: no effect kind sets a joint limit's impedance (solimp)",
}


def _inertia_about_y(model: mujoco.MjModel, body: int) -> float:
    """The y-y entry of a body's inertia tensor in its own frame."""
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, model.body_iquat[body])
    rotation = rotation.reshape(3, 3)
    return float((rotation @ np.diag(model.body_inertia[body]) @ rotation.T)[1, 1])


def _same_planar_inertia(source: mujoco.MjModel, target: mujoco.MjModel, body: str) -> bool:
    """Whether ``body`` has the same mass, centre of mass and moment about y in both models: all
    of its inertia that a robot whose every hinge turns about y feels."""
    i = mujoco.mj_name2id(source, mujoco.mjtObj.mjOBJ_BODY, body)
    j = mujoco.mj_name2id(target, mujoco.mjtObj.mjOBJ_BODY, body)
    hinges = source.jnt_type == mujoco.mjtJoint.mjJNT_HINGE
    if not np.all(source.jnt_axis[hinges] == [0, 1, 0]):
        return False
    return (math.isclose(source.body_mass[i], target.body_mass[j], rel_tol=1e-12)
            and np.allclose(source.body_ipos[i], target.body_ipos[j], rtol=0, atol=1e-12)
            and math.isclose(_inertia_about_y(source, i), _inertia_about_y(target, j), rel_tol=1e-9))


def account_for_differences(target: mujoco.MjModel | None = None) -> dict[str, str]:
    """Each line of :func:`model_differences` with what it is: the effect of
    :func:`true_difference_effects` that sets it, or why none does."""
    source = gymnasium_model()
    target = dm_cheetah_model() if target is None else target
    effects = true_difference_effects(target)
    by_object = {(e["kind"], e["target"]): e for e in effects}
    accounts: dict[str, str] = {}
    for line in model_differences(target):
        head = line.split(":")[0]
        field, _, rest = head.partition("[")
        name = rest.rstrip("]") or None
        limited = name is not None and field.startswith("jnt_") and bool(
            source.jnt_limited[mujoco.mj_name2id(source, mujoco.mjtObj.mjOBJ_JOINT, name)])
        if field in ("body_inertia", "body_iquat") and _same_planar_inertia(source, target, str(name)):
            accounts[line] = ("no effect on the dynamics: mass, centre of mass and the moment about y (the "
                              "only axis the planar robot turns about) are the same")
        elif head in _NO_DYNAMICS or field in _NO_DYNAMICS:
            accounts[line] = _NO_DYNAMICS.get(head) or _NO_DYNAMICS[field]
        elif field == "actuator_gear" and ("gear", name) in by_object:
            accounts[line] = f"effect {by_object[('gear', name)]}"
        elif field == "geom_friction" and ("friction", name) in by_object:
            accounts[line] = f"effect {by_object[('friction', name)]} (torsional and rolling unused: condim 3)"
        elif field == "geom_solimp" and ("contact_solimp", None) in by_object:
            accounts[line] = f"effect {by_object[('contact_solimp', None)]}"
        elif field == "jnt_range":
            moved = [e for e in effects if e["kind"] in ("joint_range", "joint_limit") and e["target"] == name]
            accounts[line] = "; ".join(f"effect {e}" for e in moved)
        elif field.startswith("jnt_") and name is not None and not limited:
            accounts[line] = "no effect on the dynamics: the root joint has no limit"
        elif field in _NOT_EXPRESSIBLE:
            accounts[line] = _NOT_EXPRESSIBLE[field]
        else:
            raise CrossModelError(f"no account of the difference {line!r}: add its effect or its reason to cross_model.py")
    return accounts


# --- the evaluator's errors ---------------------------------------------------------------------

def _errors_json(evaluator: ResidualEvaluator, hypothesis: Hypothesis) -> dict[str, float | None]:
    """The numbers ``diagnose`` reports for a hypothesis (``loop._errors``), plus its noise floor."""
    summary = evaluator.summary(hypothesis)
    horizon, heldout_horizon = summary.get("horizon"), summary.get("horizon_heldout")
    return {"one_step_nrmse": summary["train"].nrmse,
            "heldout_one_step_nrmse": summary["heldout"].nrmse,
            "heldout_trimmed_one_step_nrmse": summary["heldout"].trimmed_nrmse,
            "horizon_nrmse": None if horizon is None else horizon.nrmse,
            "heldout_horizon_nrmse": None if heldout_horizon is None else heldout_horizon.nrmse,
            "noise_floor": float(evaluator.noise_floor()[0])}  # measured from the data: the same for every hypothesis


def _evaluator(source: SourceSimulator, transitions: Transitions) -> ResidualEvaluator:
    settings = DiagnosisSettings()  # the split and horizon diagnose() uses by default
    return ResidualEvaluator(source, transitions, horizon=settings.horizon, heldout_fraction=settings.heldout_fraction,
                             screen_rows=settings.screen_rows, fit_rows=settings.fit_rows, seed=settings.seed)


class ExactModelSource(SourceSimulator):
    """The source env's observation map and control step, predicting with another model of the
    same layout (the one that recorded the data). Relies on ``SourceSimulator`` rolling out
    ``model_with(...)`` on its ``_datas``."""

    def __init__(self, env_id: str, model: mujoco.MjModel) -> None:
        super().__init__(env_id)
        if frame_skip(model) != self.frame_skip:
            raise CrossModelError(f"the model steps {frame_skip(model)} times per control step, {env_id} "
                                  f"{self.frame_skip}; expected the same timestep")
        if mujoco.mj_stateSize(model, FULL_PHYSICS) != self.state_size:
            raise CrossModelError(f"the model's physics state has {mujoco.mj_stateSize(model, FULL_PHYSICS)} "
                                  f"numbers, {env_id}'s {self.state_size}; expected the same layout")
        if not hasattr(self, "_datas"):
            raise AssertionError("SourceSimulator no longer keeps _datas: update ExactModelSource")
        self.exact_model = model
        self._datas = [mujoco.MjData(model) for _ in range(self.nthread)]

    def model_with(self, effects: Sequence[ModelEffect]) -> mujoco.MjModel:
        if effects:
            raise CrossModelError("the exact target model takes no effects")
        return self.exact_model


def hand_set_errors(data: Mapping[str, np.ndarray] | Transitions, env_id: str = ENV_ID, *,
                    effects: Sequence[Mapping[str, Any]] | None = None,
                    target_model: mujoco.MjModel | None = None) -> dict[str, dict[str, float | None]]:
    """Held-out one-step and H-step normalized errors that the diagnosis's own evaluator
    (``ResidualEvaluator`` on ``SourceSimulator(env_id)``, ``DiagnosisSettings()`` defaults:
    horizon 10, held-out fraction 0.3, seed 0) gives on ``data`` for

    - ``"stock"``: the source as it is;
    - ``"hand_set"``: the source plus ``effects`` (default :func:`true_difference_effects`);
    - ``"exact"`` (only with ``target_model``): the model that recorded the data, a floor that
      should be ~0.
    """
    transitions = data if isinstance(data, Transitions) else Transitions(**data)
    hypothesis = tuple(Effect.from_dict(e) for e in (true_difference_effects() if effects is None else effects))
    evaluator = _evaluator(SourceSimulator(env_id), transitions)
    out = {"stock": _errors_json(evaluator, ()), "hand_set": _errors_json(evaluator, hypothesis)}
    if target_model is not None:
        out["exact"] = _errors_json(_evaluator(ExactModelSource(env_id, target_model), transitions), ())
    return out
