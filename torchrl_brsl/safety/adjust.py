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
                 obstacle_generators: Tensor, obstacle_mask: Tensor, start: float | None = None) -> Adjustment:
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
