"""``RolloutPlanner``: roll a policy through the world model to write a plan ``[..., n_plan, m]``."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor

from torchrl_brsl.models.ensemble import as_ensemble

PROPAGATIONS = ("ts_inf", "ts1")


class RolloutPlanner(TensorDictModuleBase):
    """Plans ``n_plan`` actions by rolling ``policy`` through a probabilistic ensemble.

    The paper's "roll out a trajectory" step (Algorithm 1): from the real observation
    ``o_0`` the policy proposes ``a_0``; the world model imagines ``o_1 ~ f(o_0, a_0)``, the
    policy proposes ``a_1`` at ``o_1``, and so on::

        a_0 = policy(o_0)                      (the policy's own call on the input TensorDict)
        o_{j+1} = propagate(o_j, a_j, member_j) (one Gaussian sample of one ensemble member)
        a_j = policy(o_j)                      j = 1 .. n_plan - 1

    and writes ``plan = (a_0, ..., a_{n_plan-1})`` ``[..., n_plan, m]`` and
    ``action = plan[..., 0, :]``. Each batch element is one imagined trajectory.

    - The first action is exactly the policy's proposal: the policy is called once on the
      input TensorDict itself (so whatever else it writes, e.g. log-probabilities, is kept), and
      ``plan[..., 0, :]`` is that action.
    - Imagined steps call the policy on a TensorDict holding only the policy's ``in_keys``
      with the observation replaced by the imagined one; inputs the model does not predict
      keep their real values.
    - Trajectory sampling (Chua et al. 2018): ``propagation="ts_inf"`` draws one member per
      trajectory, uniformly, and keeps it for the whole rollout; ``"ts1"`` redraws the member
      uniformly at every step. ``sample=False`` uses the chosen member's mean instead of a
      draw from its Gaussian.
    - Randomness: member indices and model noise come from ``generator`` when given, else
      from the global RNG, so ``torch.manual_seed(s)`` before the call reproduces the plan
      (a stochastic policy draws its noise from its own source, usually the global RNG).
    - Gradients: called outside :func:`torch.no_grad`, the plan is differentiable with
      respect to the policy parameters (and the model parameters), through the actions and
      through the imagined observations (reparameterised samples). Collectors call policies
      under ``no_grad``, where no graph is built.

    Args:
        policy: a TensorDict module reading ``observation_key`` (and possibly more) and writing
            ``action_key`` ``[..., m]``, e.g. a TD3 actor followed by exploration noise.
        world_model: a :class:`~torchrl_brsl.models.ProbabilisticEnsemble` or
            :class:`~torchrl_brsl.models.WorldModel`.
        n_plan: plan length (``>= 1``; ``1`` makes the planner the policy plus a ``plan`` key).
        propagation: ``"ts_inf"`` or ``"ts1"`` (see above).
        sample: sample the model's Gaussian (``True``) or use the member's mean.
        generator: RNG for member indices and model noise.
        observation_key, action_key, plan_key: TensorDict keys.
        return_observations: also write ``observations_key``: the imagined observations
            ``[..., n_plan, d]``, entry ``j`` being the predicted observation after executing
            ``plan[..., j, :]`` (one extra model step).
        observations_key: key of the imagined observations.
        return_members: also write ``members_key``: the member used at each step
            ``[..., n_plan]`` (int64; entry ``j`` predicted the observation after action ``j``;
            without ``return_observations`` the last entry is drawn but not used).
        members_key: key of the member indices.

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_brsl.models import ProbabilisticEnsemble
        >>> policy = TensorDictModule(torch.nn.Sequential(torch.nn.Linear(23, 2), torch.nn.Tanh()),
        ...                           in_keys=["observation"], out_keys=["action"])
        >>> planner = RolloutPlanner(policy, ProbabilisticEnsemble(23, 2), n_plan=8)
        >>> td = planner(TensorDict(observation=torch.randn(4, 23), batch_size=[4]))
        >>> td["plan"].shape, td["action"].shape
        (torch.Size([4, 8, 2]), torch.Size([4, 2]))
        >>> torch.equal(td["action"], td["plan"][:, 0])
        True
        >>> td = planner(TensorDict(observation=torch.randn(23)))  # unbatched
        >>> td["plan"].shape
        torch.Size([8, 2])
    """

    def __init__(self, policy: TensorDictModuleBase, world_model, n_plan: int, *, propagation: str = "ts_inf",
                 sample: bool = True, generator: torch.Generator | None = None,
                 observation_key: NestedKey = "observation", action_key: NestedKey = "action",
                 plan_key: NestedKey = "plan", return_observations: bool = False,
                 observations_key: NestedKey = "plan_observations", return_members: bool = False,
                 members_key: NestedKey = "plan_members"):
        super().__init__()
        if int(n_plan) < 1:
            raise ValueError(f"`n_plan` must be a positive integer, got {n_plan}")
        if propagation not in PROPAGATIONS:
            raise ValueError(f"`propagation` must be one of {PROPAGATIONS}, got {propagation!r}")
        self.policy = policy
        self.world_model = world_model
        self.__dict__["ensemble"] = as_ensemble(world_model)
        self.n_plan = int(n_plan)
        self.propagation = propagation
        self.sample = bool(sample)
        self.generator = generator
        self.observation_key, self.action_key, self.plan_key = observation_key, action_key, plan_key
        self.return_observations, self.observations_key = bool(return_observations), observations_key
        self.return_members, self.members_key = bool(return_members), members_key
        policy_in = list(getattr(policy, "in_keys", [observation_key]))
        if observation_key not in policy_in:
            policy_in.append(observation_key)
        self.in_keys = policy_in
        out_keys = list(getattr(policy, "out_keys", [action_key]))
        for key, on in ((action_key, True), (plan_key, True), (observations_key, self.return_observations),
                        (members_key, self.return_members)):
            if on and key not in out_keys:
                out_keys.append(key)
        self.out_keys = out_keys

    def sample_members(self, batch: int, steps: int, device=None) -> Tensor:
        """Member index per trajectory and model step, ``[batch, steps]`` (int64).

        ``"ts_inf"``: one uniform draw per row, repeated along the steps; ``"ts1"``: an
        independent uniform draw per entry.
        """
        E = self.ensemble.ensemble_size
        if self.propagation == "ts_inf":
            members = torch.randint(E, (batch, 1), generator=self.generator, device=device)
            return members.expand(batch, steps)
        return torch.randint(E, (batch, steps), generator=self.generator, device=device)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes ``plan [..., n_plan, m]`` and ``action [..., m]`` into ``tensordict``.

        ``tensordict`` has any batch size (``[]``, ``[B]``, ``[B1, B2]``, ...); its observation is
        ``[..., d]``.
        """
        batch = tensordict.batch_size
        tensordict = self.policy(tensordict)
        first = tensordict.get(self.action_key)
        observation = tensordict.get(self.observation_key)
        n_rows = batch.numel()
        obs = observation.reshape(n_rows, observation.shape[-1])
        action = first.reshape(n_rows, first.shape[-1])
        model_steps = self.n_plan if self.return_observations else self.n_plan - 1
        members = self.sample_members(n_rows, self.n_plan, device=obs.device)
        actions, observations = [action], []
        if model_steps > 0:
            imagined = tensordict.select(*self.in_keys, strict=False).reshape(n_rows)
            for j in range(model_steps):
                obs, _ = self.ensemble.propagate(obs, action, members[:, j], sample=self.sample,
                                                 generator=self.generator)
                observations.append(obs)
                if j + 1 == self.n_plan:  # the extra step for ``return_observations``
                    break
                imagined.set(self.observation_key, obs)
                imagined = self.policy(imagined)
                action = imagined.get(self.action_key)
                actions.append(action)
        plan = torch.stack(actions, dim=-2).reshape(*batch, self.n_plan, first.shape[-1])
        tensordict.set(self.plan_key, plan)
        tensordict.set(self.action_key, first)
        if self.return_observations:
            tensordict.set(self.observations_key,
                           torch.stack(observations, dim=-2).reshape(*batch, self.n_plan, observation.shape[-1]))
        if self.return_members:
            tensordict.set(self.members_key, members.reshape(*batch, self.n_plan))
        return tensordict
