"""Reachable sets of a plan plus its failsafe tail, and their safety verdict."""
from __future__ import annotations

import copy
import itertools
import warnings
from typing import Any, Callable, NamedTuple, Sequence

import torch
from torch import Tensor

from torchrl_brsl._compiling import inductor_kwargs, own_code, plain_layout, quick_tracing, warn_fallback
from torchrl_brsl.collision import (PairFacets, ZonotopeCollisionChecker, collision_value, pair_facets, pair_gauge,
                                    split_pair_facets)
from torchrl_brsl.collision.closed_form import CLOSED_FORM_DIMS, rows_at
from torchrl_brsl.reach import DataDrivenReach
from torchrl_brsl.safety.failsafe import Failsafe
from torchrl_brsl.sets import Obstacles, Zonotope, reduce_girard
from torchrl_brsl.sets._checks import check_tensor, skip_value_checks, value_checks_enabled
from torchrl_brsl.sets.reduction import girard_columns


COLLISION_CHECKS = ("auto", "exact", "lp")
"""How sets are checked against obstacles: ``"exact"`` the closed form (zonotope obstacles in 1-3 D),
``"lp"`` the differentiable LP (any dimension, polytope obstacles), ``"auto"`` the closed form where
it is exact, else the LP."""

DEFAULT_STOP_SLACK = 0.15
"""``stop_slack`` when neither it nor ``stop_tolerance`` is given (units of the stop dims, e.g. m/s)."""

FUSE_FROM_STEPS = 16
"""With compiled steps, a braking tail's Jacobian chain of at least this many steps runs as one graph
(:meth:`PlanChecker.run_fused`): on one CPU thread a compiled chain of 6 steps costs what the eager loop does, one of
47 steps a quarter to a half."""

TAIL_FUSE_FROM_STEPS = 2
"""With compiled steps, a braking policy's rollout of at least this many steps runs as one graph: each eager step
calls the policy and rounds, clips and maps its action (a few operations each), so even a tail of 6 steps (the
Turtlebot's) ran 1.6x faster compiled on one CPU thread (``benchmarks/bench_failsafe.py --models "" --parts
--compile``)."""

MIN_SET_RADIUS = 1e-6
"""Half-width (state units) of the box added to every plan-dependent set's obstacle-space projection."""


class PlanEvaluation(NamedTuple):
    """What :meth:`PlanChecker.evaluate` returns for a batch of ``B`` plans.

    Attributes:
        actions: ``[B, T, m]`` the full sequence: the plan then the braking tail.
        centers: ``[B, T, n]`` centres of ``R_1 .. R_T``.
        values: ``[B, T, K]`` collision values v* (``inf`` for masked obstacles).
        stop_excess: ``[B]`` how far the final set is from "stopped" (<= 0 means stopped).
        safe: ``[B]`` every set collision-free (``v* > 1 + margin``), the final set stopped and
            every step inside the model's data (its domain, or its cells for a local model).
        stop_room: ``[B, s]`` the final centre is "stopped" when ``|centre| <= stop_room`` on
            the stop dims (the tolerance minus the final set's radius there).
        covered: ``[B]`` every step lies where the model's data make a claim (``False`` is
            flagged ``out_of_data`` by the layer).
    """

    actions: Tensor
    centers: Tensor
    values: Tensor
    stop_excess: Tensor
    safe: Tensor
    stop_room: Tensor
    covered: Tensor


class PlanChecker:
    """Verifies plans: reachable sets of plan + braking tail against obstacles, and a final stop.

    For a global model (``DataDrivenReach.fit(method="global")``) the generators of every
    reachable set from a measured state do not depend on the plan, so their projections onto
    the obstacle space are reduced once here, and the facet table of each (set, obstacle)
    pair is rebuilt only when the obstacles change; with open-loop braking (no braking
    policy) the centres of all ``T`` sets are one affine map of the measured state and the
    plan, precomputed per plan length, so a check costs one product for the centres and one
    for the collision values. For a local model (the default) the sets depend on the plan:
    they are computed step by step and each check builds their facet data against the obstacles,
    kept per owner and never as a table per pair (:func:`~torchrl_brsl.collision.pair_facets`).

    Args:
        reach: the fitted reachability model.
        failsafe: the braking manoeuvre appended to plans.
        horizon: ``T``, the number of reachable sets checked (plan length + braking steps).
        position_dims: state dims of the obstacle space (default: the model's
            translation-invariant dims).
        stop_dims: state dims that must be ~0 when stopped (velocities).
        stop_tolerance: the final set's interval on ``stop_dims`` must lie in
            ``[-stop_tolerance, stop_tolerance]`` (a float, or one value per stop dim). For a
            global model it must exceed the final set's own radius on those dims, which the
            error message reports.
        stop_slack: instead of ``stop_tolerance``: the final set's interval must lie within
            ``stop_slack`` of its own radius around rest, i.e. ``|final centre| <= stop_slack``
            on the stop dims (the tolerance is the set's radius plus the slack, per plan).
            Without either, ``stop_slack`` = :data:`DEFAULT_STOP_SLACK`. For a model of a
            restricted domain (``reach.bounded_domain``, e.g. a low-speed model) the slack is at
            most half the largest ``|value|`` its data reach on each stop dim: a slack chosen for
            the robot's full speed (0.15 m/s) would call every state of data below 0.1 m/s
            stopped. A stop check that no
            state of the offline data could fail (tolerance at or beyond the largest
            ``|value|`` the data reach on a stop dim) tests nothing and raises a
            ``UserWarning`` saying so: see :meth:`vacuous_stop_dims`.
        set_generators: width of the projected sets after Girard reduction
            (default ``4 d``).
        margin: a set counts as colliding when ``v* <= 1 + margin``.
        action_low, action_high: ``[m]`` bounds; braking actions are clipped to them.
        action_dtype: the dtype actions reach the robot in; braking actions are rounded to it
            so that the verified sequence is exactly the executed one.
    """

    def __init__(self, reach: DataDrivenReach, failsafe: Failsafe, horizon: int, *, stop_dims: Sequence[int],
                 action_low: Tensor, action_high: Tensor, stop_tolerance: float | Sequence[float] | Tensor | None = None,
                 stop_slack: float | Sequence[float] | Tensor | None = None,
                 position_dims: Sequence[int] | None = None, set_generators: int | None = None,
                 margin: float = 1e-6, action_dtype: torch.dtype = torch.float64, collision: str = "auto"):
        if collision not in COLLISION_CHECKS:
            raise ValueError(f"`collision` must be one of {COLLISION_CHECKS}, got {collision!r}")
        self.collision = collision
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
        if collision == "exact" and d not in CLOSED_FORM_DIMS:
            raise ValueError(f"`collision='exact'` (the closed form) needs an obstacle space of {CLOSED_FORM_DIMS} "
                             f"dims, `position_dims` has {d}: use 'lp' or 'auto'")
        self.set_width = set_generators or 4 * d
        self.set_generators = reduce_girard(errors[:, self.position_dims], self.set_width)  # [T, d, ps]
        self.plan_dependent = reach.plan_dependent
        self.stop_radius = errors[-1, self.stop_dims].abs().sum(-1)  # [len(stop_dims)], global model
        if stop_tolerance is not None and stop_slack is not None:
            raise ValueError("give at most one of `stop_tolerance` and `stop_slack`")
        if stop_tolerance is None and stop_slack is None:
            stop_slack = DEFAULT_STOP_SLACK
        self.stop_slack = None if stop_slack is None else torch.as_tensor(stop_slack, dtype=dtype).expand(
            len(self.stop_dims))
        top = self._top_speed() if reach.bounded_domain and self.stop_slack is not None else None
        if top is not None:
            self.stop_slack = torch.minimum(self.stop_slack, top.to(dtype) / 2)
        if stop_tolerance is None:
            stop_tolerance = self.stop_radius + self.stop_slack
        self.stop_tolerance = torch.as_tensor(stop_tolerance, dtype=dtype).expand(len(self.stop_dims))
        if not self.plan_dependent and self.stop_dims and bool((self.stop_radius >= self.stop_tolerance).any()):
            raise ValueError(
                f"`stop_tolerance`={self.stop_tolerance.tolist()} is not above the final reachable set's radius "
                f"{self.stop_radius.tolist()} on the stop dims: no plan could ever be accepted. Raise the "
                "tolerance, shorten the horizon or use tighter offline data.")
        self._obstacle_generators: Tensor | None = None
        self._checker: ZonotopeCollisionChecker | None = None
        self._columns: tuple[Tensor, ...] = ()
        self._facets: PairFacets | None = None  # a plan-dependent model's, per check
        self._memo: dict = {}
        self._position_index = _index(self.position_dims)
        self._stop_index = _index(self.stop_dims)
        self._threshold = 1 + self.margin
        self._stop_room = self.stop_tolerance - self.stop_radius  # stopped: |final centre| <= room
        # a model of a restricted domain: the boxes of R_0 (a point) .. R_{T-1} must stay in it
        self._domain_radius = (torch.cat((errors.new_zeros(1, errors.shape[1]), errors[:-1].abs().sum(-1)))
                               if reach.bounded_domain and not self.plan_dependent else None)
        if reach.compile_options is not None and failsafe.policy is not None and (
                self.plan_dependent or self.horizon - 1 >= TAIL_FUSE_FROM_STEPS):
            self._warm_up_tails()
        vacuous = self.vacuous_stop_dims()
        if vacuous:
            top, tolerance = self._top_speed(), self._stop_tolerance_at_rest()
            details = ", ".join(f"dim {d}: tolerance {float(tolerance[i]):.3g} >= {float(top[i]):.3g}"
                                for i, d in enumerate(self.stop_dims) if d in vacuous)
            warnings.warn(
                f"the stop check certifies nothing on stop dims {vacuous} ({details}, the largest |value| in the "
                "offline data): a final reachable set within the tolerance may still hold every speed the robot "
                "reaches, so 'accepted plans end stopped' (paper Theorem 1) is not shown; the centre is still "
                "checked. Tighten the final set (more or local data, a shorter horizon, a braking policy that "
                "stops in fewer steps) or lower `stop_slack` / `stop_tolerance`.",
                UserWarning, stacklevel=3)

    def vacuous_stop_dims(self) -> list[int]:
        """Stop dims whose tolerance (the final set's radius plus the slack, from rest under the
        braking manoeuvre for a plan-dependent model) reaches the largest ``|value|`` of that dim
        in the model's offline data: there "stopped" holds for every state the robot reaches.
        Empty when the model carries no data."""
        top = self._top_speed()
        if top is None or not self.stop_dims:
            return []
        tolerance = self._stop_tolerance_at_rest()
        return [d for d, t, v in zip(self.stop_dims, tolerance.tolist(), top.tolist()) if t >= v]

    def _top_speed(self) -> Tensor | None:
        """Largest ``|value|`` on each stop dim over the offline data (``None`` without data)."""
        x_minus, x_plus = getattr(self.reach, "x_minus", None), getattr(self.reach, "x_plus", None)
        if x_minus is None or x_plus is None or not x_minus.numel():
            return None
        return torch.cat((x_minus, x_plus))[:, self.stop_dims].abs().amax(0)

    def _stop_tolerance_at_rest(self) -> Tensor:
        """The stop tolerance on the stop dims; for a plan-dependent model with ``stop_slack``,
        the final set's radius of braking from rest plus the slack."""
        if not self.plan_dependent or self.stop_slack is None:
            return self.stop_tolerance
        rest = torch.zeros(1, self.reach.state_dim, dtype=self.action_low.dtype, device=self.action_low.device)
        with torch.no_grad():
            _, sets, _ = self.rollout_sets(rest, self.hold(rest).view(1, 1, -1))
        return sets.generators[0, -1, self.stop_dims].abs().sum(-1) + self.stop_slack

    def checker(self, obstacle_generators: Tensor) -> ZonotopeCollisionChecker:
        """The facet table for ``obstacle_generators`` ``[B, K, d, p]`` (rebuilt on change)."""
        cached = self._obstacle_generators
        if cached is None or cached.shape != obstacle_generators.shape or not torch.equal(cached, obstacle_generators):
            self._checker = ZonotopeCollisionChecker(self.set_generators.unsqueeze(-3).unsqueeze(0),
                                                     obstacle_generators.unsqueeze(-4), widen=True)
            self._columns = tuple(w.contiguous() for w in self._checker.table.weights.unbind(-1))
            self._obstacle_generators = obstacle_generators.clone()
        return self._checker

    def subset(self, index: Tensor) -> PlanChecker:
        """A checker for the envs ``index`` of the cached obstacle batch, sharing every other cache.

        Avoids rebuilding the facet table when only some envs of a batch are checked again.
        """
        sub = copy.copy(self)
        if self._checker is not None and not self.plan_dependent:  # plan-dependent tables are rebuilt per check
            table = type(self._checker.table)(*(t[index] for t in self._checker.table))
            checker = copy.copy(self._checker)
            checker.table = table
            checker.batch_shape = table.supports.shape[:-1]
            sub._checker = checker
            sub._columns = tuple(c[index] for c in self._columns)
            sub._obstacle_generators = self._obstacle_generators[index]
        return sub

    def affine(self, plan_steps: int, dtype: torch.dtype | None = None,
               device: torch.device | None = None) -> AffineRollout | None:
        """The centres of plan + braking tail as an affine map of (state, plan), or ``None``.

        Exists when the braking is open-loop (no braking policy): then the whole action
        sequence, and hence every centre, is affine in the plan. Cached per plan length.
        """
        if self.failsafe.policy is not None or self.plan_dependent:
            return None
        return self._memo_affine(int(plan_steps), self.horizon, dtype, device)

    def _memo_affine(self, plan_steps: int, horizon: int, dtype: torch.dtype | None,
                     device: torch.device | None) -> AffineRollout:
        A = self.reach.state_matrix
        dtype = A.dtype if dtype is None else dtype
        device = A.device if device is None else device
        return self.memo(("affine", plan_steps, horizon, dtype, device),
                         lambda: self._build_affine(plan_steps, horizon).to(dtype, device))

    def memo(self, key: tuple, build: Callable[[], Any]) -> Any:
        """``build()``, computed once per ``key`` and kept: tables that depend only on the checker's
        fixed model, failsafe and bounds (its affine rollouts; the adjusters' box rows and Jacobian
        blocks)."""
        if key not in self._memo:
            self._memo[key] = build()
        return self._memo[key]

    def _build_affine(self, plan_steps: int, horizon: int) -> AffineRollout:
        n, m = self.reach.state_dim, self.reach.action_dim
        n_tail = horizon - plan_steps
        if n_tail < 0:
            raise ValueError(f"the plan has {plan_steps} steps, more than the horizon T={horizon}")
        powers, transfer, drift = self.reach._transfer(horizon)
        tail = self.hold(powers).expand(n_tail, m).contiguous()
        n_vars = plan_steps * m
        constant = transfer[:, n_vars:] @ tail.flatten() + drift.flatten()
        plan_map = transfer[:, :n_vars].T.contiguous()  # [P m, T n]
        by_step = plan_map.view(n_vars, horizon, n)
        return AffineRollout(
            state_map=powers.reshape(horizon * n, n).T.contiguous(),
            plan_map=plan_map,
            constant=constant,
            tail=tail,
            position_jacobian=by_step[:, :, self.position_dims].permute(1, 2, 0).contiguous(),
            stop_jacobian=by_step[:, -1, self.stop_dims].T.contiguous(),
        )

    def affine_for(self, x0: Tensor, plan: Tensor) -> AffineRollout | None:
        """:meth:`affine` when it applies to this batch: open-loop braking, ``x0`` ``[B, n]`` and
        ``plan`` ``[B, P, m]`` in the model's dtype."""
        if self.failsafe.policy is not None or not self._affine_batch(x0, plan):
            return None
        return self.affine(plan.shape[1], plan.dtype, plan.device)

    def _affine_batch(self, x0: Tensor, plan: Tensor) -> bool:
        """A global model, ``x0`` ``[B, n]`` and ``plan`` ``[B, P, m]`` in its dtype: the plan's centres
        are one cached affine map."""
        return (not self.plan_dependent and x0.ndim == 2 and plan.ndim == 3
                and plan.dtype == self.reach.state_matrix.dtype)

    def rollout(self, x0: Tensor, plan: Tensor) -> tuple[Tensor, Tensor]:
        """Nominal centres of ``plan`` followed by braking up to the horizon.

        Args:
            x0: ``[B, n]`` measured states.
            plan: ``[B, P, m]`` with ``P <= T``.

        Returns:
            ``(actions [B, T, m], centers [B, T, n])``; differentiable w.r.t. ``plan``.
        """
        if self.plan_dependent:
            actions, sets, _ = self.rollout_sets(x0, plan)
            return actions, sets.center
        n_tail = self.horizon - plan.shape[-2]
        if self.failsafe.policy is None:  # open-loop braking: the whole sequence is affine in the plan
            affine = self.affine_for(x0, plan)
            if affine is not None:
                return _apply_affine(affine, x0, plan)
            actions = torch.cat((plan, self.hold(plan).expand(plan.shape[0], n_tail, -1)), dim=1)
            return actions, self.reach.reach_centers(x0, actions)
        if self._affine_batch(x0, plan):  # the plan's part is affine: the same cached map, without a tail
            _, centers = _apply_affine(self._memo_affine(plan.shape[1], plan.shape[1], plan.dtype, plan.device),
                                       x0, plan)
        else:
            centers = self.reach.reach_centers(x0, plan)
        if not n_tail:
            return plan, centers
        tail_actions, tail_centers = self._braking_tail(centers[:, -1], n_tail)
        return torch.cat((plan, tail_actions), dim=1), torch.cat((centers, tail_centers), dim=1)

    def _braking_tail(self, center: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        """The braking policy rolled out on the nominal model from ``center`` ``[B, n]`` (a global model):
        ``(actions [B, steps, m], centers [B, steps, n])`` (:func:`_policy_tail`, through :meth:`run_fused`)."""
        A_T, B_T, k = self.memo(("tail map", center.dtype, center.device), lambda: tuple(
            t.to(center) for t in (self.reach.state_matrix.T, self.reach.input_matrix.T, self.reach.offset)))
        low, high = self._action_bounds(center.device)
        return self.run_fused(_policy_tail, center, self.failsafe.policy, A_T, B_T, k, low, high, self.action_dtype,
                              steps, length=steps, fuse_from=TAIL_FUSE_FROM_STEPS)

    def _action_bounds(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """The action bounds in the action dtype on ``device``: ``[m]`` twice (what :func:`_brake_action` clips to)."""
        return self.memo(("action bounds", device), lambda: tuple(
            bound.to(device=device, dtype=self.action_dtype) for bound in (self.action_low, self.action_high)))

    @quick_tracing
    def _warm_up_tails(self) -> None:
        """Compile the braking policy's tail now, not at a control step: the local model's in the plan's loop (one
        plan and several are graphs of their own), the global model's for the tails the layer checks (braking from
        the state, a plan of :attr:`plan_steps` steps; each length is a graph of its own)."""
        rest = self.action_low.new_zeros(1, self.reach.state_dim)
        lengths = [1] if self.plan_dependent else sorted(n for n in {1, self.plan_steps} if 1 <= n < self.horizon)
        rollout = self.rollout_sets if self.plan_dependent else self.rollout
        with torch.no_grad():
            for length, plans in itertools.product(lengths, (1, 2) if self.plan_dependent else (1,)):
                rollout(rest.expand(plans, -1), self.hold(rest).expand(plans, length, -1))

    @quick_tracing
    def prepare_checks(self, obstacles: Obstacles) -> None:
        """Compile the closed-form check of a compiled local model's sets (:meth:`evaluate_with_gauge`) for obstacles of
        the shapes of ``obstacles`` ``[B, K, d, ...]`` (their values unused) now, not at the first control step: each
        count of obstacles and of their generators is a graph of its own (one plan, and several), 10-15 s to compile
        on a 2-core CPU with an empty cache; so is the check in the plan's loop (:meth:`_fuses_check`), with the
        adjusters' tangents as well, about 5 s more a graph on the Turtlebot's model (inductor keeps no graph that
        holds a loop in its cache). :class:`~torchrl_brsl.safety.BRSLSafetyLayer` calls it with its env's obstacle
        specs. Otherwise (eager or global model, obstacles checked by the LP) nothing."""
        if (not self.plan_dependent or self.reach.compile_options is None or self.uses_lp(obstacles)
                or not obstacles.center.shape[-2]):
            return
        like = dict(dtype=self.action_low.dtype, device=self.action_low.device)
        center, generators = obstacles.center, obstacles.generators
        for plans in (1, 2):
            rest = self.action_low.new_zeros(plans, self.reach.state_dim)
            placeholders = Obstacles(center.new_zeros(plans, *center.shape[-2:], **like),
                                     generators.new_zeros(plans, *generators.shape[-3:], **like),
                                     torch.zeros(plans, center.shape[-2], dtype=torch.bool, device=rest.device))
            plan = self.hold(rest).expand(plans, 1, -1)
            with torch.no_grad():
                self.evaluate(rest, plan, placeholders)
                self.evaluate_with_gauge(rest, plan, placeholders, rollout=self.rollout_sets(rest, plan))
                if plans > 1:  # the adjusters' linearisation, which pads one plan to two: >= 2 directions
                    plan = self.hold(rest).expand(plans, min(2, self.horizon), -1)
                    self.evaluate_with_gauge(rest, plan, placeholders, tangents=plan_axes(plan, self.reach.state_dim))

    def run_fused(self, function: Callable, batch: Tensor, *args, length: int,
                  fuse_from: int = FUSE_FROM_STEPS) -> Any:
        """``function(batch, *args, fused=...)``, a loop of ``length`` steps: compiled when the model's steps
        are (:attr:`~torchrl_brsl.reach.DataDrivenReach.compile_options`), the loop has at least ``fuse_from``
        steps and no input needs gradients (a compiled backward would compile a graph of its own at a control
        step), with ``fused=True``, else eagerly.

        A loop over the braking tail costs a few operations per step eagerly; compiled, it is one
        graph (one per value of the non-tensor arguments, e.g. the tail's length), whose call has a
        fixed cost of its own (guards, buffers) that shorter loops do not pay back. Every batch size
        ``[B, ...]`` of ``batch`` shares the graph (:meth:`_compiled`). A compilation that fails warns
        and runs eagerly from then on.
        """
        differentiable = torch.is_grad_enabled() and any(
            isinstance(t, Tensor) and t.requires_grad for t in (batch, *args))
        if self.reach.compile_options is None or length < fuse_from or differentiable or not len(batch):
            return function(batch, *args)
        result = self._compiled(function, (batch,), *args, fused=True)
        return function(batch, *args) if result is None else result

    def _compiled(self, function: Callable, batched: tuple[Tensor, ...], *args, cpp_wrapper: bool = False,
                  single: bool = False, **kwargs) -> tuple[Tensor, ...] | None:
        """``function(*batched, *args, **kwargs)`` compiled with the model's options (and inductor's C++ wrapper with
        ``cpp_wrapper``: faster calls of a graph of many small kernels), without gradients (one graph, whatever the
        caller's grad mode); ``None`` where compiling failed (a warning says why, and it is not tried again). The
        tensors ``batched`` ``[B, ...]`` (``B >= 1``) are padded to at least 2 rows and marked dynamic
        (the compiler specialises sizes 0 and 1), so that every batch size shares the graph; with ``single``, a batch
        of one is a graph of its own instead (half the work). The results' leading dims are ``B``. The function is
        compiled from its own copy of the code, kept in the memo the checker's subsets share, so its graphs and the
        compiler's limit on recompilations are this checker's."""
        if self._memo.get(("eager", function)):
            return None
        options = self.reach.compile_options
        try:
            compiled = self.memo(("compiled", function, repr(sorted(options.items()))),
                                 lambda: torch.compile(own_code(function),
                                                       **inductor_kwargs(options, cpp_wrapper=cpp_wrapper)))
            count, padded = batched[0].shape[0], []
            for tensor in batched:
                tensor = plain_layout(tensor.expand(2, *tensor.shape[1:]) if count < 2 and not single else tensor)
                if count > 1 or not single:
                    torch._dynamo.mark_dynamic(tensor, 0)
                padded.append(tensor)
            with torch.no_grad():
                return tuple(t[:count] for t in compiled(*padded, *args, **kwargs))
        except Exception as error:  # the compiler's failure must not stop a control loop
            warn_fallback(f"the compiled {function.__name__}", error)
            self._memo[("eager", function)] = True
            return None

    def rollout_sets(self, x0: Tensor, plan: Tensor, tangents: tuple[Tensor, Tensor] | None = None,
                     finish: tuple | None = None) -> tuple:
        """Reachable sets of ``plan`` followed by braking up to the horizon (a local model).

        Args:
            x0: ``[B, n]`` measured states.
            plan: ``[B, P, m]`` with ``P <= T``.
            tangents: optional ``(dx [B, n, k], du [B, P, m, k])``, directions of the state and the plan,
                mapped to the centres' to first order (:meth:`DataDrivenReach.reach_covered`), a braking
                policy's tail with :meth:`brake_tangent`.
            finish: optional ``(function, batched, args)``: what is computed from the sets, in the same compiled
                graph (:meth:`DataDrivenReach.reach_covered`); its results replace ``(sets, covered)``.

        Returns:
            ``(actions [B, T, m], sets [B, T], covered [B])``, differentiable w.r.t. ``plan``; with
            ``tangents`` also the centres' directions ``[B, T, n, k]``.
        """
        n_tail = self.horizon - plan.shape[-2]
        if n_tail < 0:
            raise ValueError(f"the plan has {plan.shape[-2]} steps, more than the horizon T={self.horizon}")
        # the start is the point x0 (no Zonotope: its construction cost a tenth of a compiled check)
        x0, plan = check_tensor("x0", x0, min_ndim=1).to(plan.dtype), check_tensor("plan", plan, min_ndim=2)
        if self.failsafe.policy is None:
            actions = torch.cat((plan, self.hold(plan).expand(plan.shape[0], n_tail, -1)), dim=1)
            if tangents is not None:  # the constant brake's actions do not move
                du = tangents[1]
                tangents = (tangents[0], torch.cat((du, du.new_zeros(*du.shape[:-3], n_tail, *du.shape[-2:])), -3))
            return (actions, *self.reach._covered_sets(x0, None, actions, tangents, finish=finish))
        brake = (self._tail_brake(plan), n_tail) + ((self._tail_brake_tangent(plan),) if tangents is not None else ())
        *result, actions = self.reach._covered_sets(x0, None, plan, tangents, brake, finish)
        return (actions, *result)

    def _tail_brake(self, like: Tensor) -> Callable[[Tensor], Tensor]:
        """:meth:`brake` as one function per dtype and device, kept in the memo the checker's subsets share: the
        compiled plan loop keys its graph on the function, so every subset reuses it."""
        def build() -> Callable[[Tensor], Tensor]:
            low, high = self._action_bounds(like.device)
            policy, action_dtype = self.failsafe.actions, self.action_dtype
            return lambda states: _brake_action(policy, states, low, high, action_dtype)
        return self.memo(("tail brake", like.dtype, like.device), build)

    def brake_tangent(self, states: Tensor, directions: Tensor | None = None) -> Tensor:
        """The braking action's derivative at ``states`` ``[..., n]`` along ``directions`` ``[..., n, k]``:
        ``[..., m, k]``, zero where the action is clipped to the bounds; ``None``: along the state axes, the
        policy's Jacobian ``[..., m, n]``.

        By central differences of the policy (step ``eps^(1/3) (1 + |x|)``, ``eps`` of the policy's output
        dtype), so that it traces into the local model's compiled plan loop, which cannot differentiate
        (:meth:`~torchrl_brsl.reach.DataDrivenReach.reach_covered`); a float64 policy's derivative to about
        ``1e-10`` where it is smooth. The adjusters only linearise with it: every plan is checked exactly.
        """
        return self._tail_brake_tangent(states)(states, directions)

    def _tail_brake_tangent(self, like: Tensor) -> Callable[[Tensor, Tensor | None], Tensor]:
        """:meth:`brake_tangent` as one function per dtype and device (as :meth:`_tail_brake`); the policy's output
        dtype, which sets the step, is read once, from its action at rest, and the state axes built once."""
        def build() -> Callable[[Tensor, Tensor | None], Tensor]:
            low, high, policy = self.action_low.to(like), self.action_high.to(like), self.failsafe.policy
            output_dtype = policy(like.new_zeros(1, self.reach.state_dim)).dtype
            axes = torch.eye(self.reach.state_dim, dtype=like.dtype, device=like.device)
            return lambda states, directions: _brake_tangent(policy, states, axes if directions is None else directions,
                                                             low, high, output_dtype, axes=directions is None)
        return self.memo(("tail brake tangent", like.dtype, like.device), build)

    def policy_reads_state(self, states: Tensor) -> bool:
        """Whether the braking policy's action at ``states`` ``[..., n]`` depends on them (autograd records it; a
        constant's does not, and its derivative is zero). Once it has, it is taken to always (kept in the memo),
        which spares the adjusters a probe with autograd per linearisation."""
        key = ("policy reads the state", states.dtype, states.device)
        if not self._memo.get(key):
            with torch.enable_grad():
                self._memo[key] = self.failsafe.policy(states.detach().requires_grad_(True)).requires_grad
        return self._memo[key]

    @property
    def plan_steps(self) -> int:
        """The most steps a checked plan has before its braking tail: ``horizon - n_brk``."""
        return self.horizon - self.failsafe.n_brk

    def hold(self, like: Tensor) -> Tensor:
        """The open-loop braking action as the robot receives it (clipped to the bounds, rounded to the
        action dtype), in ``like``'s dtype: ``[m]``."""
        hold = torch.minimum(torch.maximum(self.failsafe.hold_action.to(like), self.action_low), self.action_high)
        return hold.to(self.action_dtype).to(like.dtype)

    def brake(self, states: Tensor) -> Tensor:
        """The braking policy's action at ``states`` ``[..., n]`` as the robot receives it: ``[..., m]``."""
        return self._tail_brake(states)(states)

    def evaluate(self, x0: Tensor, plan: Tensor, obstacles: Obstacles) -> PlanEvaluation:
        """Verify a batch of plans from measured states.

        A pair's value is the closed-form gauge ``max_f |w_f . (c_obstacle - c_set)|`` of the
        cached facet table; a non-finite value (non-finite or overflowing centres) counts as
        ``0``, i.e. colliding.

        Args:
            x0: ``[B, n]``.
            plan: ``[B, P, m]`` (``P <= T``); the rest of the horizon is the braking tail.
            obstacles: batch ``[B]``, in the model's dtype.
        """
        return self.evaluate_with_gauge(x0, plan, obstacles, detail=False)[0]

    def evaluate_with_gauge(self, x0: Tensor, plan: Tensor, obstacles: Obstacles, detail: bool = True,
                            rollout: tuple[Tensor, Zonotope, Tensor] | None = None,
                            tangents: tuple[Tensor, Tensor] | None = None) -> tuple:
        """:meth:`evaluate`, with the signed facet products, the facet attaining each value and the
        facet weights (``detail``): what the adjusters linearise (``None`` from the LP). ``rollout``:
        the plan's :meth:`rollout_sets` when already at hand (a local model); without it, a compiled local model
        checks the plan in the loop that computes its sets (:meth:`_fuses_check`). ``tangents``: ``(dx [B, n, k],
        du [B, P, m, k])`` (a local model, no ``rollout``), mapped along the same rollout as :meth:`rollout_sets`
        maps them; the centres' directions ``[B, T, n, k]`` then follow the gauge.

        A plan with NaN or infinite entries is never verified: a local model's rollout rejects it (``ValueError``)
        and a global model's values count it as colliding, but where the value checks are off (inside
        :class:`~torchrl_brsl.safety.SafetyDecision`, whose inputs are sanitised and whose adjusters may reach such
        plans) it is checked as the hold action and reported unsafe."""
        if tangents is not None and (rollout is not None or not self.plan_dependent):
            raise ValueError("`tangents` need a local model's own rollout (no `rollout`)")
        finite = None if value_checks_enabled() or rollout is not None else torch.isfinite(plan).flatten(1).all(-1)
        if finite is not None and not bool(finite.all()):
            plan = torch.where(finite.view(-1, 1, 1), plan, self.hold(plan))
            evaluation, *rest = self._evaluate_with_gauge(x0, plan, obstacles, detail, rollout, tangents)
            return evaluation._replace(safe=evaluation.safe & finite), *rest
        return self._evaluate_with_gauge(x0, plan, obstacles, detail, rollout, tangents)

    def _evaluate_with_gauge(self, x0: Tensor, plan: Tensor, obstacles: Obstacles, detail: bool,
                             rollout: tuple[Tensor, Zonotope, Tensor] | None,
                             tangents: tuple[Tensor, Tensor] | None) -> tuple:
        lp, moved, compiled_gauge = self.uses_lp(obstacles), (), True
        if self.plan_dependent and rollout is None and not lp and self._fuses_check(x0, plan):
            finish = (_checked_sets, (obstacles.center, obstacles.generators, obstacles.mask), self.check_args)
            actions, *checked = self.rollout_sets(x0, plan, tangents, finish=finish)
            moved = (checked.pop(),) if tangents is not None else ()
            centers, generators, covered, stop_room, values, stop_excess, safe, picked, weights, full = checked
            if bool(full.all()):
                evaluation = PlanEvaluation(actions, centers, values, stop_excess, safe, stop_room, covered)
                return self._in_domain(x0, evaluation, generators), Gauge(picked, weights) if detail else None, *moved
            with skip_value_checks():  # pairs not certified full-dimensional: the eager check below
                rollout, compiled_gauge = (actions, Zonotope(centers, generators), covered), False
        if self.plan_dependent:
            if rollout is None:
                actions, sets, covered, *moved = self.rollout_sets(x0, plan, tangents)
            else:
                actions, sets, covered = rollout
            centers, generators = sets.center, sets.generators
            stop_room = _stop_room(generators, self.stop_tolerance, self.stop_slack, self._stop_index)
        else:
            actions, centers = self.rollout(x0, plan)
            covered, generators = torch.ones(centers.shape[0], dtype=torch.bool, device=centers.device), None
            stop_room = self._stop_room.to(centers).expand(centers.shape[0], -1)
        positions = _take(centers, self._position_index)  # [B, T, d]
        if lp:
            projected = self._projected(generators) if self.plan_dependent else self.set_generators.to(centers)
            values, gauge = _lp_values(positions, projected, obstacles), None
        elif self.plan_dependent:
            values, gauge = self._plan_values(generators, centers, obstacles, detail, compiled_gauge)
        else:
            self.checker(obstacles.generators)
            values, gauge = self._closed_form_values(positions, obstacles, detail)
        values, stop_excess, safe = _verdict(values, obstacles.mask, centers, stop_room, covered, self._stop_index,
                                             self._threshold)
        evaluation = PlanEvaluation(actions, centers, values, stop_excess, safe, stop_room, covered)
        return self._in_domain(x0, evaluation, generators), gauge, *moved

    def _in_domain(self, x0: Tensor, evaluation: PlanEvaluation, generators: Tensor | None) -> PlanEvaluation:
        """``evaluation`` with the plans marked uncovered and unsafe where a step starts outside the domain a local
        model was fitted on (its sets' generators ``[B, T, n, p]``; ``None``: a global model), or beyond the
        checked radius around the data (``domain_radius``)."""
        bounded = generators is not None and self.reach.bounded_domain  # every step starts inside the model's domain
        if not bounded and self._domain_radius is None:
            return evaluation
        centers, inside = evaluation.centers, True
        starts = torch.cat((x0.to(centers).unsqueeze(1), centers[:, :-1]), dim=1)
        if bounded:
            radius = generators.abs().sum(-1)
            radius = torch.cat((torch.zeros_like(radius[:, :1]), radius[:, :-1]), dim=1)
            inside = self.reach._boxes_in_domain(starts, radius, evaluation.actions)
        if self._domain_radius is not None:
            inside = inside & self.reach._boxes_in_domain(starts, self._domain_radius.to(centers), evaluation.actions)
        return evaluation._replace(safe=evaluation.safe & inside, covered=evaluation.covered & inside)

    def _fuses_check(self, x0: Tensor, plan: Tensor) -> bool:
        """Whether the closed-form check of a local model's plan runs in the plan's compiled loop, one graph and one
        call (:meth:`DataDrivenReach.reach_covered`'s ``finish``): the model is compiled and nothing needs
        gradients. Two plans of one action and 6 braking steps on the Turtlebot's body-frame model: 0.73-0.75 instead
        of 0.91-0.95 ms a check, one plan 0.52-0.53 instead of 0.71-0.73 (``benchmarks/bench_check.py``)."""
        return self._fused_checks and self.reach.compile_options is not None and not (
            torch.is_grad_enabled() and (plan.requires_grad or x0.requires_grad))

    _fused_checks = True  # the check in the plan's loop (False: after it, for comparison; benchmarks/bench_check.py)

    @property
    def check_args(self) -> tuple:
        """The constants of :func:`_checked_sets` after the obstacles (a ``finish`` of the plan's loop checks with
        them): the position and stop dims, the sets' projected width, the stop tolerance and slack, the threshold."""
        return (self._position_index, self.set_width, self._stop_index, self.stop_tolerance, self.stop_slack,
                self._threshold)

    def uses_lp(self, obstacles: Obstacles) -> bool:
        """Whether ``obstacles`` are checked by the LP (``collision``): polytopes, or a space beyond 3-D."""
        needs_lp = obstacles.constrained or obstacles.dim not in CLOSED_FORM_DIMS
        if needs_lp and self.collision == "exact":
            raise ValueError(f"`collision='exact'` (the closed form) checks zonotope obstacles in {CLOSED_FORM_DIMS} "
                             f"dims; these are {'polytopes' if obstacles.constrained else f'{obstacles.dim}-D'}: "
                             "use collision='lp' or 'auto'")
        return self.collision == "lp" or needs_lp

    def _plan_values(self, generators: Tensor, centers: Tensor, obstacles: Obstacles, detail: bool,
                     compiled: bool = True) -> tuple[Tensor, Gauge | None]:
        """``v*`` ``[B, T, K]`` of plan-dependent sets ``Z(centers [B, T, n], generators [B, T, n, p])`` by the closed
        form, with the :class:`Gauge` when ``detail``; ``compiled=False``: eagerly (the compiled gauge could not
        certify these pairs).

        Where the model's steps are compiled and no centre needs gradients, the whole check (the sets' projections,
        their facets against the obstacles' and the gauges) runs as one compiled graph (:func:`_plan_gauge`; one
        16-step plan against 12 obstacles: 0.5 ms eagerly, 0.14 ms compiled), compiled by :meth:`prepare_checks` or at
        the first check. Pairs it cannot certify as full-dimensional (none where the sets carry noise) and every other
        case are checked eagerly, facet data first (:meth:`_plan_facets`)."""
        gauged = None
        if compiled and self.reach.compile_options is not None and not (
                torch.is_grad_enabled() and centers.requires_grad):
            gauged = self._compiled(_plan_gauge, (generators, centers, obstacles.center, obstacles.generators),
                                    self._position_index, self.set_width, cpp_wrapper=True, single=True)
        if gauged is not None and bool(gauged[-1].all()):
            values, picked, weights, _ = gauged
        else:
            self._plan_facets(self._projected(generators), obstacles.generators)
            positions = _take(centers, self._position_index)
            offsets = obstacles.center.unsqueeze(-3) - positions.unsqueeze(-2)  # [B, T, K, d]
            values, picked, weights = pair_gauge(offsets, self._facets)
        return values, Gauge(picked, weights) if detail else None

    def _closed_form_values(self, positions: Tensor, obstacles: Obstacles, detail: bool) -> tuple[Tensor, Gauge | None]:
        """``v*`` ``[B, T, K]`` of a global model's sets from the cached facet table, with the :class:`Gauge` when
        ``detail``."""
        offsets = obstacles.center.unsqueeze(-3) - positions.unsqueeze(-2)  # [B, T, K, d]
        parts = offsets.unsqueeze(-1).unbind(-2)  # d x [B, T, K, 1]
        products = self._columns[0] * parts[0]  # [B, T, K, F]
        for column, part in zip(self._columns[1:], parts[1:]):
            products = products.addcmul_(column, part)
        if not detail:
            return products.abs().amax(-1), None
        values, best = products.abs().max(-1)
        table = self._checker.table.weights  # [(B,) T, K, F, d]
        weights = rows_at(table.expand(*best.shape, *table.shape[-2:]), best)
        return values, Gauge(products.gather(-1, best.unsqueeze(-1)).squeeze(-1), weights)

    def _projected(self, generators: Tensor) -> Tensor:
        """Generators ``[B, T, d, ps]`` of plan-dependent sets (theirs: ``[B, T, n, p]``) on the obstacle space,
        reduced to ``set_width``.

        Each projection is enlarged by a box of half-width :data:`MIN_SET_RADIUS` (a larger set
        only makes the check stricter) so that ``Z(0, [G_set, G_obstacle])`` is always
        full-dimensional, also against the zero generators of empty obstacle slots when a
        step's sets are flat in some direction (the closed form would refuse the pair).
        """
        return _projected_generators(generators, self._position_index, self.set_width)

    def _plan_facets(self, projected: Tensor, obstacle_generators: Tensor) -> None:
        """Facet data of plan-dependent sets (projected, ``[B, T, d, ps]``) against the obstacles ``[B, K, d, p]``:
        kept by owner (used once per check, never as a table of every pair)."""
        self._facets = pair_facets(projected.detach().unsqueeze(-3), obstacle_generators.detach().unsqueeze(-4),
                                   widen=True)


class AffineRollout(NamedTuple):
    """Centres of plan + open-loop braking tail: ``centers = x0 @ state_map + plan @ plan_map + constant``.

    Attributes:
        state_map: ``[n, T n]``.
        plan_map: ``[P m, T n]`` (the plan flattened step-major).
        constant: ``[T n]`` drift plus the braking tail's contribution.
        tail: ``[T - P, m]`` the braking actions.
        position_jacobian: ``[T, d, P m]`` d (positions of every centre) / d plan.
        stop_jacobian: ``[s, P m]`` d (stop dims of the final centre) / d plan.
    """

    state_map: Tensor
    plan_map: Tensor
    constant: Tensor
    tail: Tensor
    position_jacobian: Tensor
    stop_jacobian: Tensor

    def to(self, dtype: torch.dtype, device: torch.device) -> AffineRollout:
        return AffineRollout(*(t.to(dtype=dtype, device=device) for t in self))


class Gauge(NamedTuple):
    """What the adjusters linearise of a closed-form check: for every (step, obstacle) pair, the facet
    ``f`` attaining its value ``max_f |w_f . (c_obstacle - c_set)|``.

    Attributes:
        picked: ``[B, T, K]`` the signed ``w_f . (c_obstacle - c_set)`` of that facet (its absolute
            value is the pair's value).
        weights: ``[B, T, K, d]`` that facet's ``w_f``.
    """

    picked: Tensor
    weights: Tensor


def _brake_action(policy: Callable[[Tensor], Tensor], states: Tensor, low: Tensor, high: Tensor,
                  action_dtype: torch.dtype) -> Tensor:
    """``policy(states)`` as the robot receives it, rounded to ``action_dtype`` and clipped to ``[low, high]`` (the
    bounds in ``action_dtype``), in the dtype of ``states`` ``[..., n]``: ``[..., m]``. Rounding is monotone, so
    rounding first and clipping to the rounded bounds is clipping first and rounding: one conversion fewer."""
    return torch.clamp(policy(states).to(action_dtype), low, high).to(states.dtype)


def _brake_tangent(policy: Callable[[Tensor], Tensor], states: Tensor, directions: Tensor, low: Tensor,
                   high: Tensor, output_dtype: torch.dtype, axes: bool = False) -> Tensor:
    """:meth:`PlanChecker.brake_tangent` of ``policy``: central differences along each column of ``directions``
    ``[..., n, k]`` scaled to a step of ``eps^(1/3) (1 + |states|_inf)`` (``eps`` of ``output_dtype``, the
    policy's), the action and its ``2 k`` shifted points in one policy call; ``[..., m, k]``. ``axes``:
    ``directions`` is the identity ``[n, n]`` (unit columns, no scaling), the policy's Jacobian."""
    step = torch.finfo(output_dtype).eps ** (1 / 3) * (1 + states.abs().amax(-1, keepdim=True))  # [..., 1]
    if axes:
        scale = step.unsqueeze(-1)  # [..., 1, 1]
        shift = scale * directions
    else:
        columns = directions.transpose(-1, -2)  # [..., k, n]
        size = columns.abs().amax(-1, keepdim=True)
        scale = step.unsqueeze(-1) / torch.where(size > 0, size, torch.ones_like(size))  # [..., k, 1]
        shift = scale * columns
    around = states.unsqueeze(-2).expand(*shift.shape[:-2], 1, -1)
    values = policy(torch.cat((around, around + shift, around - shift), -2)).to(states.dtype)  # [..., 1 + 2 k, m]
    k = shift.shape[-2]
    raw, ahead, behind = values.split((1, k, k), dim=-2)
    unclipped = (raw > low) & (raw < high)  # [..., 1, m]
    return ((ahead - behind) / (2 * scale)).mT * unclipped.mT


def _policy_tail(center: Tensor, policy: Callable[[Tensor], Tensor], A_T: Tensor, B_T: Tensor, k: Tensor,
                 low: Tensor, high: Tensor, action_dtype: torch.dtype, steps: int,
                 fused: bool = False) -> tuple[Tensor, Tensor]:
    """``steps`` of ``u = brake(c)``, ``c <- c A^T + u B^T + k`` from ``center`` ``[B, n]``: ``(actions [B, steps, m],
    centers [B, steps, n])``. ``fused``: the products as sums of broadcast products, which a compiler fuses
    across steps (eager, the matrix products are faster)."""
    actions, centers = [], []
    for _ in range(steps):
        u = _brake_action(policy, center, low, high, action_dtype)
        if fused:
            center = k + (center.unsqueeze(-1) * A_T).sum(-2) + (u.unsqueeze(-1) * B_T).sum(-2)
        else:
            center = torch.addmm(k, center, A_T).addmm_(u, B_T)
        actions.append(u)
        centers.append(center)
    return torch.stack(actions, dim=1), torch.stack(centers, dim=1)


def _apply_affine(affine: AffineRollout, x0: Tensor, plan: Tensor) -> tuple[Tensor, Tensor]:
    """``(actions [B, T, m], centers [B, T, n])`` of ``plan`` ``[B, P, m]`` from ``x0`` ``[B, n]`` by the cached map."""
    n_envs, plan_steps, m = plan.shape
    centers = torch.addmm(affine.constant, x0.to(plan.dtype), affine.state_map)
    centers = centers.addmm_(plan.reshape(n_envs, plan_steps * m), affine.plan_map)
    actions = torch.cat((plan, affine.tail.expand(n_envs, -1, m)), dim=1) if affine.tail.shape[0] else plan
    return actions, centers.view(n_envs, -1, x0.shape[-1])


def _projected_generators(generators: Tensor, index: slice | list[int], width: int) -> Tensor:
    """The obstacle-space projections ``[..., d, width]`` of sets' ``generators`` ``[..., n, p]`` (the dims ``index``),
    each with a box of half-width :data:`MIN_SET_RADIUS`, reduced (Girard) or padded to ``width`` columns. Compiled,
    without the value checks (a graph cannot raise on values): a non-finite set's pairs are then not full-dimensional
    (:func:`_plan_gauge`), and its check goes the eager way."""
    positions = _take(generators.transpose(-1, -2), index).transpose(-1, -2)
    floor = torch.diag_embed(positions.new_full(positions.shape[:-1], MIN_SET_RADIUS))
    columns = torch.cat((positions, floor), dim=-1)
    if not torch.compiler.is_compiling():
        return reduce_girard(columns, width)
    if columns.shape[-1] > width:
        return girard_columns(columns, width)
    return torch.nn.functional.pad(columns, (0, width - columns.shape[-1]))


def _plan_gauge(generators: Tensor, centers: Tensor, obstacle_centers: Tensor, obstacle_generators: Tensor,
                index: slice | list[int], width: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The closed-form check of plan-dependent sets ``Z(centers [B, T, n], generators [B, T, n, p])`` against the
    obstacles ``Z(obstacle_centers [B, K, d], obstacle_generators [B, K, d, q])`` (``d`` = 2 or 3 dims ``index``, the
    sets' projections of ``width`` columns), as one traceable function (:meth:`PlanChecker._plan_values` compiles it):
    ``(values, picked [B, T, K], weights [B, T, K, d], full [B, T, K])`` (:func:`pair_gauge`), valid where ``full``
    (:func:`split_pair_facets`)."""
    projected = _projected_generators(generators, index, width).unsqueeze(-3)  # [B, T, 1, d, width]
    facets = split_pair_facets(projected, obstacle_generators.unsqueeze(-4))
    offsets = obstacle_centers.unsqueeze(-3) - _take(centers, index).unsqueeze(-2)  # [B, T, K, d]
    return (*pair_gauge(offsets, facets), facets.full)


def plan_axes(plan: Tensor, state_dim: int) -> tuple[Tensor, Tensor]:
    """The tangents ``(dx [B, n, N], du [B, P, m, N])`` of :meth:`PlanChecker.rollout_sets` along every variable of
    ``plan`` ``[B, P, m]`` (``N = P m``; the start held fixed): the centres' directions are ``d centres / d plan``."""
    n_envs, plan_steps, m = plan.shape
    axes = torch.eye(plan_steps * m, dtype=plan.dtype, device=plan.device).view(plan_steps, m, plan_steps * m)
    return plan.new_zeros(n_envs, state_dim, plan_steps * m), axes.expand(n_envs, -1, -1, -1)


def _checked_sets(centers: Tensor, generators: Tensor, covered: Tensor, obstacle_centers: Tensor,
                  obstacle_generators: Tensor, mask: Tensor, index: slice | list[int], width: int,
                  stop_index: slice | list[int], stop_tolerance: Tensor, stop_slack: Tensor | None,
                  threshold: float, directions: Tensor | None = None) -> tuple[Tensor, ...]:
    """The check of a plan's sets ``Z(centers [B, T, n], generators [B, T, n, p])``, ``covered`` ``[B]``, against the
    obstacles ``Z(obstacle_centers [B, K, d], obstacle_generators [B, K, d, q])`` (``mask`` ``[B, K]``), traced after
    the plan's loop, in its graph (:meth:`PlanChecker.evaluate_with_gauge`): ``(centers, generators, covered,
    stop_room, values, stop_excess, safe, picked, weights, full)`` (:func:`_stop_room`, :func:`_verdict`,
    :func:`_plan_gauge`), valid where ``full``; the centres' ``directions`` ``[B, T, n, k]`` last where given."""
    stop_room = _stop_room(generators, stop_tolerance, stop_slack, stop_index)
    values, picked, weights, full = _plan_gauge(generators, centers, obstacle_centers, obstacle_generators, index,
                                                width)
    return (centers, generators, covered, stop_room,
            *_verdict(values, mask, centers, stop_room, covered, stop_index, threshold), picked, weights, full,
            *(() if directions is None else (directions,)))


def _stop_room(generators: Tensor, tolerance: Tensor, slack: Tensor | None, index: slice | list[int]) -> Tensor:
    """How far ``[B, s]`` the final centre of plan-dependent sets (``generators`` ``[B, T, n, p]``) may lie from rest on
    the stop dims ``index``: ``slack`` where given, else ``tolerance`` less the final set's radius."""
    if slack is not None:
        return slack.expand(generators.shape[0], -1)
    return tolerance - _take(generators[:, -1].abs().sum(-1), index)


def _verdict(values: Tensor, mask: Tensor, centers: Tensor, stop_room: Tensor, covered: Tensor,
             stop_index: slice | list[int], threshold: float) -> tuple[Tensor, Tensor, Tensor]:
    """``(values, stop_excess, safe)`` of plans with centres ``[B, T, n]``: the pairs' values ``[B, T, K]`` with
    the empty obstacle slots (``mask`` ``[B, K]`` false) at ``inf`` and the non-finite values at 0 (colliding), how
    far ``[B]`` the final centre lies beyond ``stop_room`` ``[B, s]`` on the stop dims, and whether each plan is
    safe: every value above ``threshold``, stopped and ``covered`` ``[B]``."""
    values = torch.where(mask.unsqueeze(-2), torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0), float("inf"))
    if stop_room.shape[-1]:
        stop_excess = (_take(centers.select(-2, -1), stop_index).abs() - stop_room).amax(-1)
    else:
        stop_excess = centers.new_zeros(centers.shape[0])
    if values.shape[-1] and values.shape[-2]:
        collision_free = values.amin((-1, -2)) > threshold
    else:
        collision_free = torch.ones_like(covered)
    return values, stop_excess, collision_free & (stop_excess <= 0) & covered


def _lp_values(positions: Tensor, projected: Tensor, obstacles: Obstacles) -> Tensor:
    """``v*`` ``[B, T, K]`` of the sets ``Z(positions [B, T, d], projected [(B,) T, d, ps])`` against every
    obstacle, by the differentiable LP (:func:`~torchrl_brsl.collision.collision_value`, ``0`` where a
    pair cannot be certified)."""
    generators = projected.expand(*positions.shape, projected.shape[-1])
    with skip_value_checks():  # non-finite sets are the checker's to flag (value 0), not an error
        sets = Zonotope(positions.unsqueeze(-2), generators.unsqueeze(-3))  # [B, T, 1]
        return collision_value(sets, obstacles.as_sets()[:, None], backend="lp")


def _index(dims: Sequence[int]) -> slice | list[int]:
    """A slice when ``dims`` are consecutive (a view, no copy), else the list."""
    dims = list(dims)
    if dims and dims[0] >= 0 and dims == list(range(dims[0], dims[0] + len(dims))):
        return slice(dims[0], dims[0] + len(dims))
    return dims


def _take(x: Tensor, index: slice | list[int]) -> Tensor:
    if isinstance(index, slice):
        return x.narrow(-1, index.start, index.stop - index.start)
    return x[..., index]
