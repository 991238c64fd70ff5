"""RTS: reachability-based trajectory safeguard over parameterised braking trajectories.

Shao, Chen, Kousik, Vasudevan, "Reachability-based trajectory safeguard (RTS): a safe and fast
reinforcement learning safety layer for continuous control", RA-L 2021; reference code
``roahmlab/reachability-based_trajectory_safeguard`` (MATLAB; the quadrotor example samples 15
candidates).

A trajectory parameter ``k`` (the action, ``[m]``, in the action bounds) is held for ``n_peak``
steps (velocity-commanded robots: the commanded peak velocity; the double integrator: the
acceleration that reaches its peak velocity at ``n_peak``), then ``n_brk`` braking steps
``u = L x̂_peak`` (``L = 0``: zero command; the double integrator: constant deceleration
``-v̂_peak / (n_brk dt)``). For an affine nominal model ``x' = A x + B u + c``
(:class:`AffineModel`) every state of the trajectory is affine in ``(x0, k)``, so the forward
reachable set of a *parameter cell* (a box of the grid over the action bounds) at each step is
exactly a zonotope: centre affine in ``x0`` and the cell centre, generators the cell's
half-widths mapped through the trajectory, plus a tracking-error box: the model residual bound
propagated through ``A`` (the task's noise is in the residual). The generators are computed
once, offline; online only centres move.

Online (per step, batched over envs): the proposal's cell is checked against every obstacle
with the project's closed-form zonotope check; if its reachable set meets an obstacle,
``n_samples`` candidates are drawn near ``k``, the safe ones kept and the nearest one executed;
if none is safe the previous safe trajectory continues (and after its end the braking policy).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.data import Bounded, Unbounded

from torchrl_brsl.baselines._common import ActionFilter, AffineModel, check_dims, obstacle_tensors
from torchrl_brsl.collision import ZonotopeCollisionChecker
from torchrl_brsl.sets import Zonotope


class TrajectoryReachableSets(nn.Module):
    """Offline reachable sets of the parameterised trajectories, per parameter cell (float64).

    Args:
        model: the nominal affine model and its residual bound (``model.residual [n]``).
        n_peak: steps at the parameter (>= 1).
        n_brk: braking steps.
        position_dims: the ``d`` position indices of the state.
        action_low: ``[m]``; the parameter space is ``[action_low, action_high]``.
        action_high: ``[m]``.
        cells_per_dim: grid cells per parameter dimension.
        braking_gain: ``L [m, n]`` of the braking phase (default zeros: zero command).
        error_scale: multiplies the residual bound (the tracking-error bound).

    Attributes:
        state_map: ``[T, n, n]``, ``param_map``: ``[T, n, m]``, ``offset``: ``[T, n]``: the nominal
            state at step ``t + 1`` is ``state_map[t] x0 + param_map[t] k + offset[t]``.
        action_state_map, action_param_map, action_offset: ``[T, m, n]``, ``[T, m, m]``, ``[T, m]``:
            the nominal (open-loop) action at step ``t``.
        generators: ``[T, d, m + d]`` position generators of one cell's set (cell + error box).

    Examples:
        >>> dt = 0.1
        >>> A = torch.eye(2) + torch.tensor([[0.0, dt], [0.0, 0.0]])
        >>> model = AffineModel(A, torch.tensor([[0.0], [dt]]), torch.zeros(2))
        >>> frs = TrajectoryReachableSets(model, n_peak=3, n_brk=5, position_dims=(0,), action_low=-torch.ones(1),
        ...                               action_high=torch.ones(1), cells_per_dim=4,
        ...                               braking_gain=torch.tensor([[0.0, -1 / (5 * dt)]]))
        >>> sets = frs.sets(torch.zeros(1, 2), torch.tensor([[0.9]]))
        >>> sets.center.shape, sets.generators.shape
        (torch.Size([1, 8, 1]), torch.Size([1, 8, 1, 2]))
        >>> frs.final_speed_bound(torch.zeros(2), torch.tensor([0.9]), velocity_dims=(1,)) < 1e-6
        tensor(True)
    """

    def __init__(self, model: AffineModel, *, n_peak: int, n_brk: int, position_dims: Sequence[int],
                 action_low: Tensor, action_high: Tensor, cells_per_dim: int = 10, braking_gain: Tensor | None = None,
                 error_scale: float = 1.0):
        super().__init__()
        n, m = model.state_dim, model.action_dim
        if int(n_peak) < 1 or int(n_brk) < 0:
            raise ValueError(f"`n_peak` must be >= 1 and `n_brk` >= 0, got {n_peak}, {n_brk}")
        if int(cells_per_dim) < 1:
            raise ValueError(f"`cells_per_dim` must be >= 1, got {cells_per_dim}")
        if error_scale < 0:
            raise ValueError(f"`error_scale` must be >= 0, got {error_scale}")
        self.position_dims = check_dims("position_dims", position_dims, n)
        low, high = (torch.as_tensor(t, dtype=torch.float64).reshape(-1) for t in (action_low, action_high))
        if low.shape != (m,) or high.shape != (m,) or not bool((high > low).all()):
            raise ValueError(f"`action_low` and `action_high` must be [{m}] with low < high, got {low}, {high}")
        gain = torch.zeros(m, n, dtype=torch.float64) if braking_gain is None else torch.as_tensor(
            braking_gain, dtype=torch.float64)
        if gain.shape != (m, n):
            raise ValueError(f"`braking_gain` must be [m, n] = [{m}, {n}], got {tuple(gain.shape)}")
        self.n_peak, self.n_brk, self.cells_per_dim = int(n_peak), int(n_brk), int(cells_per_dim)
        self.register_buffer("low", low)
        self.register_buffer("high", high)
        self.register_buffer("braking_gain", gain)
        steps = self.n_peak + self.n_brk
        A, B, c = model.A, model.B, model.c
        # the trajectory as affine maps of z = [x0 (n), k (m), 1]
        X = torch.cat([torch.eye(n), torch.zeros(n, m + 1)], dim=1).double()
        hold = torch.cat([torch.zeros(m, n), torch.eye(m), torch.zeros(m, 1)], dim=1).double()
        shift = torch.cat([torch.zeros(n, n + m), c.reshape(n, 1)], dim=1)
        states, actions, peak = [], [], None
        for t in range(steps):
            if t == self.n_peak:
                peak = X
            U = hold if t < self.n_peak else gain @ peak
            X = A @ X + B @ U + shift
            states.append(X)
            actions.append(U)
        S, U = torch.stack(states), torch.stack(actions)
        self.register_buffer("state_map", S[..., :n])
        self.register_buffer("param_map", S[..., n:n + m])
        self.register_buffer("offset", S[..., -1])
        self.register_buffer("action_state_map", U[..., :n])
        self.register_buffer("action_param_map", U[..., n:n + m])
        self.register_buffer("action_offset", U[..., -1])
        # tracking error: e_{t+1} = A e_t + w_t, |w_t| <= residual; its interval hull per step
        radius = error_scale * model.residual
        err, hull = torch.zeros(n, 0, dtype=torch.float64), []
        for _ in range(steps):
            err = torch.cat([A @ err, torch.diag(radius)], dim=1)
            hull.append(err.abs().sum(1))
        self.register_buffer("error_radius", torch.stack(hull))  # [T, n]
        dims = list(self.position_dims)
        cell = torch.diag((high - low) / (2 * self.cells_per_dim))
        error_box = torch.diag_embed(self.error_radius[:, dims].clamp_min(1e-9))  # keeps the sets full-dimensional
        self.register_buffer("generators", torch.cat([self.param_map[:, dims] @ cell, error_box], dim=-1))

    @property
    def steps(self) -> int:
        """``T = n_peak + n_brk`` sets per trajectory."""
        return self.n_peak + self.n_brk

    def cell_center(self, param: Tensor) -> Tensor:
        """Centre ``[..., m]`` of the grid cell containing each parameter ``[..., m]``."""
        width = (self.high - self.low) / self.cells_per_dim
        index = ((param.to(torch.float64) - self.low) / width).floor().clamp(0, self.cells_per_dim - 1)
        return self.low + (index + 0.5) * width

    def sets(self, state: Tensor, param: Tensor) -> Zonotope:
        """The position reachable sets of the cells of ``param [..., m]`` from ``state [..., n]``:
        a :class:`Zonotope` batch ``[..., T]`` of dimension ``d``."""
        dims = list(self.position_dims)
        center = (self.state_map[:, dims] @ state.to(torch.float64).unsqueeze(-1).unsqueeze(-3)).squeeze(-1) \
            + (self.param_map[:, dims] @ self.cell_center(param).unsqueeze(-1).unsqueeze(-3)).squeeze(-1) \
            + self.offset[:, dims]
        return Zonotope(center, self.generators.expand(*center.shape[:-1], *self.generators.shape[-2:]))

    def actions(self, state: Tensor, param: Tensor) -> Tensor:
        """The open-loop action sequence ``[..., T, m]`` of the trajectory of ``param`` from ``state``."""
        x, k = state.to(torch.float64).unsqueeze(-1).unsqueeze(-3), param.to(torch.float64).unsqueeze(-1).unsqueeze(-3)
        return (self.action_state_map @ x).squeeze(-1) + (self.action_param_map @ k).squeeze(-1) + self.action_offset

    def final_speed_bound(self, state: Tensor, param: Tensor, velocity_dims: Sequence[int]) -> Tensor:
        """Largest nominal ``|velocity|`` at the trajectory's end for the exact ``param`` (``[...]``)."""
        dims = list(velocity_dims)
        final = self.state_map[-1] @ state.to(torch.float64).unsqueeze(-1) \
            + self.param_map[-1] @ param.to(torch.float64).unsqueeze(-1)
        return (final.squeeze(-1) + self.offset[-1])[..., dims].abs().amax(-1)


class RTSSafeguard(ActionFilter):
    """RTS as a TorchRL transform: execute the first action of a verified trajectory.

    Reads ``state_key [..., n]`` and ``obstacles_key``; the proposal ``action [..., m]`` is the
    trajectory parameter. Keeps the current safe trajectory in the TensorDict (registered in
    ``full_state_spec``, reset per env): ``plan_key [..., T, m]`` float64 and
    ``plan_step_key [..., 1]`` int64 (the next row to execute; ``T``: exhausted). Writes
    ``next[safe_action_key]`` and ``next[diagnostics_key]`` (``intervened``: the proposal's cell
    was unsafe; ``fallback``: no candidate was safe; ``compute_time``).

    Args:
        frs: the offline :class:`TrajectoryReachableSets`.
        braking_policy: ``state [..., n] -> action [..., m]`` once a trajectory is exhausted.
        n_samples: candidates drawn near an unsafe proposal (the reference: 15).
        sample_std: their standard deviation, in units of half the parameter range.
        tol: slack on the collision value (``v* > 1 + tol`` counts as safe).
        seed: seed of the candidate sampler.
        state_key, obstacles_key, action_key, safe_action_key, diagnostics_key, reward_key:
            TensorDict keys; ``plan_key``, ``plan_step_key``: the stored trajectory.
        penalty: reward subtracted when the proposal was replaced.

    Examples:
        >>> import envs
        >>> from torchrl.envs import TransformedEnv
        >>> info = envs.safety_info("point_boxes")
        >>> model = AffineModel(torch.eye(4), 0.1 * torch.eye(4, 2), torch.zeros(4), torch.full((4,), 1e-3))
        >>> frs = TrajectoryReachableSets(model, n_peak=2, n_brk=2, position_dims=(0, 1),
        ...                               action_low=info.action_low, action_high=info.action_high)
        >>> rts = RTSSafeguard(frs, info.braking_policy)
        >>> td = TransformedEnv(envs.make("point_boxes", seed=0), rts).rollout(3)
        >>> td["next", "rts_plan"].shape
        torch.Size([3, 4, 2])
    """

    extra_flags = ("fallback",)

    def __init__(self, frs: TrajectoryReachableSets, braking_policy: Callable[[Tensor], Tensor], *, n_samples: int = 15,
                 sample_std: float = 0.3, tol: float = 1e-9, seed: int = 0, plan_key: NestedKey = "rts_plan",
                 plan_step_key: NestedKey = "rts_plan_step", **keys):
        super().__init__(**keys)
        if int(n_samples) < 0 or sample_std <= 0:
            raise ValueError(f"`n_samples` must be >= 0 and `sample_std` > 0, got {n_samples}, {sample_std}")
        self.frs, self.braking_policy = frs, braking_policy
        self.n_samples, self.sample_std, self.tol = int(n_samples), float(sample_std), float(tol)
        self.plan_key, self.plan_step_key = plan_key, plan_step_key
        self._generator = torch.Generator().manual_seed(int(seed))
        self._checkers: dict = {}

    # ----------------------------------------------------------------- specs and reset
    def transform_observation_spec(self, observation_spec):
        observation_spec = super().transform_observation_spec(observation_spec)
        batch, device = observation_spec.shape, observation_spec.device
        observation_spec[self.plan_key] = self._plan_spec(batch, device)
        observation_spec[self.plan_step_key] = self._step_spec(batch, device)
        return observation_spec

    def transform_input_spec(self, input_spec):
        if input_spec["full_state_spec"] is None:
            from torchrl.data import Composite

            input_spec["full_state_spec"] = Composite(shape=input_spec.shape, device=input_spec.device)
        input_spec["full_state_spec"][self.plan_key] = self._plan_spec(input_spec.shape, input_spec.device)
        input_spec["full_state_spec"][self.plan_step_key] = self._step_spec(input_spec.shape, input_spec.device)
        return input_spec

    def _plan_spec(self, batch, device):
        return Unbounded(shape=(*batch, self.frs.steps, self.frs.low.shape[0]), dtype=torch.float64, device=device)

    def _step_spec(self, batch, device):
        return Bounded(low=0, high=self.frs.steps, shape=(*batch, 1), dtype=torch.int64, device=device)

    def _reset(self, tensordict, tensordict_reset):
        tensordict_reset = super()._reset(tensordict, tensordict_reset)
        batch, device = tensordict_reset.batch_size, tensordict_reset.device
        fresh = torch.zeros(*batch, self.frs.steps, self.frs.low.shape[0], dtype=torch.float64, device=device)
        steps = torch.full((*batch, 1), self.frs.steps, dtype=torch.int64, device=device)
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        previous = tensordict.get(self.plan_key, None) if tensordict is not None else None
        if reset is not None and previous is not None:
            fresh = torch.where(reset.reshape(*batch, 1, 1), fresh, previous.to(fresh))
            steps = torch.where(reset.reshape(*batch, 1), steps, tensordict.get(self.plan_step_key, steps))
        tensordict_reset.set(self.plan_key, fresh)
        tensordict_reset.set(self.plan_step_key, steps)
        return tensordict_reset

    # ----------------------------------------------------------------- the safeguard
    def safe(self, state: Tensor, params: Tensor, centers: Tensor, generators: Tensor, mask: Tensor) -> Tensor:
        """Whether each candidate's cell set misses every obstacle at every step.

        Args:
            state: ``[B, n]``.
            params: ``[B, C, m]`` candidates.
            centers, generators, mask: ``[B, K, d]``, ``[B, K, d, p]``, ``[B, K]``.

        Returns:
            ``[B, C]`` bool.
        """
        sets = self.frs.sets(state.unsqueeze(1), params)  # [B, C, T]
        # empty slots: a unit box far away, masked out below (the closed form needs full-dimensional pairs)
        eye = torch.eye(generators.shape[-2], generators.shape[-1], dtype=torch.float64, device=generators.device)
        generators = torch.where(mask[..., None, None], generators, eye)
        centers = torch.where(mask[..., None], centers, torch.full_like(centers, 1e6))
        checker = ZonotopeCollisionChecker(self.frs.generators.to(generators)[None, None, :, None],
                                           generators[:, None, None])  # [1, 1, T, 1] x [B, 1, 1, K]
        value = checker.value(sets.center.unsqueeze(-2), centers[:, None, None])  # [B, C, T, K]
        clear = (value > 1 + self.tol) | ~mask[:, None, None]
        return clear.all(-1).all(-1)

    def filter(self, tensordict: TensorDictBase):
        batch = tensordict.batch_size
        state = tensordict.get(self.state_key).to(torch.float64)
        action = tensordict.get(self.action_key).to(torch.float64)
        centers, generators, mask = obstacle_tensors(tensordict, self.obstacles_key, batch)
        n, m, T = state.shape[-1], action.shape[-1], self.frs.steps
        state, action = state.reshape(-1, n), action.reshape(-1, m)
        centers, generators = centers.reshape(-1, *centers.shape[-2:]), generators.reshape(-1, *generators.shape[-3:])
        mask = mask.reshape(-1, mask.shape[-1])
        plan = tensordict.get(self.plan_key, None)
        step = tensordict.get(self.plan_step_key, None)
        B = state.shape[0]
        plan = torch.zeros(B, T, m, dtype=torch.float64) if plan is None else plan.reshape(B, T, m).to(torch.float64)
        step = torch.full((B,), T, dtype=torch.int64) if step is None else step.reshape(B)
        low, high = self.frs.low, self.frs.high
        proposal = torch.maximum(torch.minimum(action, high), low)
        noise = torch.randn(B, self.n_samples, m, generator=self._generator, dtype=torch.float64)
        samples = (proposal.unsqueeze(1) + self.sample_std * (high - low) / 2 * noise)
        candidates = torch.cat([proposal.unsqueeze(1), torch.maximum(torch.minimum(samples, high), low)], dim=1)
        safe = self.safe(state, candidates, centers, generators, mask)  # [B, 1 + S]
        distance = (candidates - proposal.unsqueeze(1)).norm(dim=-1)
        distance = torch.where(safe, distance, torch.full_like(distance, torch.inf))
        best = distance.argmin(-1)
        found = safe.any(-1)
        chosen = candidates[torch.arange(B), best]
        new_plan = self.frs.actions(state, chosen)  # [B, T, m]
        # no safe candidate: the previous trajectory's next action, or braking once it is exhausted
        exhausted = step >= T
        previous = plan[torch.arange(B), step.clamp(max=T - 1)]
        previous = torch.where(exhausted.unsqueeze(-1), self.braking_policy(state).to(torch.float64), previous)
        executed = torch.where(found.unsqueeze(-1), new_plan[:, 0], previous)
        plan = torch.where(found[:, None, None], new_plan, plan)
        step = torch.where(found, torch.ones_like(step), (step + 1).clamp(max=T))
        tensordict.set(self.plan_key, plan.reshape(*batch, T, m))
        tensordict.set(self.plan_step_key, step.reshape(*batch, 1))
        intervened = ~safe[:, 0]
        return executed.reshape(*batch, m), intervened.reshape(batch), {"fallback": (~found).reshape(batch)}

    def _step(self, tensordict, next_tensordict):
        next_tensordict = super()._step(tensordict, next_tensordict)
        next_tensordict.set(self.plan_key, tensordict.get(self.plan_key))
        next_tensordict.set(self.plan_step_key, tensordict.get(self.plan_step_key))
        return next_tensordict
