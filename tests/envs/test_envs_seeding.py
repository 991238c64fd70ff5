"""Seeds, fixed evaluation layouts, and copies that step as the original."""
import copy

import numpy as np
import pytest
import torch

import envs



def _layout_signature(env):
    layout = env.layout
    return np.concatenate(
        [layout.obstacle_center.ravel(), layout.obstacle_generators.ravel(), layout.goals.ravel(), layout.start.ravel()]
    )


def _rollout(env, steps=15):
    info = envs.safety_info(env.task.name)
    generator = torch.Generator().manual_seed(0)

    def policy(td):
        u = torch.rand(info.action_dim, generator=generator)
        return td.set("action", info.action_low + u * (info.action_high - info.action_low))

    return env.rollout(steps, policy, break_when_any_done=False)


@pytest.mark.parametrize("name", envs.TASKS)
def test_same_seed_same_episodes(name):
    a, b = envs.make(name, seed=7), envs.make(name, seed=7)
    for _ in range(2):
        td_a, td_b = a.reset(), b.reset()
        np.testing.assert_array_equal(_layout_signature(a), _layout_signature(b))
        assert torch.equal(td_a["obstacles", "center"], td_b["obstacles", "center"])
    # including the process noise
    assert torch.equal(_rollout(a)["next", "state"], _rollout(b)["next", "state"])


@pytest.mark.parametrize("name", envs.TASKS)
def test_different_seeds_and_resets_differ(name):
    a, b = envs.make(name, seed=1), envs.make(name, seed=2)
    a.reset(), b.reset()
    first = _layout_signature(a)
    assert not np.array_equal(first, _layout_signature(b))
    a.reset()
    assert not np.array_equal(first, _layout_signature(a))


@pytest.mark.parametrize("name", envs.TASKS)
def test_fixed_layout_ignores_seed_and_resets(name):
    a, b = envs.make(name, seed=0, layout=3), envs.make(name, seed=123, layout=3)
    a.reset(), b.reset()
    reference = _layout_signature(a)
    np.testing.assert_array_equal(reference, _layout_signature(b))
    a.reset()
    np.testing.assert_array_equal(reference, _layout_signature(a))
    c = envs.make(name, seed=0, layout=4)
    c.reset()
    assert not np.array_equal(reference, _layout_signature(c))
    if name == "hexarotor_wind":
        np.testing.assert_array_equal(a.task.wind, b.task.wind)


def test_set_seed_reproduces_episodes():
    env = envs.make("diffdrive_nav", seed=None)
    env.set_seed(11)
    env.reset()
    first = _layout_signature(env)
    env.reset()
    env.set_seed(11)
    env.reset()
    np.testing.assert_array_equal(first, _layout_signature(env))


ROBOTS = [("point_boxes", None), ("point_circle", None), ("diffdrive_nav", "kinematic"), ("diffdrive_nav", "wheeled"),
          ("quadrotor_nav", "kinematic"), ("quadrotor_nav", "rotor"), ("hexarotor_wind", "kinematic"),
          ("hexarotor_wind", "rotor")]


@pytest.mark.parametrize("name, robot", ROBOTS)
def test_a_deep_copy_steps_as_the_original_to_the_bit(name, robot):
    """Copies taken after a reset and mid-episode take the original's steps exactly (noise included: the copy's
    random state is the original's), e.g. to sample many noisy futures from one reached state. A copy of MuJoCo's
    data alone would not: a velocity servo's first step pushed as if from rest, and a rotor robot flew without its
    onboard controller."""
    options = {} if robot is None else {"robot": robot}
    info = envs.safety_info(name, **options)
    env = envs.make(name, seed=3, empty=True, episode_steps=10_000, **options)
    gen = torch.Generator().manual_seed(0)

    def action():
        return (info.action_low + (info.action_high - info.action_low) * torch.rand(info.action_low.shape,
                                                                                   generator=gen)).float()

    for warm in (0, 3):
        td = env.reset()
        for _ in range(warm):
            td = env.step_mdp(env.step(td.set("action", action())))
        twin, plan, runs = copy.deepcopy(env), [action() for _ in range(4)], []
        for robot_env in (twin, env):
            x, states = td.clone(), []
            for u in plan:
                x = robot_env.step(x.set("action", u))
                states.append(x["next", "state"])
                x = robot_env.step_mdp(x)
            runs.append(torch.stack(states))
        assert torch.equal(runs[0], runs[1])
