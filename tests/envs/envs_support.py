"""Zonotope membership and robot placement shared by the tests of ``envs``."""
from __future__ import annotations

import itertools

import mujoco
import numpy as np


def zonotope_contains(center: np.ndarray, generators: np.ndarray, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Exact membership of ``points [N, d]`` in the full-dimensional zonotope ``Z(c, G)``, d in {2, 3}.

    Uses the facet normals: perpendiculars of the generators in 2-D, cross products
    of generator pairs in 3-D; ``p ∈ Z`` iff ``|n·(p - c)| <= Σ_j |n·g_j|`` for all of them.
    """
    g = generators[:, np.linalg.norm(generators, axis=0) > 1e-12]
    if len(center) == 2:
        normals = np.stack([-g[1], g[0]], axis=1)
    else:
        normals = np.array([np.cross(g[:, i], g[:, j]) for i, j in itertools.combinations(range(g.shape[1]), 2)])
        normals = normals[np.linalg.norm(normals, axis=1) > 1e-12]
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    radius = np.abs(normals @ g).sum(axis=1)
    return np.all(np.abs((points - center) @ normals.T) <= radius + tol, axis=1)


def place_robot(env, position: np.ndarray, velocity: np.ndarray | None = None, heading: float | None = None) -> None:
    """Teleports the robot of a task env (position ``[d]``), optionally with a velocity and heading."""
    physics = env.physics
    d = len(position)
    physics.data.qpos[:d] = position
    if heading is not None:
        physics.data.qpos[2] = heading
    if velocity is not None:
        physics.data.qvel[: len(velocity)] = velocity
    physics.forward()


def manual_step(env, action) -> np.ndarray:
    """What ``control.Environment.step`` does, without its episode bookkeeping; returns the next state."""
    raw = env._env
    task, physics = raw.task, raw.physics
    task.before_step(action, physics)
    physics.step(int(round(raw.control_timestep() / physics.timestep())))
    task.after_step(physics)
    return task.state(physics)


def robot_obstacle_distance(env, position: np.ndarray, geom: int) -> float:
    """Signed distance between the robot's collision geom, centred at ``position``, and ``geom``."""
    physics = env.physics
    model, data = physics.model.ptr, physics.data.ptr
    physics.data.qpos[: len(position)] = position
    mujoco.mj_kinematics(model, data)
    robot = physics.model.name2id("robot", "geom")
    return mujoco.mj_geomDistance(model, data, robot, geom, 10.0, None)
