import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict

from torchrl_brsl.models import EnsembleLinear, ProbabilisticEnsemble, WorldModel, as_ensemble

D, M, E = 4, 2, 5


def _model(**kwargs):
    torch.manual_seed(kwargs.pop("seed", 0))
    return ProbabilisticEnsemble(D, M, ensemble_size=E, **kwargs)


def _reference_member(model: ProbabilisticEnsemble, e: int, x: torch.Tensor):
    """Member ``e`` as a plain per-member MLP with ``F.linear`` (the definition, no batching)."""
    h = x
    for i, layer in enumerate(model.layers):
        h = F.linear(h, layer.weight[e].T, layer.bias[e, 0])
        if i < len(model.layers) - 1:
            h = F.leaky_relu(h, 0.01)
    mean, raw = h.chunk(2, dim=-1)
    log_var = model.max_log_var - F.softplus(model.max_log_var - raw)
    log_var = model.min_log_var + F.softplus(log_var - model.min_log_var)
    return mean, log_var


def test_architecture_follows_the_paper():
    model = _model()
    widths = [(layer.in_features, layer.out_features) for layer in model.layers]
    assert widths == [(D + M, 200), (200, 200), (200, 200), (200, 2 * (D + 1))]
    assert all(layer.weight.shape == (E, layer.in_features, layer.out_features) for layer in model.layers)


def test_batched_members_equal_the_per_member_definition():
    model = _model()
    x = torch.randn(E, 16, D + M)
    mean, log_var = model.network(x)
    for e in range(E):
        ref_mean, ref_log_var = _reference_member(model, e, x[e])
        torch.testing.assert_close(mean[e], ref_mean, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(log_var[e], ref_log_var, atol=1e-5, rtol=1e-5)
    shared = torch.randn(16, D + M)
    mean, _ = model.network(shared)
    torch.testing.assert_close(mean, model.network(shared.expand(E, 16, D + M))[0])


def test_all_members_cost_one_batched_product_per_layer():
    model = _model()
    with torch.no_grad(), torch.profiler.profile() as prof:
        model(torch.randn(8, D), torch.randn(8, M))
    calls = sum(evt.count for evt in prof.key_averages() if evt.key in ("aten::baddbmm", "aten::bmm", "aten::mm",
                                                                          "aten::addmm", "aten::matmul"))
    assert calls == len(model.layers)


def test_members_differ_from_initialisation():
    model = _model()
    w = model.layers[0].weight
    assert all(not torch.equal(w[0], w[e]) for e in range(1, E))
    with torch.no_grad():
        loc, _, _, _ = model(torch.randn(32, D), torch.randn(32, M))  # [32, E, D]
    spread = (loc - loc.mean(1, keepdim=True)).abs().amax(dim=(0, 2))
    assert torch.all(spread > 1e-3)


def test_initialisation_is_truncated_normal():
    layer = EnsembleLinear(3, 400, 50)
    std = 1 / (2 * 400 ** 0.5)
    assert layer.weight.abs().max() <= 2 * std + 1e-7
    assert 0.7 * std < layer.weight.std() < std
    assert torch.all(layer.bias == 0)


@pytest.mark.parametrize("bounds", [(0.5, -10.0), (-1.0, -3.0)])
def test_log_variance_stays_within_the_soft_bounds(bounds):
    model = _model(init_max_log_var=bounds[0], init_min_log_var=bounds[1])
    x = torch.cat([torch.randn(200, D + M) * s for s in (1.0, 1e2, 1e4)])
    with torch.no_grad():
        _, log_var = model.network(x)
    upper = model.max_log_var + F.softplus(model.min_log_var - model.max_log_var)
    assert torch.all(log_var >= model.min_log_var) and torch.all(log_var <= upper + 1e-6)
    # extreme inputs push the raw log-variance far out: the bounds are what holds it
    assert log_var.max() > bounds[0] - 0.05 and log_var.min() < bounds[1] + 0.05


def test_log_variance_bounds_are_learnable():
    model = _model()
    _, log_var = model.network(torch.randn(8, D + M) * 1e3)
    (log_var.sum() + model.log_var_bound_penalty()).backward()
    assert model.max_log_var.grad.abs().sum() > 0 and model.min_log_var.grad.abs().sum() > 0


@pytest.mark.parametrize("batch", [(), (7,), (2, 3)])
def test_forward_shapes(batch):
    model = _model()
    obs_loc, obs_scale, rew_loc, rew_scale = model(torch.randn(*batch, D), torch.randn(*batch, M))
    assert obs_loc.shape == obs_scale.shape == (*batch, E, D)
    assert rew_loc.shape == rew_scale.shape == (*batch, E, 1)
    assert torch.all(obs_scale > 0) and torch.all(rew_scale > 0)


def test_forward_undoes_the_normalisation():
    model = _model()
    obs, act = torch.randn(50, D) * 3 + 1, torch.randn(50, M)
    model.fit_normalizers(obs, act, obs + 0.1 * torch.randn(50, D) + 2, torch.randn(50, 1) * 5 - 3)
    with torch.no_grad():
        obs_loc, obs_scale, rew_loc, rew_scale = model(obs, act)
        x = (torch.cat((obs, act), -1) - model.input_normalizer.mean) / model.input_normalizer.std
        mean, log_var = model.network(x)  # [E, N, D + 1]
    mean = mean.transpose(0, 1) * model.target_normalizer.std + model.target_normalizer.mean
    std = (0.5 * log_var.transpose(0, 1)).exp() * model.target_normalizer.std
    torch.testing.assert_close(obs_loc, obs.unsqueeze(1) + mean[..., :D])
    torch.testing.assert_close(rew_loc, mean[..., D:])
    torch.testing.assert_close(obs_scale, std[..., :D])
    torch.testing.assert_close(rew_scale, std[..., D:])


def test_without_reward():
    model = ProbabilisticEnsemble(D, M, ensemble_size=E, predict_reward=False)
    out = model(torch.randn(3, D), torch.randn(3, M))
    assert len(out) == 2 and out[0].shape == (3, E, D)
    next_obs, reward = model.propagate(torch.randn(3, D), torch.randn(3, M), torch.zeros(3, dtype=torch.long))
    assert next_obs.shape == (3, D) and reward is None


def test_propagate_uses_the_chosen_member():
    model = _model()
    obs, act = torch.randn(10, D), torch.randn(10, M)
    member = torch.tensor([0, 1, 2, 3, 4, 4, 3, 2, 1, 0])
    with torch.no_grad():
        obs_loc, _, rew_loc, _ = model(obs, act)
        next_obs, reward = model.propagate(obs, act, member, sample=False)
    rows = torch.arange(10)
    torch.testing.assert_close(next_obs, obs_loc[rows, member])
    torch.testing.assert_close(reward, rew_loc[rows, member])


def test_propagate_samples_the_members_gaussian():
    model = _model()
    model.fit_normalizers(torch.randn(50, D), torch.randn(50, M), torch.randn(50, D) * 2, torch.randn(50, 1))
    obs, act = torch.randn(1, D).expand(20000, D), torch.randn(1, M).expand(20000, M)
    member = torch.full((20000,), 3)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        obs_loc, obs_scale, rew_loc, rew_scale = model(obs[:1], act[:1])
        next_obs, reward = model.propagate(obs, act, member, generator=gen)
    torch.testing.assert_close(next_obs.mean(0), obs_loc[0, 3], atol=4 * obs_scale[0, 3].max().item() / 141, rtol=0)
    torch.testing.assert_close(next_obs.std(0), obs_scale[0, 3], atol=0, rtol=0.03)
    torch.testing.assert_close(reward.std(0), rew_scale[0, 3], atol=0, rtol=0.03)


def test_propagate_is_reproducible_and_differentiable():
    model = _model()
    obs = torch.randn(6, D, requires_grad=True)
    act = torch.randn(6, M, requires_grad=True)
    member = torch.randint(E, (6,))
    a, _ = model.propagate(obs, act, member, generator=torch.Generator().manual_seed(3))
    b, _ = model.propagate(obs, act, member, generator=torch.Generator().manual_seed(3))
    c, _ = model.propagate(obs, act, member, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)
    a.sum().backward()
    assert act.grad.abs().sum() > 0 and obs.grad.abs().sum() > 0
    assert model.layers[0].weight.grad.abs().sum() > 0


def test_propagate_keeps_the_observation_dtype():
    model = _model()
    next_obs, reward = model.propagate(torch.randn(2, D, dtype=torch.float64), torch.randn(2, M), torch.tensor([0, 1]))
    assert next_obs.dtype == reward.dtype == torch.float64


def test_bad_shapes_raise():
    model = _model()
    with pytest.raises(ValueError):
        model(torch.randn(3, D + 1), torch.randn(3, M))
    with pytest.raises(ValueError):
        model(torch.randn(3, D), torch.randn(4, M))
    with pytest.raises(ValueError):
        model.propagate(torch.randn(D), torch.randn(M), torch.tensor(0))
    with pytest.raises(ValueError):
        ProbabilisticEnsemble(D, M, num_layers=1)


@pytest.mark.parametrize("batch", [[], [5], [2, 3]])
def test_world_model_tensordict_module(batch):
    world_model = WorldModel(_model())
    td = TensorDict(observation=torch.randn(*batch, D), action=torch.randn(*batch, M), batch_size=batch)
    out = world_model(td)
    assert out is td
    assert td["next", "observation_loc"].shape == td["next", "observation_scale"].shape == (*batch, E, D)
    assert td["next", "reward_loc"].shape == td["next", "reward_scale"].shape == (*batch, E, 1)
    assert world_model.in_keys == ["observation", "action"]
    assert as_ensemble(world_model) is world_model.ensemble


def test_world_model_custom_keys():
    world_model = WorldModel(ProbabilisticEnsemble(D, M, ensemble_size=2, predict_reward=False),
                             in_keys=[("agent", "obs"), "act"], out_keys=["mu", "sigma"])
    td = TensorDict(agent=TensorDict(obs=torch.randn(3, D), batch_size=[3]), act=torch.randn(3, M), batch_size=[3])
    world_model(td)
    assert td["mu"].shape == td["sigma"].shape == (3, 2, D)
    with pytest.raises(ValueError):
        WorldModel(ProbabilisticEnsemble(D, M), out_keys=["mu", "sigma"])  # the reward needs two more
