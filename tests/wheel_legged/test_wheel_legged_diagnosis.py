"""Gap diagnosis of the clean model on the human operator's target data (slow: a 100,000-transition
rebuild, checked against the manifest, then the full diagnosis loop, a few minutes on 2 cores).

The issue asks for the dead zone and the wheel friction, each within 15%. Two things hid them
until the search changed: the sensors' noise exceeds what a 5 ms step moves the tilt and the
displacement, and the dead zone (0.05) lies below every fixed screening trial (0.1 and up) while
78% of the operator's commands lie inside it. With stored states the search now compares the
physics with them (the sensors are read off the difference), and the dead zone's trials include
the recorded command magnitudes. The shipped target's worn tyre is constant; the last test
records tyres that wear within the data and checks that the drift is reported.
"""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from offdyn_bench import make_robot_env
from offdyn_bench.datasets import build_dataset
from offdyn_bench.datasets.manifest import read_manifest
from offdyn_bench.diagnose import Transitions
from offdyn_bench.diagnose.loop import Diagnosis, DiagnosisSettings, diagnose
from offdyn_bench.wheel_legged.operator import HumanOperator
from offdyn_bench.wheel_legged.pairs import (
    DRIVE_FRICTIONLOSS,
    MOTOR_DEADZONE,
    WHEEL_FRICTION_SCALE,
    real_robot_effects,
)

DATASET = "offdyn/wheellegged-standstill/human-operator-v0"
SOURCE = "offdyn/WheelLegged-standstill-source-v0"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def diagnosis(tmp_path_factory: pytest.TempPathFactory) -> Diagnosis:
    entry = read_manifest().entries[DATASET]
    root = tmp_path_factory.mktemp("minari")
    # The rebuild must give the manifest's bytes (build_dataset refuses and installs nothing otherwise).
    built = build_dataset(entry.recipe, root=root, recorded=entry)
    assert built.installed_at is not None
    return diagnose(SOURCE, str(pathlib.Path(built.installed_at)), DiagnosisSettings())


def _step_of(diagnosis: Diagnosis, kind: str):
    return next(step for step in diagnosis.steps if step.effect["kind"] == kind)


def test_diagnosis_finds_the_dead_zone_and_the_wheel_friction(diagnosis: Diagnosis):
    found = {e["kind"]: e for e in diagnosis.effects_added}
    deadzone = found["action_deadzone"]
    # One actuator drives the axle: "all" and "wheel_motors" are the same dead zone.
    assert deadzone["target"] in ("wheel_motors", None)
    assert deadzone["value"] == pytest.approx(MOTOR_DEADZONE, rel=0.15)
    friction = found["friction"]
    assert friction["value"] == pytest.approx(WHEEL_FRICTION_SCALE, rel=0.15)
    # Only the tyres touch the floor, and they set the contact's coefficient (priority 1): scaling
    # every geom's friction is the tyres' change, and the report names that alternative.
    if friction["target"] is None:
        assert any(alt.startswith("friction on wheels") for alt in _step_of(diagnosis, "friction").equivalent_alternatives)
    else:
        assert friction["target"] == "wheels"
    # The drive's dry friction, which the dead zone used to be mistaken for.
    assert found["frictionloss"]["value"] == pytest.approx(DRIVE_FRICTIONLOSS, rel=0.15)
    assert found["frictionloss"]["target"] in ("wheel_axle", None)


def test_the_sensors_are_read_off_the_stored_states_and_the_noise_stays_the_floor(diagnosis: Diagnosis):
    """The target's sensors lag one control step and are noisy. The delays come from the stored
    states (the displacement's one-step change is too far below its noise to show its lag); the
    reported one-step error stays against the recorded observations, whose floor is that noise."""
    assert diagnosis.state_source == "stored qpos/qvel"
    assert any("stored states" in note for note in diagnosis.notes)
    delays = {e["target"]: e["value"] for e in diagnosis.effects_added if e["kind"] == "obs_delay"}
    names = list(diagnosis.dimension_names)
    assert {names[i] for i in delays} >= {"qpos[rooty]", "qvel[rooty]", "qvel[rootx]"}
    assert set(delays.values()) == {1}
    assert diagnosis.noise_floor > 0.5
    assert diagnosis.error_after.heldout_one_step_nrmse <= 1.02 * diagnosis.noise_floor
    # Over ten steps the dynamics show above the noise: the found effects cut that error by 3x or more.
    assert diagnosis.error_after.heldout_horizon_nrmse < diagnosis.error_before.heldout_horizon_nrmse / 3
    assert not diagnosis.unexplained_residual
    # Constant effects, constant data: no drift is reported.
    assert diagnosis.identifiability is not None and diagnosis.identifiability.drifts == ()


def _record_wearing_tyres(task: str, scales: np.ndarray, steps: int) -> Transitions:
    """The human operator on the real robot, one episode per tyre friction scale (in recording
    order), ``steps`` control steps each; the physics state before each step stored."""
    operator = HumanOperator(task, seed=7)
    columns: dict[str, list] = {k: [] for k in ("observations", "actions", "next_observations", "terminations",
                                                "truncations", "qpos", "qvel")}
    for k, scale in enumerate(scales):
        effects = [e.to_dict() for e in real_robot_effects(task)]
        for effect in effects:
            if effect["kind"] == "friction":
                effect["scale"] = float(scale)
        env = make_robot_env("WheelLegged", effects=effects, task=task)
        nq, nv = env.unwrapped.model.nq, env.unwrapped.model.nv
        obs, _ = env.reset(seed=1000 + k)
        operator.start_episode(1000 + k)
        for t in range(steps):
            action = operator(obs)
            next_obs, _, terminated, truncated, info = env.step(action)
            truncated = truncated or t == steps - 1
            for key, value in (("observations", obs), ("actions", action), ("next_observations", next_obs),
                               ("terminations", terminated), ("truncations", truncated and not terminated),
                               ("qpos", info["prev_state"][1:1 + nq]), ("qvel", info["prev_state"][1 + nq:1 + nq + nv])):
                columns[key].append(value)
            obs = next_obs
            if terminated:
                break
    return Transitions(**{key: np.asarray(value) for key, value in columns.items()})


def test_tyres_wearing_within_the_recording_are_reported_not_averaged_away():
    """The real robot's tyres wear from friction x0.5 to x0.3 over twelve episodes (12,000
    transitions). Every effect of the vocabulary is constant: the diagnosis fits a compromise and
    says that the tyre friction drifts, with each half's value; it does not call the data explained."""
    scales = np.linspace(0.5, 0.3, 12)
    result = diagnose(SOURCE, _record_wearing_tyres("standstill", scales, 1000), DiagnosisSettings())
    found = {e["kind"]: e for e in result.effects_added}
    assert found["action_deadzone"]["value"] == pytest.approx(MOTOR_DEADZONE, rel=0.15)
    assert result.identifiability is not None
    drift = next(d for d in result.identifiability.drifts if d.label.startswith("friction on"))
    assert drift.earlier == pytest.approx(scales[:6].mean(), rel=0.15)
    assert drift.later == pytest.approx(scales[6:].mean(), rel=0.15)
    assert drift.earlier > drift.later
    assert result.unexplained_residual and "drift" in result.stop_reason
    assert any("earlier half of the episodes" in note for note in result.notes)
