"""Reachable sets of a plan plus its failsafe tail, and their safety verdict."""
from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from torchrl_brsl.collision import ZonotopeCollisionChecker
from torchrl_brsl.reach import DataDrivenReach
from torchrl_brsl.safety.failsafe import Failsafe
from torchrl_brsl.sets import reduce_girard


class PlanEvaluation(NamedTuple):
    """What :meth:`PlanChecker.evaluate` returns for a batch of ``B`` plans.

    Attributes:
        actions: ``[B, T, m]`` the full sequence: the plan then the braking tail.
        centers: ``[B, T, n]`` centres of ``R_1 .. R_T``.
        values: ``[B, T, K]`` collision values v* (``inf`` for masked obstacles).
        stop_excess: ``[B]`` how far the final set is from "stopped" (<= 0 means stopped).
        safe: ``[B]`` every set collision-free (``v* > 1 + margin``) and the final set stopped.
    """

    actions: Tensor
    centers: Tensor
    values: Tensor
    stop_excess: Tensor
    safe: Tensor


class PlanChecker:
    """Verifies plans: reachable sets of plan + braking tail against obstacles, and a final stop.

    The generators of every reachable set from a measured state do not depend on the plan
    (see :class:`DataDrivenReach`), so their projections onto the obstacle space are reduced
    once here, and the facet table of each (set, obstacle) pair is rebuilt only when the
    obstacles change. A check then costs the centre recursion and one batched product.

    Args:
        reach: the fitted reachability model.
        failsafe: the braking manoeuvre appended to plans.
        horizon: ``T``, the number of reachable sets checked (plan length + braking steps).
        position_dims: state dims of the obstacle space (default: the model's
            translation-invariant dims).
        stop_dims: state dims that must be ~0 when stopped (velocities).
        stop_tolerance: the final set's interval on ``stop_dims`` must lie in
            ``[-stop_tolerance, stop_tolerance]`` (a float, or one value per stop dim). It must
            exceed the final set's own radius on those dims, which the error message reports.
        set_generators: width of the projected sets after Girard reduction
            (default ``4 d``).
        margin: a set counts as colliding when ``v* <= 1 + margin``.
        action_low, action_high: ``[m]`` bounds; braking actions are clipped to them.
        action_dtype: the dtype actions reach the robot in; braking actions are rounded to it
            so that the verified sequence is exactly the executed one.
    """

    def __init__(self, reach: DataDrivenReach, failsafe: Failsafe, horizon: int, *, stop_dims: Sequence[int],
                 stop_tolerance: float | Sequence[float] | Tensor, action_low: Tensor, action_high: Tensor,
                 position_dims: Sequence[int] | None = None, set_generators: int | None = None,
                 margin: float = 1e-6, action_dtype: torch.dtype = torch.float64):
        self.reach = reach
        self.failsafe = failsafe
        self.horizon = int(horizon)
        dtype = reach.state_matrix.dtype
        self.position_dims = list(reach.translation_invariant_dims if position_dims is None else position_dims)
        if not self.position_dims:
            raise ValueError("`position_dims` must name the state dims of the obstacle space")
        self.stop_dims = list(stop_dims)
        self.margin = float(margin)
        self.action_dtype = action_dtype
        self.action_low = action_low.to(dtype)
        self.action_high = action_high.to(dtype)
        errors = reach.error_generators_sequence(self.horizon)  # [T, n, p]
        d = len(self.position_dims)
        self.set_generators = reduce_girard(errors[:, self.position_dims], set_generators or 4 * d)  # [T, d, ps]
        self.stop_radius = errors[-1, self.stop_dims].abs().sum(-1)  # [len(stop_dims)]
        self.stop_tolerance = torch.as_tensor(stop_tolerance, dtype=dtype).expand(len(self.stop_dims))
        if self.stop_dims and bool((self.stop_radius >= self.stop_tolerance).any()):
            raise ValueError(
                f"`stop_tolerance`={self.stop_tolerance.tolist()} is not above the final reachable set's radius "
                f"{self.stop_radius.tolist()} on the stop dims: no plan could ever be accepted. Raise the "
                "tolerance, shorten the horizon or use tighter offline data.")
        self._obstacle_generators: Tensor | None = None
        self._checker: ZonotopeCollisionChecker | None = None

    def checker(self, obstacle_generators: Tensor) -> ZonotopeCollisionChecker:
        """The facet table for ``obstacle_generators`` ``[B, K, d, p]`` (rebuilt on change)."""
        cached = self._obstacle_generators
        if cached is None or cached.shape != obstacle_generators.shape or not torch.equal(cached, obstacle_generators):
            self._checker = ZonotopeCollisionChecker(self.set_generators.unsqueeze(-3).unsqueeze(0),
                                                     obstacle_generators.unsqueeze(-4))
            self._obstacle_generators = obstacle_generators.clone()
        return self._checker

    def rollout(self, x0: Tensor, plan: Tensor) -> tuple[Tensor, Tensor]:
        """Nominal centres of ``plan`` followed by braking up to the horizon.

        Args:
            x0: ``[B, n]`` measured states.
            plan: ``[B, P, m]`` with ``P <= T``.

        Returns:
            ``(actions [B, T, m], centers [B, T, n])``; differentiable w.r.t. ``plan``.
        """
        n_tail = self.horizon - plan.shape[1]
        if self.failsafe.policy is None:  # open-loop braking: the whole sequence is affine in the plan
            hold = torch.minimum(torch.maximum(self.failsafe.hold_action.to(plan), self.action_low), self.action_high)
            actions = torch.cat((plan, hold.to(self.action_dtype).to(plan.dtype).expand(plan.shape[0], n_tail, -1)),
                                dim=1)
            return actions, self.reach.reach_centers(x0, actions)
        centers = self.reach.reach_centers(x0, plan)
        actions = [plan]
        A, B, k = self.reach.state_matrix, self.reach.input_matrix, self.reach.offset
        c = centers[:, -1]
        tail_centers, tail_actions = [], []
        for _ in range(n_tail):
            u = torch.minimum(torch.maximum(self.failsafe.actions(c), self.action_low), self.action_high)
            u = u.to(self.action_dtype).to(c.dtype)
            c = c @ A.T + u @ B.T + k
            tail_actions.append(u)
            tail_centers.append(c)
        if tail_actions:
            actions.append(torch.stack(tail_actions, dim=1))
            centers = torch.cat((centers, torch.stack(tail_centers, dim=1)), dim=1)
        return torch.cat(actions, dim=1), centers

    def evaluate(self, x0: Tensor, plan: Tensor, obstacle_centers: Tensor, obstacle_generators: Tensor,
                 obstacle_mask: Tensor) -> PlanEvaluation:
        """Verify a batch of plans from measured states.

        Args:
            x0: ``[B, n]``.
            plan: ``[B, P, m]`` (``P <= T``); the rest of the horizon is the braking tail.
            obstacle_centers: ``[B, K, d]``.
            obstacle_generators: ``[B, K, d, p]``.
            obstacle_mask: ``[B, K]`` bool, ``True`` for real obstacles.
        """
        actions, centers = self.rollout(x0, plan)
        positions = centers[..., self.position_dims]  # [B, T, d]
        values = self.checker(obstacle_generators).value(positions.unsqueeze(-2), obstacle_centers.unsqueeze(-3))
        values = torch.where(obstacle_mask.unsqueeze(-2), values, torch.full_like(values, float("inf")))
        if self.stop_dims:
            final = centers[:, -1, self.stop_dims].abs() + self.stop_radius
            stop_excess = (final - self.stop_tolerance).amax(-1)
        else:
            stop_excess = centers.new_zeros(centers.shape[0])
        collision_free = (values > 1 + self.margin).flatten(1).all(-1)
        return PlanEvaluation(actions, centers, values, stop_excess, collision_free & (stop_excess <= 0))
