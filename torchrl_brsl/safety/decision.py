"""The safety decision of one control step on plain tensors: check, adjust, local model, failsafe, hold.

:class:`SafetyDecision` is what :class:`~torchrl_brsl.safety.BRSLSafetyLayer` runs at every
step, without TensorDicts, keys or specs, so it can be called (and tested) on its own:

1. **Check** the proposal (clamped into the action bounds) with its braking tail.
2. **Adjust** the proposals that fail (:class:`~torchrl_brsl.safety.GradientAdjuster`,
   :class:`~torchrl_brsl.safety.FacetQPAdjuster`), from the previous safe plan.
3. **Local model**: a proposal still unverified is tried under the restricted-domain
   checker, its actions clipped into that domain (and adjusted there).
4. **Failsafe**: braking from the measured state, verified by the main checker, then the local
   one; else the previous safe plan continues, shifted by one step.
5. **Hold**: once the previous safe plan has no verified action left, the braking policy acts
   on the measured state (paper Assumption 1).

Inputs whose values are unusable (NaN, inf, beyond :data:`INPUT_LIMIT`) never reach a check: the
env keeps its previous safe plan and is flagged ``invalid_input``.
"""
from __future__ import annotations

import warnings
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from torchrl_brsl.safety.failsafe import Failsafe
from torchrl_brsl.safety.plan_check import PlanChecker, PlanEvaluation
from torchrl_brsl.sets import Obstacles
from torchrl_brsl.sets._checks import skip_value_checks

INPUT_LIMIT = 1e100
"""Magnitude from which an entry of the state, proposal or a real obstacle counts as invalid (like NaN/inf)."""


class StepDecision(NamedTuple):
    """What one control step decided for ``B`` envs.

    Attributes:
        executed: ``[B, m]`` the action sent to the robot.
        safe_plan: ``[B, T, m]`` the next fallback plan (the chosen one, shifted by one step).
        safe_steps: ``[B]`` how many of its leading actions are verified.
        diagnostics: ``{name: [B]}``, the layer's ``DIAGNOSTICS`` but ``compute_time``.
    """

    executed: Tensor
    safe_plan: Tensor
    safe_steps: Tensor
    diagnostics: dict[str, Tensor]


class _Plans(NamedTuple):
    """The plan each env holds so far in a decision: ``accepted [B]``, ``actions [B, T, m]``, ``values [B, T, K]``."""

    accepted: Tensor
    actions: Tensor
    values: Tensor


class SafetyDecision:
    """One batched safety decision (module docstring), in the checker's dtype.

    Args:
        checker: verifies plans with the main model.
        failsafe: the braking manoeuvre.
        adjuster: called as ``adjuster(checker, x0, plan, obstacles, start=, reference=)`` on the
            envs whose proposal fails (see :mod:`~torchrl_brsl.safety.adjust`); ``None``: never adjust.
            It returns an :class:`~torchrl_brsl.safety.adjust.Adjustment` whose ``evaluation`` is the checker's
            verdict on its plans (``checker.evaluate``, which raises on a NaN plan: an adjuster checks only finite
            ones); a claim on actions beyond the robot's bounds (the main checker's) or not finite is withdrawn (the
            failsafe acts) with a warning. Its ``prepare(checker)``, if it has one, is called here for each checker
            (e.g. to compile). Its ``evaluate_paired(checker, x0, plan, reference, obstacles)``, if it has one, checks
            the proposals where the last step adjusted every env, and what it returns beside the evaluation reaches
            the adjuster as ``reference_rollout`` (:meth:`~torchrl_brsl.safety.FacetQPAdjuster.evaluate_paired`).
        local_checker: verifies plans with a restricted-domain model (its action bounds the
            local domain's), or ``None``.

    Examples:
        >>> decide = SafetyDecision(checker, Failsafe(torch.zeros(2), n_brk=6), FacetQPAdjuster())
        >>> step = decide(x0, proposal, safe_plan, safe_steps, obstacles)
        >>> step.executed.shape, step.diagnostics["failsafe"].shape
        (torch.Size([B, 2]), torch.Size([B]))
    """

    def __init__(self, checker: PlanChecker, failsafe: Failsafe, adjuster: Callable | None = None,
                 local_checker: PlanChecker | None = None):
        self.checker, self.failsafe, self.adjuster, self.local_checker = checker, failsafe, adjuster, local_checker
        if hasattr(adjuster, "prepare"):  # e.g. compile the adjuster's graphs now, not at a control step
            for each in filter(None, (checker, local_checker)):
                adjuster.prepare(each)
        self.horizon = checker.horizon
        self._pair = False  # evaluate the proposals and the adjuster's references in one batch (:meth:`_adjust`)
        # how far an action may lie beyond the bounds and count as inside them (rounding: the bounds may be float32)
        self.bound_tolerance = 1e-6 * (checker.action_high - checker.action_low).clamp_min(1.0)  # [m]

    def __call__(self, x0: Tensor, proposal: Tensor, safe_plan: Tensor, safe_steps: Tensor, obstacles: Obstacles,
                 start: float | None = None) -> StepDecision:
        """Decide for ``B`` envs.

        Args:
            x0: ``[B, n]`` measured states.
            proposal: ``[B, P, m]`` proposed plans (``P <= n_plan``), in the dtype actions reach
                the robot in (they are verified as the robot will receive them).
            safe_plan: ``[B, T, m]`` the previous fallback plans; safe_steps: ``[B]`` their
                verified leading actions.
            obstacles: batch ``[B]``.
            start: ``time.perf_counter()`` at the start of the step (the adjusters' time budget).

        The inputs are sanitised first (:func:`_sanitize`); inside, the checks skip their NaN scans
        (:func:`~torchrl_brsl.sets._checks.skip_value_checks`): a plan an adjuster reached with NaN entries is
        checked, never verified, and the env brakes instead of the control loop stopping on an error.
        """
        with skip_value_checks():
            return self._decide(x0, proposal, safe_plan, safe_steps, obstacles, start)

    def _decide(self, x0: Tensor, proposal: Tensor, safe_plan: Tensor, safe_steps: Tensor, obstacles: Obstacles,
                start: float | None) -> StepDecision:
        dtype = self.checker.reach.state_matrix.dtype
        x0, plan, safe_plan = x0.to(dtype), proposal.to(dtype), safe_plan.to(dtype)
        x0, plan, obstacles, safe_plan, safe_steps, valid, corrupt = _sanitize(
            x0, plan, obstacles.to_dtype(dtype), safe_plan, safe_steps, self._hold(safe_plan))
        low, high = self.checker.action_low, self.checker.action_high
        outside = ((plan < low - self.bound_tolerance) | (plan > high + self.bound_tolerance)).flatten(1).any(-1)
        plan = torch.clamp(plan, low, high)
        with torch.no_grad():
            if self._pair and hasattr(self.adjuster, "evaluate_paired"):
                evaluation, reference_rollout = self.adjuster.evaluate_paired(self.checker, x0, plan, safe_plan,
                                                                              obstacles)
            else:
                evaluation, reference_rollout = self.checker.evaluate(x0, plan, obstacles), None
        proposal_safe = _and_valid(evaluation.safe, valid)
        plans = _Plans(proposal_safe, evaluation.actions, evaluation.values)
        plans, iterations = self._adjust(plans, x0, plan, safe_plan, obstacles, valid, start, reference_rollout)
        plans, local = self._retry_locally(plans, x0, plan, safe_plan, obstacles, valid, start)
        usable, actions, local = self._brake(plans, x0, obstacles, valid, local)
        executed, next_plan, next_steps, exhausted = self._execute(usable, actions, x0, safe_plan, safe_steps, valid)
        values = plans.values
        invalid = outside if valid is None else outside | ~valid
        diagnostics = {
            "intervened": ~proposal_safe,
            "failsafe": ~plans.accepted,
            "local": local,
            "unverified_hold": exhausted,
            "invalid_input": invalid if corrupt is None else invalid | corrupt,
            "out_of_data": _and_valid(~evaluation.covered, valid),
            "min_collision_value": (values.flatten(1).amin(-1) if values.shape[-1] and values.shape[-2]
                                    else values.new_full(values.shape[:1], float("inf"))),
            "adjust_iterations": iterations,
        }
        return StepDecision(executed, next_plan, next_steps, diagnostics)

    def _adjust(self, plans: _Plans, x0: Tensor, plan: Tensor, safe_plan: Tensor, obstacles: Obstacles,
                valid: Tensor | None, start: float | None, reference_rollout: tuple | None) -> tuple[_Plans, Tensor]:
        """The adjuster on the envs whose proposal failed: their plans and iteration counts."""
        iterations = torch.zeros(x0.shape[0], dtype=torch.long, device=x0.device)
        todo = _and_valid(~plans.accepted, valid)
        self._pair = bool(todo.all())  # adjustments come in runs: the next step likely adjusts too
        if self.adjuster is None or not bool(todo.any()):
            return plans, iterations
        idx, sub = _for_envs(self.checker, todo, obstacles)
        paired = {} if reference_rollout is None else {"reference_rollout": [_take(t, idx) for t in reference_rollout]}
        adjusted = self.adjuster(sub, _take(x0, idx), _take(plan, idx), _take(obstacles, idx), start=start,
                                 reference=_take(safe_plan, idx), **paired)
        found = _vetted(adjusted, self.checker, self.bound_tolerance, x0.shape[0] if idx is None else idx.shape[0])
        plans = _Plans(*(_put(old, idx, new) for old, new in zip(plans, (found.safe, found.actions, found.values))))
        return plans, _put(iterations, idx, adjusted.iterations)

    def _retry_locally(self, plans: _Plans, x0: Tensor, plan: Tensor, safe_plan: Tensor, obstacles: Obstacles,
                       valid: Tensor | None, start: float | None) -> tuple[_Plans, Tensor]:
        """Proposals still unverified, clipped into the local domain and checked (and adjusted) there."""
        local = torch.zeros_like(plans.accepted)
        retry = _and_valid(~plans.accepted, valid)
        if self.local_checker is None or not bool(retry.any()):
            return plans, local
        idx, sub = _for_envs(self.local_checker, retry, obstacles)
        x0_i, obstacles_i = _take(x0, idx), _take(obstacles, idx)
        candidate = _take(plan, idx).clamp(sub.action_low, sub.action_high)
        with torch.no_grad():
            evaluation = sub.evaluate(x0_i, candidate, obstacles_i)
        if self.adjuster is not None and not bool(evaluation.safe.all()):
            evaluation = _vetted(self.adjuster(sub, x0_i, candidate, obstacles_i, start=start,
                                               reference=_take(safe_plan, idx)), self.checker, self.bound_tolerance,
                                 x0_i.shape[0])
        return _merge_safe(plans, idx, evaluation), _put(local, idx, evaluation.safe)

    def _brake(self, plans: _Plans, x0: Tensor, obstacles: Obstacles, valid: Tensor | None,
               local: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Braking from the measured state where no plan was accepted, verified by each checker in turn.

        Re-verifying the braking manoeuvre every step is a closed-loop hold: where a stopped
        robot does not stay stopped by itself (noise on a double integrator), holding open loop
        would drift past the verified horizon. Returns ``(usable [B], actions [B, T, m], local [B])``.
        """
        usable, actions = plans.accepted, plans.actions
        for checker in (self.checker, self.local_checker):
            braking = _and_valid(~usable, valid)
            if checker is None or not bool(braking.any()):
                continue
            idx, sub = _for_envs(checker, braking, obstacles)
            x0_i = _take(x0, idx)
            with torch.no_grad():
                braked = sub.evaluate(x0_i, sub.brake(x0_i).unsqueeze(1), _take(obstacles, idx))
            merged = _merge_safe(_Plans(usable, actions, plans.values), idx, braked)
            usable, actions = merged.accepted, merged.actions
            if checker is self.local_checker:
                local = _put(local, idx, braked.safe)
        return usable, actions, local

    def _execute(self, usable: Tensor, actions: Tensor, x0: Tensor, safe_plan: Tensor, safe_steps: Tensor,
                 valid: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The executed action, the next safe plan and its verified steps, and where the hold acts.

        Beyond the verified part of the safe plan only the failsafe remains: the braking policy
        acts on the measured state (a closed-loop hold, paper Assumption 1) rather than an
        open-loop action, unless the state itself is unusable.
        """
        checker, n_envs = self.checker, x0.shape[0]
        chosen = torch.where(usable.view(-1, 1, 1), actions, safe_plan)
        executed = chosen[:, 0]
        exhausted = ~usable & (safe_steps <= 0)
        if bool(exhausted.any()):
            feedback = checker.brake(x0)
            if valid is not None:
                feedback = torch.where(valid.unsqueeze(-1), feedback, checker.hold(x0))
            executed = torch.where(exhausted.unsqueeze(-1), feedback, executed)
        next_plan = torch.cat((chosen[:, 1:], self._hold(chosen).expand(n_envs, 1, -1)), dim=1)
        next_steps = torch.where(usable, torch.full_like(safe_steps, self.horizon - 1), (safe_steps - 1).clamp_min(0))
        return executed, next_plan, next_steps, exhausted

    def _hold(self, like: Tensor) -> Tensor:
        """The failsafe's hold action in ``like``'s dtype and device: ``[m]``."""
        return self.failsafe.hold_action.to(like)


def _sanitize(x0: Tensor, plan: Tensor, obstacles: Obstacles, safe_plan: Tensor, safe_steps: Tensor, hold: Tensor):
    """The inputs with unusable values neutralised, and which envs are ``valid`` (``None``: all of them).

    One cheap test covers the usual case: a sum of squares below ``INPUT_LIMIT²`` means every
    magnitude is below :data:`INPUT_LIMIT` (NaN and inf fail it). Otherwise, per env: a stored
    safe plan with such values (not written by the layer) is dropped for the hold (``corrupt``);
    an env with such a state, proposal or real obstacle is invalid, its inputs zeroed; an
    obstacle slot counts only when its mask is set, and unusable slots become empty ones.

    Returns:
        ``(x0, plan, obstacles, safe_plan, safe_steps, valid, corrupt)``.
    """
    parts = [obstacles.center, obstacles.generators]  # [B, K, ...] each
    if obstacles.constraint_matrix is not None:
        parts += [obstacles.constraint_matrix, obstacles.constraint_offset]
    flat = torch.cat([t.reshape(-1) for t in (x0, plan, *parts, safe_plan)])
    if float(torch.dot(flat, flat)) < INPUT_LIMIT ** 2:
        return x0, plan, obstacles, safe_plan, safe_steps, None, None
    corrupt = ~(safe_plan.abs() < INPUT_LIMIT).flatten(1).all(-1)
    safe_plan = torch.where(corrupt.view(-1, 1, 1), hold.expand_as(safe_plan), safe_plan)
    safe_steps = torch.where(corrupt, torch.zeros_like(safe_steps), safe_steps)
    slot_ok = torch.stack([(part.abs() < INPUT_LIMIT).flatten(2).all(-1) for part in parts]).all(0)  # [B, K]
    valid = ((x0.abs() < INPUT_LIMIT).all(-1) & (plan.abs() < INPUT_LIMIT).flatten(1).all(-1)
             & (slot_ok | ~obstacles.mask).all(-1))
    x0 = torch.where(valid.unsqueeze(-1), x0, torch.zeros_like(x0))
    plan = torch.where(valid.view(-1, 1, 1), plan, torch.zeros_like(plan))
    # so that the batched check stays finite; invalid envs' verdicts are never used
    keep = slot_ok & valid.unsqueeze(-1)
    cleaned = [torch.where(keep.view(*keep.shape, *[1] * (part.ndim - 2)), part, 0.0) for part in parts]
    obstacles = Obstacles(cleaned[0], cleaned[1], obstacles.mask & keep, *cleaned[2:])
    return x0, plan, obstacles, safe_plan, safe_steps, valid, corrupt


def _vetted(adjusted, checker: PlanChecker, tolerance: Tensor, n_envs: int) -> PlanEvaluation:
    """An adjuster's verdict on ``n_envs`` plans, its claims withdrawn on plans the robot would not receive as
    checked (an action beyond the robot's action bounds, those of the main ``checker`` give or take ``tolerance``
    ``[m]``, where it clips, or not finite) or with NaN collision values: those envs fall back to the failsafe, with
    a warning. A result of the wrong kind or shape is an error naming what came back. (A local domain's narrower
    bounds are its own checker's business: its model's coverage decides there.)"""
    found = getattr(adjusted, "evaluation", None)
    if not isinstance(found, PlanEvaluation):
        raise TypeError("an adjuster must return an `Adjustment` whose `evaluation` is a `PlanEvaluation` "
                        f"(`PlanChecker.evaluate`'s result), got {type(adjusted).__name__}")
    low, high = checker.action_low, checker.action_high
    if tuple(found.safe.shape) != (n_envs,) or tuple(found.actions.shape) != (n_envs, checker.horizon, low.shape[-1]):
        raise ValueError(f"the adjuster's evaluation has `safe` of shape {tuple(found.safe.shape)} and `actions` of "
                         f"shape {tuple(found.actions.shape)}; expected [B={n_envs}] and "
                         f"[B={n_envs}, T={checker.horizon}, m={low.shape[-1]}]")
    inside = ((found.actions >= low - tolerance) & (found.actions <= high + tolerance)).flatten(1).all(-1)  # not NaN
    withdrawn = found.safe & ~(inside & ~torch.isnan(found.values).flatten(1).any(-1))
    if bool(withdrawn.any()):
        warnings.warn(f"the adjuster claimed {int(withdrawn.sum())} plan(s) safe with actions beyond the action bounds "
                      "or not finite, or NaN collision values; they fall back to the failsafe", RuntimeWarning)
        found = found._replace(safe=found.safe & ~withdrawn)
    return found


def _for_envs(checker: PlanChecker, selected: Tensor, obstacles: Obstacles) -> tuple[Tensor | None, PlanChecker]:
    """The envs ``selected`` ``[B]`` as an index (``None``: all of them) and the checker restricted to them.

    A global model's facet table is built for the whole obstacle batch first (once per batch)
    and shared by the subsets.
    """
    if bool(selected.all()):
        return None, checker
    if not checker.plan_dependent:
        checker.checker(obstacles.generators)
    idx = selected.nonzero().squeeze(-1)
    return idx, checker.subset(idx)


def _take(value, idx: Tensor | None):
    """``value[idx]`` (a tensor, :class:`Obstacles`, :class:`Zonotope` or a named tuple of per-env tensors), or ``value``
    itself for every env (and ``None``)."""
    if idx is None or value is None:
        return value
    return type(value)(*(field[idx] for field in value)) if isinstance(value, tuple) else value[idx]


def _put(target: Tensor, idx: Tensor | None, value: Tensor) -> Tensor:
    """``target`` with its envs ``idx`` replaced by ``value`` (out of place); ``value`` for every env."""
    return value if idx is None else target.index_copy(0, idx, value)


def _merge_safe(plans: _Plans, idx: Tensor | None, evaluation: PlanEvaluation) -> _Plans:
    """``plans`` with the envs ``idx`` taking ``evaluation``'s verdict, and its plan where it is safe."""
    safe = evaluation.safe.view(-1, 1, 1)
    actions = torch.where(safe, evaluation.actions, _take(plans.actions, idx))
    values = torch.where(safe, evaluation.values, _take(plans.values, idx))
    return _Plans(_put(plans.accepted, idx, evaluation.safe), _put(plans.actions, idx, actions),
                  _put(plans.values, idx, values))


def _and_valid(mask: Tensor, valid: Tensor | None) -> Tensor:
    """``mask`` restricted to the envs with valid inputs (``valid`` None: all are valid)."""
    return mask if valid is None else valid & mask
