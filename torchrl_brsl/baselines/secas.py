"""SECAS: a linearised safety layer with a closed-form action correction.

Dalal, Dvijotham, Vecerik, Hester, Paduraru, Tassa, "Safe exploration in continuous action
spaces", arXiv:1801.08757 (2018); reference code ``AgrawalAmey/safe-explorer``
(``safety_layer.py``) and ``utiasDSL/safe-control-gym`` (``safe_explorer_utils.py``).

Per constraint ``i`` (here: one per obstacle slot) a linear model of the next constraint value
``c_i(s') ≈ c_i(s) + g(s, o_i) · a``; ``g`` is a small MLP (two hidden layers of 10, as in the
references) trained by MSE on random-input transitions collected before RL. The constraint
signal is ``c_i(s) = margin - clearance_i(s)`` (clearance of the robot position from obstacle
``i``, :func:`~torchrl_brsl.baselines.point_clearance`) and the constraint ``c_i <= 0``. One
network serves every slot: it sees the state and the slot's obstacle relative to the robot, so
it applies to layouts it was not trained on.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn

from torchrl_brsl.baselines._common import ActionFilter, check_dims, obstacle_tensors, point_clearance


def obstacle_features(state: Tensor, centers: Tensor, generators: Tensor, position_dims: Sequence[int]) -> Tensor:
    """Input of the safety model per obstacle slot: ``[state, centre - position, generators]``.

    Args:
        state: ``[..., n]``.
        centers: ``[..., K, d]``.
        generators: ``[..., K, d, p]``.
        position_dims: the ``d`` position indices of ``state``.

    Returns:
        ``[..., K, n + d + d p]`` in float32 (the network's dtype).

    Examples:
        >>> obstacle_features(torch.zeros(4), torch.ones(3, 2), torch.ones(3, 2, 2), (0, 1)).shape
        torch.Size([3, 10])
    """
    state = state.to(torch.float64)
    k = centers.shape[-2]
    position = state[..., list(position_dims)]
    relative = centers.to(torch.float64) - position.unsqueeze(-2)
    expanded = state.unsqueeze(-2).expand(*state.shape[:-1], k, state.shape[-1])
    return torch.cat([expanded, relative, generators.to(torch.float64).flatten(-2)], dim=-1).to(torch.float32)


class LinearSafetyModel(nn.Module):
    """``g(s, o) -> [m]``: the action gradient of the next constraint value of one obstacle.

    Args:
        feature_dim: size of :func:`obstacle_features` (``n + d + d p``).
        action_dim: ``m``.
        hidden: hidden layer widths (the references: two of 10).

    Examples:
        >>> g = LinearSafetyModel(10, 2)
        >>> g(torch.zeros(5, 3, 10)).shape
        torch.Size([5, 3, 2])
    """

    def __init__(self, feature_dim: int, action_dim: int, hidden: Sequence[int] = (10, 10)):
        super().__init__()
        if feature_dim < 1 or action_dim < 1:
            raise ValueError(f"`feature_dim` and `action_dim` must be positive, got {feature_dim}, {action_dim}")
        layers, width = [], feature_dim
        for h in hidden:
            layers += [nn.Linear(width, int(h)), nn.ReLU()]
            width = int(h)
        layers.append(nn.Linear(width, action_dim))
        self.net = nn.Sequential(*layers)
        self.feature_dim, self.action_dim = feature_dim, action_dim
        # input normalisation, set by fit_safety_model
        self.register_buffer("feature_mean", torch.zeros(feature_dim))
        self.register_buffer("feature_std", torch.ones(feature_dim))

    def forward(self, features: Tensor) -> Tensor:
        return self.net((features - self.feature_mean) / self.feature_std)


def fit_safety_model(model: LinearSafetyModel, data: TensorDict, obstacles: TensorDict, position_dims: Sequence[int],
                     *, pairings: int = 4, steps: int = 2000, batch_size: int = 256, lr: float = 1e-3,
                     margin: float = 0.0, seed: int = 0) -> Tensor:
    """Trains ``g`` by MSE of ``c(s) + g(s, o) · a`` against ``c(s')`` on offline transitions.

    Each transition (random inputs, e.g. :func:`torchrl_brsl.reach.collect_offline_data` in the
    empty task) is paired with ``pairings`` obstacle layouts drawn from ``obstacles``; the
    constraint values are computed exactly from the positions, so the data costs no extra robot
    steps: it is the same offline budget BRSL gets.

    Args:
        model: the network to train (in place).
        data: ``x_minus [N, n]``, ``u_minus [N, m]``, ``x_plus [N, n]``.
        obstacles: layouts ``center [L, K, d]``, ``generators [L, K, d, p]``, ``mask [L, K]``.
        position_dims: position indices of the state.
        pairings: layouts per transition.
        steps: Adam steps.
        batch_size: (transition, layout) pairs per step.
        lr: Adam learning rate.
        margin: the constraint's margin (see the module docstring; it cancels in the target).
        seed: seed of the pairing and the minibatches.

    Returns:
        The training losses ``[steps]``.
    """
    if steps < 1 or batch_size < 1 or pairings < 1:
        raise ValueError(f"`steps`, `batch_size` and `pairings` must be positive, got {steps}, {batch_size}, "
                         f"{pairings}")
    gen = torch.Generator().manual_seed(seed)
    x, u, x_next = (data[k].to(torch.float64) for k in ("x_minus", "u_minus", "x_plus"))
    n_layouts = obstacles["center"].shape[0]
    layout = torch.randint(n_layouts, (pairings * x.shape[0],), generator=gen)
    x, u, x_next = x.repeat(pairings, 1), u.repeat(pairings, 1), x_next.repeat(pairings, 1)
    centers, generators = obstacles["center"][layout].double(), obstacles["generators"][layout].double()
    mask = obstacles["mask"][layout].bool()
    dims = list(position_dims)
    c_now = margin - point_clearance(x[:, dims], centers, generators, mask)
    c_next = margin - point_clearance(x_next[:, dims], centers, generators, mask)
    feats = obstacle_features(x, centers, generators, dims)[mask]  # [P, f] valid pairs only
    u_pairs = u.unsqueeze(1).expand(-1, mask.shape[1], -1)[mask].float()
    target = (c_next - c_now)[mask].float()
    model.feature_mean.copy_(feats.mean(0))
    std = feats.std(0)
    model.feature_std.copy_(torch.where(std > 1e-6, std, torch.ones_like(std)))  # constant features pass
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = torch.empty(steps)
    for i in range(steps):
        idx = torch.randint(feats.shape[0], (min(batch_size, feats.shape[0]),), generator=gen)
        pred = (model(feats[idx]) * u_pairs[idx]).sum(-1)
        loss = (pred - target[idx]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses[i] = loss.detach()
    return losses


def secas_correction(action: Tensor, gradients: Tensor, constraint: Tensor, mask: Tensor | None = None) -> Tensor:
    """The closed-form correction of Dalal et al., eq. (5), in float64.

    ``λ_i = relu((g_i · a + c_i - C_i) / (g_i · g_i))`` with ``C_i = 0`` here, and
    ``a* = a - λ_max g_{i_max}``: exact for one active constraint (the paper's assumption).

    Args:
        action: ``[..., m]`` proposals.
        gradients: ``[..., K, m]`` the ``g_i``.
        constraint: ``[..., K]`` current values ``c_i(s)`` (safe: ``c_i(s') <= 0``).
        mask: ``[..., K]`` constraints that apply (others get ``λ = 0``).

    Returns:
        ``[..., m]`` corrected actions, float64.

    Examples:
        >>> a = torch.tensor([1.0, 0.0])
        >>> secas_correction(a, torch.tensor([[1.0, 0.0]]), torch.tensor([-0.5]))
        tensor([0.5000, 0.0000], dtype=torch.float64)
    """
    action, gradients, constraint = (t.to(torch.float64) for t in (action, gradients, constraint))
    norm = (gradients * gradients).sum(-1)
    excess = (gradients * action.unsqueeze(-2)).sum(-1) + constraint
    lam = torch.where(norm > 1e-12, (excess / norm.clamp_min(1e-12)).clamp_min(0.0), torch.zeros_like(norm))
    if mask is not None:
        lam = torch.where(mask, lam, torch.zeros_like(lam))
    lam_max, i_max = lam.max(-1)
    g_max = gradients.gather(-2, i_max[..., None, None].expand(*i_max.shape, 1, gradients.shape[-1])).squeeze(-2)
    return action - lam_max.unsqueeze(-1) * g_max


class SECASSafetyLayer(ActionFilter):
    """SECAS as a TorchRL transform: the proposal is corrected by :func:`secas_correction`.

    Reads ``state_key [..., n]`` (float64) and ``obstacles_key`` (``center [..., K, d]``,
    ``generators [..., K, d, p]``, ``mask [..., K]``), replaces ``action_key [..., m]`` by the
    corrected action (clipped to ``[action_low, action_high]`` when given: the linearised
    constraint is then only guaranteed when the correction stays inside the bounds), and
    writes ``next[safe_action_key]`` and ``next[diagnostics_key]`` (``intervened``,
    ``compute_time``). An unbatched or batched env alike.

    Args:
        model: a trained :class:`LinearSafetyModel`.
        position_dims: the ``d`` position indices of the state.
        margin: the distance the layer keeps: ``c_i = margin - clearance_i <= 0``.
        action_low: ``[m]`` lower bounds (or None).
        action_high: ``[m]`` upper bounds (or None).
        state_key, obstacles_key, action_key, safe_action_key, diagnostics_key, reward_key:
            TensorDict keys.
        penalty: reward subtracted when the proposal was corrected.

    Examples:
        >>> import envs
        >>> from torchrl.envs import TransformedEnv
        >>> env = envs.make("point_boxes", seed=0)
        >>> n, d, p = 4, 2, env.reset()["obstacles", "generators"].shape[-1]
        >>> layer = SECASSafetyLayer(LinearSafetyModel(n + d + d * p, 2), position_dims=(0, 1), margin=0.05)
        >>> td = TransformedEnv(env, layer).rollout(3)
        >>> td["next", "baseline", "intervened"].shape
        torch.Size([3, 1])
    """

    def __init__(self, model: LinearSafetyModel, *, position_dims: Sequence[int], margin: float = 0.0,
                 action_low: Tensor | None = None, action_high: Tensor | None = None, **keys):
        super().__init__(**keys)
        if margin < 0:
            raise ValueError(f"`margin` must be >= 0, got {margin}")
        self.model = model
        self.position_dims = tuple(int(d) for d in position_dims)
        if not self.position_dims:
            raise ValueError("`position_dims` must name at least one state index")
        self.margin = float(margin)
        self.action_low = None if action_low is None else torch.as_tensor(action_low, dtype=torch.float64)
        self.action_high = None if action_high is None else torch.as_tensor(action_high, dtype=torch.float64)

    def constraints(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor, Tensor]:
        """``(c [..., K], g [..., K, m], mask [..., K])`` of the current step, float64."""
        batch = tensordict.batch_size
        state = tensordict.get(self.state_key).to(torch.float64)
        check_dims("position_dims", self.position_dims, state.shape[-1])
        centers, generators, mask = obstacle_tensors(tensordict, self.obstacles_key, batch)
        c = self.margin - point_clearance(state[..., list(self.position_dims)], centers, generators, mask)
        with torch.no_grad():
            g = self.model(obstacle_features(state, centers, generators, self.position_dims)).to(torch.float64)
        return c, g, mask

    def filter(self, tensordict):
        action = tensordict.get(self.action_key)
        c, g, mask = self.constraints(tensordict)
        corrected = secas_correction(action, g, torch.where(mask, c, torch.zeros_like(c)), mask)
        if self.action_low is not None or self.action_high is not None:
            low = None if self.action_low is None else self.action_low.to(corrected.device)
            high = None if self.action_high is None else self.action_high.to(corrected.device)
            corrected = corrected.clamp(low, high)
        intervened = (corrected - action.to(torch.float64)).abs().amax(-1) > 1e-9
        return corrected, intervened, {}
