"""SAILR: intervenes exactly when the cost advantage exceeds eta, and the learner's episode ends there."""
import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

import envs
from torchrl_brsl.baselines import AffineModel, SAILRIntervener, point_clearance, rollout_cost
from torchrl_brsl.reach import collect_offline_data

from baselines_support import boxes, braking, double_integrator


def _brute_force_cost(model, state, first, centers, generators, mask, horizon, gamma=0.99, margin=0.0):
    """The rule for one state, in a plain loop: discounted cost of the first hit, unless the robot stops first."""
    x = state.clone()
    for t in range(1, horizon + 1):
        x = model(x, first if t == 1 and first is not None else braking(x))
        if point_clearance(x[:2], centers, generators, mask).min() <= margin:
            return gamma ** t
        if (x[2:].abs() <= 1e-3).all():
            return 0.0
    return 0.0


def test_intervenes_exactly_when_the_advantage_exceeds_eta():
    gen = torch.Generator().manual_seed(0)
    model, B = double_integrator(), 200
    centers, generators, mask = boxes(B, 3, gen)
    state = torch.cat([2 * torch.rand(B, 2, generator=gen, dtype=torch.float64) - 1,
                       3 * (2 * torch.rand(B, 2, generator=gen, dtype=torch.float64) - 1)], -1)
    action = 2 * torch.rand(B, 2, generator=gen, dtype=torch.float64) - 1
    td = TensorDict({"state": state, "action": action,
                     "obstacles": {"center": centers, "generators": generators, "mask": mask}}, batch_size=[B])
    for eta, margin in ((0.0, 0.0), (-0.5, 0.1), (0.5, 0.0), (0.01, 0.05)):
        sailr = SAILRIntervener(model, braking, horizon=25, position_dims=(0, 1), velocity_dims=(2, 3), eta=eta,
                                margin=margin)
        adv = sailr.advantage(td)
        args = [(state[i], centers[i], generators[i], mask[i]) for i in range(B)]
        expected = torch.tensor([_brute_force_cost(model, s, a, c, g, k, 25, margin=margin)
                                 - _brute_force_cost(model, s, None, c, g, k, 25, margin=margin)
                                 for (s, c, g, k), a in zip(args, action)], dtype=torch.float64)
        assert torch.allclose(adv, expected, atol=1e-12, rtol=0)
        executed, intervened, _ = sailr.filter(td.clone())
        assert torch.equal(intervened, adv > eta)
        assert torch.equal(executed[intervened], braking(state)[intervened])
        assert torch.equal(executed[~intervened], action[~intervened])
    assert (adv > 0.5).any() and (adv == 0).any()
    # an action that only brings an unavoidable crash closer also has a positive advantage
    assert ((adv > 0) & (adv < 0.5)).any()


def test_the_margin_shrinks_the_model_safe_set():
    model = double_integrator()
    state = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    push = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    x = model(state, push)
    for _ in range(20):
        x = model(x, braking(x))
    stop = x[0, 0].item()  # where the model stops after the push
    # a box whose face lies 0.05 m past that point: no hit, but one with a margin of 0.1 m
    centers = torch.tensor([[[stop + 0.05 + 0.2, 0.0]]], dtype=torch.float64)
    generators = torch.diag_embed(torch.tensor([[[0.2, 0.2]]], dtype=torch.float64))
    mask = torch.ones(1, 1, dtype=torch.bool)
    common = dict(horizon=20, position_dims=(0, 1), velocity_dims=(2, 3))
    assert rollout_cost(model, braking, state, push, centers, generators, mask, **common).item() == 0
    assert rollout_cost(model, braking, state, push, centers, generators, mask, margin=0.1, **common).item() > 0.5
    smooth = rollout_cost(model, braking, state, push, centers, generators, mask, cost_smoothing=0.2,
                          **common).item()
    assert smooth > 0  # near the box the ramp costs, though nothing is hit


@pytest.fixture(scope="module")
def point_circle_model():
    torch.manual_seed(0)
    data = collect_offline_data(envs.make("point_circle", seed=1, empty=True), 300)
    return AffineModel.fit(data["x_minus"], data["u_minus"], data["x_plus"])


def _wall_seeking(td):
    td["action"] = torch.where(td["state"][..., :2] >= 0, 1.0, -1.0).float()
    return td


def test_in_the_env_the_episode_ends_with_the_lowest_reward_at_the_intervention(point_circle_model):
    info = envs.safety_info("point_circle")
    backup = lambda s: info.braking_policy(s).double()  # noqa: E731
    sailr = SAILRIntervener(point_circle_model, backup, horizon=30, position_dims=info.position_dims, velocity_dims=(2, 3),
                            intervention_reward=-5.0, margin=0.05)
    env = TransformedEnv(envs.make("point_circle", seed=3), sailr)
    check_env_specs(env)
    td = env.rollout(200, _wall_seeking)
    intervened = td["next", "baseline", "intervened"].squeeze(-1)
    assert intervened.any()
    first = int(intervened.nonzero()[0])
    assert first == td.shape[0] - 1  # the learner's episode ends at the first intervention
    last = td[-1]
    assert last["next", "terminated"].item() and last["next", "done"].item()
    assert last["next", "reward"].item() == -5.0
    assert last["next", "baseline", "advantage"].item() > 0
    assert torch.allclose(last["next", "safe_action"].double(), backup(last["state"]).clamp(-1, 1).float().double())
    assert not td["next", "terminated"][:-1].any() and not td["next", "collision"].any()
    assert (td["next", "reward"][:-1] != -5.0).all()


def test_evaluation_mode_keeps_the_episode_and_the_backup_keeps_the_robot_off_the_walls(point_circle_model):
    info = envs.safety_info("point_circle")
    sailr = SAILRIntervener(point_circle_model, lambda s: info.braking_policy(s).double(), horizon=30,
                            position_dims=info.position_dims, velocity_dims=(2, 3), cost_smoothing=0.1,
                            stop_tolerance=info.stop_tolerance, terminate_on_intervention=False)
    env = TransformedEnv(SerialEnv(2, functools.partial(envs.make, "point_circle", seed=5)), sailr)
    check_env_specs(env)
    td = env.rollout(120, _wall_seeking, break_when_any_done=False)
    assert td["next", "baseline", "intervened"].sum() > 10
    assert not td["next", "collision"].any()


def test_bad_options_are_named(point_circle_model):
    dims = dict(position_dims=(0, 1), velocity_dims=(2, 3))
    with pytest.raises(ValueError, match="horizon"):
        SAILRIntervener(point_circle_model, braking, horizon=0, **dims)
    with pytest.raises(ValueError, match="margin"):
        SAILRIntervener(point_circle_model, braking, horizon=3, margin=-0.1, **dims)
    with pytest.raises(ValueError, match="gamma"):
        SAILRIntervener(point_circle_model, braking, horizon=3, gamma=0.0, **dims)
    with pytest.raises(ValueError, match="penalty"):
        SAILRIntervener(point_circle_model, braking, horizon=3, penalty=-1.0, **dims)
    bad = SAILRIntervener(point_circle_model, braking, horizon=3, position_dims=(5,), velocity_dims=(2, 3))
    with pytest.raises(ValueError, match="position_dims"):
        TransformedEnv(envs.make("point_circle"), bad).rollout(2)
