"""The wheeled ``diffdrive_nav`` robot (``robot="wheeled"``): specs, braking, holding still, noise, collisions."""
import numpy as np
import pytest
import torch

import envs
from envs.diffdrive_nav import ARENA, WHEEL_RADIUS, WheeledDiffDriveNav
from envs_support import manual_step, place_robot, zonotope_contains

torch.set_num_threads(1)
INFO = envs.safety_info("diffdrive_nav")


def _wheeled(**kwargs):
    return envs.make("diffdrive_nav", robot="wheeled", **kwargs)


def _drive(env, td, command, steps):
    """Steps ``command`` and returns the last TensorDict (after ``step_mdp``) and the visited states."""
    states = []
    for _ in range(steps):
        td = env.step(td.set("action", torch.as_tensor(command, dtype=torch.float32)))
        assert not td["next", "done"]
        states.append(td["next", "state"])
        td = env.step_mdp(td)
    return td, torch.stack(states)


def test_specs_and_keys_match_the_kinematic_robot():
    wheeled, kinematic = _wheeled(seed=0), envs.make("diffdrive_nav", seed=0)
    assert isinstance(wheeled.task, WheeledDiffDriveNav)
    assert wheeled.observation_spec == kinematic.observation_spec
    assert wheeled.action_spec == kinematic.action_spec and wheeled.reward_spec == kinematic.reward_spec
    td = wheeled.reset()
    assert td["state"].shape == (6,) and td["observation"].shape == (23,)
    assert td["obstacles", "center"].shape == (12, 2) and int(td["obstacles", "mask"].sum()) == 12
    assert set(wheeled.rollout(3).keys(True)) == set(kinematic.rollout(3).keys(True))


def test_unknown_robot_and_kinematic_limits_are_rejected():
    with pytest.raises(ValueError, match=r"'tank'.*'kinematic', 'wheeled'"):
        envs.make("diffdrive_nav", robot="tank")
    with pytest.raises(ValueError, match="max_acceleration"):
        _wheeled(max_acceleration=None)


@pytest.mark.parametrize("command", [(0.25, 0.0), (0.0, 0.5), (0.0, -0.5), (0.25, 0.5)])
def test_braking_stops_within_n_brk_from_full_speed(command):
    env = _wheeled(seed=0, empty=True, episode_steps=1000)
    td = env.reset()
    place_robot(env, np.zeros(2), velocity=np.zeros(6))
    td, states = _drive(env, td, command, 10)
    np.testing.assert_allclose(states[-1, 4:].numpy(), command, atol=0.02)  # cruising at the command
    td, states = _drive(env, td, INFO.braking_action, INFO.n_brk + 4)
    stopped = INFO.is_stopped(states).tolist()
    assert all(stopped[INFO.n_brk - 1:]), stopped


def test_zero_command_keeps_a_stopped_robot_stopped():
    env = _wheeled(seed=0, empty=True, episode_steps=1000)
    td = env.reset()
    place_robot(env, np.zeros(2), velocity=np.zeros(6))
    pose = env.physics.data.qpos[:3].copy()
    td, states = _drive(env, td, INFO.braking_action, 50)
    speeds = states[:, 4:].abs().amax(0).numpy()
    assert speeds[0] <= 0.005 + 1e-3 and speeds[1] <= 0.01 + 1e-3  # the last step's noise, nothing more
    assert np.abs(env.physics.data.qpos[:3] - pose).max() < 2e-3


def test_noise_changes_only_v_and_omega_within_their_bounds():
    env = _wheeled(seed=0, empty=True)
    env.reset()
    physics, task = env.physics, env.task
    rng = np.random.RandomState(0)
    for _ in range(10):
        action = rng.uniform(INFO.action_low.numpy(), INFO.action_high.numpy())
        before = physics.get_state().copy()
        task.noise_scale = 1.0
        noisy = manual_step(env, action)
        drawn = task.last_noise
        after = physics.get_state().copy()
        physics.set_state(before)
        physics.forward()
        task.noise_scale = 0.0
        difference = noisy - manual_step(env, action)
        physics.set_state(after)
        physics.forward()
        np.testing.assert_allclose(difference, drawn, atol=1e-9)  # what the task reports it added
        np.testing.assert_allclose(difference[:4], 0.0, atol=1e-12)
        assert abs(difference[4]) <= 0.005 + 1e-12 and abs(difference[5]) <= 0.01 + 1e-12
        wheels = physics.data.qvel[4:6] * WHEEL_RADIUS
        assert abs(wheels.mean() - noisy[4]) < 0.01  # the kick keeps the wheels rolling with the chassis


def test_driving_into_a_wall_collides():
    env = _wheeled(seed=0)
    td = env.reset()
    place_robot(env, np.array([0.0, -ARENA + 0.5]), heading=-np.pi / 2)  # 0.39 m from the south wall
    assert not env.task._in_contact(env.physics)
    for _ in range(40):
        td = env.step(td.set("action", torch.tensor([0.25, 0.0])))
        if td["next", "done"]:
            break
        td = env.step_mdp(td)
    nxt = td["next"]
    assert nxt["collision"] and nxt["terminated"] and not nxt["truncated"]
    position = nxt["state"][:2].double().numpy()[None]
    layout = env.layout
    assert any(zonotope_contains(c, g, position, 1e-4)[0] for c, g in
               zip(layout.obstacle_center, layout.obstacle_generators))


def test_empty_variant_starts_rolling_and_truncates_outside_the_data_region():
    env = _wheeled(seed=0, empty=True)
    speeds = []
    for _ in range(5):
        state = env.reset()["state"].double().numpy()
        speeds.append(state[4:])
        np.testing.assert_allclose(env.physics.data.qvel[4:6].mean() * WHEEL_RADIUS, state[4], atol=1e-9)
    speeds = np.array(speeds)
    assert (speeds[:, 0] >= 0).all() and (speeds[:, 0] <= 0.25).all() and (np.abs(speeds[:, 1]) <= 0.5).all()
    assert np.ptp(speeds, axis=0).min() > 0.01  # random, not all at rest
    td = env.reset()
    place_robot(env, np.array([30.0, 0.0]))
    nxt = env.step(td.set("action", INFO.braking_action.clone()))["next"]
    assert nxt["truncated"] and not nxt["terminated"]
