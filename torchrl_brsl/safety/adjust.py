"""Adjusters: move an unsafe plan until its reachable sets are collision-free (paper Alg. 3)."""
from __future__ import annotations

import time
from typing import NamedTuple

import torch
from torch import Tensor

from torchrl_brsl.safety.plan_check import PlanChecker, PlanEvaluation


class Adjustment(NamedTuple):
    """Result of an adjuster on a batch of ``B`` plans.

    Attributes:
        plan: ``[B, P, m]`` the adjusted plans (unchanged where already safe).
        evaluation: the verdict of the final plans.
        iterations: ``[B]`` gradient steps spent on each plan.
    """

    plan: Tensor
    evaluation: PlanEvaluation
    iterations: Tensor


class GradientAdjuster:
    """Projected gradient on the collision values, as in the paper (Algorithm 3).

    Each iteration raises every colliding value ``v* <= 1 + target_margin`` (and pulls the
    final set towards "stopped") by a gradient step on the plan, normalised per plan in
    action-range units, then projects onto the action box. Gradients flow through the
    reachable-set centres, which are affine in the plan (exact chain rule, eq. (11)), and
    through the braking tail. Plans that become safe stop moving; the loop ends when all
    are safe, after ``max_iterations``, or when the time budget runs out.

    Args:
        max_iterations: gradient steps at most.
        step_size: step length as a fraction of the action range (max-norm).
        target_margin: the adjuster aims for ``v* > 1 + target_margin`` so that accepted plans
            are not on the boundary.
        time_budget: seconds; ``None`` for no limit.

    Examples:
        >>> adjuster = GradientAdjuster(max_iterations=50, time_budget=0.1)
        >>> result = adjuster(checker, x0, plan, centers, generators, mask)  # doctest: +SKIP
    """

    def __init__(self, max_iterations: int = 50, step_size: float = 0.1, target_margin: float = 0.05,
                 time_budget: float | None = 0.1):
        if max_iterations < 0:
            raise ValueError(f"`max_iterations` must be >= 0, got {max_iterations}")
        if step_size <= 0:
            raise ValueError(f"`step_size` must be positive, got {step_size}")
        self.max_iterations = int(max_iterations)
        self.step_size = float(step_size)
        self.target_margin = float(target_margin)
        self.time_budget = time_budget

    def __call__(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacle_centers: Tensor,
                 obstacle_generators: Tensor, obstacle_mask: Tensor, start: float | None = None,
                 reference: Tensor | None = None) -> Adjustment:
        """Adjust ``plan`` ``[B, P, m]``; ``reference`` (the previous safe plan) is not used."""
        start = time.perf_counter() if start is None else start
        low, high = checker.action_low, checker.action_high
        scale = (high - low).clamp_min(1e-12)
        iterations = torch.zeros(plan.shape[0], dtype=torch.long, device=plan.device)
        for iteration in range(self.max_iterations + 1):
            plan = plan.detach().requires_grad_(True)
            evaluation = checker.evaluate(x0, plan, obstacle_centers, obstacle_generators, obstacle_mask)
            active = ~evaluation.safe
            out_of_time = self.time_budget is not None and time.perf_counter() - start > self.time_budget
            if iteration == self.max_iterations or out_of_time or not bool(active.any()):
                break
            finite = torch.nan_to_num(evaluation.values, posinf=1e6)
            shortfall = torch.relu(1 + self.target_margin - finite).sum((-1, -2))
            loss = (shortfall + torch.relu(evaluation.stop_excess)) * active
            (grad,) = torch.autograd.grad(loss.sum(), plan)
            grad = grad * scale
            norm = grad.flatten(1).abs().amax(-1).clamp_min(1e-12).view(-1, 1, 1)
            with torch.no_grad():
                moved = torch.minimum(torch.maximum(plan - self.step_size * scale * grad / norm, low), high)
                plan = torch.where(active.view(-1, 1, 1), moved, plan)
                iterations += active.long()
        evaluation = PlanEvaluation(*(t.detach() for t in evaluation))
        return Adjustment(plan.detach(), evaluation, iterations)


class FacetQPAdjuster:
    """Facet-locked quadratic program: the fast adjuster.

    Under a reference plan that is already safe (the previous safe plan, shifted), every
    (step, obstacle) pair is separated by the facet attaining its collision value. Locking
    each pair to that facet and linearising the reachable-set centres in the plan (exact for
    the plan part, which is affine; first order for a feedback braking tail) turns safety into
    linear constraints, which the reference satisfies. The adjuster then projects the proposal
    onto them, ``min ||u - u_proposed||^2`` subject to the locked facets, the stop condition
    and the action box, by accelerated projected gradient on the dual (batched, fixed
    iteration count). The result is pulled back towards the reference until the exact
    check (:meth:`PlanChecker.evaluate`) accepts it; if even that fails the plan is reported
    unsafe and the layer keeps its safe plan.

    Args:
        iterations: dual gradient iterations.
        target_margin: the projection aims for ``v* >= 1 + target_margin`` on every locked pair
            (or the reference's own value if smaller).
        backtracking: halvings of the step from the reference towards the projection tried
            when the exact check rejects it.
    """

    def __init__(self, iterations: int = 50, target_margin: float = 0.05, backtracking: int = 4):
        if iterations < 1:
            raise ValueError(f"`iterations` must be positive, got {iterations}")
        self.iterations = int(iterations)
        self.target_margin = float(target_margin)
        self.backtracking = int(backtracking)

    def __call__(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacle_centers: Tensor,
                 obstacle_generators: Tensor, obstacle_mask: Tensor, start: float | None = None,
                 reference: Tensor | None = None) -> Adjustment:
        if reference is None:
            raise ValueError("FacetQPAdjuster needs the `reference` plan (the previous safe plan)")
        n_envs, horizon = plan.shape[:2]
        reference = reference[:, :horizon].to(plan)
        low, high = checker.action_low, checker.action_high
        with torch.no_grad():
            ref_eval = checker.evaluate(x0, reference, obstacle_centers, obstacle_generators, obstacle_mask)
        jacobian = _centre_jacobian(checker, x0, reference)  # [B, T, n, P, m]
        pos_jac = jacobian[:, :, checker.position_dims].flatten(-2)  # [B, T, d, N]
        table = checker.checker(obstacle_generators).table
        offsets = obstacle_centers.unsqueeze(-3) - ref_eval.centers[..., checker.position_dims].unsqueeze(-2)
        products = (table.weights @ offsets.unsqueeze(-1)).squeeze(-1)  # [B, T, K, F]
        best = products.abs().argmax(-1, keepdim=True)
        weight = table.weights.gather(-2, best.unsqueeze(-1).expand(*best.shape, table.weights.shape[-1])).squeeze(-2)
        sign = products.gather(-1, best).squeeze(-1).sign()
        value_ref = products.gather(-1, best).squeeze(-1).abs()
        level = torch.minimum(torch.full_like(value_ref, 1 + self.target_margin), value_ref)
        # s w . (c_o - p_ref - J dz) >= level   <=>   (s w J) dz <= s w . Δ_ref - level
        rows = [(sign.unsqueeze(-1) * weight).unsqueeze(-2) @ pos_jac.unsqueeze(2)]  # [B, T, K, 1, N]
        rows = rows[0].squeeze(-2).flatten(1, 2)  # [B, T K, N]
        bounds = (value_ref - level).flatten(1)
        active = obstacle_mask.unsqueeze(1).expand(-1, ref_eval.values.shape[1], -1).flatten(1)
        rows = torch.where(active.unsqueeze(-1), rows, torch.zeros_like(rows))
        bounds = torch.where(active, bounds, torch.ones_like(bounds))
        eye = torch.eye(rows.shape[-1], dtype=rows.dtype, device=rows.device).expand(n_envs, -1, -1)
        ref_flat = reference.flatten(1)
        box_rows = torch.cat((eye, -eye), dim=1)
        box_bounds = torch.cat((high.repeat(horizon) - ref_flat, ref_flat - low.repeat(horizon)), dim=1)
        all_rows, all_bounds = [rows, box_rows], [bounds, box_bounds]
        if checker.stop_dims:
            stop_jac = jacobian[:, -1, checker.stop_dims].flatten(-2)  # [B, s, N]
            stop_ref = ref_eval.centers[:, -1, checker.stop_dims]
            room = (checker.stop_tolerance - checker.stop_radius).to(stop_ref)
            all_rows += [stop_jac, -stop_jac]
            all_bounds += [(room - stop_ref).clamp_min(0), (room + stop_ref).clamp_min(0)]
        A, b = torch.cat(all_rows, dim=1), torch.cat(all_bounds, dim=1).clamp_min(0)
        # rows that no step inside the action box can make active are dropped (for every env)
        reach_of_box = (A.abs() * (high - low).repeat(horizon)).sum(-1)
        needed = (reach_of_box > b).any(0)
        A, b = A[:, needed], b[:, needed]
        target = (torch.minimum(torch.maximum(plan, low), high) - reference).flatten(1)
        step = _project_polytope(A, b, target, self.iterations)
        # keep the linearised constraints exactly: scale back towards the reference
        excess = (A @ step.unsqueeze(-1)).squeeze(-1)
        scale = torch.where(excess > b, b / excess.clamp_min(1e-12), torch.ones_like(b)).amin(-1).clamp(0, 1)
        step = step * scale.unsqueeze(-1)
        best_plan, best_eval = reference, ref_eval
        accepted = torch.zeros(n_envs, dtype=torch.bool, device=plan.device)
        tries = torch.zeros(n_envs, dtype=torch.long, device=plan.device)
        for attempt in range(self.backtracking + 1):
            candidate = reference + step.view_as(reference) / (2 ** attempt)
            with torch.no_grad():
                evaluation = checker.evaluate(x0, candidate, obstacle_centers, obstacle_generators, obstacle_mask)
            take = evaluation.safe & ~accepted
            tries += (~accepted).long()
            best_plan = torch.where(take.view(-1, 1, 1), candidate, best_plan)
            best_eval = PlanEvaluation(*(torch.where(take.view(-1, *[1] * (new.ndim - 1)), new, old)
                                         for new, old in zip(evaluation, best_eval)))
            accepted |= take
            if bool(accepted.all()):
                break
        return Adjustment(best_plan, best_eval, tries)


def _centre_jacobian(checker: PlanChecker, x0: Tensor, plan: Tensor, eps: float = 1e-6) -> Tensor:
    """``d centres / d plan``: ``[B, T, n, P, m]``.

    One batched rollout of the plan and its ``P m`` forward perturbations: exact up to
    rounding for the plan part (affine in the plan), first order for a feedback braking tail.
    """
    n_envs, horizon, m = plan.shape
    n_vars = horizon * m
    basis = torch.eye(n_vars, dtype=plan.dtype, device=plan.device).view(n_vars, horizon, m)
    plans = torch.cat((plan.unsqueeze(1), plan.unsqueeze(1) + eps * basis), dim=1)  # [B, 1 + N, P, m]
    states = x0.unsqueeze(1).expand(-1, n_vars + 1, -1)
    centres = checker.rollout(states.reshape(-1, x0.shape[-1]), plans.reshape(-1, horizon, m))[1]
    centres = centres.view(n_envs, n_vars + 1, *centres.shape[1:])
    jacobian = (centres[:, 1:] - centres[:, :1]) / eps  # [B, N, T, n]
    return jacobian.permute(0, 2, 3, 1).reshape(n_envs, *centres.shape[2:], horizon, m)


def _project_polytope(A: Tensor, b: Tensor, target: Tensor, iterations: int) -> Tensor:
    """Approximately solve ``min ||z - target||^2 s.t. A z <= b`` (batched).

    Accelerated projected gradient on the dual ``min_{l >= 0} 1/2 l^T A A^T l - l^T (A t - b)``,
    ``z = t - A^T l``. ``A`` ``[B, C, N]``, ``b`` ``[B, C]``, ``target`` ``[B, N]``.
    """
    gram = A @ A.transpose(-1, -2)
    lipschitz = gram.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-12).view(-1, 1, 1)  # trace >= max eigenvalue
    step_matrix = torch.eye(gram.shape[-1], dtype=A.dtype, device=A.device) - gram / lipschitz
    offset = ((A @ target.unsqueeze(-1)) - b.unsqueeze(-1)) / lipschitz  # [B, C, 1]
    lam = torch.zeros_like(offset)
    momentum, t = lam, 1.0
    for _ in range(iterations):
        new = torch.baddbmm(offset, step_matrix, momentum).clamp_min_(0)
        t_next = (1 + (1 + 4 * t * t) ** 0.5) / 2
        momentum = torch.add(new, new - lam, alpha=(t - 1) / t_next)
        lam, t = new, t_next
    return target - (A.transpose(-1, -2) @ lam).squeeze(-1)
