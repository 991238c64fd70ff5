"""The "Bring your own robot" page (``docs/own_robot.md``) runs as written, and its claims hold."""
import re
from pathlib import Path

import pytest
import torch

from torchrl_brsl.reach import collect_offline_data

PAGE = Path(__file__).resolve().parents[2] / "docs" / "own_robot.md"


def section_code() -> str:
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)
    assert len(blocks) >= 6, "the page lost its code"
    return "\n".join(blocks)


@pytest.fixture(scope="module")
def walkthrough():
    torch.set_num_threads(1)
    namespace = {"__name__": "guide"}
    exec(compile(section_code(), str(PAGE), "exec"), namespace)
    return namespace


def test_the_braking_policy_meets_assumption_1_and_coasting_does_not(walkthrough):
    speeds = walkthrough["speeds"]
    n_brk = walkthrough["brake"].n_brk
    assert walkthrough["stopped_after_brk"] < 0.05  # stopped within n_brk steps, and it stays stopped
    assert speeds["coast"][n_brk - 1] > 0.2  # zero acceleration does not stop it


def test_the_sets_contain_the_true_trajectories(walkthrough):
    inside, covered = walkthrough["inside"], walkthrough["covered"]
    assert int(covered.sum()) >= 150
    assert inside[covered].all()


def test_the_one_step_sets_hold_at_the_worst_noise(walkthrough):
    worst, claimed = walkthrough["worst"], walkthrough["claimed"]
    assert claimed.float().mean() > 0.9
    assert not worst[claimed].any()


def test_the_error_budget_shows_the_steps_errors_adding_up_near_the_data(walkthrough):
    last = walkthrough["last_step"]  # the velocities' parts at the plans' last step
    torch.testing.assert_close(last["radius"], walkthrough["budget"]["radius"][:, -1].median(0).values)
    assert (last["carried"][2:] > last["added"][2:]).all() and (last["added"][2:] > last["noise"][2:]).all()
    assert (last["far"][2:] < last["leaf"][2:]).all()


def test_the_layer_keeps_the_rover_collision_free_and_moving(walkthrough):
    assert walkthrough["unprotected"] > 0  # the random policy does collide without the layer
    assert walkthrough["collisions"] == 0
    shares = walkthrough["shares"]
    assert shares["failsafe"] < 0.2 and shares["unverified_hold"] < 0.05
    assert shares["invalid_input"] == 0 and shares["out_of_data"] < 0.05
    # the constant brake breaks Assumption 1 (the rover coasts on): nothing is guaranteed, and
    # the layer intervenes much more often
    assert walkthrough["coast_shares"]["intervened"] > 2 * shares["intervened"]


def test_the_envs_obstacles_are_the_public_helpers_output(walkthrough):
    env = walkthrough["Rover"]()
    obstacles = env.reset()["obstacles"]
    assert obstacles["center"].shape == (8, 2) and obstacles["generators"].shape == (8, 2, 6)
    assert obstacles["mask"].all()


def test_offline_data_are_reproducible_from_a_generator(walkthrough):
    rover = walkthrough["Rover"]
    first = collect_offline_data(rover(empty=True, seed=1), 50, generator=torch.Generator().manual_seed(5))
    torch.manual_seed(123)  # the global RNG plays no part
    again = collect_offline_data(rover(empty=True, seed=1), 50, generator=torch.Generator().manual_seed(5))
    other = collect_offline_data(rover(empty=True, seed=1), 50, generator=torch.Generator().manual_seed(6))
    assert torch.equal(first["u_minus"], again["u_minus"]) and torch.equal(first["x_plus"], again["x_plus"])
    assert not torch.equal(first["u_minus"], other["u_minus"])
    assert (first["u_minus"].abs() <= 2.0).all()  # uniform in the action box
