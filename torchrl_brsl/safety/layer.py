"""``BRSLSafetyLayer``: the TorchRL transform that makes every executed action safe."""
from __future__ import annotations

import time
import warnings
from typing import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_brsl.reach import DataDrivenReach
from torchrl_brsl.safety.adjust import FacetQPAdjuster, GradientAdjuster
from torchrl_brsl.safety.decision import SafetyDecision
from torchrl_brsl.safety.failsafe import Failsafe
from torchrl_brsl.safety.plan_check import PlanChecker
from torchrl_brsl.sets import Obstacles

ADJUSTERS = {"gradient": GradientAdjuster, "facet_qp": FacetQPAdjuster}

DIAGNOSTICS = {
    "intervened": torch.bool,  # the executed action differs from the proposal (unsafe, clamped or invalid)
    "failsafe": torch.bool,  # no safe plan found: braking from the state, or the previous safe plan
    "local": torch.bool,  # the executed plan was verified by the local (restricted-domain) model
    "unverified_hold": torch.bool,  # beyond every verified plan: the braking policy holds (paper Assumption 1)
    "invalid_input": torch.bool,  # NaN/inf (or beyond INPUT_LIMIT) in the state, proposal, a real obstacle or
                                  # the stored safe plan, or a proposal outside the action bounds
    "out_of_data": torch.bool,  # the proposal's sets left the region the offline data cover: not verifiable
    "min_collision_value": torch.float64,  # min v* of the (adjusted) proposal's sets (inf: no obstacle)
    "adjust_iterations": torch.int64,
    "compute_time": torch.float64,  # seconds of the layer's one batched call this step (the same for every env)
}


class BRSLSafetyLayer(Transform):
    """Black-box Reachability-based Safety Layer (Selim et al., 2022) as a TorchRL transform.

    Append it to any env whose TensorDict carries the robot ``state`` and the ``obstacles``
    (a padded batch of zonotopes: ``center [..., K, d]``, ``generators [..., K, d, p]``,
    ``mask [..., K]``). At every step it reads the proposal, either a ``plan``
    ``[..., n_plan, m]`` written by a planner or a plain ``action`` ``[..., m]`` (a plan of one
    action), completes it with the braking failsafe up to ``T = n_plan + n_brk`` steps, and
    computes the data-driven reachable sets of that sequence from the measured state. If any
    set meets an obstacle or the last set is not stopped, the plan is adjusted by projected
    gradient on the collision values. An accepted plan becomes the new safe plan; otherwise
    the failsafe takes over: braking from the measured state if its sets verify, else the
    previous safe plan, shifted by one step (at episode start: stay stopped).
    Only the first action of the safe plan reaches the robot.

    With a ``local_reach`` (a model fitted on a restricted domain, e.g. low speeds, whose
    sets are much tighter), a proposal that ``reach`` cannot verify, even adjusted, is tried
    again under the local model with its actions clipped into the local domain, and so is
    braking: near obstacles the robot then creeps and turns instead of freezing. Local plans
    count only when every step stays in the local domain (:meth:`DataDrivenReach.in_domain`).

    Safety (paper Theorem 1): every executed action begins a sequence whose reachable sets,
    braking tail included, were verified collision-free and end stopped; so under the
    assumptions of :class:`DataDrivenReach` and paper Assumption 1 the robot never collides,
    whatever the policy proposed.

    Inputs. Every entry the layer reads is checked against the others and against the model:
    ``state`` ``[..., n]`` (the model's ``state_dim``), ``action`` ``[..., m]`` and ``plan``
    ``[..., 1..n_plan, m]`` (its ``action_dim``), the obstacles' ``center`` ``[..., K, d]``,
    ``generators`` ``[..., K, d, p]`` and ``mask`` ``[..., K]`` (one ``K``, ``d`` the obstacle
    space; ``K = 0`` is allowed), floating-point dtypes and a bool mask. The parent env's specs
    are checked when the layer is appended, the TensorDict at every reset and step; a wrong
    structure raises a ``ValueError`` naming the key, its shape and the expected one. Wrong
    *values* never raise: NaN, inf or magnitudes beyond :data:`INPUT_LIMIT` in the state, the
    proposal or a real (unmasked) obstacle never reach the robot (the previous safe plan
    continues, ``invalid_input`` and ``failsafe`` are flagged); a proposal outside the action
    bounds is clamped, the clamped plan verified like any other, and ``invalid_input``
    flagged; a stored safe plan with such values (not written by the layer) is dropped for
    the braking policy. ``intervened`` is set whenever the executed action differs from the
    proposal.

    Keys written. TorchRL's collector stores the root TensorDict *before* this transform's
    inverse pass, so the executed action and diagnostics are written to the ``"next"``
    TensorDict (and at reset): ``safe_action_key`` ``[..., m]`` (the action sent to the
    robot), ``safe_plan_key`` ``[..., T, m]`` and ``safe_steps_key`` ``[..., 1]`` (per-env state,
    also in ``full_state_spec``: the fallback plan and how many of its leading actions are
    verified; once none is left the braking policy acts on the measured state), and under ``diagnostics_key`` the entries of
    :data:`DIAGNOSTICS` ``[..., 1]``. With ``penalty > 0`` the reward is reduced by
    ``penalty`` whenever the layer intervened (the paper's penalty for unsafe proposals; a
    proposal clamped into the action bounds counts too). ``compute_time`` is the duration of
    the layer's one batched call, the same value for every env of a batch.

    Batched envs: put the layer outside a ``SerialEnv``/``ParallelEnv`` so one batched
    computation serves every env; partial resets only reset the safe plans of the envs
    being reset.

    Args:
        reach: the fitted reachability model (float64).
        failsafe: the braking manoeuvre (:class:`Failsafe`).
        n_plan: plan length ``n_plan``.
        stop_dims: state dims that must be ~0 when stopped (velocities).
        stop_tolerance: bound on ``|stop_dims|`` over the final reachable set (a float or one
            value per stop dim; see :class:`PlanChecker`).
        stop_slack: instead of ``stop_tolerance``: ``|final centre| <= stop_slack`` on the stop
            dims, the tolerance being the final set's own radius plus the slack. Without either,
            ``stop_slack`` is :data:`~torchrl_brsl.safety.plan_check.DEFAULT_STOP_SLACK` (0.15); a
            tolerance that reaches the top speed of the offline data warns (the check would
            certify nothing, see :meth:`PlanChecker.vacuous_stop_dims`).
        action_low, action_high: ``[m]`` action bounds (default: the parent's action spec).
        position_dims: state dims of the obstacle space (default: the model's
            translation-invariant dims).
        adjuster: ``"gradient"`` (:class:`GradientAdjuster`, the paper's), ``"facet_qp"``
            (:class:`FacetQPAdjuster`, faster), a configured adjuster instance, or ``None`` to
            never adjust.
        penalty: reward penalty for unsafe proposals.
        local_reach: an optional second model of a restricted domain (see above), with the
            same state and action dims; its stop slack is at most half the top speed of its
            data (:class:`PlanChecker`).
        set_generators: generator width of the projected reachable sets.
        margin: sets count as colliding when ``v* <= 1 + margin``.
        collision: ``"auto"`` (the closed form for zonotope obstacles in 1-3 D, else the
            differentiable LP), ``"exact"`` or ``"lp"`` (:data:`~torchrl_brsl.safety.plan_check.COLLISION_CHECKS`).
            Polytope obstacles come as constrained zonotopes: the ``obstacles`` entry then also
            holds ``constraint_matrix [..., K, c, p]`` and ``constraint_offset [..., K, c]``
            (:func:`~torchrl_brsl.sets.obstacle_batch` writes them).
        state_key, obstacles_key, plan_key, action_key: TensorDict keys of what the layer reads.
        safe_action_key, safe_plan_key, diagnostics_key, reward_key: TensorDict keys of what it writes.

    Examples:
        >>> reach = DataDrivenReach.from_env(make_env(empty=True), noise=W, steps=500,
        ...                                  translation_invariant_dims=(0, 1))
        >>> layer = BRSLSafetyLayer(reach, Failsafe(torch.zeros(2), n_brk=6), n_plan=8,
        ...                         stop_dims=(3, 4), stop_tolerance=0.05)
        >>> env = TransformedEnv(make_env(), layer)
        >>> td = env.rollout(100)  # any policy; td["next", "safe_action"] is what was executed
    """

    def __init__(self, reach: DataDrivenReach, failsafe: Failsafe, n_plan: int, *, stop_dims: Sequence[int],
                 stop_tolerance: float | Sequence[float] | None = None,
                 stop_slack: float | Sequence[float] | None = None, action_low: Tensor | None = None,
                 action_high: Tensor | None = None, position_dims: Sequence[int] | None = None,
                 adjuster: str | Callable | None = "gradient", penalty: float = 0.0,
                 set_generators: int | None = None, margin: float = 1e-6, collision: str = "auto",
                 state_key: NestedKey = "state", obstacles_key: NestedKey = "obstacles", plan_key: NestedKey = "plan",
                 action_key: NestedKey = "action", safe_action_key: NestedKey = "safe_action",
                 safe_plan_key: NestedKey = "safe_plan", safe_steps_key: NestedKey = "safe_plan_steps",
                 diagnostics_key: NestedKey = "brsl",
                 reward_key: NestedKey = "reward", local_reach: DataDrivenReach | None = None):
        super().__init__(in_keys=[], out_keys=[])
        if not isinstance(reach, DataDrivenReach):
            raise ValueError(f"`reach` must be a DataDrivenReach, got {type(reach).__name__}")
        if not isinstance(failsafe, Failsafe):
            raise ValueError(f"`failsafe` must be a Failsafe, got {type(failsafe).__name__}")
        if int(n_plan) < 1:
            raise ValueError(f"`n_plan` must be a positive integer, got {n_plan}")
        if failsafe.hold_action.shape[-1] != reach.action_dim:
            raise ValueError(f"`failsafe.hold_action` has {failsafe.hold_action.shape[-1]} entries, the model "
                             f"expects {reach.action_dim} actions")
        if local_reach is not None and (not isinstance(local_reach, DataDrivenReach)
                                        or (local_reach.state_dim, local_reach.action_dim)
                                        != (reach.state_dim, reach.action_dim)):
            raise ValueError(f"`local_reach` must be a DataDrivenReach with {reach.state_dim} states and "
                             f"{reach.action_dim} actions, like `reach`")
        n, m = reach.state_dim, reach.action_dim
        for name, dims in (("stop_dims", stop_dims), ("position_dims", position_dims)):
            if dims is not None and any(not -n <= int(dim) < n for dim in dims):
                raise ValueError(f"`{name}`={list(dims)} names dims outside the model's {n} states")
        for name, bound in (("action_low", action_low), ("action_high", action_high)):
            if bound is not None:
                bound = torch.as_tensor(bound)
                if tuple(bound.shape) != (m,) or not bool(torch.isfinite(bound).all()):
                    raise ValueError(f"`{name}` must be {m} finite values (the model's action_dim), got shape "
                                     f"{tuple(bound.shape)}")
        if action_low is not None and action_high is not None and bool(
                (torch.as_tensor(action_low) > torch.as_tensor(action_high)).any()):
            raise ValueError(f"`action_low`={list(map(float, action_low))} exceeds "
                             f"`action_high`={list(map(float, action_high))}")
        self.reach = reach
        self.local_reach = local_reach
        self.failsafe = failsafe
        self.n_plan = int(n_plan)
        self.horizon = self.n_plan + int(failsafe.n_brk)
        self.stop_dims = list(stop_dims)
        self.stop_tolerance, self.stop_slack = stop_tolerance, stop_slack
        self.position_dims = position_dims
        if isinstance(adjuster, str):
            if adjuster not in ADJUSTERS:
                raise ValueError(f"`adjuster` must be one of {sorted(ADJUSTERS)}, an adjuster or None; got {adjuster!r}")
            adjuster = ADJUSTERS[adjuster]()
        elif adjuster is not None and not callable(adjuster):
            raise ValueError(f"`adjuster` must be a name, a callable adjuster or None; got {type(adjuster).__name__}")
        self.adjuster = adjuster
        self.penalty = float(penalty)
        self.set_generators = set_generators
        self.margin = float(margin)
        self.collision = collision
        self.state_key, self.obstacles_key, self.plan_key = state_key, obstacles_key, plan_key
        self.action_key, self.safe_action_key, self.safe_plan_key = action_key, safe_action_key, safe_plan_key
        self.safe_steps_key = safe_steps_key
        self.diagnostics_key, self.reward_key = diagnostics_key, reward_key
        self._bounds = (action_low, action_high)
        self._checker: PlanChecker | None = None
        self._local_checker: PlanChecker | None = None
        self._decision: SafetyDecision | None = None
        self._prepared: Obstacles | None = None  # the obstacle shapes the compiled checks were prepared for
        self.register_load_state_dict_post_hook(BRSLSafetyLayer._rebuild_checkers)
        if action_low is not None and action_high is not None:
            _ = self.checker, self.local_checker  # validate the settings now rather than at the first step

    # ----------------------------------------------------------------- set-up
    @property
    def checker(self) -> PlanChecker:
        """The plan verifier (built on first use, when the action bounds are known)."""
        if self._checker is None:
            low, high = self._bounds
            if low is None or high is None:
                spec = self.parent.full_action_spec[self.action_key] if self.parent is not None else None
                if spec is None or not hasattr(spec.space, "low"):
                    raise ValueError("`action_low`/`action_high` must be given when the env has no bounded action spec")
                low, high = spec.space.low.reshape(-1, spec.shape[-1])[0], spec.space.high.reshape(-1, spec.shape[-1])[0]
            dtype = self.reach.state_matrix.dtype
            self._checker = self._plan_checker(self.reach, torch.as_tensor(low, dtype=dtype),
                                               torch.as_tensor(high, dtype=dtype))
        return self._checker

    @property
    def local_checker(self) -> PlanChecker | None:
        """The verifier of ``local_reach``, its actions clipped into the local domain (or None)."""
        if self.local_reach is not None and self._local_checker is None:
            n, checker = self.local_reach.state_dim, self.checker
            low = torch.maximum(checker.action_low, self.local_reach.domain_low[n:].to(checker.action_low))
            high = torch.minimum(checker.action_high, self.local_reach.domain_high[n:].to(checker.action_high))
            self._local_checker = self._plan_checker(self.local_reach, low, high)
            reason = self.local_model_unusable()
            if reason:
                warnings.warn(f"`local_reach` will never verify a plan: {reason}", UserWarning, stacklevel=2)
        return self._local_checker

    @property
    def decision(self) -> SafetyDecision:
        """The safety decision of one step (:class:`~torchrl_brsl.safety.decision.SafetyDecision`) on these checkers."""
        if self._decision is None:
            self._decision = SafetyDecision(self.checker, self.failsafe, self.adjuster, self.local_checker)
        return self._decision

    def local_model_unusable(self) -> str:
        """Why ``local_reach`` can never verify a plan, or ``""`` when it can.

        A local plan counts only when every set it starts a step from stays in the local
        domain. Braking from rest (state 0, clipped into the domain) is the easiest sequence
        there is; if even its sets leave the domain (typically the model's own one-step error
        is wider than the domain on a restricted dim, e.g. a speed cap of 0.1 m/s against a
        set of radius 0.2 m/s), no plan ever will, and the reason names the step, the dim,
        the set's interval and the domain's.
        """
        if self.local_reach is None:
            return ""
        local = self.local_checker
        reach = self.local_reach
        n, dtype = reach.state_dim, local.action_low.dtype
        low, high = reach.domain_low.to(dtype), reach.domain_high.to(dtype)
        rest = torch.zeros(1, n, dtype=dtype).clamp(low[:n], high[:n])
        brake = local.brake(rest).unsqueeze(1)
        d = len(local.position_dims)
        no_obstacles = Obstacles(rest.new_zeros(1, 0, d), rest.new_zeros(1, 0, d, 1),
                                 torch.zeros(1, 0, dtype=torch.bool))
        with torch.no_grad():
            evaluation = local.evaluate(rest, brake, no_obstacles)
            if bool(evaluation.covered.all()):
                return ""
            if local.plan_dependent:
                _, sets, _ = local.rollout_sets(rest, brake)
                radius = sets.generators[0].abs().sum(-1)  # [T, n]
            else:
                radius = reach.error_generators_sequence(self.horizon).abs().sum(-1)
        centers = evaluation.centers[0]
        for j in range(self.horizon - 1):  # R_{j+1} must lie in the domain to start step j + 2
            lo, hi = centers[j] - radius[j], centers[j] + radius[j]
            outside = ((lo < low[:n]) | (hi > high[:n])).nonzero().flatten().tolist()
            if outside:
                d = outside[0]
                return (f"braking from rest, its set after {j + 1} step(s) spans [{float(lo[d]):.3g}, "
                        f"{float(hi[d]):.3g}] on state dim {d}, outside its domain [{float(low[d]):.3g}, "
                        f"{float(high[d]):.3g}] (its one-step error alone is {float(radius[0, d]):.3g} wide there "
                        "on each side). Widen the domain on that dim, collect more low-speed data, or drop "
                        "`local_reach`.")
        return ("braking from rest leaves its data (out_of_data): collect low-speed data that cover a robot at "
                "rest under the braking action.")

    def _plan_checker(self, reach: DataDrivenReach, low: Tensor, high: Tensor) -> PlanChecker:
        return PlanChecker(reach, self.failsafe, self.horizon, stop_dims=self.stop_dims,
                           stop_tolerance=self.stop_tolerance, stop_slack=self.stop_slack, action_low=low,
                           action_high=high,
                           position_dims=self.position_dims, set_generators=self.set_generators,
                           margin=self.margin, action_dtype=self._action_dtype(), collision=self.collision)

    def _hold_plan(self, batch: torch.Size, like: Tensor) -> Tensor:
        hold = self.failsafe.hold_action.to(device=like.device, dtype=torch.float64)
        return hold.expand(*batch, self.horizon, hold.shape[-1]).clone()

    def set_container(self, container) -> None:
        """Appended to an env: its state, action and obstacle specs are checked against the model."""
        super().set_container(container)
        self._check_specs()

    def _check_specs(self) -> None:
        """At construction: the parent env's state, action and obstacle specs against the model."""
        try:
            parent = self.parent
            observations = parent.full_observation_spec if parent is not None else None
            actions = parent.full_action_spec if parent is not None else None
        except Exception:  # an env that cannot describe itself yet: checked on the first step instead
            return
        if observations is None:
            return
        batch = tuple(parent.batch_size)
        n, m = self.reach.state_dim, self.reach.action_dim
        shapes = {}
        for key, spec in ((self.state_key, observations), (self.action_key, actions),
                          *((_join(self.obstacles_key, name), observations) for name in ("center", "generators", "mask"))):
            try:
                shapes[key] = spec[key]
            except KeyError:
                pass
        if self.state_key in shapes:
            _check_structure(self.state_key, shapes[self.state_key].zero(), batch, (n,),
                             f"the model's state_dim={n}", dtype="any")
        if self.action_key in shapes:
            _check_structure(self.action_key, shapes[self.action_key].zero(), batch, (m,),
                             f"the model's action_dim={m}", dtype="any")
        keys = [_join(self.obstacles_key, name) for name in ("center", "generators", "mask")]
        if all(key in shapes for key in keys):
            d = len(self.position_dims) if self.position_dims is not None else len(self.reach.translation_invariant_dims)
            center, generators, mask = (shapes[key].zero() for key in keys)
            _check_structure(keys[0], center, batch, (None, d), f"[K obstacles, d={d}] (the obstacle space)",
                             dtype="any")
            reference = f"K={center.shape[-2]} obstacles, as `{_name(keys[0])}` {tuple(center.shape)}"
            _check_structure(keys[1], generators, batch, (center.shape[-2], d, None), reference, dtype="any")
            _check_structure(keys[2], mask, batch, (center.shape[-2],), reference, dtype="any")
            polytopes = _join(self.obstacles_key, "constraint_matrix") in observations.keys(True)
            if not polytopes:  # polytopes are checked by the LP: nothing to compile
                self._prepare_checks(Obstacles(center.reshape(-1, *center.shape[-2:]),
                                               generators.reshape(-1, *generators.shape[-3:]),
                                               mask.reshape(-1, mask.shape[-1]).bool()))

    def _prepare_checks(self, obstacles: Obstacles) -> None:
        """Compile a compiled local model's checks and its adjuster's programs for the env's obstacle shapes ``[B, K,
        ...]`` (``B`` envs) now (:meth:`PlanChecker.prepare_checks`, the adjuster's ``prepare_obstacles`` if it has
        one), not at the first step."""
        self._prepared = obstacles
        if not any(reach is not None and reach.plan_dependent and reach.compile_options is not None
                   for reach in (self.reach, self.local_reach)):
            return
        for checker in filter(None, (self.checker, self.local_checker)):
            checker.prepare_checks(obstacles)
            if hasattr(self.adjuster, "prepare_obstacles"):
                self.adjuster.prepare_obstacles(checker, obstacles)

    def _apply(self, fn, recurse=True):
        """``.to()``, ``.double()`` and the like: where they move or cast the models, the checkers follow
        (:meth:`_rebuild_checkers`), their tables built on the models' new device and dtype."""
        def placement():
            models = (getattr(self, "reach", None), getattr(self, "local_reach", None))
            return [(r.state_matrix.device, r.state_matrix.dtype) for r in models if r is not None]

        before = placement()
        result = super()._apply(fn, recurse)
        if placement() != before:
            if self._prepared is not None:  # the shapes to prepare for, on the models' new device
                device = self.reach.state_matrix.device
                self._prepared = self._prepared._map(lambda t, _: t.to(device))
            BRSLSafetyLayer._rebuild_checkers(self, None)
        return result

    @staticmethod
    def _rebuild_checkers(layer: BRSLSafetyLayer, incompatible_keys) -> None:
        """After ``load_state_dict`` (or a move, :meth:`_apply`): the checkers and the decision, whose tables (affine
        rollouts, stop tolerances, the adjusters' rows) came from the models' old buffers, are built again from the
        new ones (and their compiled checks prepared again)."""
        layer._checker = layer._local_checker = layer._decision = None
        if layer._bounds[0] is not None and layer._bounds[1] is not None:
            _ = layer.checker, layer.local_checker
        if layer._prepared is not None:
            layer._prepare_checks(layer._prepared)

    # ----------------------------------------------------------------- specs
    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        batch = observation_spec.shape
        m, device = self.reach.action_dim, observation_spec.device
        observation_spec[self.safe_plan_key] = Unbounded(shape=(*batch, self.horizon, m), dtype=torch.float64,
                                                         device=device)
        observation_spec[self.safe_steps_key] = self._steps_spec(batch, device)
        observation_spec[self.safe_action_key] = Unbounded(shape=(*batch, m), dtype=self._action_dtype(),
                                                           device=device)
        diag = Composite(shape=batch, device=device)
        for name, dtype in DIAGNOSTICS.items():
            if dtype is torch.bool:
                diag[name] = Bounded(low=0, high=1, shape=(*batch, 1), dtype=torch.bool, device=device)
            else:
                diag[name] = Unbounded(shape=(*batch, 1), dtype=dtype, device=device)
        observation_spec[self.diagnostics_key] = diag
        return observation_spec

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        if input_spec["full_state_spec"] is None:
            input_spec["full_state_spec"] = Composite(shape=input_spec.shape, device=input_spec.device)
        batch, m = input_spec.shape, self.reach.action_dim
        input_spec["full_state_spec"][self.safe_plan_key] = Unbounded(shape=(*batch, self.horizon, m),
                                                                      dtype=torch.float64, device=input_spec.device)
        input_spec["full_state_spec"][self.safe_steps_key] = self._steps_spec(batch, input_spec.device)
        return input_spec

    def _steps_spec(self, batch: torch.Size, device) -> Bounded:
        return Bounded(low=0, high=self.horizon, shape=(*batch, 1), dtype=torch.int64, device=device)

    def _action_dtype(self) -> torch.dtype:
        parent = self.parent
        if parent is None:
            return torch.get_default_dtype()
        return parent.full_action_spec[self.action_key].dtype

    # ----------------------------------------------------------------- reset / step
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        state = _entry(tensordict_reset, self.state_key, "state")
        _check_structure(self.state_key, state, tuple(batch), (self.reach.state_dim,),
                         f"the model's state_dim={self.reach.state_dim}")
        fresh = self._hold_plan(batch, state)
        previous = tensordict.get(self.safe_plan_key, None) if tensordict is not None else None
        reset = tensordict.get(self._reset_key, None) if tensordict is not None else None
        steps = torch.zeros(*batch, 1, dtype=torch.int64, device=state.device)
        if previous is not None and reset is not None:
            fresh = torch.where(reset.reshape(*batch, 1, 1), fresh, previous.to(fresh))
            steps = torch.where(reset.reshape(*batch, 1), steps, tensordict.get(self.safe_steps_key, steps))
        tensordict_reset.set(self.safe_plan_key, fresh)
        tensordict_reset.set(self.safe_steps_key, steps)
        tensordict_reset.set(self.safe_action_key, fresh[..., 0, :].to(self._action_dtype()))
        for name, dtype in DIAGNOSTICS.items():
            value = torch.full((*batch, 1), float("inf")) if name == "min_collision_value" else torch.zeros(*batch, 1)
            tensordict_reset.set((self.diagnostics_key, name), value.to(dtype=dtype, device=state.device))
        return tensordict_reset

    @property
    def _reset_key(self) -> NestedKey:
        """Where the parent env marks the envs being reset (its first reset key; ``"_reset"`` without one)."""
        parent = self.parent
        keys = list(parent.reset_keys) if parent is not None else []
        return keys[0] if keys else "_reset"

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        batch = tensordict.batch_size
        state, action, proposal, obstacles = self._read_inputs(tensordict)
        safe_plan = tensordict.get(self.safe_plan_key, None)
        safe_steps = tensordict.get(self.safe_steps_key, None)
        if safe_plan is None:
            safe_plan = self._hold_plan(batch, state)
            safe_steps = torch.zeros(*batch, 1, dtype=torch.int64, device=state.device)
        else:  # the layer's own per-env state, as the TensorDict carries it
            m = self.reach.action_dim
            _check_structure(self.safe_plan_key, safe_plan, tuple(batch), (self.horizon, m),
                             f"[T = n_plan + n_brk = {self.horizon}, action_dim={m}]")
            if safe_steps is None:
                safe_steps = torch.zeros(*batch, 1, dtype=torch.int64, device=state.device)
            _check_structure(self.safe_steps_key, safe_steps, tuple(batch), (1,), "one count per env", dtype="int")
        if proposal is None:
            proposal = action.unsqueeze(-2)
        # the plan is verified as the robot will receive it: rounded to the action dtype
        action_dtype = self._action_dtype() if action is None else action.dtype
        proposal = proposal.to(action_dtype)
        n_envs = batch.numel()
        executed, new_safe_plan, new_safe_steps, diagnostics = self.decision(
            state.reshape(n_envs, state.shape[-1]), proposal.reshape(n_envs, *proposal.shape[-2:]),
            safe_plan.reshape(n_envs, *safe_plan.shape[-2:]), safe_steps.reshape(n_envs),
            obstacles.reshape(n_envs), start)
        executed = executed.reshape(*batch, -1).to(action_dtype)
        # not executed as proposed: unsafe, clamped into the bounds, or invalid (NaN never equals)
        differs = (executed != proposal[..., 0, :]).any(-1).reshape(-1)
        diagnostics["intervened"] = diagnostics["intervened"] | differs
        tensordict.set(self.action_key, executed)
        tensordict.set(self.safe_plan_key, new_safe_plan.reshape(*batch, *new_safe_plan.shape[-2:]))
        tensordict.set(self.safe_steps_key, new_safe_steps.reshape(*batch, 1))
        for name, value in diagnostics.items():
            tensordict.set((self.diagnostics_key, name), value.reshape(*batch, 1).to(DIAGNOSTICS[name]))
        tensordict.set((self.diagnostics_key, "compute_time"),
                       torch.full((*batch, 1), time.perf_counter() - start, dtype=torch.float64))
        return tensordict

    # ----------------------------------------------------------------- input validation
    def _read_inputs(self, tensordict: TensorDictBase):
        """Every entry the layer reads, its structure checked against the others and the model.

        A wrong structure (shape, dtype, a missing entry) raises a ``ValueError`` naming the key
        and both shapes; wrong *values* (NaN, inf, out of bounds) are handled by the safety
        logic (a verified action, ``invalid_input`` flagged). Returns ``(state [*B, n],
        action [*B, m] (or None beside a plan), plan [*B, P, m] or None, obstacles [*B])``.
        """
        batch = tuple(tensordict.batch_size)
        n, m, d = self.reach.state_dim, self.reach.action_dim, len(self.checker.position_dims)
        state = _entry(tensordict, self.state_key, "state")
        _check_structure(self.state_key, state, batch, (n,), f"the model's state_dim={n}")
        plan = tensordict.get(self.plan_key, None)
        action = _entry(tensordict, self.action_key, "action") if plan is None else tensordict.get(self.action_key, None)
        if action is not None:
            _check_structure(self.action_key, action, batch, (m,), f"the model's action_dim={m}")
        if plan is not None:
            _check_structure(self.plan_key, plan, batch, (None, m), f"[n_plan steps, action_dim={m}]")
            if not 1 <= plan.shape[-2] <= self.n_plan:
                raise ValueError(f"`{_name(self.plan_key)}` has {plan.shape[-2]} steps (shape {tuple(plan.shape)}); "
                                 f"it must have 1 to n_plan={self.n_plan}")
        _entry(tensordict, self.obstacles_key, "obstacles")
        keys = {name: _join(self.obstacles_key, name) for name in ("center", "generators", "mask")}
        center, generators, mask = (_entry(tensordict, keys[name], f"obstacle {name}")
                                    for name in ("center", "generators", "mask"))
        _check_structure(keys["center"], center, batch, (None, d), f"[K obstacles, d={d}] (the obstacle space)")
        k = center.shape[-2]
        reference = f"K={k} obstacles, as `{_name(keys['center'])}` {tuple(center.shape)}"
        _check_structure(keys["generators"], generators, batch, (k, d, None), reference)
        _check_structure(keys["mask"], mask, batch, (k,), reference, dtype="bool")
        constraints = self._read_constraints(tensordict, batch, generators.shape)
        if generators.shape[-1] == 0:  # point obstacles: one zero generator keeps the facet table defined
            generators = generators.new_zeros(*generators.shape[:-1], 1)
            if constraints[0] is not None:
                constraints = (constraints[0].new_zeros(*constraints[0].shape[:-1], 1), constraints[1])
        return state, action, plan, Obstacles(center, generators, mask, *constraints)

    def _read_constraints(self, tensordict: TensorDictBase, batch: tuple, generators: torch.Size):
        """The polytope obstacles' ``(constraint_matrix, constraint_offset)``, or ``(None, None)`` for zonotopes."""
        keys = [_join(self.obstacles_key, name) for name in ("constraint_matrix", "constraint_offset")]
        matrix, offset = (tensordict.get(key, None) for key in keys)
        if matrix is None and offset is None:
            return None, None
        if matrix is None or offset is None:
            raise ValueError(f"`{_name(keys[0])}` and `{_name(keys[1])}` come together; the TensorDict holds only "
                             f"`{_name(keys[0] if offset is None else keys[1])}`")
        k, p = generators[-3], generators[-1]
        reference = f"K={k} obstacles of p={p} generators, as `{_name(_join(self.obstacles_key, 'generators'))}`"
        _check_structure(keys[0], matrix, batch, (k, None, p), reference)
        _check_structure(keys[1], offset, batch, (k, matrix.shape[-2]), reference)
        return matrix, offset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.safe_plan_key, tensordict.get(self.safe_plan_key))
        next_tensordict.set(self.safe_steps_key, tensordict.get(self.safe_steps_key))
        return write_step_outputs(tensordict, next_tensordict, self.action_key, self.safe_action_key,
                                  self.diagnostics_key, self.reward_key, self.penalty)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(f"{type(self).__name__} acts inside an environment's step: append it to a TransformedEnv.")

def _name(key: NestedKey) -> str:
    """A TensorDict key as written in messages: ``"obstacles/center"``."""
    return key if isinstance(key, str) else "/".join(key)


def _join(key: NestedKey, name: str) -> NestedKey:
    return (key, name) if isinstance(key, str) else (*key, name)


def _entry(tensordict: TensorDictBase, key: NestedKey, what: str):
    value = tensordict.get(key, None)
    if value is None:
        raise ValueError(f"the layer reads the {what} from `{_name(key)}`, which the TensorDict does not hold "
                         f"(keys: {sorted(map(str, tensordict.keys(include_nested=True, leaves_only=True)))})")
    return value


def _check_structure(key: NestedKey, value, batch: tuple, trailing: tuple, why: str, dtype: str = "float") -> None:
    """``value`` must be a tensor ``[*batch, *trailing]`` (``None``: any size) of a float (or bool) dtype."""
    if not isinstance(value, Tensor):
        raise ValueError(f"`{_name(key)}` must be a tensor, got {type(value).__name__}")
    expected = (*batch, *trailing)
    shape = tuple(value.shape)
    if len(shape) != len(expected) or any(e is not None and e != s for e, s in zip(expected, shape)):
        shown = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ("," if len(expected) == 1 else "") + ")"
        raise ValueError(f"`{_name(key)}` has shape {shape}, expected {shown}: env batch {batch}, then {why}")
    if dtype == "bool" and value.dtype is not torch.bool:
        raise ValueError(f"`{_name(key)}` must be a bool tensor (True for real obstacles), got {value.dtype}")
    if dtype == "float" and not value.is_floating_point():
        raise ValueError(f"`{_name(key)}` must be a floating-point tensor, got {value.dtype}")
    if dtype == "int" and (value.is_floating_point() or value.is_complex() or value.dtype is torch.bool):
        raise ValueError(f"`{_name(key)}` must be an integer tensor, got {value.dtype}")


def write_step_outputs(tensordict: TensorDictBase, next_tensordict: TensorDictBase, action_key: NestedKey,
                       safe_action_key: NestedKey, diagnostics_key: NestedKey, reward_key: NestedKey,
                       penalty: float) -> TensorDictBase:
    """An action filter's part of ``next``: the executed action, the step's diagnostics, and the
    reward less ``penalty`` where the proposal was ``intervened`` on (layer and baselines alike)."""
    next_tensordict.set(safe_action_key, tensordict.get(action_key))
    next_tensordict.set(diagnostics_key, tensordict.get(diagnostics_key).clone())
    if penalty:
        unsafe = tensordict.get((diagnostics_key, "intervened"))
        reward = next_tensordict.get(reward_key)
        next_tensordict.set(reward_key, reward - penalty * unsafe.to(reward.dtype).reshape(reward.shape))
    return next_tensordict
