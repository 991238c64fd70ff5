import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import Bounded
from torchrl.modules import MLP, AdditiveGaussianModule

from torchrl_brsl.models import ProbabilisticEnsemble, WorldModel
from torchrl_brsl.planning import RolloutPlanner

D, M, E, N_PLAN = 5, 2, 3, 6


def _model(dtype=torch.float32, seed=0, hidden=32):
    torch.manual_seed(seed)
    model = ProbabilisticEnsemble(D, M, ensemble_size=E, hidden_size=hidden, dtype=dtype)
    g = torch.Generator().manual_seed(seed)
    obs, act = torch.randn(200, D, generator=g, dtype=dtype), torch.randn(200, M, generator=g, dtype=dtype)
    model.fit_normalizers(obs, act, obs + torch.randn(200, D, generator=g, dtype=dtype), torch.randn(200, 1, dtype=dtype))
    return model


def _policy(seed=1, dtype=torch.float32):
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(D, 16), torch.nn.Tanh(), torch.nn.Linear(16, M), torch.nn.Tanh()).to(dtype)
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def _noisy_policy():
    spec = Bounded(-torch.ones(M), torch.ones(M), shape=(M,))
    actor = TensorDictModule(MLP(in_features=D, out_features=M, num_cells=[32, 32]), in_keys=["observation"],
                             out_keys=["action"])
    return TensorDictSequential(actor, AdditiveGaussianModule(spec, sigma_init=0.5, sigma_end=0.5))


def _td(batch, seed=2, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(observation=torch.randn(*batch, D, generator=g, dtype=dtype), batch_size=batch)


@pytest.mark.parametrize("batch", [[], [1], [8], [2, 3]])
def test_shapes(batch):
    planner = RolloutPlanner(_policy(), _model(), N_PLAN, return_observations=True, return_members=True)
    td = planner(_td(batch))
    assert td["plan"].shape == (*batch, N_PLAN, M)
    assert td["action"].shape == (*batch, M)
    assert td["plan_observations"].shape == (*batch, N_PLAN, D)
    assert td["plan_members"].shape == (*batch, N_PLAN) and td["plan_members"].dtype == torch.int64
    assert torch.equal(td["action"], td["plan"][..., 0, :])
    assert set(td.keys()) == {"observation", "action", "plan", "plan_observations", "plan_members"}


def test_multi_dim_batch_is_the_flat_batch_reshaped():
    model, policy = _model(), _policy()
    plans = []
    for batch in ([2, 3], [6]):
        planner = RolloutPlanner(policy, model, N_PLAN, generator=torch.Generator().manual_seed(0))
        plans.append(planner(_td([6]).reshape(*batch))["plan"].reshape(6, N_PLAN, M))
    assert torch.equal(plans[0], plans[1])


def test_keys_are_configurable():
    policy = TensorDictModule(_policy().module, in_keys=["observation"], out_keys=["act"])
    planner = RolloutPlanner(policy, WorldModel(_model()), 4, action_key="act", plan_key=("agent", "plan"),
                             return_observations=True, observations_key="imagined")
    td = planner(_td([3]))
    assert td["agent", "plan"].shape == (3, 4, M) and td["imagined"].shape == (3, 4, D)
    assert torch.equal(td["act"], td["agent", "plan"][:, 0])
    assert "plan" not in td.keys() and "action" not in td.keys()
    assert set(planner.out_keys) >= {"act", ("agent", "plan"), "imagined"}
    assert planner.in_keys == ["observation"]


@pytest.mark.parametrize("batch", [[], [4]])
def test_first_action_is_the_policys_proposal(batch):
    policy = _policy()
    planner = RolloutPlanner(policy, _model(), N_PLAN)
    expected = policy(_td(batch))["action"]
    td = planner(_td(batch))
    assert torch.equal(td["plan"][..., 0, :], expected) and torch.equal(td["action"], expected)


def test_first_action_is_the_noisy_policys_proposal():
    policy = _noisy_policy()
    planner = RolloutPlanner(policy, _model(), N_PLAN)
    torch.manual_seed(5)
    expected = policy(_td([4]))["action"]
    torch.manual_seed(5)
    td = planner(_td([4]))
    assert torch.equal(td["action"], expected) and torch.equal(td["plan"][:, 0], expected)
    assert td["plan"].abs().max() <= 1  # the exploration module keeps actions in the spec


@pytest.mark.parametrize("propagation", ["ts_inf", "ts1"])
@pytest.mark.parametrize("sample", [False, True])
def test_plan_is_the_policy_rolled_through_the_recorded_members(propagation, sample):
    model, policy = _model(), _policy()
    planner = RolloutPlanner(policy, model, N_PLAN, propagation=propagation, sample=sample,
                             return_observations=True, return_members=True,
                             generator=torch.Generator().manual_seed(7))
    td = planner(_td([8]))
    # replay from the definition: members drawn first, then one Gaussian draw per model step
    gen = torch.Generator().manual_seed(7)
    shape = (8, 1) if propagation == "ts_inf" else (8, N_PLAN)
    members = torch.randint(E, shape, generator=gen).expand(8, N_PLAN)
    assert torch.equal(td["plan_members"], members)
    obs = _td([8])["observation"]
    with torch.no_grad():
        for j in range(N_PLAN):
            action = policy(TensorDict(observation=obs, batch_size=[8]))["action"]
            torch.testing.assert_close(td["plan"][:, j], action, rtol=0, atol=1e-6)
            obs, _ = model.propagate(obs, action, members[:, j], sample=sample, generator=gen)
            torch.testing.assert_close(td["plan_observations"][:, j], obs, rtol=0, atol=1e-5)


def test_ts_inf_keeps_one_member_per_trajectory():
    planner = RolloutPlanner(_policy(), _model(), N_PLAN, propagation="ts_inf", return_members=True)
    torch.manual_seed(0)
    members = planner(_td([600]))["plan_members"]
    assert torch.all(members == members[:, :1])
    freq = torch.bincount(members[:, 0], minlength=E) / 600
    assert torch.all((freq - 1 / E).abs() < 0.07)


def test_ts1_redraws_the_member_every_step():
    planner = RolloutPlanner(_policy(), _model(), N_PLAN, propagation="ts1", return_members=True)
    torch.manual_seed(0)
    members = planner(_td([600]))["plan_members"]
    changes = (members[:, 1:] != members[:, :-1]).float().mean()
    assert abs(changes - (1 - 1 / E)) < 0.05  # independent uniform draws change w.p. 1 - 1/E
    for j in range(N_PLAN):
        freq = torch.bincount(members[:, j], minlength=E) / 600
        assert torch.all((freq - 1 / E).abs() < 0.07)


def test_deterministic_given_a_seed():
    planner = RolloutPlanner(_noisy_policy(), _model(), N_PLAN)
    plans = []
    for seed in (0, 0, 1):
        torch.manual_seed(seed)
        plans.append(planner(_td([4]))["plan"])
    assert torch.equal(plans[0], plans[1]) and not torch.allclose(plans[0], plans[2])


def test_deterministic_given_a_generator():
    model, policy = _model(), _policy()
    plans = []
    for seed, global_seed in ((3, 0), (3, 1), (4, 0)):
        torch.manual_seed(global_seed)
        planner = RolloutPlanner(policy, model, N_PLAN, generator=torch.Generator().manual_seed(seed))
        plans.append(planner(_td([4]))["plan"])
    assert torch.equal(plans[0], plans[1]) and not torch.allclose(plans[0][:, 1:], plans[2][:, 1:])


def test_sampling_changes_the_imagined_steps_only():
    model, policy = _model(), _policy()
    mean_plan = RolloutPlanner(policy, model, N_PLAN, sample=False)(_td([4]))["plan"]
    sampled = RolloutPlanner(policy, model, N_PLAN, sample=True)(_td([4]))["plan"]
    assert torch.equal(mean_plan[:, 0], sampled[:, 0]) and not torch.allclose(mean_plan[:, 1:], sampled[:, 1:])


def test_imagined_steps_keep_the_other_policy_inputs():
    """A policy reading a key the model does not predict sees its real value at every step."""
    torch.manual_seed(0)
    net = torch.nn.Linear(D + 2, M)
    policy = TensorDictModule(lambda obs, goal: torch.tanh(net(torch.cat((obs, goal), -1))),
                              in_keys=["observation", "goal"], out_keys=["action"])
    model = _model()
    planner = RolloutPlanner(policy, model, 4, sample=False, return_members=True, return_observations=True)
    td = _td([3])
    td["goal"] = torch.randn(3, 2)
    out = planner(td.clone())
    assert torch.equal(out["goal"], td["goal"])
    obs = td["observation"]
    for j in range(4):
        action = policy(TensorDict(observation=obs, goal=td["goal"], batch_size=[3]))["action"]
        torch.testing.assert_close(out["plan"][:, j], action)
        obs, _ = model.propagate(obs, action, out["plan_members"][:, j], sample=False)
    assert planner.in_keys == ["observation", "goal"]


def test_differentiable_in_the_policy_parameters():
    policy = _policy()
    planner = RolloutPlanner(policy, _model(), N_PLAN)
    plan = planner(_td([4]))["plan"]
    assert plan.requires_grad
    grads = torch.autograd.grad(plan[:, 1:].square().sum(), list(policy.parameters()))
    assert all(g.abs().sum() > 0 for g in grads)
    with torch.no_grad():
        assert not planner(_td([4]))["plan"].requires_grad


def test_gradients_through_the_imagined_observations_match_finite_differences():
    """``gradcheck`` (float64) of the plan and imagined observations w.r.t. a policy's weights."""
    model = _model(dtype=torch.float64, hidden=8)
    obs = _td([3], dtype=torch.float64)

    def plan_of(weight, bias):
        policy = TensorDictModule(lambda o: torch.tanh(o @ weight + bias), in_keys=["observation"], out_keys=["action"])
        planner = RolloutPlanner(policy, model, 4, generator=torch.Generator().manual_seed(0), return_observations=True)
        td = planner(obs.clone())
        return td["plan"], td["plan_observations"]

    weight = (0.5 * torch.randn(D, M, dtype=torch.float64)).requires_grad_()
    bias = torch.randn(M, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(plan_of, (weight, bias), eps=1e-6, atol=1e-5)
    # and the imagined steps do depend on the weights through the model, not just directly
    plan, _ = plan_of(weight, bias)
    detached = RolloutPlanner(TensorDictModule(lambda o: torch.tanh(o.detach() @ weight + bias),
                                               in_keys=["observation"], out_keys=["action"]),
                              model, 4, generator=torch.Generator().manual_seed(0))(obs.clone())["plan"]
    torch.testing.assert_close(plan, detached)
    g_full = torch.autograd.grad(plan[:, 2:].sum(), weight)[0]
    g_direct = torch.autograd.grad(detached[:, 2:].sum(), weight)[0]
    assert (g_full - g_direct).abs().max() > 1e-6


def test_single_step_plan():
    policy = _policy()
    td = RolloutPlanner(policy, _model(), 1)(_td([2]))
    assert td["plan"].shape == (2, 1, M) and torch.equal(td["plan"][:, 0], td["action"])


def test_float64_observations_with_a_float32_model():
    policy = _policy(dtype=torch.float64)
    td = RolloutPlanner(policy, _model(), 3, return_observations=True)(_td([2], dtype=torch.float64))
    assert td["plan"].dtype == td["plan_observations"].dtype == torch.float64


def test_bad_arguments():
    with pytest.raises(ValueError):
        RolloutPlanner(_policy(), _model(), 0)
    with pytest.raises(ValueError):
        RolloutPlanner(_policy(), _model(), 3, propagation="ts2")
    with pytest.raises(ValueError):
        RolloutPlanner(_policy(), torch.nn.Linear(2, 2), 3)
