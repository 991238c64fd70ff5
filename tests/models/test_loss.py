import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_brsl.models import ProbabilisticEnsemble, WorldModel, WorldModelLoss, train_world_model

D, M, E = 3, 2, 4


def _transitions(n, seed=0, d=D, m=M):
    g = torch.Generator().manual_seed(seed)
    obs, act = torch.randn(n, d, generator=g), torch.randn(n, m, generator=g)
    nxt = obs + 0.1 * act.sum(-1, keepdim=True) + 0.01 * torch.randn(n, d, generator=g)
    reward = -obs.square().sum(-1, keepdim=True)
    return TensorDict(observation=obs, action=act, next=TensorDict(observation=nxt, reward=reward, batch_size=[n]),
                      batch_size=[n])


def _buffer(n=300, seed=0):
    buffer = ReplayBuffer(storage=LazyTensorStorage(1000))
    buffer.extend(_transitions(n, seed))
    return buffer


def _model(seed=0, **kwargs):
    torch.manual_seed(seed)
    return ProbabilisticEnsemble(D, M, ensemble_size=E, hidden_size=32, **kwargs)


def _manual_nll(model, obs, act, nxt, rew):
    """Per-member NLL ``[E]`` written out from the definition, for inputs ``[E, N, *]``."""
    x = model.input_normalizer.normalize(torch.cat((obs, act), -1))
    mean, log_var = model.network(x)
    z = model.target_normalizer.normalize(torch.cat((nxt - obs, rew), -1))
    return (0.5 * ((mean - z) ** 2 / log_var.exp() + log_var)).mean(dim=(1, 2))


def test_loss_on_replay_buffer_samples():
    model = _model()
    loss_module = WorldModelLoss(model)
    out = loss_module(_buffer().sample(64))
    assert set(out.keys()) == {"loss_world_model", "nll", "mse"}
    assert out["loss_world_model"].shape == () and out["loss_world_model"].requires_grad
    assert not out["nll"].requires_grad and not out["mse"].requires_grad
    out["loss_world_model"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_shared_batch_matches_the_definition():
    model = _model()
    model.fit_normalizers(*(_transitions(300).get(k) for k in ("observation", "action", ("next", "observation"),
                                                              ("next", "reward"))))
    td = _transitions(50, seed=1)
    out = WorldModelLoss(model, bootstrap=False, log_var_bound_coef=0.01)(td)
    args = [td.get(k).expand(E, *td.get(k).shape) for k in ("observation", "action", ("next", "observation"),
                                                             ("next", "reward"))]
    nll = _manual_nll(model, *args)
    expected = nll.sum() + 0.01 * (model.max_log_var.sum() - model.min_log_var.sum())
    torch.testing.assert_close(out["loss_world_model"], expected)
    torch.testing.assert_close(out["nll"], nll.mean())


def test_per_member_batches_train_each_member_on_its_row():
    model = _model()
    td = _transitions(E * 20, seed=2).reshape(E, 20)
    out = WorldModelLoss(model, log_var_bound_coef=0.0)(td)
    nll = _manual_nll(model, *(td.get(k) for k in ("observation", "action", ("next", "observation"),
                                                   ("next", "reward"))))
    torch.testing.assert_close(out["loss_world_model"], nll.sum())
    # member 0's gradient depends on row 0 only
    grad = torch.autograd.grad(out["loss_world_model"], model.layers[0].weight)[0]
    td2 = td.clone()
    td2[1:] = _transitions((E - 1) * 20, seed=3).reshape(E - 1, 20)
    grad2 = torch.autograd.grad(WorldModelLoss(model, log_var_bound_coef=0.0)(td2)["loss_world_model"],
                                model.layers[0].weight)[0]
    torch.testing.assert_close(grad[0], grad2[0])
    assert not torch.allclose(grad[1], grad2[1])


def test_bootstrap_resamples_per_member():
    model = _model()
    td = _transitions(64, seed=4)
    shared = WorldModelLoss(model, bootstrap=False)
    boot = WorldModelLoss(model, bootstrap=True)
    assert torch.equal(shared(td)["loss_world_model"], shared(td)["loss_world_model"])
    torch.manual_seed(0)
    a = boot(td)["loss_world_model"]
    torch.manual_seed(0)
    b = boot(td)["loss_world_model"]
    c = boot(td)["loss_world_model"]
    assert torch.equal(a, b) and not torch.equal(a, c) and not torch.equal(a, shared(td)["loss_world_model"])
    # each member sees its own resample
    captured = {}
    original = model.normalized_prediction

    def spy(obs, act):
        captured["obs"] = obs
        return original(obs, act)

    model.normalized_prediction = spy
    boot(td)
    assert captured["obs"].shape == (E, 64, D)
    assert not torch.equal(captured["obs"][0], captured["obs"][1])


def test_configurable_keys_and_wrapped_model():
    model = _model(predict_reward=False)
    td = _transitions(32).rename_key_("observation", "obs").rename_key_(("next", "observation"), ("next", "obs"))
    del td["next", "reward"]
    loss_module = WorldModelLoss(WorldModel(model))
    loss_module.set_keys(observation="obs")
    assert loss_module.in_keys == ["obs", "action", ("next", "obs")]
    assert loss_module(td)["loss_world_model"].isfinite()
    with pytest.raises(KeyError):
        WorldModelLoss(model)(td)


def test_train_world_model_fits_normalizers_and_lowers_the_loss():
    model = _model()
    buffer = _buffer(400)
    loss_module = WorldModelLoss(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    torch.manual_seed(0)
    losses = train_world_model(model, loss_module, buffer, 150, optimizer, batch_size=32)
    data = buffer[:]
    torch.testing.assert_close(model.input_normalizer.mean,
                               torch.cat((data["observation"], data["action"]), -1).mean(0))
    assert losses.shape == (150,) and torch.isfinite(losses).all()
    assert losses[-20:].mean() < losses[:20].mean() - 3


def test_train_world_model_rejects_a_loss_of_another_model():
    with pytest.raises(ValueError):
        train_world_model(_model(), WorldModelLoss(_model(seed=1)), _buffer(), 1,
                          torch.optim.SGD(_model().parameters(), 0.1))
    empty = ReplayBuffer(storage=LazyTensorStorage(10))
    model = _model()
    with pytest.raises(ValueError):
        train_world_model(model, WorldModelLoss(model), empty, 1, torch.optim.SGD(model.parameters(), 0.1))
