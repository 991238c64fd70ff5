"""A second, low-speed model lets the layer creep and turn near obstacles instead of freezing."""
import functools

import pytest
import torch
from torchrl.envs import SerialEnv, TransformedEnv

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

TASK = "diffdrive_nav"
LINEAR = {"max_acceleration": None, "max_turn_acceleration": None}  # only the kinematics are nonlinear
SLOW = 0.1  # the local domain: forward speed and speed command <= 0.1 m/s
N_ENVS, STEPS = 6, 150


@functools.lru_cache(maxsize=None)
def models():
    info = envs.safety_info(TASK)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    # the low-speed domain model is a global fit on a restricted domain, beside a global model
    options = {"translation_invariant_dims": info.position_dims, "max_generators": 30, "method": "global"}
    torch.manual_seed(0)
    reach = DataDrivenReach.from_data(collect_offline_data(envs.make(TASK, empty=True, seed=1, **LINEAR), 2000),
                                      noise, **options)
    high = torch.tensor([SLOW, 0.5])

    def slow_inputs(td):
        td["action"] = torch.rand(2) * (high - info.action_low) + info.action_low
        return td

    data = collect_offline_data(envs.make(TASK, empty=True, seed=2, **LINEAR), 2000, policy=slow_inputs)
    inf = torch.inf
    domain = (torch.full((8,), -inf), torch.tensor([inf, inf, inf, inf, SLOW, inf, SLOW, inf]))
    return reach, DataDrivenReach.from_data(data, noise, domain=domain, **options)


def layer(local: bool, **kwargs):
    info = envs.safety_info(TASK)
    reach, slow = models()
    return BRSLSafetyLayer(reach, Failsafe(info.braking_action, 3), 1, stop_dims=info.velocity_dims,
                           stop_tolerance=0.2, action_low=info.action_low, action_high=info.action_high,
                           adjuster="facet_qp", local_reach=slow if local else None, **kwargs)


def towards_nearest_obstacle(td):
    """Adversarial: full speed, steering at the nearest obstacle."""
    state = td["state"]
    centers, mask = td["obstacles", "center"], td["obstacles", "mask"]
    offset = centers - state[..., None, :2]
    distance = torch.where(mask, offset.norm(dim=-1), torch.full_like(mask, float("inf"), dtype=offset.dtype))
    target = offset.gather(-2, distance.argmin(-1, keepdim=True).unsqueeze(-1).expand(-1, 1, 2)).squeeze(-2)
    bearing = torch.atan2(target[..., 1], target[..., 0]) - torch.atan2(state[..., 3], state[..., 2])
    bearing = torch.atan2(torch.sin(bearing), torch.cos(bearing))
    td["action"] = torch.stack((torch.full_like(bearing, 0.25), (2 * bearing).clamp(-0.5, 0.5)), -1)
    return td


def rollout(local: bool):
    base = SerialEnv(N_ENVS, [functools.partial(envs.make, TASK, seed=i, episode_steps=STEPS, **LINEAR)
                              for i in range(N_ENVS)])
    env = TransformedEnv(base, layer(local))
    env.set_seed(0)
    td = env.rollout(STEPS, towards_nearest_obstacle, break_when_any_done=False)
    env.close()
    return td["next"]


def test_local_model_keeps_the_robot_safe_and_moving_near_obstacles():
    plain, local = rollout(False), rollout(True)
    for out in (plain, local):
        assert not out["collision"].any()  # MuJoCo contacts: the ground truth
    assert not plain["brsl", "local"].any()
    used = local["brsl", "local"].squeeze(-1)
    assert used.any()
    # what the local model verified respects its domain: speed commands <= SLOW
    assert (local["safe_action"][..., 0][used] <= SLOW + 1e-6).all()
    # and it replaces most of the freezing: far fewer steps end in the failsafe
    assert local["brsl", "failsafe"].float().mean() < 0.5 * plain["brsl", "failsafe"].float().mean()


def test_local_model_must_match_the_dims():
    info = envs.safety_info("point_boxes")
    other = DataDrivenReach.from_data(
        collect_offline_data(envs.make("point_boxes", empty=True, seed=0, max_acceleration=None), 100),
        Zonotope(info.noise_center.double(), info.noise_generators.double()), translation_invariant_dims=(0, 1))
    with pytest.raises(ValueError, match="local_reach"):
        BRSLSafetyLayer(models()[0], Failsafe(torch.zeros(2), 3), 1, stop_dims=(4, 5), stop_tolerance=0.2,
                        action_low=torch.tensor([0.0, -0.5]), action_high=torch.tensor([0.25, 0.5]), local_reach=other)
