"""Adjusters: move an unsafe plan until its reachable sets are collision-free (paper Alg. 3)."""
from __future__ import annotations

import time
from typing import NamedTuple

import torch
from torch import Tensor

from torchrl_brsl._compiling import quick_tracing, small_matmul
from torchrl_brsl.safety.plan_check import (FUSE_FROM_STEPS, AffineRollout, Gauge, PlanChecker, PlanEvaluation,
                                             _checked_sets, plan_axes)
from torchrl_brsl.sets import Obstacles


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
    are safe, after ``max_iterations``, or when the time budget runs out. On a global model
    the gradient is in closed form: with the constant brake from the affine rollout, with a
    braking policy from the tail linearised along the current nominal rollout (the same
    gradient as autograd, without its graph). On a local model, whose sets' sizes also depend
    on the plan, it is the gradient through the centres with the sets' generators held fixed
    (eq. (11) as the paper states it), each centre's Jacobian taken along the rollout that checks
    the plan with each step's leaf models and relaxations held fixed (:meth:`PlanChecker.evaluate_with_gauge`
    with tangents: one compiled loop per iteration when compiled, where autograd ran compiled steps
    forward and backward; ``benchmarks/bench_gradient.py``). Obstacles checked by the LP: autograd.

    Args:
        max_iterations: gradient steps at most.
        step_size: step length as a fraction of the action range (max-norm).
        target_margin: the adjuster aims for ``v* > 1 + target_margin`` so that accepted plans
            are not on the boundary.
        time_budget: seconds; ``None`` for no limit.

    Examples:
        >>> adjuster = GradientAdjuster(max_iterations=50, time_budget=0.1)
        >>> result = adjuster(checker, x0, plan, obstacles)  # doctest: +SKIP
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

    def prepare(self, checker: PlanChecker) -> None:
        """Compile what this adjuster runs on ``checker`` now, not at its first control step
        (:func:`prepare_linearisation`); :class:`~torchrl_brsl.safety.SafetyDecision` calls it for its checkers."""
        prepare_linearisation(checker)

    def __call__(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles,
                 start: float | None = None, reference: Tensor | None = None) -> Adjustment:
        """Adjust ``plan`` ``[B, P, m]``; ``reference`` (the previous safe plan) is not used."""
        start = time.perf_counter() if start is None else start
        if checker.uses_lp(obstacles):  # the LP's values have no facets: gradients by autograd through it
            return self._autograd(checker, x0, plan, obstacles, start)
        if not self._analytic or plan.requires_grad:
            return self._autograd(checker, x0, plan, obstacles, start)
        affine = checker.affine_for(x0, plan)
        with torch.no_grad():
            if affine is not None:
                return self._analytic_steps(checker, affine, x0, plan, obstacles, start)
            if _feedback_linearisable(checker, x0, plan):
                return self._feedback_steps(checker, x0, plan, obstacles, start)
            if checker.plan_dependent and x0.ndim == 2 and plan.ndim == 3:
                return self._leaf_steps(checker, x0, plan, obstacles, start)
        return self._autograd(checker, x0, plan, obstacles, start)

    _analytic = True  # closed-form gradients (False: autograd through the rollout, for comparison)

    def _step(self, plan: Tensor, grad: Tensor, active: Tensor, low: Tensor, high: Tensor,
              scale: Tensor) -> Tensor:
        """One projected step along ``-grad`` for the ``active`` plans (max-norm in action-range units)."""
        grad = grad * scale
        norm = grad.flatten(1).abs().amax(-1).clamp_min(1e-12).view(-1, 1, 1)
        moved = torch.minimum(torch.maximum(plan - self.step_size * scale * grad / norm, low), high)
        return torch.where(active.view(-1, 1, 1), moved, plan)

    def _autograd(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles,
                  start: float) -> Adjustment:
        """Gradients by autograd through the rollout (any braking policy)."""
        low, high = checker.action_low, checker.action_high
        scale = (high - low).clamp_min(1e-12)
        iterations = torch.zeros(plan.shape[0], dtype=torch.long, device=plan.device)
        for iteration in range(self.max_iterations + 1):
            plan = plan.detach().requires_grad_(True)
            evaluation = checker.evaluate(x0, plan, obstacles)
            active = ~evaluation.safe
            out_of_time = self.time_budget is not None and time.perf_counter() - start > self.time_budget
            if iteration == self.max_iterations or out_of_time or not bool(active.any()):
                break
            finite = torch.nan_to_num(evaluation.values, posinf=1e6)
            shortfall = torch.relu(1 + self.target_margin - finite).sum((-1, -2))
            loss = (shortfall + torch.relu(evaluation.stop_excess)) * active
            (grad,) = torch.autograd.grad(loss.sum(), plan)
            with torch.no_grad():
                plan = self._step(plan, grad, active, low, high, scale)
                iterations += active.long()
        evaluation = PlanEvaluation(*(t.detach() for t in evaluation))
        return Adjustment(plan.detach(), evaluation, iterations)

    def _analytic_steps(self, checker: PlanChecker, affine: AffineRollout, x0: Tensor, plan: Tensor,
                        obstacles: Obstacles, start: float) -> Adjustment:
        """The same iteration with the gradient in closed form (:func:`_closed_form_gradient`; open-loop braking,
        the centres' Jacobian exact and constant). Every iterate is still checked exactly by
        :meth:`PlanChecker.evaluate`."""
        def linearise(plan: Tensor) -> tuple:
            evaluation, gauge = checker.evaluate_with_gauge(x0, plan, obstacles)
            return evaluation, gauge, lambda: (affine.position_jacobian, affine.stop_jacobian)

        return self._closed_form_steps(checker, linearise, plan, start)

    def _feedback_steps(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles,
                        start: float) -> Adjustment:
        """The iteration of :meth:`_analytic_steps` for a braking *policy* (global model).

        The plan part of every centre is still affine in the plan; the braking tail is
        linearised along the current nominal trajectory, ``J_{j+1} = (A + B Dπ(c_j)) J_j``
        (``Dπ`` by central differences, :func:`_brake_jacobian`, zero where the brake is clipped),
        the gradient of the tail as rolled out to about 1e-11. Every iterate is checked exactly.
        """
        def linearise(plan: Tensor) -> tuple:
            evaluation, gauge = checker.evaluate_with_gauge(x0, plan, obstacles)

            def jacobians() -> tuple[Tensor, Tensor]:
                jacobian = _feedback_jacobian(checker, evaluation.centers, plan.shape[1])  # [B, T, n, N]
                return jacobian[:, :, checker.position_dims], jacobian[:, -1, checker.stop_dims]
            return evaluation, gauge, jacobians

        return self._closed_form_steps(checker, linearise, plan, start)

    def _leaf_steps(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles,
                    start: float) -> Adjustment:
        """The iteration of :meth:`_analytic_steps` on a local model: the centres' Jacobian along the plan's own
        sets (:func:`_leaf_check`, the sets' generators held fixed), from the rollout that checks it."""
        def linearise(plan: Tensor) -> tuple:
            evaluation, gauge, jacobian = _leaf_check(checker, x0, plan, obstacles)  # [B, T, n, P, m]
            jacobian = jacobian.flatten(-2)
            return evaluation, gauge, lambda: (jacobian[:, :, checker.position_dims],
                                               jacobian[:, -1, checker.stop_dims])

        return self._closed_form_steps(checker, linearise, plan, start)

    def _closed_form_steps(self, checker: PlanChecker, linearise, plan: Tensor, start: float) -> Adjustment:
        """Projected steps with the gradient from ``linearise(plan)``: ``(evaluation, gauge, jacobians)``, where
        ``jacobians()`` gives the positions' ``[(B,) T, d, N]`` and the final stop dims' ``[(B,) s, N]``
        Jacobians in the plan (:func:`_closed_form_gradient`)."""
        low, high = checker.action_low, checker.action_high
        scale = (high - low).clamp_min(1e-12)
        iterations = torch.zeros(plan.shape[0], dtype=torch.long, device=plan.device)
        for iteration in range(self.max_iterations + 1):
            evaluation, gauge, jacobians = linearise(plan)
            active = ~evaluation.safe
            out_of_time = self.time_budget is not None and time.perf_counter() - start > self.time_budget
            if iteration == self.max_iterations or out_of_time or not bool(active.any()):
                break
            grad = _closed_form_gradient(checker, evaluation, gauge, *jacobians(), 1 + self.target_margin)
            plan = self._step(plan, grad.view_as(plan), active, low, high, scale)
            iterations += active.long()
        return Adjustment(plan, evaluation, iterations)


def _closed_form_gradient(checker: PlanChecker, evaluation: PlanEvaluation, gauge: Gauge, position_jacobian: Tensor,
                          stop_jacobian: Tensor, threshold: float) -> Tensor:
    """The gradient in the plan ``[B, N]`` of :class:`GradientAdjuster`'s loss (the colliding values' shortfall
    below ``threshold`` and the stop excess): a value ``v = |w_f* . (c_o - p)|`` (facet ``f*`` attaining the gauge)
    has gradient ``-sign(w_f* . (c_o - p)) w_f* J`` with ``J`` ``position_jacobian`` ``[(B,) T, d, N]`` of its
    set's centre; the stop excess through ``stop_jacobian`` ``[(B,) s, N]`` of the final centre's stop dims."""
    values = evaluation.values  # masked: inf; non-finite: 0 (no gradient, as with autograd)
    coef = torch.where((values < threshold) & (values > 0), gauge.picked.sign(), 0.0)  # [B, T, K]
    per_step = (coef.unsqueeze(-2) @ gauge.weights).squeeze(-2)  # [B, T, d]
    grad = (per_step.flatten(1).unsqueeze(1) @ position_jacobian.flatten(-3, -2)).squeeze(1)  # [B, N]
    if checker.stop_dims:
        final = _stop_centres(checker, evaluation.centers)  # [B, s]
        excess = evaluation.stop_excess.unsqueeze(-1)
        attains = (final.abs() - evaluation.stop_room) == excess  # amax: shared equally between ties
        share = attains * (final.sign() * (excess > 0)) / attains.sum(-1, keepdim=True).clamp_min(1)
        grad = grad + (share.unsqueeze(1) @ stop_jacobian).squeeze(1)
    return grad


class FacetQPAdjuster:
    """Facet-locked quadratic program: the fast adjuster.

    Under a reference plan that is already safe (the previous safe plan, shifted), every
    (step, obstacle) pair is separated by the facet attaining its collision value. Locking
    each pair to that facet and linearising the reachable-set centres in the plan (exact for
    the plan part, which is affine; first order for a feedback braking tail) turns safety into
    linear constraints, which the reference satisfies. The adjuster then projects the proposal
    onto them, ``min ||u - u_proposed||^2`` subject to the locked facets, the stop condition
    and the action box, by accelerated projected gradient on the dual (batched, fixed
    iteration count), or exactly where the plan has at most :data:`SMALL_PROGRAM` variables
    (:func:`_project_small`: one action of a 2-D command); on a compiled local model the program is
    set up and solved as one compiled graph (:func:`_locked_step`). The result is pulled back towards
    the reference until the exact check (:meth:`PlanChecker.evaluate`) accepts it; if even that
    fails the plan is reported unsafe and the layer keeps its safe plan. Obstacles checked by the
    LP (polytopes, spaces beyond 3-D) have no facets to lock: there it runs
    :class:`GradientAdjuster` instead.

    Args:
        iterations: dual gradient iterations (plans of more than :data:`SMALL_PROGRAM` variables).
        target_margin: the projection aims for ``v* >= 1 + target_margin`` on every locked pair
            (or the reference's own value if smaller).
        backtracking: halvings of the step from the reference towards the projection tried
            when the exact check rejects it.
        polish: projections of the dual's solution onto its most violated linearised constraint
            before the pull-back. A fixed number of dual iterations leaves small violations; where
            the reference already sits on a constraint (hovering at the target margin above a
            floor: no room, ``A z <= 0``), pulling back to remove them scaled the whole step to
            zero, motion along the floor included, and the robot stood still. The exact solution
            needs none.
    """

    def __init__(self, iterations: int = 20, target_margin: float = 0.05, backtracking: int = 4, polish: int = 8):
        if iterations < 1:
            raise ValueError(f"`iterations` must be positive, got {iterations}")
        if polish < 0:
            raise ValueError(f"`polish` must be non-negative, got {polish}")
        self.iterations = int(iterations)
        self.polish = int(polish)
        self.target_margin = float(target_margin)
        self.backtracking = int(backtracking)
        self._early = 1.0  # running share of adjustments whose full or half step was safe (:data:`EARLY_SHARE`)

    def prepare(self, checker: PlanChecker) -> None:
        """Compile what this adjuster runs on ``checker`` now, not at its first control step
        (:func:`prepare_linearisation`); :class:`~torchrl_brsl.safety.SafetyDecision` calls it for its checkers."""
        prepare_linearisation(checker)

    @quick_tracing
    def prepare_obstacles(self, checker: PlanChecker, obstacles: Obstacles) -> None:
        """Compile what depends on the obstacles' shapes ``[B, K, d, ...]`` (their values unused) now: on a compiled
        local model, the program (:meth:`_compiled_step`) of the plans a layer checks, of one action (an env's action
        without a plan) and of :attr:`~PlanChecker.plan_steps` actions, for one env and for several, and the paired
        check with the program's step and candidates (:meth:`_ahead`) of such plans for ``B`` envs (whose decisions
        pair every env); otherwise nothing.
        :class:`~torchrl_brsl.safety.BRSLSafetyLayer` calls it with its env's obstacle specs, beside
        :meth:`PlanChecker.prepare_checks`. A plan of another length compiles at its first adjustment; obstacles
        checked by the LP have no facets to lock, and nothing is compiled for them."""
        if not checker.plan_dependent or checker.reach.compile_options is None or checker.uses_lp(obstacles):
            return
        m, d = checker.action_low.shape[-1], len(checker.position_dims)
        like, s, k = checker.action_low, len(checker.stop_dims), obstacles.center.shape[-2]
        paired_envs = obstacles.center.shape[:-2].numel()
        for steps in sorted({1, max(checker.plan_steps, 1)}):
            box = (*self._box(checker, steps, like), checker.action_low, checker.action_high)
            for envs in (1, 2):
                zeros = [like.new_zeros(envs, *shape) for shape in (
                    (checker.horizon, k), (checker.horizon, k, d), (checker.horizon, d, steps * m))]
                locked = (*zeros, torch.ones(envs, k, dtype=torch.bool, device=like.device),
                          like.new_zeros(envs, s, steps * m), like.new_zeros(envs, s), like.new_zeros(envs, s),
                          like.new_zeros(envs, steps, m), like.new_zeros(envs, steps, m))
                self._compiled_step(checker, locked, box)
                if envs != min(paired_envs, 2):  # one env's paired check is a graph of its own
                    continue
                paired = Obstacles(like.new_zeros(2 * envs, *obstacles.center.shape[-2:]),
                                   like.new_zeros(2 * envs, *obstacles.generators.shape[-3:]),
                                   torch.ones(2 * envs, k, dtype=torch.bool, device=like.device))
                with torch.no_grad():
                    self._ahead(checker, like.new_zeros(2 * envs, checker.reach.state_dim),
                                checker.hold(like).expand(2 * envs, steps, m), paired)

    def __call__(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles,
                 start: float | None = None, reference: Tensor | None = None,
                 reference_rollout: tuple | None = None) -> Adjustment:
        """Adjust ``plan`` ``[B, P, m]`` from ``reference`` ``[B, >= P, m]``; ``reference_rollout``: the
        reference's Jacobian and check from :meth:`evaluate_paired`, where it made them."""
        if reference is None:
            raise ValueError("FacetQPAdjuster needs the `reference` plan (the previous safe plan)")
        if checker.uses_lp(obstacles):  # no facets to lock: projected gradient through the LP
            return GradientAdjuster(target_margin=self.target_margin)(checker, x0, plan, obstacles, start=start)
        with torch.no_grad():
            return self._adjust(checker, x0, plan.detach(), obstacles,
                                reference.detach(), reference_rollout)

    def evaluate_paired(self, checker: PlanChecker, x0: Tensor, plan: Tensor, reference: Tensor,
                        obstacles: Obstacles) -> tuple[PlanEvaluation, tuple | None]:
        """:meth:`PlanChecker.evaluate` of ``plan`` ``[B, P, m]``, and what this adjuster starts from on a local model,
        from the same batch, for ``reference_rollout``: the centres' Jacobian of ``reference[:, :P]`` along its sets
        (:func:`_leaf_check`), its evaluation, its :class:`Gauge`, and on a compiled model the program's step and its
        first candidates' evaluation (:meth:`_ahead`, else ``None``); ``None`` where it would not use them.

        :class:`~torchrl_brsl.safety.SafetyDecision` calls this where the last step adjusted every env. The compiled
        plan loop with tangents pads one plan to two, so the reference rides along, its tangents costing 0.3 ms on the
        Turtlebot's 16-step plans; a rollout of its own would cost 2.1 ms. Both are checked in one call as well, and on
        a compiled model the program and the check of its first candidates run in that call's graph too: an adjusting
        step of the Turtlebot's body-frame model (one action then braking) took 1.8-2.0 ms instead of 2.4-2.5
        (``benchmarks/bench_layer.py``'s wall scene, the decision alone), where the proposal is checked and
        adjusted in three calls.
        """
        if not checker.plan_dependent or checker.uses_lp(obstacles):
            return checker.evaluate(x0, plan, obstacles), None
        n_envs = x0.shape[0]
        reference = reference[:, :plan.shape[1]].to(plan)
        starts, plans, paired = torch.cat((x0, x0)), torch.cat((plan, reference)), obstacles.repeat(2)
        ahead = self._ahead(checker, starts, plans, paired)
        if ahead is None:
            (evaluation, gauge, jacobian), step, candidates = _leaf_check(checker, starts, plans, paired), None, None
        else:
            evaluation, gauge, jacobian, step, candidates = ahead
        proposal, reference_check = (PlanEvaluation(*(t[part] for t in evaluation))
                                     for part in (slice(n_envs), slice(n_envs, None)))
        return proposal, (jacobian[n_envs:], reference_check, Gauge(*(t[n_envs:] for t in gauge)), step, candidates)

    def _ahead(self, checker: PlanChecker, starts: Tensor, plans: Tensor, obstacles: Obstacles) -> tuple | None:
        """:func:`_leaf_check` of the proposals and references ``plans`` ``[2B, P, m]`` and, in the same compiled graph
        (:func:`_paired_ahead`), the program's step from each reference and the check of the first
        :data:`FIRST_HALVINGS` candidates: ``(evaluation, gauge, jacobian, step [B, N], candidates)``, the candidates'
        :class:`PlanEvaluation` env by env ``[B, A, ...]`` (``None``, with ``step``, where an env needs more rows than
        the compiled program holds or a candidate's pair is not certified full-dimensional). ``None`` where the
        model's plan loop is not compiled with its check (:meth:`PlanChecker._fuses_check`), or where a proposal's or
        reference's pair is not certified (their eager check decides)."""
        if not checker._fuses_check(starts, plans):
            return None
        n_envs, count, like = plans.shape[0] // 2, min(FIRST_HALVINGS, self.backtracking + 1), plans
        box = (*self._box(checker, plans.shape[1], like), checker.action_low, checker.action_high)
        program = (checker._position_index, checker._stop_index, self.target_margin, LOCKED_ROWS, self.iterations,
                   self.polish, *box)
        brake = (checker.hold(like), None) if checker.failsafe.policy is None else (None, checker._tail_brake(like))
        batched = (obstacles.center, obstacles.generators, obstacles.mask, starts, plans)
        finish = (_paired_ahead, batched, (checker.check_args, program, (count, *brake, checker.reach._local_step())))
        actions, *out = checker.rollout_sets(starts, plans, plan_axes(plans, checker.reach.state_dim), finish=finish)
        centers, generators, covered, stop_room, values, stop_excess, safe, picked, weights, full = out[:10]
        if not bool(full.all()):
            return None
        evaluation = checker._in_domain(starts, PlanEvaluation(actions, centers, values, stop_excess, safe, stop_room,
                                                               covered), generators)
        directions, step, too_many, tried, *checked = out[10:]
        jacobian = directions.reshape(*directions.shape[:3], *plans.shape[1:])
        if bool(too_many.any()) or not bool(checked[-1].all()):
            return evaluation, Gauge(picked, weights), jacobian, None, None
        centers, generators, covered, stop_room, values, stop_excess, safe = checked[:7]
        candidates = checker._in_domain(starts[:n_envs].repeat(count, 1), PlanEvaluation(
            tried, centers, values, stop_excess, safe, stop_room, covered), generators)
        by_env = PlanEvaluation(*(t.unflatten(0, (count, n_envs)).transpose(0, 1) for t in candidates))
        return evaluation, Gauge(picked, weights), jacobian, step, by_env

    def _adjust(self, checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles,
                reference: Tensor, reference_rollout: tuple | None) -> Adjustment:
        n_envs, horizon = plan.shape[:2]
        reference = reference[:, :horizon]
        if reference.dtype != plan.dtype or reference.device != plan.device:
            reference = reference.to(plan)
        step = checked = None
        if reference_rollout is not None:  # from :meth:`evaluate_paired`: the reference's Jacobian and check
            jacobian, ref_eval, gauge, step, checked = reference_rollout
        else:
            if checker.plan_dependent:  # a local model: one rollout checks the reference and gives its Jacobian
                ref_eval, gauge, jacobian = _leaf_check(checker, x0, reference, obstacles)
            else:
                (ref_eval, gauge), jacobian = checker.evaluate_with_gauge(x0, reference, obstacles), None
        if step is None:
            step = self._program_step(checker, x0, plan, reference, obstacles, ref_eval, gauge, jacobian)
        step = step.view_as(reference)
        if checker.plan_dependent:  # a check costs a rollout of sets: the halvings in one or two batches
            first = FIRST_HALVINGS if self._early >= EARLY_SHARE else self.backtracking + 1
            adjustment = _first_safe(checker, x0, reference, step, obstacles, ref_eval, self.backtracking,
                                     first_batch=first, checked=checked)
            early = float((adjustment.iterations <= FIRST_HALVINGS).double().mean())
            self._early = 0.8 * self._early + 0.2 * early
            return adjustment
        best_plan, best_eval = reference, ref_eval
        accepted = torch.zeros(n_envs, dtype=torch.bool, device=plan.device)
        tries = torch.zeros(n_envs, dtype=torch.long, device=plan.device)
        for attempt in range(self.backtracking + 1):
            candidate = reference + step / (2 ** attempt) if attempt else reference + step
            evaluation = checker.evaluate(x0, candidate, obstacles)
            if attempt == 0 and bool(evaluation.safe.all()):  # the usual case: no merging needed
                return Adjustment(candidate, evaluation, torch.ones_like(tries))
            take = evaluation.safe & ~accepted
            tries += (~accepted).long()
            best_plan = torch.where(take.view(-1, 1, 1), candidate, best_plan)
            best_eval = PlanEvaluation(*(torch.where(take.view(-1, *[1] * (new.ndim - 1)), new, old)
                                         for new, old in zip(evaluation, best_eval)))
            accepted |= take
            if bool(accepted.all()):
                break
        return Adjustment(best_plan, best_eval, tries)

    def _program_step(self, checker: PlanChecker, x0: Tensor, plan: Tensor, reference: Tensor, obstacles: Obstacles,
                      ref_eval: PlanEvaluation, gauge: Gauge, jacobian: Tensor | None) -> Tensor:
        """The program's step ``[B, N]`` from ``reference`` towards ``plan`` ``[B, P, m]``: the pairs locked by the
        reference's ``gauge``, its centres linearised in the plan (``jacobian`` ``[B, T, n, P, m]`` along a local
        model's sets, where at hand)."""
        n_envs, horizon = plan.shape[:2]
        affine = checker.affine_for(x0, reference)  # None for a local model
        if affine is None and _feedback_linearisable(checker, x0, reference):  # braking policy: linearised tail
            jacobian = _feedback_jacobian(checker, ref_eval.centers, horizon)  # [B, T, n, N]
            pos_jac = jacobian[:, :, checker.position_dims]  # [B, T, d, N]
            stop_jac = jacobian[:, -1, checker.stop_dims]  # [B, s, N]
        elif affine is None:  # local model, or feedback braking: linearise along the reference's sets
            jacobian = _centre_jacobian(checker, x0, reference) if jacobian is None else jacobian  # [B, T, n, P, m]
            pos_jac = jacobian[:, :, checker.position_dims].flatten(-2)  # [B, T, d, N]
            stop_jac = jacobian[:, -1, checker.stop_dims].flatten(-2)  # [B, s, N]
        else:  # exact and shared by all envs
            pos_jac, stop_jac = affine.position_jacobian, affine.stop_jacobian  # [T, d, N], [s, N]
        if checker.stop_dims:
            stop_ref = _stop_centres(checker, ref_eval.centers)
            room = ref_eval.stop_room * (1 - 1e-9)  # not exactly on the boundary, where rounding decides
            stop_jac = stop_jac.expand(n_envs, *stop_jac.shape[-2:])
        else:
            stop_ref = room = plan.new_zeros(n_envs, 0)
            stop_jac = plan.new_zeros(n_envs, 0, horizon * plan.shape[-1])
        locked = (gauge.picked, gauge.weights, pos_jac, obstacles.mask, stop_jac, stop_ref, room, reference, plan)
        box = (*self._box(checker, horizon, plan), checker.action_low, checker.action_high)
        step = self._compiled_step(checker, locked, box)
        if step is None:
            step = _locked_step(*locked, *box, self.target_margin, None, self.iterations, self.polish)[0]
        return step

    def _compiled_step(self, checker: PlanChecker, locked: tuple[Tensor, ...], box: tuple[Tensor, ...]
                       ) -> Tensor | None:
        """:func:`_locked_step` on a compiled local model as one compiled graph (one per plan length) with
        :data:`LOCKED_ROWS` rows an env; ``None`` where it does not apply, where an env needs more rows, or where
        compiling failed (the caller solves it eagerly)."""
        if not checker.plan_dependent or checker.reach.compile_options is None or locked[-2].requires_grad:
            return None
        result = checker._compiled(_locked_step, locked, *box, self.target_margin, LOCKED_ROWS, self.iterations,
                                   self.polish, cpp_wrapper=True, single=True)
        return None if result is None or bool(result[1].any()) else result[0]

    @staticmethod
    def _box(checker: PlanChecker, horizon: int, like: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per plan length: the action range per variable ``[N]``, the box rows ``[2N, N]`` and the
        upper and lower bounds ``[N]`` (cached on the checker, whose bounds are fixed)."""
        def build():
            low, high = checker.action_low.to(like), checker.action_high.to(like)
            eye = torch.eye(horizon * low.shape[0], dtype=like.dtype, device=like.device)
            return (high - low).repeat(horizon), torch.cat((eye, -eye)), high.repeat(horizon), low.repeat(horizon)

        return checker.memo(("box", horizon, like.dtype, like.device), build)


FIRST_HALVINGS = 2
"""Candidates of :func:`_first_safe` checked in its first batch when most adjustments take one of them, and in the
paired check's graph (:meth:`FacetQPAdjuster._ahead`) always."""

EARLY_SHARE = 0.6
"""The facet QP checks its full and half step first, and the other halvings only for the envs where both fail,
while a running share (weight 0.2 per call) of at least this many adjustments took one of those two; else all in
one batch. At one env the full and the half step are one batch of two plans (1.8 ms on the Turtlebot's 16-step
plans, against 2.7 for all five and 2.2 for the last three, measured when one plan was padded to two): the first
batch alone pays off from a share of about 0.6. On ``bench_layer.py``'s wall scene 71 of 85 adjustments took
one of the two (11.0-11.4 -> 8.8-9.7 ms a step, with :meth:`FacetQPAdjuster.evaluate_paired`); on
``bench_layer_batch.py``'s walls fewer do, and two batches took 6.7-6.9 against 6.2-7.2 ms at one env and
17.5-18.1 against 14.6-15.9 at four (three runs each, alternated in one process)."""


def _first_safe(checker: PlanChecker, x0: Tensor, reference: Tensor, step: Tensor, obstacles: Obstacles,
                ref_eval: PlanEvaluation, backtracking: int, first_batch: int | None = None,
                checked: PlanEvaluation | None = None) -> Adjustment:
    """The first safe of ``reference + step / 2^a``, ``a = 0 .. backtracking``, per env: the first ``first_batch``
    (``None``: all) in one batch, the others in a second batch for the envs that found none. ``checked``: the first
    batch's evaluation, env by env ``[B, A, ...]``, made ahead (:meth:`FacetQPAdjuster._ahead`; its candidates are
    its actions, as checked), which sets the first batch's size.

    The same choice as checking them in turn (the reference's evaluation where none is safe);
    ``iterations`` counts the candidates up to the one taken.
    """
    n_envs, attempts, horizon = reference.shape[0], backtracking + 1, reference.shape[1]
    taken_at = torch.full((n_envs,), attempts, dtype=torch.long, device=step.device)  # attempts: none safe
    plan, chosen = reference, ref_eval
    todo = torch.arange(n_envs, device=step.device)
    split = checked.safe.shape[1] if checked is not None else attempts if first_batch is None else first_batch
    split = min(split, attempts)
    for tried in (range(split), range(split, attempts)):
        if not len(tried) or not len(todo):
            continue
        count, size = len(tried), len(todo)
        if checked is not None and tried.start == 0:  # every env, halving by halving
            evaluation = PlanEvaluation(*(t[:, :count].transpose(0, 1).flatten(0, 1) for t in checked))
            candidates = evaluation.actions[:, :horizon]
        else:
            halving = 2.0 ** -torch.arange(tried.start, tried.stop, dtype=step.dtype, device=step.device)
            starts, refs, steps, batch = ((x0, reference, step, obstacles) if size == n_envs  # every env: no copies
                                          else (x0[todo], reference[todo], step[todo], obstacles[todo]))
            candidates = (refs + halving.view(-1, 1, 1, 1) * steps).flatten(0, 1)  # [A b, P, m]
            evaluation = checker.evaluate(torch.cat((starts,) * count), candidates, batch.repeat(count))
        safe = evaluation.safe.view(count, size)
        found, taken = safe.any(0), safe.to(torch.uint8).argmax(0)  # [b]: the first safe candidate's row
        envs, pick = todo[found], (taken * size + torch.arange(size, device=step.device))[found]
        taken_at[envs] = tried.start + taken[found]
        plan = plan.index_copy(0, envs, candidates[pick])
        chosen = PlanEvaluation(*(old.index_copy(0, envs, new[pick]) for new, old in zip(evaluation, chosen)))
        todo = todo[~found]
    return Adjustment(plan, chosen, (taken_at + 1).clamp_max(attempts))


def _paired_ahead(centers: Tensor, generators: Tensor, covered: Tensor, obstacle_centers: Tensor,
                  obstacle_generators: Tensor, mask: Tensor, starts: Tensor, plans: Tensor, check: tuple,
                  program: tuple, tail: tuple, directions: Tensor) -> tuple[Tensor, ...]:
    """The ``finish`` of the paired plans' loop (:meth:`FacetQPAdjuster._ahead`): the check of the proposals and
    references ``plans`` ``[2B, P, m]`` from ``starts`` ``[2B, n]`` (their sets ``[2B, T, ...]``, the obstacles ``[2B,
    K, ...]`` twice), then the facet QP's step from each reference (:func:`_locked_step`, on the reference's gauge and
    centres' ``directions`` ``[2B, T, n, P m]``) and the check of its first ``A`` halvings ``reference + step / 2^a``
    in a second loop of the model's sets: ``(*checked, directions, step [B, N], too_many [B], actions [A B, T, m],
    *candidates_checked)`` (:func:`~torchrl_brsl.safety.plan_check._checked_sets`, the candidates halving by halving).

    ``check``: the checker's :attr:`~PlanChecker.check_args`; ``program``: ``(position_dims, stop_dims, margin,
    rows_kept, iterations, polish, *box)``; ``tail``: ``(A, hold, policy, local_step)``, the braking tail's open-loop
    action ``[m]`` or its traceable policy, and the model's :class:`~torchrl_brsl.reach.local_step.LocalStep`.
    """
    checked = _checked_sets(centers, generators, covered, obstacle_centers, obstacle_generators, mask, *check)
    _, _, _, stop_room, _, _, _, picked, weights, _ = checked
    position_dims, stop_dims, margin, rows_kept, iterations, polish, *box = program
    count, hold, policy, local = tail
    n_envs, (plan_steps, m) = plans.shape[0] // 2, plans.shape[1:]
    reference, moved = plans[n_envs:], directions[n_envs:]  # the references' half
    room = stop_room[n_envs:] * (1 - 1e-9)  # not exactly on the boundary, where rounding decides
    step, too_many = _locked_step(picked[n_envs:], weights[n_envs:], moved[:, :, position_dims], mask[:n_envs],
                                  moved[:, -1, stop_dims], centers[n_envs:, -1, stop_dims], room, reference,
                                  plans[:n_envs], *box, margin, rows_kept, iterations, polish)
    halving = 2.0 ** -torch.arange(count, dtype=step.dtype, device=step.device)
    tried = (reference + halving.view(-1, 1, 1, 1) * step.view_as(reference)).flatten(0, 1)  # [A B, P, m]
    tail_steps = centers.shape[1] - plan_steps
    rows = tried.shape[0]
    actions = torch.cat((tried, tried.new_zeros(rows, tail_steps, m) if hold is None else
                         hold.expand(rows, tail_steps, m)), 1)
    start = starts[:n_envs].repeat(count, 1)
    again = local._loop(start, start.new_zeros(*start.shape, local.max_generators),
                        actions.transpose(0, 1).contiguous(), None, policy,
                        torch.tensor(plan_steps, device=start.device) if policy is not None else None,
                        finish=_checked_sets, finish_inputs=(obstacle_centers[:n_envs].repeat(count, 1, 1),
                                                             obstacle_generators[:n_envs].repeat(count, 1, 1, 1),
                                                             mask[:n_envs].repeat(count, 1), *check))
    if policy is not None:
        actions, again = again[-1].transpose(0, 1), again[:-1]
    return (*checked, directions, step, too_many, actions, *again)


def _feedback_linearisable(checker: PlanChecker, x0: Tensor, plan: Tensor) -> bool:
    """A braking policy on a global model, batched ``x0`` ``[B, n]`` and ``plan`` ``[B, P, m]`` in
    the model's dtype: the tail can be linearised along the nominal rollout."""
    return (checker.failsafe.policy is not None and not checker.plan_dependent and x0.ndim == 2 and plan.ndim == 3
            and plan.dtype == checker.reach.state_matrix.dtype)


def _feedback_jacobian(checker: PlanChecker, centers: Tensor, plan_steps: int) -> Tensor:
    """``d centres / d plan`` ``[B, T, n, P m]`` of a plan with a braking-policy tail (global model).

    The first ``P`` centres are affine in the plan (the model's block-Toeplitz input map); each
    tail step ``c_{j+1} = A c_j + B clip(π(c_j)) + k`` multiplies the Jacobian by
    ``A + B Dπ(c_j)``, with ``Dπ`` evaluated at the nominal ``centers`` ``[B, T, n]`` (:func:`_brake_jacobian`)
    and zero where the braking action is clipped. Where
    ``Dπ`` vanishes along the whole tail (a saturated brake, a policy constant there) this is
    the open-loop map's Jacobian, cached, and no product is formed.
    """
    reach = checker.reach
    n_envs, horizon, n = centers.shape
    open_loop = checker.memo(("open-loop jacobian", plan_steps, horizon, centers.dtype, centers.device), lambda: (
        reach._transfer(horizon)[1].view(horizon, n, horizon, reach.action_dim)[:, :, :plan_steps]
        .reshape(horizon, n, -1).to(centers).contiguous()))  # [T, n, P m]
    n_tail = horizon - plan_steps
    derivative = _brake_jacobian(checker, centers[:, plan_steps - 1:horizon - 1]) if n_tail else None
    if derivative is None or not bool(derivative.any()):
        return open_loop.expand(n_envs, *open_loop.shape)
    closed_loop = reach.state_matrix.to(centers) + reach.input_matrix.to(centers) @ derivative  # [B, n_tail, n, n]
    (tail,) = checker.run_fused(_chain, closed_loop, open_loop[plan_steps - 1], length=n_tail)
    return torch.cat((open_loop[:plan_steps].expand(n_envs, -1, -1, -1), tail), dim=1)


def _chain(factors: Tensor, start: Tensor, fused: bool = False) -> tuple[Tensor]:
    """The running products ``F_k ... F_1 S`` of ``factors`` ``[B, K, n, n]`` and ``start`` ``[n, N]``:
    ``([B, K, n, N],)``. ``fused``: as sums of broadcast products, which a compiler fuses across steps."""
    current, out = start.expand(factors.shape[0], *start.shape), []
    for factor in factors.unbind(1):
        current = (factor.unsqueeze(-1) * current.unsqueeze(-3)).sum(-2) if fused else factor @ current
        out.append(current)
    return (torch.stack(out, dim=1),)


def _brake_jacobian(checker: PlanChecker, states: Tensor) -> Tensor:
    """``d brake / d state`` ``[..., m, n]`` of the braking policy at ``states`` ``[..., n]``, zero where the braking
    action is clipped to the action bounds. A policy whose output does not depend on the state
    (:meth:`PlanChecker.policy_reads_state`: a constant) gets zeros at once; any other
    :meth:`PlanChecker.brake_tangent` along every state axis (central differences, the local model's way: one
    policy call on the state and ``2 n`` points around it, faster than a backward pass per action dim, equal to it
    to about 1e-11 on a float64 policy)."""
    if not checker.policy_reads_state(states):
        return states.new_zeros(*states.shape[:-1], checker.action_low.shape[-1], states.shape[-1])
    return checker.brake_tangent(states)


@quick_tracing
def prepare_linearisation(checker: PlanChecker) -> None:
    """Compile the linearisation the adjusters run on ``checker``, so that no control step stalls on it: with a
    compiled global model and a braking policy, the Jacobian chain along a tail of
    :data:`~torchrl_brsl.safety.plan_check.FUSE_FROM_STEPS` or more steps (a plan of
    :attr:`~torchrl_brsl.safety.PlanChecker.plan_steps` steps, linearised at rest: where the policy's derivative
    vanishes there, the chain compiles at the first step that needs it). A local model linearises in its plan's loop
    with the check (:func:`_leaf_check`), which needs the obstacles' shapes:
    :meth:`~torchrl_brsl.safety.PlanChecker.prepare_checks` compiles it. Otherwise nothing."""
    if checker.failsafe.policy is None or checker.reach.compile_options is None or checker.plan_dependent:
        return
    steps = checker.plan_steps
    if steps >= 1 and checker.failsafe.n_brk >= FUSE_FROM_STEPS:
        rest = checker.action_low.new_zeros(1, checker.reach.state_dim)
        plan = checker.hold(rest).expand(1, steps, -1).to(checker.reach.state_matrix.dtype)
        with torch.no_grad():
            _feedback_jacobian(checker, checker.rollout(rest.to(plan), plan)[1], steps)


def _leaf_check(checker: PlanChecker, x0: Tensor, plan: Tensor, obstacles: Obstacles
                ) -> tuple[PlanEvaluation, Gauge | None, Tensor]:
    """:meth:`PlanChecker.evaluate_with_gauge` of a local model's ``plan`` ``[B, P, m]`` and, from the same rollout,
    ``d centres / d plan`` ``[B, T, n, P, m]`` along the plan's own sets.

    Each step maps the centres' directions with the leaf models and relaxations it chose (held fixed;
    :meth:`DataDrivenReach.reach_covered` ``tangents``, in the plan's compiled loop with the check when compiled),
    and a braking policy's tail with the policy's derivative at the centres (:meth:`PlanChecker.brake_tangent`):
    one rollout, where finite differences of the whole plan need ``P m + 1``.
    Exact at a point set between kinks; a linearisation elsewhere (every iterate is still checked).
    """
    evaluation, gauge, moved = checker.evaluate_with_gauge(x0, plan, obstacles,
                                                           tangents=plan_axes(plan, checker.reach.state_dim))
    return evaluation, gauge, moved.reshape(*moved.shape[:3], *plan.shape[1:])


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


LOCKED_ROWS = 16
"""Constraint rows of the facet QP (facets and stop rows that a step inside the action box can make active) that its
compiled program (:meth:`FacetQPAdjuster._compiled_step`) holds per env, padded with zero rows: a fixed shape, where
the eager program keeps as many as the batch's largest count. An env with more is solved eagerly. On
``bench_layer.py``'s wall scene no adjustment needed more, with one action or ten."""


def _locked_step(picked: Tensor, weights: Tensor, pos_jac: Tensor, mask: Tensor, stop_jac: Tensor, stop_ref: Tensor,
                 room: Tensor, reference: Tensor, plan: Tensor, span: Tensor, box_rows: Tensor, upper: Tensor,
                 lower: Tensor, low: Tensor, high: Tensor, margin: float, rows_kept: int | None, iterations: int,
                 polish: int) -> tuple[Tensor, Tensor]:
    """The facet QP's step from ``reference`` ``[B, P, m]`` towards ``plan``: ``([B, N], too_many [B])``, ``N = P m``.

    The program of :func:`_locked_program` (its arguments), projected onto exactly up to :data:`SMALL_PROGRAM`
    variables (:func:`_project_small`), else by ``iterations`` dual steps and ``polish`` sweeps, and the result scaled
    back towards the reference until it keeps the linearised constraints (beyond rounding: on a row with no room, ``b
    = 0``, a product 1e-18 off would otherwise scale the step to nothing; the exact check decides).
    """
    A, b, target, too_many = _locked_program(picked, weights, pos_jac, mask, stop_jac, stop_ref, room, reference, plan,
                                             span, box_rows, upper, lower, low, high, margin, rows_kept)
    if A.shape[-1] <= SMALL_PROGRAM:  # one action of a 2-D command (the recipes' plans): solved exactly
        step = _project_small(A, b, target)
    else:
        step = _polish(A, b, _project_polytope(A, b, target, iterations), polish)
    excess = small_matmul(A, step.unsqueeze(-1)).squeeze(-1)
    rounding = 1e-9 * small_matmul(A.abs(), step.abs().unsqueeze(-1)).squeeze(-1)
    scale = torch.where(excess > b + rounding, b / excess.clamp_min(1e-12), 1.0).amin(-1).clamp(0, 1)
    return step * scale.unsqueeze(-1), too_many


def _locked_program(picked: Tensor, weights: Tensor, pos_jac: Tensor, mask: Tensor, stop_jac: Tensor,
                    stop_ref: Tensor, room: Tensor, reference: Tensor, plan: Tensor, span: Tensor, box_rows: Tensor,
                    upper: Tensor, lower: Tensor, low: Tensor, high: Tensor, margin: float, rows_kept: int | None
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The facet QP's program ``min ||z - target||`` s.t. ``A z <= b`` for the step ``z`` ``[B, N]`` from
    ``reference``: ``(A [B, C, N], b [B, C], target [B, N], too_many [B])``.

    Each (step, obstacle) pair is locked to the facet attaining its value under the reference (``picked`` ``[B, T,
    K]``, signed, and the facets' ``weights`` ``[B, T, K, d]``), the centres linearised in the plan (``pos_jac`` ``[B,
    T, d, N]`` or shared ``[T, d, N]``): ``s w . (c_o - p_ref - J dz) >= level <=> (s w J) dz <= s w . Δ_ref -
    level``; masked pairs (``mask`` ``[B, K]``) are never constraints. The final centre's stop dims stay within their
    ``room`` ``[B, s]`` of zero (``stop_jac`` ``[B, s, N]``, ``stop_ref`` ``[B, s]``), and the plan within the action
    box (``span`` ``[N]``, ``box_rows`` ``[2N, N]``, ``upper``, ``lower`` ``[N]``); ``target`` is ``plan`` clamped to
    ``low``, ``high`` ``[m]``, less the reference. Rows that no step inside the box can make active are dropped: each
    env's own rows first, padded with zero rows (never active) to ``rows_kept`` (``too_many`` where an env has more)
    or, with ``None``, to the most any env keeps, so that an env's result does not depend on the batch.
    """
    rows = small_matmul(weights * picked.sign().unsqueeze(-1), pos_jac).flatten(1, 2)  # [B, T K, N]
    bounds = torch.where(mask.unsqueeze(-2), (picked.abs() - (1 + margin)).clamp_min(0), float("inf")).flatten(1)
    rows = torch.cat((rows, stop_jac, -stop_jac), dim=1)
    bounds = torch.cat((bounds, room - stop_ref, room + stop_ref), dim=1).clamp_min(0)
    needed = small_matmul(rows.abs(), span.unsqueeze(-1)).squeeze(-1) > bounds
    count = needed.sum(-1)
    size = int(count.max()) if rows_kept is None else min(rows_kept, rows.shape[1])
    order = torch.argsort((~needed).to(torch.uint8), dim=-1, stable=True)[:, :size]
    keep = needed.gather(1, order)
    rows = rows.gather(1, order.unsqueeze(-1).expand(-1, -1, rows.shape[-1])) * keep.unsqueeze(-1)
    bounds = torch.where(keep, bounds.gather(1, order), 0.0)
    ref_flat = reference.flatten(1)
    A = torch.cat((rows, box_rows.expand(rows.shape[0], -1, -1)), dim=1)
    b = torch.cat((bounds, (upper - ref_flat).clamp_min(0), (ref_flat - lower).clamp_min(0)), dim=1)
    return A, b, (torch.clamp(plan, low, high) - reference).flatten(1), count > size


def _project_polytope(A: Tensor, b: Tensor, target: Tensor, iterations: int) -> Tensor:
    """Approximately solve ``min ||z - target||^2 s.t. A z <= b`` (batched).

    Accelerated projected gradient on the dual ``min_{l >= 0} 1/2 l^T A A^T l - l^T (A t - b)``,
    ``z = t - A^T l``, with step ``1 / ||A||_2^2`` (the exact Lipschitz constant, from the
    ``N x N`` matrix ``A^T A``). ``A`` ``[B, C, N]``, ``b`` ``[B, C]``, ``target`` ``[B, N]``.
    """
    At = A.transpose(-1, -2)
    gram = A @ At
    largest = torch.linalg.eigvalsh(At @ A)[..., -1] if A.shape[-2] else gram.new_zeros(A.shape[0])
    lipschitz = (largest * (1 + 1e-9)).clamp_min(1e-12).view(-1, 1, 1)
    step_matrix = torch.eye(gram.shape[-1], dtype=A.dtype, device=A.device) - gram / lipschitz
    offset = ((A @ target.unsqueeze(-1)) - b.unsqueeze(-1)) / lipschitz  # [B, C, 1]
    lam = torch.zeros_like(offset)
    momentum, t = lam, 1.0
    for _ in range(iterations):
        new = torch.baddbmm(offset, step_matrix, momentum).clamp_min_(0)
        t_next = (1 + (1 + 4 * t * t) ** 0.5) / 2
        momentum = torch.lerp(new, lam, (1 - t) / t_next)  # new + (t - 1) / t_next (new - lam)
        lam, t = new, t_next
    return target - (At @ lam).squeeze(-1)


SMALL_PROGRAM = 2
"""Plan variables (``P m``) up to which the facet QP's projection is solved exactly (:func:`_project_small`) instead
of by dual iterations: one action of a 2-D command, the recipes' plans. Timed alone (one env, 16 rows, one thread), 20
dual iterations took 0.12 ms and the 8 polishing sweeps 0.16 ms, the exact solution 0.13 ms."""


def _project_small(A: Tensor, b: Tensor, target: Tensor) -> Tensor:
    """Exactly ``argmin ||z - target||`` subject to ``A z <= b`` in at most two variables (batched), where ``b >= 0``
    (``z = 0``, the reference, is feasible): ``A`` ``[B, C, N]``, ``b`` ``[B, C]``, ``target`` ``[B, N]``.

    The optimum lies inside, on an edge or at a vertex of the polygon (an interval for ``N = 1``), so it is the
    feasible point closest to ``target`` among the target itself, its projections onto each row's boundary and (``N =
    2``) the boundaries' pairwise intersections; feasible to rounding (``1e-9`` of the row's magnitudes). Zero rows
    (padding) are never active.
    """
    n_rows, n_vars = A.shape[-2:]
    norms = A.square().sum(-1)  # [B, C]
    excess = (A @ target.unsqueeze(-1)).squeeze(-1) - b
    candidates = [target.unsqueeze(1), target.unsqueeze(1) - (excess / norms.clamp_min(1e-300)).unsqueeze(-1) * A]
    usable = [norms.new_ones(norms.shape[0], 1, dtype=torch.bool), norms > 0]
    if n_vars == 2 and n_rows > 1:
        i, j = torch.triu_indices(n_rows, n_rows, 1, device=A.device)
        (a1, a2), (c1, c2), (b1, b2) = A[:, i].unbind(-1), A[:, j].unbind(-1), (b[:, i], b[:, j])
        det = a1 * c2 - a2 * c1  # the rows' determinant: parallel boundaries never meet
        solved = det.abs() > 1e-12 * (norms[:, i] * norms[:, j]).sqrt()
        det = torch.where(solved, det, 1.0)
        candidates.append(torch.stack(((b1 * c2 - b2 * a2) / det, (a1 * b2 - c1 * b1) / det), -1))
        usable.append(solved)
    points = torch.cat(candidates, 1)  # [B, K, N]
    slack = (points @ A.transpose(-1, -2)) - b.unsqueeze(1)  # [B, K, C]
    rounding = 1e-9 * (points.abs() @ A.abs().transpose(-1, -2) + b.abs().unsqueeze(1))
    feasible = torch.cat(usable, 1) & (slack <= rounding).all(-1)
    distance = (points - target.unsqueeze(1)).square().sum(-1).masked_fill(~feasible, float("inf"))
    best = distance.argmin(-1)
    closest = points.gather(1, best.view(-1, 1, 1).expand(-1, 1, n_vars)).squeeze(1)
    return torch.where(feasible.any(-1, keepdim=True), closest, torch.zeros_like(closest))


def _polish(A: Tensor, b: Tensor, z: Tensor, sweeps: int) -> Tensor:
    """``sweeps`` projections of each ``z`` ``[B, N]`` onto its most violated halfspace of ``A z <= b``.

    Each moves ``z`` the least distance that satisfies that row (Kaczmarz's method restricted to the
    violated rows), so a solution nearly feasible keeps its direction along the satisfied ones.
    """
    norms = A.square().sum(-1).clamp_min(1e-30)  # [B, C]
    lengths = norms.sqrt()
    for _ in range(sweeps):
        excess = (A @ z.unsqueeze(-1)).squeeze(-1) - b  # [B, C]
        worst = (excess / lengths).argmax(-1, keepdim=True)  # the row farthest outside, per env
        over = excess.gather(-1, worst).clamp_min(0) / norms.gather(-1, worst)  # [B, 1]
        z = z - over * A.gather(1, worst.unsqueeze(-1).expand(-1, 1, A.shape[-1])).squeeze(1)
    return z


def _stop_centres(checker: PlanChecker, centers: Tensor) -> Tensor:
    """The stop dims of the final centres: ``[B, s]``."""
    return centers[:, -1, checker.stop_dims]
