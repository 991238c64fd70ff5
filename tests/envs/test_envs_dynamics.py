"""Collisions, process noise, braking, termination and goals, checked in simulation."""
import numpy as np
import pytest
import torch

import envs
from envs_support import manual_step, place_robot, zonotope_contains



def _step(env, td, action):
    td = env.step(td.set("action", torch.as_tensor(action, dtype=torch.float32)))
    return td, td["next"].clone()


def test_point_collision_iff_outside_safe_box():
    env = envs.make("point_circle", seed=0, terminate_on_collision=False)  # keeps going through the walls
    td = env.reset()
    collisions, states = [], []
    for _ in range(60):
        td, nxt = _step(env, td, [1.0, 0.4])
        collisions.append(bool(nxt["collision"]))
        states.append(nxt["state"].double().numpy())
        td = env.step_mdp(td)
    states = np.array(states)
    outside = (np.abs(states[:, 0]) > 1.2) | (np.abs(states[:, 1]) > 1.2)
    clear = np.minimum(np.abs(np.abs(states[:, 0]) - 1.2), np.abs(np.abs(states[:, 1]) - 1.2)) > 1e-3
    assert any(collisions)
    assert np.array_equal(np.array(collisions)[clear], outside[clear])


def _obstacle_in_reach(layout, start_offset):
    """Index of the first non-boundary obstacle and a start point ``start_offset`` m off its footprint."""
    first = 4 if layout.obstacle_center.shape[1] == 2 else 6
    obstacle = layout.obstacles[first]
    centre = obstacle.pos[: layout.obstacle_center.shape[1]].copy()
    direction = -centre[:2] / np.linalg.norm(centre[:2])  # from the obstacle towards the arena centre
    start = centre.copy()
    start[:2] += direction * (obstacle.xy_radius + start_offset)
    return first, start, -direction


@pytest.mark.parametrize(
    "name, speed", [("diffdrive_nav", 0.25), ("quadrotor_nav", 3.0), ("hexarotor_wind", 3.0), ("point_boxes", 1.0)]
)
def test_driving_straight_into_an_obstacle_collides(name, speed):
    env = envs.make(name, seed=1)
    td = env.reset()
    layout = env.layout
    index, start, direction = _obstacle_in_reach(layout, start_offset=env.task.robot_radius + 0.4)
    if name == "diffdrive_nav":
        place_robot(env, start, heading=float(np.arctan2(direction[1], direction[0])))
        action = [speed, 0.0]
    elif name == "point_boxes":
        place_robot(env, start)
        action = speed * direction
    else:
        place_robot(env, start)
        action = [*(speed * direction), 0.0]
    assert not env.task._in_contact(env.physics)
    for _ in range(60):
        td, nxt = _step(env, td, action)
        if nxt["done"]:
            break
        td = env.step_mdp(td)
    assert nxt["collision"] and nxt["terminated"] and not nxt["truncated"]
    assert nxt["reward"] <= -10 + 1.0
    position = nxt["state"][: layout.obstacle_center.shape[1]].double().numpy()
    assert zonotope_contains(layout.obstacle_center[index], layout.obstacle_generators[index], position[None], 1e-4)[0]


def test_quadrotor_descending_hits_the_floor():
    env = envs.make("quadrotor_nav", seed=0)
    td = env.reset()
    for step in range(40):
        td, nxt = _step(env, td, [0.0, 0.0, -5.0])
        if nxt["done"]:
            break
        td = env.step_mdp(td)
    assert nxt["collision"] and nxt["terminated"]
    assert float(nxt["state"][2]) <= 0.3 + 0.05


@pytest.mark.parametrize("name", envs.TASKS)
def test_no_collision_in_the_empty_variant(name):
    info = envs.safety_info(name)
    env = envs.make(name, seed=0, empty=True)
    generator = torch.Generator().manual_seed(0)

    def random_policy(td):
        u = torch.rand(info.action_dim, generator=generator)
        return td.set("action", info.action_low + u * (info.action_high - info.action_low))

    td = env.rollout(300, random_policy, break_when_any_done=False)
    assert not td["next", "collision"].any()
    assert td["next", "speed"].max() > 0.1 * info.action_high.abs().max()  # it did move around


def _snapshot(env):
    """The physics state and the controller memory (``hexarotor_wind``'s integral offset)."""
    return env.physics.get_state().copy(), getattr(env.task, "offset", None)


def _restore(env, snapshot):
    state, offset = snapshot
    env.physics.set_state(state)
    env.physics.forward()
    if offset is not None:
        env.task.offset = offset


@pytest.mark.parametrize("name", envs.TASKS)
def test_noise_stays_in_the_noise_zonotope(name):
    """Replay each step from the same physics state without noise: the difference of
    the next states must lie in W = Z(noise_center, noise_generators), and be the task's ``last_noise``."""
    info = envs.safety_info(name)
    env = envs.make(name, seed=0, empty=True)
    env.reset()
    task = env.task
    rng = np.random.RandomState(0)
    c = info.noise_center.double().numpy()
    G = info.noise_generators.double().numpy()
    coefficients = []
    for _ in range(40):
        action = rng.uniform(info.action_low.numpy(), info.action_high.numpy())
        snapshot = _snapshot(env)
        task.noise_scale = 1.0
        noisy = manual_step(env, action)
        drawn = task.last_noise
        after = _snapshot(env)
        _restore(env, snapshot)
        task.noise_scale = 0.0
        clean = manual_step(env, action)
        assert not task.last_noise.any()
        _restore(env, after)
        np.testing.assert_allclose(drawn, noisy - clean, atol=1e-9)  # what the task reports it added
        z, *_ = np.linalg.lstsq(G, noisy - clean - c, rcond=None)
        np.testing.assert_allclose(G @ z + c, noisy - clean, atol=1e-9)
        coefficients.append(z)
    coefficients = np.abs(np.array(coefficients))
    assert coefficients.max() <= 1.0 + 1e-6
    assert (coefficients.max(axis=0) > 0.5).all()  # every noise direction is exercised


def _random_moving_states(name, rng, n):
    """Velocities spanning the data region, extremes included."""
    if name == "point_circle":
        angles = rng.uniform(0, 2 * np.pi, n)
        speeds = np.r_[2.0, 2.0, rng.uniform(0, 2.0, n - 2)]
        return speeds[:, None] * np.stack([np.cos(angles), np.sin(angles)], 1)
    if name == "diffdrive_nav":
        v = np.r_[0.25, 0.25, rng.uniform(0, 0.25, n - 2)]
        w = np.r_[0.5, -0.5, rng.uniform(-0.5, 0.5, n - 2)]
        return np.stack([v, w], 1)
    if name == "point_boxes":  # per-axis commands in [-1, 1], plus the noise
        corners = np.array([[1.01, 1.01], [-1.01, 0.5]])
        return np.concatenate([corners, rng.uniform(-1, 1, (n - 2, 2))])
    corners = np.array([[5.0, 5.0, 5.0], [-5.0, 5.0, -5.0]])
    return np.concatenate([corners, rng.uniform(-5, 5, (n - 2, 3))])


_UNCAPPED = {"max_acceleration": None}
_LINEAR = {"point_boxes": _UNCAPPED, "quadrotor_nav": _UNCAPPED, "hexarotor_wind": _UNCAPPED,
           "diffdrive_nav": {**_UNCAPPED, "max_turn_acceleration": None}}


@pytest.mark.parametrize("name", [*envs.TASKS, *(f"{task}_linear" for task in _LINEAR)])
def test_braking_policy_stops_within_n_brk(name):
    kwargs = {}
    if name.endswith("_linear"):
        name = name.removesuffix("_linear")
        kwargs = _LINEAR[name]
    info = envs.safety_info(name)
    env = envs.make(name, seed=0, empty=True, episode_steps=1000, **kwargs)
    rng = np.random.RandomState(1)
    for velocity in _random_moving_states(name, rng, 8):
        td = env.reset()
        physics = env.physics
        if name == "diffdrive_nav":
            heading = physics.data.qpos[2]
            planar = [velocity[0] * np.cos(heading), velocity[0] * np.sin(heading), velocity[1]]
            place_robot(env, np.zeros(2), velocity=planar)
        else:
            place_robot(env, physics.data.qpos[: info.obstacle_dim].copy(), velocity=velocity)
        state = torch.as_tensor(env.task.state(physics), dtype=torch.float32)
        assert not info.is_stopped(state)
        stopped = []
        for _ in range(info.n_brk + 5):
            td = env.step(td.set("state", state).set("action", info.braking_policy(state)))
            assert not td["next", "done"]
            state = td["next", "state"]
            stopped.append(bool(info.is_stopped(state)))
            td = env.step_mdp(td)
        assert all(stopped[info.n_brk - 1 :]), (velocity, stopped)
        assert float(td["speed"]) <= info.stop_tolerance * np.sqrt(info.obstacle_dim)


@pytest.mark.parametrize("name", envs.TASKS)
def test_time_limit_truncates(name):
    info = envs.safety_info(name)
    env = envs.make(name, seed=0, episode_steps=7)
    td = env.rollout(20, lambda td: td.set("action", info.braking_action.clone()))
    assert td.shape == (7,)
    assert td["next", "truncated"][-1] and not td["next", "terminated"][-1]
    assert not td["next", "done"][:-1].any()


@pytest.mark.parametrize("name", envs.TASKS)
def test_leaving_the_data_region_truncates_the_empty_variant(name):
    info = envs.safety_info(name)
    env = envs.make(name, seed=0, empty=True)
    td = env.reset()
    far = torch.zeros(info.obstacle_dim)
    far[0] = 30.0
    place_robot(env, far.numpy(), velocity=np.zeros(info.obstacle_dim))
    td, nxt = _step(env, td, info.braking_action)
    assert nxt["truncated"] and not nxt["terminated"]


@pytest.mark.parametrize("name", ["diffdrive_nav", "quadrotor_nav"])
def test_reaching_the_goal_terminates(name):
    env = envs.make(name, seed=2)
    td = env.reset()
    layout = env.layout
    goal = layout.goals[0]
    direction = goal[:2] / np.linalg.norm(goal[:2])
    start = goal.copy()
    start[:2] -= direction * (layout.goal_radius + 0.05)
    if name == "diffdrive_nav":
        place_robot(env, start, heading=float(np.arctan2(direction[1], direction[0])))
        action = [0.25, 0.0]
    else:
        place_robot(env, start)
        action = [*(2.0 * direction), 0.0]
    for _ in range(10):
        td, nxt = _step(env, td, action)
        if nxt["done"]:
            break
        td = env.step_mdp(td)
    assert nxt["goal_reached"] and nxt["terminated"] and not nxt["collision"]
    assert nxt["reward"] >= 10.0


def test_hexarotor_checkpoints_in_order():
    env = envs.make("hexarotor_wind", seed=0)
    td = env.reset()
    goals = env.layout.goals
    rewards = 0.0
    # visiting checkpoint 1 first does not count
    place_robot(env, goals[1], velocity=np.zeros(3))
    td, nxt = _step(env, td, [0.0, 0.0, 0.0])
    assert env.task.goal_index == 0 and not nxt["goal_reached"]
    td = env.step_mdp(td)
    for k, goal in enumerate(goals):
        place_robot(env, goal, velocity=np.zeros(3))
        td, nxt = _step(env, td, [0.0, 0.0, 0.0])
        rewards += float(nxt["reward"])
        assert env.task.goal_index == k + 1
        assert bool(nxt["goal_reached"]) == (k == len(goals) - 1)
        td = env.step_mdp(td)
    assert nxt["terminated"]
    assert rewards >= 10 * len(goals) - 1.0


def test_hexarotor_wind_pushes_a_hovering_robot_until_the_integral_action_holds_it():
    """Paper Assumption 1 in wind: the zero command stops the robot and keeps it stopped."""
    env = envs.make("hexarotor_wind", seed=0, empty=True, layout=5)
    env.task.noise_scale = 0.0
    td = env.reset()
    wind = env.task.wind
    assert np.linalg.norm(wind) > 0.3
    start = np.array([0.0, 0.0, 2.5])
    place_robot(env, start, velocity=np.zeros(3))
    states = []
    for _ in range(60):
        td, nxt = _step(env, td, [0.0, 0.0, 0.0])
        states.append(nxt["state"].double().numpy())
        td = env.step_mdp(td)
    states = np.array(states)
    assert (states[0, :3] - start) @ wind > 0  # drifts downwind at first
    assert states[-1, 6:] @ wind < 0  # the offset ends up pointing upwind, cancelling the drag
    assert np.abs(states[10:, 3:6]).max() <= envs.safety_info("hexarotor_wind").stop_tolerance
    assert np.abs(states[-1, :3] - states[20, :3]).max() < 1e-3  # then it holds its position


def _uniform_policy(info, generator):
    def policy(td):
        u = torch.rand(info.action_dim, generator=generator)
        return td.set("action", info.action_low + u * (info.action_high - info.action_low))

    return policy


def test_point_boxes_random_policy_collides_in_most_episodes():
    """What the tests of safety layers rely on: without a layer, random actions crash."""
    info = envs.safety_info("point_boxes")
    env = envs.make("point_boxes", seed=0)
    policy = _uniform_policy(info, torch.Generator().manual_seed(0))
    collided = []
    for _ in range(30):
        td = env.rollout(1000, policy)
        assert td.shape[0] <= 80
        assert not td[0]["collision"]  # the start is clear
        collided.append(bool(td["next", "collision"].any()))
        if collided[-1]:
            assert td["next", "terminated"][-1] and td["next", "reward"][-1] == -10.0
    assert np.mean(collided) >= 0.5


def test_point_boxes_servo_tracks_the_command_within_the_acceleration_limit():
    env = envs.make("point_boxes", seed=0, empty=True)
    td = env.reset()
    place_robot(env, np.zeros(2), velocity=np.array([-1.0, 1.0]))
    velocities = [np.array([-1.0, 1.0])]
    for _ in range(8):
        td, nxt = _step(env, td, [1.0, 0.2])
        velocities.append(nxt["state"][2:].double().numpy())
        td = env.step_mdp(td)
    change = np.abs(np.diff(velocities, axis=0))
    assert change.max() <= 5.0 * 0.1 + 0.01 + 1e-6  # 5 m/s^2 per axis, plus the noise
    assert change[0, 0] >= 0.5 - 0.01 - 1e-6  # saturated at first
    np.testing.assert_allclose(velocities[-1], [1.0, 0.2], atol=0.012)
    assert nxt["reward"] == pytest.approx(float(np.linalg.norm(velocities[-1])), rel=1e-5)


@pytest.mark.parametrize(
    "name, axes, command, options, atol",
    [
        ("point_boxes", 2, 1.0, {}, 1e-12),
        ("quadrotor_nav", 3, 5.0, {"episode_steps": 1000}, 1e-9),
    ],
)
def test_servos_without_acceleration_limit_are_linear(name, axes, command, options, atol):
    """Noiseless steps of the uncapped variants: per axis ``v+ = a v + (1 - a) u``, ``x+ = x + c v + d u``."""
    env = envs.make(name, seed=0, empty=True, max_acceleration=None, **options)
    env.reset()
    env.task.noise_scale = 0.0
    rng = np.random.RandomState(0)
    rows, targets = [], []
    for _ in range(30):
        state = env.task.state(env.physics)
        action = rng.uniform(-command, command, axes)
        after = manual_step(env, action)
        for axis in range(axes):
            rows.append([state[axes + axis], action[axis]])
            targets.append([after[axis] - state[axis], after[axes + axis]])
    rows, targets = np.array(rows), np.array(targets)
    coefficients, *_ = np.linalg.lstsq(rows, targets, rcond=None)
    np.testing.assert_allclose(rows @ coefficients, targets, atol=atol)
    a = 0.6**5
    np.testing.assert_allclose(coefficients[:, 1], [a, 1 - a], atol=atol)
