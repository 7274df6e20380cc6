"""Scripted probes of what a policy can do on a source and on a target: how far a joint bends,
how close thumb and index finger can pinch, whether the source maze's route is still open.

Each drives the env (or casts rays in its compiled model); tests compare source and target with
them, and ``python -m offdyn_bench.robotics.probes`` prints the table the README quotes.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import gymnasium
import mujoco
import numpy as np

from offdyn_bench.robotics.mazes import (
    GOAL,
    START,
    Cell,
    cells_marked,
    shortest_path_length,
    walls_of,
)

# The thumb's and index finger's joints, palm outwards: what a thumb-index pinch can move.
PINCH_JOINTS = ("THJ4", "THJ3", "THJ2", "THJ1", "THJ0", "FFJ3", "FFJ2", "FFJ1", "FFJ0")
# A finger's first shrunk segment and its tip site: finger_length's two ends.
FINGER_LENGTH_SITES = {"index": ("ffproximal", "S_fftip"), "thumb": ("thproximal", "S_thtip")}


def _adroit_action(env: gymnasium.Env, ctrl: np.ndarray) -> np.ndarray:
    """The normalized action that makes the Adroit env command ``ctrl`` (it maps [-1, 1] onto each range)."""
    u = env.unwrapped
    return np.clip((ctrl - u.act_mean) / u.act_rng, -1.0, 1.0)


def joint_reach(env: gymnasium.Env, joint: str, steps: int = 40, seed: int = 0) -> float:
    """The angle (rad) an Adroit joint reaches when its position actuator is driven to the top of
    its range for ``steps`` steps, the rest of the hand holding its reset pose."""
    u = env.unwrapped
    env.reset(seed=seed)
    ctrl = u.data.ctrl.copy()
    actuator = u.model.actuator(f"A_{joint}").id
    ctrl[actuator] = u.model.actuator_ctrlrange[actuator, 1]
    action = _adroit_action(env, ctrl)
    for _ in range(steps):
        env.step(action)
    return float(u.data.joint(joint).qpos[0])


def pinch_gap(env: gymnasium.Env, steps: int = 80, seed: int = 0) -> float:
    """The closest (m) a scripted pinch brings the thumb tip (site ``S_thtip``) to the index tip
    (``S_fftip``): each step moves the pinch joints' position targets along the least-squares
    step that closes the gap (the tips' Jacobian), the arm holding still. About 13 mm on the
    nominal hand, where the finger pads touch."""
    u = env.unwrapped
    env.reset(seed=seed)
    model, data = u.model, u.data
    thumb, index = model.site("S_thtip").id, model.site("S_fftip").id
    joints = [model.joint(name).id for name in PINCH_JOINTS]
    dofs, qpos = model.jnt_dofadr[joints], model.jnt_qposadr[joints]
    actuators = [model.actuator(f"A_{name}").id for name in PINCH_JOINTS]
    hold = data.ctrl.copy()
    jac_thumb, jac_index = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    closest = np.inf
    for _ in range(steps):
        # Positions of the state after the last step (the env's data holds those of the step before).
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        gap = data.site_xpos[thumb] - data.site_xpos[index]
        closest = min(closest, float(np.linalg.norm(gap)))
        mujoco.mj_jacSite(model, data, jac_thumb, None, thumb)
        mujoco.mj_jacSite(model, data, jac_index, None, index)
        step = np.linalg.lstsq((jac_thumb - jac_index)[:, dofs], -gap, rcond=None)[0]
        ctrl = hold.copy()
        ctrl[actuators] = data.qpos[qpos] + 0.5 * step
        env.step(_adroit_action(env, ctrl))
    return closest


def finger_length(env: gymnasium.Env, finger_base_body: str, tip_site: str) -> float:
    """Distance (m) from a finger's base joint to its tip site in the reset pose."""
    u = env.unwrapped
    env.reset(seed=0)
    body = u.model.body(finger_base_body).id
    joint_anchor = u.data.xanchor[u.model.body_jntadr[body]]
    return float(np.linalg.norm(u.data.site_xpos[u.model.site(tip_site).id] - joint_anchor))


def sweep_return(env: gymnasium.Env, steps: int = 200, seed: int = 0) -> float:
    """The return of an open-loop sweep: every hand actuator (the last 24) opens and closes the
    hand twice a second, the arm holds still."""
    env.reset(seed=seed)
    total = 0.0
    action = np.zeros(env.action_space.shape)
    for t in range(steps):
        action[-24:] = np.sin(2 * np.pi * t / 50)
        _, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        if terminated or truncated:
            break
    return total


# --- AntMaze --------------------------------------------------------------------------------

def source_route(maze_map: Sequence[str]) -> list[Cell]:
    """One shortest route (cells, start to goal) on ``maze_map``'s free cells."""
    start, goal = cells_marked(maze_map, START)[0], cells_marked(maze_map, GOAL)[0]
    route, cell = [start], start
    remaining = shortest_path_length(maze_map, start, goal)
    if remaining is None:
        raise ValueError("the goal is walled off")
    rows = walls_of(maze_map)
    while cell != goal:
        i, j = cell
        cell = next(n for n in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1))
                    if rows[n[0]][n[1]] != "1" and shortest_path_length(maze_map, n, goal) == remaining - 1)
        remaining -= 1
        route.append(cell)
    return route


def route_obstructions(env: gymnasium.Env, route: Sequence[Cell], height: float = 0.5) -> list[str]:
    """The wall blocks a straight walk along ``route`` (cell centre to cell centre, ``height`` m
    above the floor) would run into in ``env``'s compiled maze: rays cast in the model itself."""
    u = env.unwrapped
    model, data = u.model, u.data
    mujoco.mj_forward(model, data)
    torso = model.body("torso").id
    hits: list[str] = []
    geom = np.zeros(1, dtype=np.int32)
    for a, b in itertools.pairwise(route):
        start = np.array([*u.cell_xy(a), height])
        direction = np.array([*u.cell_xy(b), height]) - start
        length = float(np.linalg.norm(direction))
        distance = mujoco.mj_ray(model, data, start, direction / length, None, 1, torso, geom)
        if 0 <= distance <= length:
            hits.append(model.geom(int(geom[0])).name)
    return list(dict.fromkeys(hits))  # a block across the route stops the walk into it and out of it


TOW_FORCE = 60.0  # N on the torso (about 2.5 body weights: enough to drag a limp Ant along the floor)
TOW_DAMPING = 20.0  # N s/m: keeps it from overshooting the turns


def towed_return(env: gymnasium.Env, route: Sequence[Cell], seed: int = 0,
                 steps: int | None = None) -> tuple[float, bool]:
    """(return, success at the end) of a scripted route follower: the Ant, its actions zero, is
    towed by a horizontal force on its torso towards the next cell centre of ``route`` (the goal
    itself for the last), as a waypoint controller would walk it. Walls stop it where they stand,
    so it measures whether ``route`` is open in the compiled maze, with the task's own reward."""
    u = env.unwrapped
    env.reset(seed=seed)
    torso = u.model.body("torso").id
    waypoints = [u.cell_xy(c) for c in route[1:-1]] + [u.goal.copy()]
    action = np.zeros(env.action_space.shape)
    total, success, k = 0.0, False, 0
    try:
        for _ in range(steps or u.maze.episode_steps):
            xy = u.data.qpos[:2]
            while k < len(waypoints) - 1 and np.linalg.norm(waypoints[k] - xy) < 1.0:
                k += 1
            heading = waypoints[k] - xy
            u.data.xfrc_applied[torso, :2] = (TOW_FORCE * heading / max(float(np.linalg.norm(heading)), 1e-6)
                                              - TOW_DAMPING * u.data.qvel[:2])
            _, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            success = bool(info["success"])
            if terminated or truncated:
                break
    finally:
        u.data.xfrc_applied[torso] = 0.0
    return total, success


def _table() -> None:  # pragma: no cover - prints the README's measurement
    from offdyn_bench.robotics.mazes import MAZES
    from offdyn_bench.tasks import TASKS

    for name, pair in TASKS.items():
        source, target = pair.make("source"), pair.make("target")
        if pair.robot.startswith("AntMaze"):
            maze = source.unwrapped.maze
            route = source_route(maze.source_map)
            start, goal = route[0], route[-1]
            layout = MAZES[maze.name].layout(pair.level)
            print(f"{name}: shortest route {len(route) - 1} -> {shortest_path_length(layout, start, goal)} cells; "
                  f"source route blocked by {route_obstructions(source, route)} -> {route_obstructions(target, route)}; "
                  f"towed along the source route: return {towed_return(source, route)[0]:.1f} -> "
                  f"{towed_return(target, route)[0]:.1f}; along the target's route: "
                  f"{towed_return(target, source_route(layout))[0]:.1f}")
        elif pair.shift == "broken-joint":
            joint = pair.target_effects[0].target
            print(f"{name}: {joint} reach {joint_reach(source, joint):.3f} -> {joint_reach(target, joint):.3f} rad; "
                  f"pinch gap {1000 * pinch_gap(source):.1f} -> {1000 * pinch_gap(target):.1f} mm; "
                  f"sweep return {sweep_return(source):.2f} -> {sweep_return(target):.2f}")
        elif pair.shift == "shrink-finger":
            base, tip = FINGER_LENGTH_SITES[pair.part]
            print(f"{name}: finger length {1000 * finger_length(source, base, tip):.1f} -> "
                  f"{1000 * finger_length(target, base, tip):.1f} mm; pinch gap {1000 * pinch_gap(source):.1f} -> {1000 * pinch_gap(target):.1f} mm; "
                  f"sweep return {sweep_return(source):.2f} -> {sweep_return(target):.2f}")


if __name__ == "__main__":
    _table()
