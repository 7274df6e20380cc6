"""Adroit: the source env is Gymnasium-Robotics' Adroit step for step; a broken joint bends less
and opens the thumb-index pinch, a shrunk finger is shorter; the compiled target changes only the
named joint or segments; bad parts and levels are refused with clear errors."""

from __future__ import annotations

import contextlib
import io

import gymnasium
import numpy as np
import pytest

from offdyn_bench.envs import make_robot_env
from offdyn_bench.errors import InvalidParameterError, UnknownNameError
from offdyn_bench.model_diff import model_differences
from offdyn_bench.robotics.adroit import (
    ADROIT_TASKS,
    FINGERS,
    LEVEL_SCALES,
    broken_joint,
    get_adroit_task,
    shrunk_finger,
)
from offdyn_bench.robotics.probes import (
    FINGER_LENGTH_SITES,
    finger_length,
    joint_reach,
    pinch_gap,
    sweep_return,
)
from offdyn_bench.tasks import TASKS

with contextlib.redirect_stderr(io.StringIO()):  # its release notice
    import gymnasium_robotics

gymnasium.register_envs(gymnasium_robotics)

ROBOTS = sorted(ADROIT_TASKS)


@pytest.mark.parametrize("robot", ROBOTS)
def test_the_source_is_gymnasium_robotics_adroit_step_for_step(robot):
    vanilla = gymnasium.make(ADROIT_TASKS[robot].vanilla_env_id)
    ours = make_robot_env(robot)
    actions = np.random.default_rng(1).uniform(-1, 1, size=(60, *ours.action_space.shape))
    obs_a, _ = vanilla.reset(seed=4)
    obs_b, _ = ours.reset(seed=4)
    np.testing.assert_array_equal(obs_a, obs_b)
    for action in actions:
        obs_a, reward_a, *_ = vanilla.step(action)
        obs_b, reward_b, _, _, info = ours.step(action)
        np.testing.assert_array_equal(obs_a, obs_b)
        assert reward_a == reward_b
    assert "state" in info


@pytest.mark.parametrize("robot", ROBOTS)
def test_a_broken_thumb_bends_less_and_cannot_close_the_pinch(robot):
    task = get_adroit_task(robot)
    _, joint = task.broken_joint
    source = make_robot_env(robot)
    reach, gap = joint_reach(source, joint), pinch_gap(source)
    high = source.unwrapped.model.joint(joint).range[1]
    assert reach > 0.95 * high  # the nominal thumb flexes to the end of its range
    assert gap < 0.014  # and the finger pads meet
    for level, scale in LEVEL_SCALES.items():
        target = TASKS[f"{robot.lower()}-broken-joint-{task.broken_joint[0]}-{level}"].make("target")
        assert joint_reach(target, joint) < scale * high + 0.01
        if level == "hard":
            assert pinch_gap(target) > 2 * gap  # 12-13 mm -> 27-33 mm: no precision grasp left
        if level == "medium":
            assert pinch_gap(target) > gap + 0.002


@pytest.mark.parametrize("robot", ROBOTS)
def test_a_shrunk_finger_is_shorter_by_its_scale(robot):
    finger = get_adroit_task(robot).shrunk_finger
    base, tip = FINGER_LENGTH_SITES[finger]
    nominal = finger_length(make_robot_env(robot), base, tip)
    for level, scale in LEVEL_SCALES.items():
        pair = TASKS[f"{robot.lower()}-shrink-finger-{finger}-{level}"]
        assert finger_length(pair.make("target"), base, tip) == pytest.approx(scale * nominal, rel=1e-6)


@pytest.mark.parametrize("robot", ROBOTS)
def test_the_compiled_target_changes_only_the_named_joint_or_segments(robot):
    task = get_adroit_task(robot)
    base = make_robot_env(robot).unwrapped.model
    joint_target = TASKS[f"{robot.lower()}-broken-joint-{task.broken_joint[0]}-hard"].make("target").unwrapped.model
    (difference,) = model_differences(base, joint_target)
    assert difference.field == "jnt_range" and difference.rows == (task.broken_joint[1],)
    finger_target = TASKS[f"{robot.lower()}-shrink-finger-{task.shrunk_finger}-hard"].make("target").unwrapped.model
    masses = {d.field: d for d in model_differences(base, finger_target)}["body_mass"]
    assert masses.rows == FINGERS[task.shrunk_finger].segments
    np.testing.assert_allclose(masses.after / masses.before, 0.2**3)


def test_a_controller_that_moves_the_pen_earns_another_return_in_every_pen_target():
    source = sweep_return(make_robot_env("AdroitPen"))
    for name, pair in TASKS.items():
        if pair.robot == "AdroitPen" and pair.level != "easy":
            assert abs(sweep_return(pair.make("target")) - source) > 10, name


def test_the_grid_has_24_adroit_pairs():
    adroit = [p for p in TASKS.values() if p.robot.startswith("Adroit")]
    assert len(adroit) == 24
    assert {(p.shift, p.level) for p in adroit} == {(s, lv) for s in ("broken-joint", "shrink-finger")
                                                    for lv in LEVEL_SCALES}


def test_an_unknown_joint_finger_level_or_task_is_refused():
    with pytest.raises(UnknownNameError, match="unknown finger joint of the Adroit hand 'THJ5'.*'THJ4'"):
        broken_joint("THJ5", "hard")
    with pytest.raises(UnknownNameError, match="unknown finger of the Adroit hand 'pinky'"):
        shrunk_finger("pinky", "hard")
    with pytest.raises(InvalidParameterError, match=r"invalid level='extreme'; expected one of \['easy', 'medium', 'hard'\]"):
        broken_joint("THJ3", "extreme")
    with pytest.raises(InvalidParameterError, match="invalid level='0.2'"):
        shrunk_finger("index", "0.2")
    with pytest.raises(UnknownNameError, match="unknown Adroit task 'AdroitKettle'"):
        get_adroit_task("AdroitKettle")
    with pytest.raises(UnknownNameError, match="unknown joint 'THJ9'"):
        make_robot_env("AdroitDoor", [{"kind": "joint_range", "target": "THJ9", "scale": 0.5}])


def test_tasks_show_names_the_broken_joint_and_the_shrunk_segments():
    from typer.testing import CliRunner

    from offdyn_bench.cli import app

    result = CliRunner().invoke(app, ["tasks", "show", "adroitrelocate-broken-joint-thumb-flex-hard"])
    assert result.exit_code == 0, result.output
    assert "jnt_range[THJ3]: [0 1.309] -> [0 0.2618]" in result.output
    result = CliRunner().invoke(app, ["tasks", "show", "adroitpen-shrink-finger-index-medium"])
    assert all(f"body_mass[{segment}]" in result.output for segment in FINGERS["index"].segments)
