"""An acceleration-commanded robot whose stopped state is not invariant (noise random-walks it).

Paper Assumption 1 (a stopped robot stays stopped under the hold action) fails for the noisy
double integrator of ``point_circle``: open-loop holds after the verified horizon let the
velocity random-walk into the walls. The layer re-verifies braking from the measured state
every step and, once no verified action is left, applies the braking policy to the measured
state (a closed-loop hold). Ground truth: MuJoCo contacts.
"""
import functools

import torch
from torchrl.envs import SerialEnv, TransformedEnv

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, FacetQPAdjuster, Failsafe
from torchrl_brsl.sets import Zonotope

TASK, N_PLAN, N_BRK, MAX_SPEED = "point_circle", 5, 12, 1.0
INFO = envs.safety_info(TASK)


def operating_regime_policy(td):
    """Random inputs, braking above ``MAX_SPEED``: offline data below the speed saturation."""
    low, high = INFO.action_low, INFO.action_high
    state = td["state"]
    action = low + (high - low) * torch.rand_like(low)
    if state[list(INFO.velocity_dims)].norm() > MAX_SPEED:
        action = INFO.braking_policy(state.double()).float().clamp(low, high)
    td["action"] = action
    return td


def wall_seeking_policy(td):
    """Full acceleration away from the centre: straight into the nearest wall."""
    position = td["state"][..., :2]
    td["action"] = torch.where(position >= 0, 1.0, -1.0)
    return td


def test_braking_is_reverified_so_noise_never_drifts_the_robot_into_a_wall():
    torch.manual_seed(0)
    data = collect_offline_data(envs.make(TASK, empty=True, seed=7), 500, policy=operating_regime_policy)
    noise = Zonotope(INFO.noise_center.double(), INFO.noise_generators.double())
    # the global model's wide sets let the verified plans run out near the wall, the situation
    # this test is about (the local model's braking verifies at every step there)
    reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=INFO.position_dims, max_generators=30,
                                      method="global")
    radius = reach.error_generators_sequence(N_PLAN + N_BRK)[-1, list(INFO.velocity_dims)].abs().sum(-1)
    layer = BRSLSafetyLayer(reach, Failsafe(INFO.braking_action, N_BRK, INFO.braking_policy), N_PLAN,
                            stop_dims=INFO.velocity_dims, stop_tolerance=(radius + 0.1).tolist(),
                            action_low=INFO.action_low, action_high=INFO.action_high, adjuster=FacetQPAdjuster())
    env = TransformedEnv(SerialEnv(4, [functools.partial(envs.make, TASK, seed=i, episode_steps=400)
                                       for i in range(4)]), layer)
    rollout = env.rollout(300, wall_seeking_policy, break_when_any_done=False)
    assert not rollout["next", "collision"].any()
    # the robot did reach the wall region, and the verified plan ran out there: the situation
    # where open-loop holding let the noise drift it into the wall
    assert rollout["next", "state"][..., :2].abs().amax() > 0.7
    exhausted = rollout["next", "brsl", "failsafe"] & (rollout["safe_plan_steps"] == 0)
    assert exhausted.sum() > 10
