"""AntMaze: the source env is Gymnasium-Robotics' AntMaze step for step, layouts are data that
wall the source route and leave a way to the goal, the compiled target shows the moved blocks,
and bad maps, layouts and options are refused with errors a person can act on."""

from __future__ import annotations

import contextlib
import io
import pathlib

import gymnasium
import numpy as np
import pytest

from offdyn_bench.effects import MazeLayout
from offdyn_bench.envs import make_robot_env
from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError
from offdyn_bench.robotics.mazes import (
    GOAL,
    MAZES,
    START,
    antmaze_robot,
    cells_marked,
    check_map,
    get_maze,
    layout_effects,
    shortest_path_length,
    shortest_route_cells,
    walls_of,
)
from offdyn_bench.robotics.probes import route_obstructions, source_route, towed_return
from offdyn_bench.tasks import TASKS

with contextlib.redirect_stderr(io.StringIO()):  # its release notice
    import gymnasium_robotics

gymnasium.register_envs(gymnasium_robotics)

LAYOUTS = [(maze.name, layout) for maze in MAZES.values() for layout in maze.layouts]


def _flat(obs: dict) -> np.ndarray:
    return np.concatenate([obs["observation"], obs["achieved_goal"], obs["desired_goal"]])


@pytest.mark.parametrize("maze, reward_type", [("small", "sparse"), ("medium", "dense"), ("large", "sparse")])
def test_the_source_is_gymnasium_robotics_antmaze_step_for_step(maze, reward_type):
    """Same map, seed and actions: the suite's env and AntMaze_*-v5 give identical observations and rewards."""
    spec = get_maze(maze)
    vanilla_id = spec.vanilla_id(reward_type)
    vanilla_map = [[int(c) if c in "01" else c for c in row] for row in spec.source_map]
    vanilla = gymnasium.make(vanilla_id, maze_map=vanilla_map)
    # Gymnasium-Robotics leaves the maze's generated MJCF in the temp folder (ant_maze<time>.xml).
    pathlib.Path(vanilla.unwrapped.tmp_xml_file_path).unlink(missing_ok=True)
    ours = make_robot_env(antmaze_robot(maze, reward_type))
    actions = np.random.default_rng(0).uniform(-1, 1, size=(150, 8))
    for seed in (0, 7):
        obs_a, _ = vanilla.reset(seed=seed)
        obs_b, info = ours.reset(seed=seed)
        np.testing.assert_array_equal(_flat(obs_a), _flat(obs_b))
        for action in actions:
            obs_a, reward_a, *_ = vanilla.step(action)
            obs_b, reward_b, _, _, info = ours.step(action)
            np.testing.assert_array_equal(_flat(obs_a), _flat(obs_b))
            assert reward_a == reward_b
        assert "state" in info and "prev_state" in info


@pytest.mark.parametrize("maze, layout", LAYOUTS)
def test_every_layout_walls_the_source_route_and_leaves_a_way(maze, layout):
    spec = get_maze(maze)
    walls = check_map(spec.layout(layout))
    start, goal = cells_marked(spec.source_map, START)[0], cells_marked(spec.source_map, GOAL)[0]
    # Same size, same start and goal, the outer wall kept (check_map), a way from start to goal left.
    assert (len(walls), len(walls[0])) == (len(spec.source_map), len(spec.source_map[0]))
    assert cells_marked(walls, START) == [start] and cells_marked(walls, GOAL) == [goal]
    assert shortest_path_length(walls, start, goal) is not None
    # No shortest route of the source survives: on the source route's cells alone, the target is walled off.
    route = shortest_route_cells(spec.source_map, start, goal)
    only_route = [
        "".join(c if (i, j) in route and c != "1" else "1" for j, c in enumerate(row))
        for i, row in enumerate(walls_of(walls))
    ]
    assert shortest_path_length(only_route, start, goal) is None


@pytest.mark.parametrize("maze, layout", LAYOUTS)
def test_the_compiled_target_moves_exactly_the_changed_blocks_and_walls_the_route(maze, layout):
    spec = get_maze(maze)
    robot = antmaze_robot(maze, "sparse")
    source, target = make_robot_env(robot), make_robot_env(robot, layout_effects(maze, layout))
    assert source.unwrapped.walls == walls_of(spec.source_map)
    assert target.unwrapped.walls == walls_of(spec.layout(layout))
    # Every geom but the moved blocks is where it was; the moved ones are the cells whose wall changed.
    moved = {source.unwrapped.model.geom(g).name for g in range(source.unwrapped.model.ngeom)
             if not np.array_equal(source.unwrapped.model.geom_pos[g], target.unwrapped.model.geom_pos[g])}
    changed = {f"block_{i}_{j}" for i, (a, b) in enumerate(zip(walls_of(spec.source_map), walls_of(spec.layout(layout))))
               for j, (x, y) in enumerate(zip(a, b)) if x != y}
    assert moved == changed
    # Walking the source's route cell to cell: clear in the source model, into a wall in the target.
    route = source_route(spec.source_map)
    assert route_obstructions(source, route) == []
    blocked = route_obstructions(target, route)
    assert blocked and set(blocked) <= changed


def test_the_task_pairs_cover_every_maze_layout_and_reward():
    for maze, layout in LAYOUTS:
        for reward_type in ("sparse", "dense"):
            pair = TASKS[f"{antmaze_robot(maze, reward_type).lower()}-layout-{layout}"]
            assert pair.source_effects == () and pair.target_effects == layout_effects(maze, layout)
            assert pair.env_id("target") == f"offdyn/{antmaze_robot(maze, reward_type)}-layout-{layout}-target-v0"
    assert sum(p.robot.startswith("AntMaze") for p in TASKS.values()) == 36


def test_sparse_and_dense_rewards_as_gymnasium_robotics_defines_them():
    sparse, dense = make_robot_env("AntMazeSmall"), make_robot_env("AntMazeSmallDense")
    at_goal, away = np.zeros(2), np.array([3.0, 4.0])
    assert sparse.unwrapped.compute_reward(at_goal, at_goal, {}) == 1.0
    assert sparse.unwrapped.compute_reward(away, at_goal, {}) == 0.0
    assert dense.unwrapped.compute_reward(away, at_goal, {}) == pytest.approx(np.exp(-5.0))
    # Vectorized over a batch of goals (hindsight relabelling).
    np.testing.assert_allclose(dense.unwrapped.compute_reward(np.stack([at_goal, away]), at_goal, {}),
                               [1.0, np.exp(-5.0)])


def test_an_unknown_layout_or_maze_names_the_valid_ones():
    with pytest.raises(UnknownNameError, match="unknown layout of the medium maze 'blocked-start'.*'blocked'"):
        layout_effects("medium", "blocked-start")
    with pytest.raises(UnknownNameError, match="unknown maze 'huge'"):
        get_maze("huge")
    with pytest.raises(UnknownNameError, match="unknown AntMaze reward type 'shaped'"):
        antmaze_robot("small", "shaped")


@pytest.mark.parametrize("walls, expected", [
    (["11111", "10201", "11111"], "strings of '1' \\(wall\\) and '0' \\(free\\)"),
    (["11111", "10000", "11111"], "every border cell '1'"),
    (["11111", "1001", "11111"], "equal-length"),
    ("11111", "a list of 3 to 64"),
    ([], "a list of 3 to 64"),
])
def test_a_malformed_wall_map_is_refused(walls, expected):
    with pytest.raises(InvalidParameterError, match=expected):
        MazeLayout(walls=walls)


def test_a_layout_of_another_size_or_one_that_walls_off_the_goal_is_refused():
    medium_walls = layout_effects("medium", "blocked")
    with pytest.raises(OffdynError, match="walls is a 8x8 map but the model's maze is 5x5 cells"):
        make_robot_env("AntMazeSmall", medium_walls)
    closed = MazeLayout(walls=("11111", "10011", "11101", "10001", "11111"))
    with pytest.raises(OffdynError, match=r"walls the goal cell \(3, 1\) off from the start cell \(1, 1\)"):
        make_robot_env("AntMazeSmall", [closed])
    on_goal = MazeLayout(walls=("11111", "10001", "11101", "11001", "11111"))
    with pytest.raises(OffdynError, match="walls the goal cell"):
        make_robot_env("AntMazeSmall", [on_goal])


def test_reset_options_place_start_and_goal_in_free_cells_only():
    env = make_robot_env("AntMazeMedium")
    obs, _ = env.reset(seed=0, options={"goal_cell": (1, 5), "reset_cell": (6, 1)})
    assert np.all(np.abs(obs["desired_goal"] - env.unwrapped.cell_xy((1, 5))) <= 1.0)
    assert np.all(np.abs(obs["achieved_goal"] - env.unwrapped.cell_xy((6, 1))) <= 1.0)
    with pytest.raises(OffdynError, match=r"goal_cell=\(0, 0\): expected a free cell of the 8x8 maze"):
        env.reset(seed=0, options={"goal_cell": (0, 0)})
    with pytest.raises(OffdynError, match="reset_cell=.*expected a free cell"):
        env.reset(seed=0, options={"reset_cell": (9, 1)})
    with pytest.raises(OffdynError, match="expected a \\(row, column\\) pair"):
        env.reset(seed=0, options={"goal_cell": "g"})
    with pytest.raises(OffdynError, match="the goal lies in the start cell"):
        env.reset(seed=0, options={"goal_cell": (1, 1)})


def _towed_returns(maze: str, layout: str) -> tuple[float, float, float]:
    """Towed along the source route on source and target, and along the target's own route on the target."""
    spec = get_maze(maze)
    robot = antmaze_robot(maze, "sparse")
    source, target = make_robot_env(robot), make_robot_env(robot, layout_effects(maze, layout))
    route = source_route(spec.source_map)
    return (towed_return(source, route)[0], towed_return(target, route)[0],
            towed_return(target, source_route(spec.layout(layout)))[0])


@pytest.mark.parametrize("maze, layout", [("small", "middle-gap"), ("medium", "blocked"), ("large", "z-shape")])
def test_a_source_route_follower_reaches_the_goal_only_in_the_source(maze, layout):
    """The scripted follower of the source route scores on the source and nothing on the target
    (a wall stops it); following the target's own route, it reaches the goal there too."""
    on_source, on_target, target_route = _towed_returns(maze, layout)
    assert on_source > 100 and on_target == 0.0 and target_route > 100


@pytest.mark.slow
@pytest.mark.parametrize("maze, layout", LAYOUTS)
def test_every_layout_stops_the_source_route_follower_and_is_solvable(maze, layout):
    on_source, on_target, target_route = _towed_returns(maze, layout)
    assert on_source > 100 and on_target == 0.0 and target_route > 100


def test_an_episodic_task_ends_at_the_goal_and_a_continuing_one_can_move_it():
    route = source_route(get_maze("small").source_map)
    episodic = make_robot_env("AntMazeSmall", continuing_task=False)
    total, success = towed_return(episodic, route)
    assert success and total == 1.0  # terminated on the first step within 0.45 m of the goal
    moving = make_robot_env("AntMazeSmall", reset_target=True)
    first_goal = moving.reset(seed=0)[0]["desired_goal"]
    towed_return(moving, route, seed=0, steps=300)  # reaches the goal after about 170 steps
    goal = moving.unwrapped.goal
    assert not np.array_equal(goal, first_goal)  # a new goal was drawn (in the one goal cell, new noise)
    site = moving.unwrapped.model.site("target").id
    np.testing.assert_array_equal(moving.unwrapped.model.site_pos[site][:2], goal)


def test_tasks_show_names_the_cells_a_layout_changes():
    from typer.testing import CliRunner

    from offdyn_bench.cli import app

    result = CliRunner().invoke(app, ["tasks", "show", "antmazemedium-layout-blocked"])
    assert result.exit_code == 0, result.output
    assert "geom_pos[block_3_3]: [-2 2 -3] -> [-2 2 1]" in result.output
    assert "geom_contype[block_3_3]: 0 -> 1" in result.output
    assert "maze_layout(8x8 cells: 11111111 / 10011001 / 10010001 / 11010111" in result.output
