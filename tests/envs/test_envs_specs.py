"""Specs, keys, shapes and the SafetyInfo of every task."""
import dataclasses

import pytest
import torch
from torchrl.envs.utils import check_env_specs

import envs
from envs._obstacles import GENERATORS_PER_OBSTACLE
from envs._safety_info import SafetyInfo
from envs.diffdrive_nav import DiffDriveNav
from envs.hexarotor_wind import HexarotorWind
from envs.point_boxes import PointBoxes
from envs.point_circle import PointCircle
from envs.quadrotor_nav import QuadrotorNav

TASK_CLASSES = {"point_circle": PointCircle, "diffdrive_nav": DiffDriveNav, "quadrotor_nav": QuadrotorNav,
                "hexarotor_wind": HexarotorWind, "point_boxes": PointBoxes}

CAPACITY = {"point_circle": 4, "diffdrive_nav": 12, "quadrotor_nav": 18, "hexarotor_wind": 14, "point_boxes": 10}
OBSERVATION_DIM = {"point_circle": 5, "diffdrive_nav": 23, "quadrotor_nav": 22, "hexarotor_wind": 26, "point_boxes": 12}


@pytest.mark.parametrize("empty", [False, True])
@pytest.mark.parametrize("name", envs.TASKS)
def test_check_env_specs(name, empty):
    check_env_specs(envs.make(name, seed=0, empty=empty))


@pytest.mark.parametrize("empty", [False, True])
@pytest.mark.parametrize("name", ["point_boxes", "quadrotor_nav", "hexarotor_wind"])
def test_check_env_specs_without_acceleration_limit(name, empty):
    check_env_specs(envs.make(name, seed=0, empty=empty, max_acceleration=None))


@pytest.mark.parametrize("name", envs.TASKS)
def test_keys_shapes_and_dtypes(name):
    info = envs.safety_info(name)
    env = envs.make(name, seed=0)
    k, d = CAPACITY[name], info.obstacle_dim
    td = env.rollout(4, policy=lambda td: td.set("action", info.braking_policy(td["state"])))
    step = td[-1]["next"]
    expected = {
        "observation": ((OBSERVATION_DIM[name],), torch.float32),
        "state": ((info.state_dim,), torch.float64),
        ("obstacles", "center"): ((k, d), torch.float64),
        ("obstacles", "generators"): ((k, d, GENERATORS_PER_OBSTACLE[d]), torch.float64),
        ("obstacles", "mask"): ((k,), torch.bool),
        "collision": ((1,), torch.bool),
        "goal_reached": ((1,), torch.bool),
        "speed": ((1,), torch.float32),
        "cost": ((1,), torch.float64),
        "reward": ((1,), torch.float32),
        "done": ((1,), torch.bool),
        "terminated": ((1,), torch.bool),
        "truncated": ((1,), torch.bool),
    }
    for key, (shape, dtype) in expected.items():
        assert step[key].shape == shape, key
        assert step[key].dtype == dtype, key
    assert td["action"].shape == (4, info.action_dim)
    mask = step["obstacles", "mask"]
    assert mask.any()
    assert (step["obstacles", "center"][~mask] == 0).all()
    assert (step["obstacles", "generators"][~mask] == 0).all()
    # real obstacles have no zero generator (facet normals stay defined)
    assert (step["obstacles", "generators"][mask].norm(dim=-2) > 0).all()


@pytest.mark.parametrize("name", envs.TASKS)
def test_empty_variant_has_no_obstacles(name):
    td = envs.make(name, seed=0, empty=True).rollout(3)
    assert not td["next", "obstacles", "mask"].any()
    assert (td["next", "obstacles", "generators"] == 0).all()


@pytest.mark.parametrize("name", envs.TASKS)
def test_safety_info_is_consistent_with_the_env(name):
    info = envs.safety_info(name)
    env = envs.make(name, seed=0)
    assert torch.equal(env.action_spec.space.low, info.action_low)
    assert torch.equal(env.action_spec.space.high, info.action_high)
    assert info.position_dims == tuple(range(info.obstacle_dim))
    assert not set(info.position_dims) & set(info.velocity_dims)
    assert info.noise_center.shape == (info.state_dim,)
    assert info.noise_generators.shape[0] == info.state_dim
    assert (info.noise_generators[list(info.position_dims)] == 0).all()
    assert info.n_plan > info.n_brk > 0
    assert info.dt == pytest.approx(0.1)
    assert ((info.braking_action >= info.action_low) & (info.braking_action <= info.action_high)).all()
    states = torch.randn(5, 3, info.state_dim)
    actions = info.braking_policy(states)
    assert actions.shape == (5, 3, info.action_dim)
    assert ((actions >= info.action_low) & (actions <= info.action_high)).all()
    assert info.is_stopped(torch.zeros(info.state_dim))
    moving = torch.zeros(info.state_dim)
    moving[info.velocity_dims[0]] = 2 * info.stop_tolerance
    assert not info.is_stopped(moving)


@pytest.mark.parametrize("name", envs.TASKS)
def test_safety_info_constants_are_the_task_class_attributes(name):
    task, info = TASK_CLASSES[name], envs.safety_info(name)
    assert (info.state_dim, info.action_dim) == (len(task.noise_center), len(task.action_low))
    for field in dataclasses.fields(SafetyInfo):
        if field.name in ("state_dim", "action_dim", "braking_policy"):
            continue
        value, expected = getattr(info, field.name), getattr(task, field.name)
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, torch.as_tensor(expected, dtype=torch.float32)), field.name
        else:
            assert value == expected, field.name
    state = torch.randn(5, info.state_dim)
    assert torch.equal(info.braking_policy(state), task.braking_policy(state))


def test_point_braking_policy_values():
    info = envs.safety_info("point_circle")
    state = torch.tensor([[0.3, -0.2, 0.05, -2.0], [0.0, 0.0, 1.0, 0.02]])
    expected = torch.tensor([[-0.5, 1.0], [-1.0, -0.2]])
    assert torch.allclose(info.braking_policy(state), expected)


def test_point_boxes_safety_info_values():
    info = envs.safety_info("point_boxes")
    assert (info.state_dim, info.action_dim, info.obstacle_dim) == (4, 2, 2)
    assert (info.position_dims, info.velocity_dims) == ((0, 1), (2, 3))
    assert (info.n_brk, info.n_plan, info.stop_tolerance) == (3, 6, 0.05)
    assert torch.equal(info.noise_generators, torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.01, 0.0], [0.0, 0.01]]))
    assert torch.equal(info.braking_action, torch.zeros(2))
    assert torch.equal(info.braking_policy(torch.ones(3, 4)), torch.zeros(3, 2))
    assert envs.TASKS[-1] == "point_boxes"


def test_make_forwards_task_arguments():
    """``build_environment`` arguments go to the task, the rest to the wrapper."""
    linear = envs.make("point_boxes", seed=0, max_acceleration=None, episode_steps=5)
    assert not linear.physics.model.actuator_forcelimited.any()
    hold = linear.action_spec.zero()  # not random actions: a collision would end the episode before the truncation
    assert linear.rollout(10, policy=lambda td: td.set("action", hold)).shape == (5,)
    assert envs.make("point_boxes", seed=0).physics.model.actuator_forcelimited.all()
    for name in ("quadrotor_nav", "hexarotor_wind"):
        assert not envs.make(name, seed=0, max_acceleration=None).physics.model.actuator_forcelimited.any()
        assert envs.make(name, seed=0).physics.model.actuator_forcelimited.all()


def test_unknown_task_raises():
    with pytest.raises(ValueError, match="unknown task"):
        envs.make("cartpole")
    with pytest.raises(ValueError, match="unknown task"):
        envs.safety_info("cartpole")


@pytest.mark.parametrize("name", envs.TASKS)
def test_observation_entries_are_copies(name):
    """Editing an output in place must not leak into the next step's output."""
    env = envs.make(name, seed=0)
    td = env.reset()
    center = td["obstacles", "center"].clone()
    mask = td["obstacles", "mask"].clone()
    td["obstacles", "center"].add_(1.0)
    td["obstacles", "mask"].logical_not_()
    td = env.step(td.set("action", envs.safety_info(name).braking_action))
    assert torch.equal(td["next", "obstacles", "center"], center)
    assert torch.equal(td["next", "obstacles", "mask"], mask)


def test_batched_serial_env():
    import functools

    from torchrl.envs import SerialEnv

    env = SerialEnv(2, [functools.partial(envs.make, "diffdrive_nav", seed=s) for s in (0, 1)])
    check_env_specs(env)
    td = env.rollout(3)
    assert td["next", "obstacles", "generators"].shape == (2, 3, 12, 2, 6)
    assert not torch.equal(td["obstacles", "center"][0], td["obstacles", "center"][1])
