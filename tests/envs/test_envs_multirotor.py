"""The rotor-driven multirotors (``robot="rotor"`` of ``quadrotor_nav`` and ``hexarotor_wind``): specs, hovering,
velocity tracking, braking, noise, crashes and seeding."""
import numpy as np
import pytest
import torch

import envs
from envs._rotor import OnboardPhysics
from envs.hexarotor_wind import RotorHexarotorWind
from envs.quadrotor_nav import RotorQuadrotorNav
from envs_support import manual_step, place_robot, zonotope_contains

torch.set_num_threads(1)
TASKS = {"quadrotor_nav": RotorQuadrotorNav, "hexarotor_wind": RotorHexarotorWind}
ROTORS = {"quadrotor_nav": 4, "hexarotor_wind": 6}
WINDY = 0  # the fixed layout of hexarotor_wind used here: wind 2.6 m/s


def _rotor(name, **kwargs):
    return envs.make(name, robot="rotor", **kwargs)


def _free_flight(name, **kwargs):
    """An empty-variant env with the robot at rest, noise off (stepped by :func:`_fly`, without episode ends)."""
    env = _rotor(name, seed=0, empty=True, **kwargs)
    env.reset()
    env.task.noise_scale = 0.0
    place_robot(env, np.array([0.0, 0.0, 2.0]), velocity=np.zeros(6))
    return env


def _fly(env, command, steps):
    """Holds ``command`` for ``steps`` control steps; returns the states ``[steps, n]``."""
    return np.array([manual_step(env, np.asarray(command, dtype=np.float64)) for _ in range(steps)])


@pytest.mark.parametrize("name", list(TASKS))
def test_specs_and_keys_match_the_kinematic_robot(name):
    rotor, kinematic = _rotor(name, seed=0), envs.make(name, seed=0)
    assert isinstance(rotor.task, TASKS[name]) and isinstance(rotor.physics, OnboardPhysics)
    assert rotor.physics.model.nu == ROTORS[name]
    assert rotor.observation_spec == kinematic.observation_spec
    assert rotor.action_spec == kinematic.action_spec and rotor.reward_spec == kinematic.reward_spec
    td, reference = rotor.reset(), kinematic.reset()
    assert td["state"].shape == reference["state"].shape and td["observation"].shape == reference["observation"].shape
    np.testing.assert_array_equal(td["obstacles", "center"], reference["obstacles", "center"])  # same layouts
    assert set(rotor.rollout(3).keys(True)) == set(kinematic.rollout(3).keys(True))
    info, default = envs.safety_info(name, robot="rotor"), envs.safety_info(name)
    assert info.n_brk == rotor.task.safety_info().n_brk == 16 and info.n_plan == 17
    for key in ("state_dim", "action_dim", "position_dims", "velocity_dims", "stop_tolerance", "dt"):
        assert getattr(info, key) == getattr(default, key)
    for key in ("action_low", "action_high", "noise_center", "noise_generators", "braking_action"):
        assert torch.equal(getattr(info, key), getattr(default, key))


def test_unknown_robot_and_kinematic_limits_are_rejected():
    with pytest.raises(ValueError, match=r"'wheeled'.*'kinematic', 'rotor'"):
        envs.make("quadrotor_nav", robot="wheeled")
    with pytest.raises(ValueError, match="max_acceleration"):
        _rotor("hexarotor_wind", max_acceleration=None)
    with pytest.raises(ValueError, match=r"'rotor'.*'kinematic', 'wheeled'"):
        envs.safety_info("diffdrive_nav", robot="rotor")


@pytest.mark.parametrize("name", list(TASKS))
def test_hovering_holds_position(name):
    """Zero command: a stopped robot stays within a millimetre over 100 steps (the hexarotor in wind, once its
    integral offset has taken up the drag), and within the stop tolerance under the process noise."""
    env = _free_flight(name, layout=WINDY)
    if name == "hexarotor_wind":
        assert np.linalg.norm(env.task.wind) > 2.0
    _fly(env, np.zeros(3), 40)
    start = env.physics.data.qpos[:3].copy()
    states = _fly(env, np.zeros(3), 100)
    assert np.abs(states[:, :3] - start).max() < 1e-3
    env.task.noise_scale = 1.0
    states = _fly(env, np.zeros(3), 100)
    info = envs.safety_info(name, robot="rotor")
    assert info.is_stopped(torch.as_tensor(states)).all()
    _, qx, qy, qz = env.physics.data.qpos[3:7]
    assert abs(qz) < 0.01 and 2 * np.arcsin(np.hypot(qx, qy)) < np.radians(10)  # heading held, tilted into the wind


@pytest.mark.parametrize("name", list(TASKS))
def test_velocity_tracking_reaches_the_command(name):
    env = _free_flight(name, layout=WINDY)
    _fly(env, np.zeros(3), 40)
    for command in ([3.0, -2.0, 1.0], [-5.0, 0.0, 0.0], [0.0, 4.0, -3.0]):
        states = _fly(env, command, 20)
        np.testing.assert_allclose(states[-1, 3:6], command, atol=0.05)
        gained = np.abs(np.diff(states[:, 3:6], axis=0)).max()
        assert gained <= 0.1 * 8.0 * 1.15  # the acceleration limit (8 m/s^2 per axis), tilting transients aside


@pytest.mark.parametrize("name", list(TASKS))
def test_braking_within_n_brk_from_sampled_reachable_states(name):
    env = _free_flight(name, layout=WINDY)
    env.task.noise_scale = 1.0
    info = envs.safety_info(name, robot="rotor")
    rng = np.random.RandomState(2)
    speeds = []
    for _ in range(12):  # random commands held (corners included), then the braking action
        for _ in range(rng.randint(1, 3)):
            command = rng.uniform(-5, 5, 3) if rng.rand() < 0.6 else 5.0 * rng.choice([-1.0, 1.0], 3)
            moving = _fly(env, command, rng.randint(3, 13))
        speeds.append(np.abs(moving[-1, 3:6]).max())
        states = _fly(env, info.braking_action.numpy(), info.n_brk + 5)
        stopped = info.is_stopped(torch.as_tensor(states)).tolist()
        assert all(stopped[info.n_brk - 1:]), stopped
    assert max(speeds) > 4.0


@pytest.mark.parametrize("name", list(TASKS))
def test_noise_stays_in_the_noise_zonotope(name):
    """Replayed from the same physics state (and integral offset) without noise, every step differs from the
    noisy one by a point of W."""
    env = _rotor(name, seed=0, empty=True)
    env.reset()
    physics, task = env.physics, env.task
    info = envs.safety_info(name, robot="rotor")
    c, G = info.noise_center.double().numpy(), info.noise_generators.double().numpy()
    rng = np.random.RandomState(0)
    for _ in range(10):
        action = rng.uniform(-5, 5, 3)
        before = physics.get_state().copy(), getattr(task, "offset", None)
        task.noise_scale = 1.0
        noisy = manual_step(env, action)
        after = physics.get_state().copy(), getattr(task, "offset", None)
        for (state, offset), scale in ((before, 0.0), (after, None)):
            physics.set_state(state)
            physics.forward()
            if offset is not None:
                task.offset = offset
            if scale is not None:
                task.noise_scale = scale
                clean = manual_step(env, action)
        z, *_ = np.linalg.lstsq(G, noisy - clean - c, rcond=None)
        np.testing.assert_allclose(G @ z + c, noisy - clean, atol=1e-9)
        assert np.abs(z).max() <= 1.0 + 1e-6


@pytest.mark.parametrize("name", list(TASKS))
def test_flying_into_an_obstacle_collides_and_terminates(name):
    env = _rotor(name, seed=1)
    td = env.reset()
    layout = env.layout
    obstacle = layout.obstacles[6]  # the first pillar
    direction = -obstacle.pos[:2] / np.linalg.norm(obstacle.pos[:2])
    start = np.array([*(obstacle.pos[:2] + direction * (obstacle.xy_radius + env.task.robot_radius + 0.4)), 2.5])
    place_robot(env, start, velocity=np.zeros(6))
    assert not env.task._in_contact(env.physics)
    for _ in range(30):
        td = env.step(td.set("action", torch.tensor([*(-3.0 * direction), 0.0], dtype=torch.float32)))
        if td["next", "done"]:
            break
        td = env.step_mdp(td)
    nxt = td["next"]
    assert nxt["collision"] and nxt["terminated"] and not nxt["truncated"] and nxt["reward"] <= -9.0
    position = nxt["state"][:3].double().numpy()[None]
    assert zonotope_contains(layout.obstacle_center[6], layout.obstacle_generators[6], position, 1e-4)[0]


def test_descending_quadrotor_hits_the_floor():
    env = _rotor("quadrotor_nav", seed=0)
    td = env.reset()
    for _ in range(30):
        td = env.step(td.set("action", torch.tensor([0.0, 0.0, -5.0])))
        if td["next", "done"]:
            break
        td = env.step_mdp(td)
    assert td["next", "collision"] and td["next", "terminated"]
    assert float(td["next", "state"][2]) <= 0.3 + 0.05


@pytest.mark.parametrize("name", list(TASKS))
def test_seeding_reproduces_episodes(name):
    actions = torch.as_tensor(np.random.RandomState(0).uniform(-5, 5, (15, 3)), dtype=torch.float32)

    def rollout(seed):
        env = _rotor(name, seed=seed, empty=True)
        td, states = env.reset(), []
        for action in actions:
            td = env.step_mdp(env.step(td.set("action", action)))
            states.append(td["state"])
        return torch.stack(states)

    first = rollout(5)
    assert torch.equal(first, rollout(5))
    assert not torch.equal(first, rollout(6))
