"""Pieces shared by the baselines: clearance signals, an affine nominal model, the action-filter transform."""
from __future__ import annotations

import time
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import Transform

from torchrl_brsl.safety.layer import write_step_outputs
from torchrl_brsl.sets.facets import facet_normals, facet_supports


def point_clearance(position: Tensor, centers: Tensor, generators: Tensor, mask: Tensor | None = None) -> Tensor:
    """Signed clearance of a point from each obstacle zonotope (float64).

    ``max_k (u_k . (p - c) - s_k)`` over the unit facet normals ``u_k`` (both signs) of the
    obstacle, ``s_k`` its support: minus the penetration depth inside (exact), a lower bound
    of the Euclidean distance outside (exact in front of a facet). The task obstacles are
    already inflated by the robot radius, so the robot touches obstacle ``i`` iff
    ``clearance_i <= 0``.

    Args:
        position: ``[..., d]`` robot positions.
        centers: ``[..., K, d]`` obstacle centres.
        generators: ``[..., K, d, p]`` obstacle generators (full-dimensional for valid slots).
        mask: ``[..., K]`` bool, valid obstacle slots; invalid ones get ``+inf``.

    Returns:
        ``[..., K]`` in float64.

    Examples:
        >>> box = torch.eye(2).expand(1, 2, 2)
        >>> point_clearance(torch.tensor([3.0, 0.0]), torch.zeros(1, 2), box)
        tensor([2.], dtype=torch.float64)
    """
    position, centers, generators = (t.to(torch.float64) for t in (position, centers, generators))
    if position.shape[-1] != centers.shape[-1] or generators.shape[-2] != centers.shape[-1]:
        raise ValueError(f"`position` [..., d], `centers` [..., K, d] and `generators` [..., K, d, p] must share d; "
                         f"got {tuple(position.shape)}, {tuple(centers.shape)}, {tuple(generators.shape)}")
    normals = facet_normals(generators)  # [..., K, F, d]
    norm = normals.norm(dim=-1)
    valid = norm > 1e-12 * norm.amax(-1, keepdim=True).clamp_min(1e-300)
    unit = normals / torch.where(valid, norm, torch.ones_like(norm)).unsqueeze(-1)
    support = facet_supports(unit, generators)  # [..., K, F]
    offset = (unit @ (position.unsqueeze(-2) - centers).unsqueeze(-1)).squeeze(-1).abs()
    value = torch.where(valid, offset - support, torch.full_like(offset, -torch.inf)).amax(-1)
    if mask is not None:
        value = torch.where(mask.to(torch.bool), value, torch.full_like(value, torch.inf))
    return value


class AffineModel(nn.Module):
    """A nominal robot model ``x' = A x + B u + c``, fitted by least squares (float64).

    The baselines that need "a robot model" (SAILR's intervener, RTS's reachable sets) get this
    one: the affine least-squares fit of the same random-input offline data BRSL gets, i.e. the
    centre of BRSL's (global) reachable sets without their error bound. :attr:`residual` is the
    largest absolute one-step residual per state dimension on that data (noise included).

    Args:
        A: ``[n, n]``.
        B: ``[n, m]``.
        c: ``[n]``.
        residual: ``[n]`` (default zeros).

    Examples:
        >>> x, u = torch.randn(50, 2, dtype=torch.float64), torch.randn(50, 1, dtype=torch.float64)
        >>> model = AffineModel.fit(x, u, x @ torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=torch.float64).T + 0.5 * u)
        >>> torch.allclose(model.B, torch.tensor([[0.5], [0.5]], dtype=torch.float64))
        True
        >>> model(x[:3], u[:3]).shape
        torch.Size([3, 2])
    """

    def __init__(self, A: Tensor, B: Tensor, c: Tensor, residual: Tensor | None = None):
        super().__init__()
        A, B, c = (torch.as_tensor(t, dtype=torch.float64) for t in (A, B, c))
        n = A.shape[0]
        if A.shape != (n, n) or B.ndim != 2 or B.shape[0] != n or c.shape != (n,):
            raise ValueError(f"`A` [n, n], `B` [n, m] and `c` [n] do not fit: {tuple(A.shape)}, {tuple(B.shape)}, "
                             f"{tuple(c.shape)}")
        residual = torch.zeros(n, dtype=torch.float64) if residual is None else torch.as_tensor(
            residual, dtype=torch.float64)
        self.register_buffer("A", A)
        self.register_buffer("B", B)
        self.register_buffer("c", c)
        self.register_buffer("residual", residual)

    @classmethod
    def fit(cls, x: Tensor, u: Tensor, x_next: Tensor) -> AffineModel:
        """Least-squares fit on transitions ``x [N, n]``, ``u [N, m]``, ``x_next [N, n]``."""
        x, u, x_next = (t.to(torch.float64) for t in (x, u, x_next))
        if x.ndim != 2 or u.ndim != 2 or x_next.shape != x.shape or u.shape[0] != x.shape[0]:
            raise ValueError(f"transitions must be x [N, n], u [N, m], x_next [N, n]; got {tuple(x.shape)}, "
                             f"{tuple(u.shape)}, {tuple(x_next.shape)}")
        n, m = x.shape[1], u.shape[1]
        if x.shape[0] < n + m + 1:
            raise ValueError(f"need at least n + m + 1 = {n + m + 1} transitions, got {x.shape[0]}")
        phi = torch.cat([x, u, torch.ones_like(x[:, :1])], dim=1)
        theta = torch.linalg.lstsq(phi, x_next).solution  # [n + m + 1, n]
        residual = (x_next - phi @ theta).abs().amax(0)
        return cls(theta[:n].T, theta[n:n + m].T, theta[-1], residual)

    @property
    def state_dim(self) -> int:
        return self.A.shape[0]

    @property
    def action_dim(self) -> int:
        return self.B.shape[1]

    def forward(self, state: Tensor, action: Tensor) -> Tensor:
        """``[..., n]``, ``[..., m]`` -> next state ``[..., n]`` (float64)."""
        return state.to(torch.float64) @ self.A.T + action.to(torch.float64) @ self.B.T + self.c


class ActionFilter(Transform):
    """Base of the baselines' transforms: replace the proposed ``action`` by an executed one.

    Subclasses implement :meth:`filter`. On every step the transform writes the executed
    action to ``next[safe_action_key]`` and ``next[diagnostics_key]`` (``intervened [1]`` bool,
    ``compute_time [1]`` float64 seconds, plus :attr:`extra_flags`), and subtracts ``penalty``
    from the reward when it intervened (the same reward shaping as :class:`BRSLSafetyLayer`).
    Like every TorchRL transform of an env, it works on any batch shape.
    """

    #: names of further bool diagnostics written by a subclass
    extra_flags: tuple[str, ...] = ()

    def __init__(self, *, state_key: NestedKey = "state", obstacles_key: NestedKey = "obstacles",
                 action_key: NestedKey = "action", safe_action_key: NestedKey = "safe_action",
                 diagnostics_key: NestedKey = "baseline", reward_key: NestedKey = "reward", penalty: float = 0.0):
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[], out_keys_inv=[])
        if penalty < 0:
            raise ValueError(f"`penalty` must be >= 0, got {penalty}")
        self.state_key, self.obstacles_key, self.action_key = state_key, obstacles_key, action_key
        self.safe_action_key, self.diagnostics_key, self.reward_key = safe_action_key, diagnostics_key, reward_key
        self.penalty = float(penalty)

    def filter(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """``(executed [..., m], intervened [...] bool, {flag: [...] bool})`` for one step."""
        raise NotImplementedError

    def _flags(self) -> tuple[str, ...]:
        return ("intervened", *self.extra_flags)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        batch, device = observation_spec.shape, observation_spec.device
        parent_action = self._action_spec()
        observation_spec[self.safe_action_key] = Unbounded(shape=(*batch, parent_action.shape[-1]),
                                                           dtype=parent_action.dtype, device=device)
        diag = Composite(shape=batch, device=device)
        for name in self._flags():
            diag[name] = Bounded(low=0, high=1, shape=(*batch, 1), dtype=torch.bool, device=device)
        diag["compute_time"] = Unbounded(shape=(*batch, 1), dtype=torch.float64, device=device)
        observation_spec[self.diagnostics_key] = diag
        return observation_spec

    def _action_spec(self):
        return self.parent.full_action_spec[self.action_key]

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        spec = self._action_spec()
        device = tensordict_reset.device
        tensordict_reset.set(self.safe_action_key, torch.zeros(*batch, spec.shape[-1], dtype=spec.dtype,
                                                               device=device))
        for name in self._flags():
            tensordict_reset.set((self.diagnostics_key, name), torch.zeros(*batch, 1, dtype=torch.bool, device=device))
        tensordict_reset.set((self.diagnostics_key, "compute_time"),
                             torch.zeros(*batch, 1, dtype=torch.float64, device=device))
        return tensordict_reset

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        batch = tensordict.batch_size
        action = tensordict.get(self.action_key)
        executed, intervened, flags = self.filter(tensordict)
        tensordict.set(self.action_key, executed.to(action.dtype))
        for name, value in {"intervened": intervened, **flags}.items():
            tensordict.set((self.diagnostics_key, name), value.reshape(*batch, 1).to(torch.bool))
        tensordict.set((self.diagnostics_key, "compute_time"),
                       torch.full((*batch, 1), time.perf_counter() - start, dtype=torch.float64, device=action.device))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return write_step_outputs(tensordict, next_tensordict, self.action_key, self.safe_action_key,
                                  self.diagnostics_key, self.reward_key, self.penalty)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(f"{type(self).__name__} acts inside an environment's step: append it to a TransformedEnv.")


def obstacle_tensors(tensordict: TensorDictBase, obstacles_key: NestedKey, batch: torch.Size):
    """``(centers [..., K, d], generators [..., K, d, p], mask [..., K])`` in float64 from a TensorDict."""
    obstacles = tensordict.get(obstacles_key)
    centers = obstacles.get("center").to(torch.float64)
    generators = obstacles.get("generators").to(torch.float64)
    mask = obstacles.get("mask").to(torch.bool)
    if mask.ndim > len(batch) + 1:  # a trailing singleton
        mask = mask.reshape(*batch, -1)
    return centers, generators, mask


def check_dims(name: str, dims: Sequence[int], size: int) -> tuple[int, ...]:
    """``dims`` as a tuple of valid indices into a vector of ``size``, or a ValueError naming ``name``."""
    dims = tuple(int(d) for d in dims)
    if not dims or any(d < 0 or d >= size for d in dims):
        raise ValueError(f"`{name}` must be non-empty indices below {size}, got {dims}")
    return dims
