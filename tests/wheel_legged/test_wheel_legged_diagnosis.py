"""Gap diagnosis of the clean model on the human operator's target data (slow: a 100,000-transition
rebuild, checked against the manifest, then the full diagnosis loop, about 4 minutes on 2 cores).

What the issue asks (find the dead zone and the wheel friction, each within 15%) is not what the
diagnosis finds today: the strict xfail below records that, and turns into a failure the day it
starts to pass (then make it a plain test). The other test pins what it does find and why.
"""

from __future__ import annotations

import pathlib

import pytest

from offdyn_bench.datasets import build_dataset
from offdyn_bench.datasets.manifest import read_manifest
from offdyn_bench.diagnose.loop import Diagnosis, DiagnosisSettings, diagnose
from offdyn_bench.wheel_legged.pairs import MOTOR_DEADZONE, WHEEL_FRICTION_SCALE

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


def test_diagnosis_sees_the_gap_but_sensor_noise_sets_its_floor(diagnosis: Diagnosis):
    """Measured: the source model's one-step error on this data (0.89 held-out) is well above what a
    perfect model would make, and one added effect takes it to the floor. That floor is high (0.63):
    near balance a 5 ms step moves the tilt and the displacement by less than their sensor noise
    (0.002 rad, 0.002 m), so those two dimensions are noise-dominated and only the velocities
    carry the dynamics. The effect found stands in for dead zone plus drive friction (both resist
    small torques): an armature (rotor inertia) on the wheel axle (`armature` on all actuated joints,
    which here is the axle)."""
    assert diagnosis.state_source == "stored qpos/qvel"
    assert diagnosis.error_before.heldout_one_step_nrmse > 1.2 * diagnosis.noise_floor
    assert diagnosis.error_after.heldout_one_step_nrmse < diagnosis.error_before.heldout_one_step_nrmse
    names = list(diagnosis.dimension_names)
    floor = dict(zip(names, diagnosis.noise_floor_per_dimension, strict=True))
    assert floor["qpos[rooty]"] > 0.5 and floor["qpos[rootx]"] > 0.5
    assert diagnosis.noise_floor > 0.5
    assert diagnosis.effects_added, "diagnosis added nothing"


@pytest.mark.xfail(strict=True, reason="measured: diagnosis adds 'armature on all' = 0.36 and every dimension is then at "
                                       "its noise floor (overall 0.63): at 200 Hz the dead zone and the friction change "
                                       "a step's motion by less than the sensor noise; it finds neither")
def test_diagnosis_finds_the_dead_zone_and_the_wheel_friction(diagnosis: Diagnosis):
    found = {(e["kind"], e["target"]): e for e in diagnosis.effects_added}
    deadzone = found.get(("action_deadzone", "wheel_motors")) or found.get(("action_deadzone", None))
    assert deadzone is not None
    assert deadzone["threshold"] == pytest.approx(MOTOR_DEADZONE, rel=0.15)
    friction = next((e for (kind, _), e in found.items() if kind == "friction"), None)
    assert friction is not None
    assert friction["scale"] == pytest.approx(WHEEL_FRICTION_SCALE, rel=0.15)
