"""A proposal whose sets leave the region of the offline data is never executed, and is flagged."""
import torch
from torchrl.envs import TransformedEnv

import envs
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe

from safety_support import fitted_reach, make_env

TASK = "point_boxes"


def layer():
    info = envs.safety_info(TASK)
    return BRSLSafetyLayer(fitted_reach(TASK, method="local"), Failsafe(info.braking_action, info.n_brk), 1,
                           stop_dims=info.velocity_dims, stop_slack=0.15, action_low=info.action_low,
                           action_high=info.action_high, adjuster=None)


def test_in_data_proposals_pass_and_are_not_flagged():
    env = TransformedEnv(make_env(TASK, seed=0), layer())
    td = env.reset()
    td["action"] = torch.tensor([0.3, 0.0])
    nxt = env.step(td)["next"]
    assert not nxt["brsl", "out_of_data"].item() and not nxt["brsl", "intervened"].item()


def test_a_state_beyond_the_data_flags_the_proposal_and_brakes():
    """The robot's data never exceed 1 m/s per axis; at 2.5 m/s nothing the model says is claimed."""
    env = TransformedEnv(make_env(TASK, seed=0), layer())
    td = env.reset()
    td["state"] = td["state"].clone()
    td["state"][2] = 2.5
    td["action"] = torch.tensor([1.0, 0.0])
    nxt = env.step(td)["next"]
    assert nxt["brsl", "out_of_data"].item() and nxt["brsl", "intervened"].item()
    assert nxt["brsl", "failsafe"].item()
    assert not torch.equal(nxt["safe_action"].float(), td["action"])
