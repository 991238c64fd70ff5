"""Every task ends its episode on a crash (point_circle: on leaving its safe box) and reports a per-step ``cost``."""
import numpy as np
import pytest
import torch

import envs


def _into_the_nearest_obstacle(name):
    """A policy heading for the first non-boundary obstacle (point_circle: the nearest wall)."""
    def policy(td):
        state = td["state"].double()
        if name == "point_circle":
            td["action"] = torch.where(state[:2] >= 0, 1.0, -1.0).float()
            return td
        info = envs.safety_info(name)
        mask = td["obstacles", "mask"]
        centers = td["obstacles", "center"][mask]
        d = info.obstacle_dim
        target = centers[(centers - state[:d]).norm(dim=-1).argmin()]
        direction = (target - state[:d]) / (target - state[:d]).norm()
        if name == "diffdrive_nav":  # turn towards the target, then drive
            heading = torch.atan2(state[3], state[2])
            error = torch.atan2(direction[1], direction[0]) - heading
            error = torch.atan2(torch.sin(error), torch.cos(error))
            td["action"] = torch.stack([torch.tensor(0.25) * (error.abs() < 0.3), 2 * error]).float()
        elif d == 3:
            td["action"] = torch.cat([info.action_high.max() * direction.float(), torch.zeros(info.action_dim - 3)])
        else:
            td["action"] = (info.action_high.max() * direction).float()
        td["action"] = td["action"].clamp(info.action_low, info.action_high)
        return td

    return policy


@pytest.mark.parametrize("name", ["point_circle", "point_boxes", "diffdrive_nav", "quadrotor_nav"])
def test_a_crash_ends_the_episode_with_cost_one(name):
    env = envs.make(name, seed=2)
    td = env.rollout(400, _into_the_nearest_obstacle(name))
    cost, collision = td["next", "cost"].squeeze(-1), td["next", "collision"].squeeze(-1)
    assert td["next", "cost"].dtype == torch.float64
    assert torch.equal(cost, collision.double())
    assert collision[-1] and td["next", "terminated"][-1].item() and not td["next", "truncated"][-1].item()
    assert not collision[:-1].any() and (cost[:-1] == 0).all()
    assert td["cost"][0].item() == 0.0  # at reset


def test_point_circle_ends_when_the_robot_leaves_the_safe_box():
    env = envs.make("point_circle", seed=0)
    td = env.rollout(200, _into_the_nearest_obstacle("point_circle"))
    position = td["next", "state"][-1, :2].numpy()
    assert td["next", "terminated"][-1].item() and np.abs(position).max() >= 1.2 - 1e-3
    assert (td["next", "state"][:-1, :2].abs() < 1.2 + 1e-3).all()
    # the previous behaviour stays available
    free = envs.make("point_circle", seed=0, terminate_on_collision=False)
    assert free.rollout(60, _into_the_nearest_obstacle("point_circle"))["next", "collision"].sum() > 1
