"""The planner as a collector policy, the collected data training the world model."""
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, LazyTensorStorage, ReplayBuffer, Unbounded
from torchrl.envs import EnvBase

from torchrl_brsl.models import ProbabilisticEnsemble, WorldModelLoss, train_world_model
from torchrl_brsl.planning import RolloutPlanner

D, M = 4, 2


class NoisyLinearEnv(EnvBase):
    """x' = A x + B u + 0.01 noise, reward -|x|^2, episodes of 20 steps."""

    def __init__(self):
        super().__init__(batch_size=torch.Size([]))
        g = torch.Generator().manual_seed(0)
        self.A = torch.eye(D) + 0.05 * torch.randn(D, D, generator=g)
        self.B = 0.3 * torch.randn(D, M, generator=g)
        self.observation_spec = Composite(observation=Unbounded(shape=(D,)))
        self.action_spec = Bounded(-torch.ones(M), torch.ones(M), shape=(M,))
        self.reward_spec = Unbounded(shape=(1,))
        self._t = 0
        self._x = torch.zeros(D)

    def _reset(self, tensordict=None):
        self._t, self._x = 0, torch.randn(D)
        return TensorDict(observation=self._x.clone(), done=torch.zeros(1, dtype=torch.bool),
                          terminated=torch.zeros(1, dtype=torch.bool))

    def _step(self, tensordict):
        u = tensordict["action"]
        self._x = self.A @ self._x + self.B @ u + 0.01 * torch.randn(D)
        self._t += 1
        done = torch.tensor([self._t >= 20])
        return TensorDict(observation=self._x.clone(), reward=-self._x.square().sum().reshape(1), done=done,
                          terminated=torch.zeros(1, dtype=torch.bool))

    def _set_seed(self, seed):
        torch.manual_seed(seed)


def test_collect_plan_and_train():
    torch.manual_seed(0)
    env = NoisyLinearEnv()
    actor = TensorDictModule(torch.nn.Sequential(torch.nn.Linear(D, M), torch.nn.Tanh()), in_keys=["observation"],
                             out_keys=["action"])
    model = ProbabilisticEnsemble(D, M, ensemble_size=3, hidden_size=64)
    planner = RolloutPlanner(actor, model, n_plan=5)
    collector = Collector(env, planner, frames_per_batch=100, total_frames=300, auto_register_policy_transforms=False)
    buffer = ReplayBuffer(storage=LazyTensorStorage(1000))
    loss_module = WorldModelLoss(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    first, last = None, None
    for batch in collector:
        assert batch["plan"].shape == (100, 5, M)
        assert torch.equal(batch["action"], batch["plan"][:, 0])
        buffer.extend(batch.reshape(-1))
        losses = train_world_model(model, loss_module, buffer, 40, optimizer, batch_size=32)
        first = losses[:5].mean() if first is None else first
        last = losses[-5:].mean()
    collector.shutdown()
    assert len(buffer) == 300
    assert last < first - 3
