"""In wind, the layer keeps the hexarotor off the wall it is blown towards, even where no plan verifies."""
import numpy as np
import pytest
import torch
from torchrl.envs import TransformedEnv

import envs
from envs import hexarotor_wind
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

TASK = "hexarotor_wind"
LINEAR = {"max_acceleration": None}
CLEARANCE = 0.05  # metres between the robot sphere and the wall and floor at the start
STEPS = 80


def _layer():
    info = envs.safety_info(TASK)
    torch.manual_seed(0)
    data = collect_offline_data(envs.make(TASK, empty=True, seed=1, **LINEAR), 500)
    reach = DataDrivenReach.from_data(data, Zonotope(info.noise_center.double(), info.noise_generators.double()),
                                      translation_invariant_dims=info.position_dims, max_generators=30)
    return BRSLSafetyLayer(reach, Failsafe(info.braking_action, info.n_brk), 1, stop_dims=info.velocity_dims,
                           stop_tolerance=0.3, action_low=info.action_low, action_high=info.action_high,
                           adjuster="facet_qp")


def _windy_layout() -> int:
    """The first evaluation layout whose wind exceeds 2.5 m/s."""
    for layout in range(50):
        env = envs.make(TASK, layout=layout, **LINEAR)
        env.reset()
        if np.linalg.norm(env.task.wind) > 2.5:
            return layout
    pytest.fail("no layout with strong wind")


def test_zero_command_in_a_downwind_corner_keeps_the_hexarotor_off_the_walls():
    layout = _windy_layout()
    env = TransformedEnv(envs.make(TASK, layout=layout, episode_steps=STEPS, **LINEAR), _layer())
    td = env.reset()
    wind = env.base_env.task.wind
    axis = int(np.argmax(np.abs(wind[:2])))
    corner = np.zeros(3)
    corner[axis] = np.sign(wind[axis]) * (hexarotor_wind.ARENA - hexarotor_wind.HexarotorWind.robot_radius - CLEARANCE)
    corner[2] = hexarotor_wind.HexarotorWind.robot_radius + CLEARANCE
    physics = env.base_env.physics
    physics.data.qpos[:3] = corner
    physics.data.qvel[:3] = 0.0
    physics.forward()
    td["state"] = torch.as_tensor(env.base_env.task.state(physics), dtype=td["state"].dtype)
    downwind = torch.zeros(3)
    downwind[axis] = float(np.sign(wind[axis])) * 5.0
    downwind[2] = -5.0

    def into_the_corner(td):  # adversarial proposals: full speed into the wall and the floor
        return td.set("action", downwind.clone())

    out = env.rollout(STEPS, into_the_corner, tensordict=td, auto_reset=False)
    nxt = out["next"]
    assert not nxt["collision"].any()  # MuJoCo contacts: the ground truth
    assert nxt["brsl", "unverified_hold"].any()  # nothing verified there: Assumption 1 carried it
    drift = (nxt["state"][-1, :3] - torch.as_tensor(corner, dtype=torch.float32)).abs().max()
    assert drift < CLEARANCE  # the integral action held the robot where it was
