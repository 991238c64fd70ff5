"""SAILR: intervenes exactly when the cost advantage exceeds eta, and the learner's episode ends there."""
import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

import envs
from torchrl_brsl.baselines import AffineModel, SAILRIntervener, point_clearance, rollout_hits
from torchrl_brsl.reach import collect_offline_data

from baselines_support import boxes, braking, double_integrator


def _brute_force_cost(model, state, first, centers, generators, mask, horizon):
    """1 when the model trajectory of one state meets a box: a plain Python loop."""
    x = state.clone()
    for t in range(horizon):
        a = first if t == 0 and first is not None else braking(x)
        x = model(x, a)
        if (point_clearance(x[:2], centers, generators, mask) < 0).any():
            return 1.0
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
    for eta in (0.0, -0.5, 0.5):
        sailr = SAILRIntervener(model, braking, horizon=25, position_dims=(0, 1), eta=eta)
        adv = sailr.advantage(td)
        expected = torch.tensor([_brute_force_cost(model, state[i], action[i], centers[i], generators[i], mask[i], 25)
                                 - _brute_force_cost(model, state[i], None, centers[i], generators[i], mask[i], 25)
                                 for i in range(B)], dtype=torch.float64)
        assert torch.equal(adv, expected)
        executed, intervened, _ = sailr.filter(td.clone())
        assert torch.equal(intervened, adv > eta)
        assert torch.equal(executed[intervened], braking(state)[intervened])
        assert torch.equal(executed[~intervened], action[~intervened])
    assert (adv == 1).any() and (adv == 0).any()


def test_shrunk_obstacles_make_the_model_permissive():
    model = double_integrator()
    state = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    push = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    x = model(state, push)
    for _ in range(20):
        x = model(x, braking(x))
    stop = x[0, 0].item()  # where the model stops after the push
    # a box whose face lies 0.05 m before that point: a hit, but not once shrunk by 0.1 m
    centers = torch.tensor([[[stop - 0.05 + 0.2, 0.0]]], dtype=torch.float64)
    generators = torch.diag_embed(torch.tensor([[[0.2, 0.2]]], dtype=torch.float64))
    mask = torch.ones(1, 1, dtype=torch.bool)
    common = dict(horizon=20, position_dims=(0, 1))
    assert rollout_hits(model, braking, state, push, centers, generators, mask, **common).item()
    assert not rollout_hits(model, braking, state, push, centers, generators, mask, shrink=0.15, **common).item()


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
    sailr = SAILRIntervener(point_circle_model, backup, horizon=30, position_dims=info.position_dims,
                            intervention_reward=-5.0, shrink=0.0)
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
                            position_dims=info.position_dims, terminate_on_intervention=False)
    env = TransformedEnv(SerialEnv(2, functools.partial(envs.make, "point_circle", seed=5)), sailr)
    check_env_specs(env)
    td = env.rollout(120, _wall_seeking, break_when_any_done=False)
    assert td["next", "baseline", "intervened"].sum() > 10
    assert not td["next", "collision"].any()


def test_bad_options_are_named(point_circle_model):
    with pytest.raises(ValueError, match="horizon"):
        SAILRIntervener(point_circle_model, braking, horizon=0, position_dims=(0, 1))
    with pytest.raises(ValueError, match="shrink"):
        SAILRIntervener(point_circle_model, braking, horizon=3, position_dims=(0, 1), shrink=-0.1)
    with pytest.raises(ValueError, match="penalty"):
        SAILRIntervener(point_circle_model, braking, horizon=3, position_dims=(0, 1), penalty=-1.0)
    bad = SAILRIntervener(point_circle_model, braking, horizon=3, position_dims=(5,))
    with pytest.raises(ValueError, match="position_dims"):
        TransformedEnv(envs.make("point_circle"), bad).rollout(2)
