"""The ensemble learns a known heteroscedastic system: x' = A x + B u + sigma(x) * noise."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_brsl.models import ProbabilisticEnsemble, WorldModelLoss, train_world_model

D, M = 4, 2


class System:
    def __init__(self):
        g = torch.Generator().manual_seed(123)
        self.A = torch.eye(D) + 0.1 * torch.randn(D, D, generator=g)
        self.B = 0.5 * torch.randn(D, M, generator=g)
        self.g = g

    def inputs(self, n):
        return torch.rand(n, D, generator=self.g) * 2 - 1, torch.rand(n, M, generator=self.g) * 2 - 1

    def mean(self, obs, act):
        return obs @ self.A.T + act @ self.B.T

    @staticmethod
    def sigma(obs):
        return 0.01 + 0.2 * obs[:, :1].abs()  # [N, 1], the same for every state dim

    def transitions(self, n):
        obs, act = self.inputs(n)
        nxt = self.mean(obs, act) + self.sigma(obs) * torch.randn(n, D, generator=self.g)
        reward = -obs.square().sum(-1, keepdim=True)
        return TensorDict(observation=obs, action=act,
                          next=TensorDict(observation=nxt, reward=reward, batch_size=[n]), batch_size=[n])


@pytest.fixture(scope="module")
def trained():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    system = System()
    buffer = ReplayBuffer(storage=LazyTensorStorage(2000))
    buffer.extend(system.transitions(2000))
    model = ProbabilisticEnsemble(D, M, ensemble_size=5)  # the paper's 4 x 200 members
    loss_module = WorldModelLoss(model)
    data = buffer[:]
    model.fit_normalizers(data["observation"], data["action"], data["next", "observation"], data["next", "reward"])
    with torch.no_grad():
        nll_before = loss_module(data)["nll"]
    train_world_model(model, loss_module, buffer, 300, torch.optim.Adam(model.parameters(), lr=1e-3), batch_size=64)
    with torch.no_grad():
        nll_after = loss_module(data)["nll"]
    obs, act = system.inputs(1000)
    with torch.no_grad():
        loc, scale, _, _ = model(obs, act)
    return dict(system=system, model=model, nll=(nll_before, nll_after), obs=obs, act=act, loc=loc, scale=scale)


def test_nll_falls(trained):
    before, after = trained["nll"]
    assert after < before - 0.7


def test_mean_prediction_error_is_well_below_the_noise(trained):
    system, obs, act = trained["system"], trained["obs"], trained["act"]
    rmse = (trained["loc"].mean(1) - system.mean(obs, act)).square().mean().sqrt()
    noise_rms = system.sigma(obs).square().mean().sqrt()
    assert rmse < 0.3 * noise_rms


def test_predicted_std_tracks_the_heteroscedastic_noise(trained):
    sigma = trained["system"].sigma(trained["obs"])[:, 0]
    predicted = trained["scale"].mean(dim=(1, 2))  # members and dims share the true sigma
    ratio = (predicted / sigma).median()
    assert 0.7 < ratio < 1.4
    assert torch.corrcoef(torch.stack((predicted, sigma)))[0, 1] > 0.85
    assert predicted[sigma > 0.16].mean() > 2 * predicted[sigma < 0.06].mean()


def test_members_disagree_away_from_the_data(trained):
    model = trained["model"]
    spread_in = trained["loc"].std(1).mean()
    far = torch.rand(1000, D) * 2 + 3
    with torch.no_grad():
        loc, _, _, _ = model(far, trained["act"])
    assert loc.std(1).mean() > 3 * spread_in


def test_log_variance_within_bounds_after_training(trained):
    model = trained["model"]
    with torch.no_grad():
        _, log_var = model.network(torch.randn(500, D + M) * 10)
    assert torch.all(log_var >= model.min_log_var - 1e-6)
    assert torch.all(log_var <= model.max_log_var + torch.nn.functional.softplus(model.min_log_var - model.max_log_var)
                     + 1e-6)
