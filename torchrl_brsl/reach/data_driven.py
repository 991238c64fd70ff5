"""Data-driven reachability of a black-box system (paper Algorithm 2, fitted once)."""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Sequence

import torch
from tensordict import TensorDict
from torch import Tensor, nn

from torchrl_brsl._compiling import quick_tracing
from torchrl_brsl.reach.body_frame import BodyFrame
from torchrl_brsl.reach.cells import Cells, fit_cells, held_out_factors
from torchrl_brsl.reach.lipschitz import covering_radius, residual_lipschitz
from torchrl_brsl.reach.local_step import LocalStep
from torchrl_brsl.sets import Zonotope, pad_generators, reduce_girard
from torchrl_brsl.sets._checks import broadcast_shapes, check_tensor, skip_value_checks

METHODS = ("local", "global")


class DataDrivenReach(nn.Module):
    """Over-approximate reachable sets of ``x+ = f(x, u) + w`` from offline data.

    Algorithm 2 of the paper recomputes ``M_j = (X+ - c_w) pinv([1; X- - x*_j; U- - u_j])``
    at every plan step. That regressor is an invertible affine re-parametrisation of
    ``[1; X-; U-]``, so slopes, residuals and the error zonotope are the same at every
    linearisation point and only the intercept moves, to the global fit evaluated there.
    This class therefore fits once, and a reachable set step is the affine map

        R_{j+1} = Ā R_j + B u_j + k + Z(0, G_E),

    whose generators never depend on the plan (they are precomputed per horizon) and whose
    centres are affine in the plan (so gradients w.r.t. actions are exact).

    **Model.** Translation-invariant dims ``T`` (positions, paper Assumption 1) enter with
    identity slope: with ``P`` the selection of ``T`` and ``φ(z) = [1; x_F; u]`` over the
    remaining dims ``F``, the least-squares fit is ``x+ - c_w - P x ≈ Θᵀ φ(z)``. The model error
    ``g(z) = f(z) - P x - Θᵀ φ(z)`` then depends on ``z = (x_F, u)`` only.

    **Error term (soundness).** At the data, ``r_i = g(z_i) + (w_i - c_w)``, so
    ``g(z_i) ∈ [r_lo, r_hi] + Z(0, G_w)``. For a query ``z`` within the covering radius
    ``δ`` (scaled inputs) of a data point ``z_i``, ``|g_k(z) - g_k(z_i)| <= L_k δ`` where
    ``L_k`` is the Lipschitz constant **of the residual g_k**, not of ``f_k``: ``g`` subtracts
    the linear model, so its constant can exceed that of ``f`` (up to ``L_f + ||[A B]||``), and
    only ``g`` is evaluated between data points. ``L_k`` is estimated from neighbouring data
    pairs with the noise width removed (:func:`residual_lipschitz`). With ``w ∈ W``,

        x+ ∈ P x + Θᵀφ(z) + c_w + [r_lo, r_hi] + Z(0, G_w) + [-Lδ, Lδ] + Z(0, G_w),

    i.e. ``G_E = [diag((r_hi - r_lo)/2 + L δ), 2 G_w]``. The guarantee holds under the paper's
    assumptions: noise in ``W`` (offline and online), ``L`` and ``δ`` representative of the
    system, and queries inside the region the data covers (see :meth:`data_distance`).

    **Local model (the default).** ``fit(method="local")`` adds per-output regression-tree
    leaves, each with its own affine model and a set-membership error bound
    (:mod:`torchrl_brsl.reach.cells`). A step then picks, per output, the model of the leaf
    holding the set's centre and the worst error over the leaves the set meets, so the
    generators depend on the plan and the sets are computed step by step
    (:meth:`step_sets`); a step outside the data's region is reported not covered
    (:meth:`reach_covered`). Where nearby data scatter beyond ``W`` (a step that depends on
    something the state does not hold), a leaf may bound part of that scatter as a hidden noise
    of every step instead of as slope, where that is tighter (:mod:`~torchrl_brsl.reach.cells`,
    :data:`~torchrl_brsl.reach.cells.HIDDEN_QUANTILES`). The one-fit form above is ``method="global"``.

    **Domain.** ``fit(..., domain=(low, high))`` keeps only the transitions whose
    ``(x, u)`` lie in that box and claims nothing outside it. A model of a small domain
    (e.g. low speeds, where a robot's kinematics are nearly linear) has much tighter sets;
    its sets are usable only while every state they start a step from, and every action,
    stay in the domain (:meth:`in_domain`). The default domain is everything.

    Data come as rows: ``x_minus[i] -> x_plus[i]`` under ``u_minus[i]`` (samples along the
    first dimension; several trajectories are simply concatenated, or passed as lists).

    Args:
        params: the fitted quantities (see :meth:`fit`); a :class:`~tensordict.TensorDict`.
        translation_invariant_dims: state indices with identity dynamics slope.
        covering_radius: ``δ`` in scaled input units.
        max_generators: generator width of the plan-independent error part of each set
            (Girard reduction); ``None`` keeps them all (width grows linearly with the horizon).

    Examples:
        >>> reach = DataDrivenReach.fit(x_minus, x_plus, u_minus, noise=W, translation_invariant_dims=(0, 1))
        >>> sets = reach.reach(Zonotope.from_point(x0), plan)  # plan [..., H, m]
        >>> sets.batch_size  # [..., H]: R_1 .. R_H
    """

    def __init__(self, params: TensorDict, translation_invariant_dims: Sequence[int], covering_radius: float,
                 max_generators: int | None = None, body_frame: BodyFrame | None = None):
        super().__init__()
        for key, value in params.items():
            self.register_buffer(key, value)
        self.translation_invariant_dims = tuple(int(d) for d in translation_invariant_dims)
        self.body_frame = body_frame
        self.covering_radius = float(covering_radius)
        self.max_generators = max_generators
        self._compile: tuple[dict, tuple, bool] | None = None  # torch.compile's arguments, code copies, loop
        self._cache: dict = {}

    # ----------------------------------------------------------------- fitting
    @classmethod
    def fit(cls, x_minus, x_plus, u_minus, noise: Zonotope, translation_invariant_dims: Sequence[int] = (),
            max_generators: int | None = None, n_neighbors: int = 10, lipschitz_margin: float | None = None,
            domain: tuple | str | None = None, method: str = "local", leaf_size: int | None = None,
            overlap: float = 0.15, extend: float = 0.25, features: bool = True,
            body_frame: BodyFrame | str | None = "auto", held_out_folds: int = 0, progress: bool = False,
            dtype: torch.dtype = torch.float64) -> DataDrivenReach:
        """Fit the model and its error zonotope from offline transitions.

        Args:
            x_minus: ``[N, n]`` states (or a list of ``[N_i, n]`` trajectories).
            x_plus: ``[N, n]`` successor states.
            u_minus: ``[N, m]`` actions.
            noise: the process-noise zonotope ``W`` (unbatched, ``n``-dimensional).
            translation_invariant_dims: state dims with identity slope (positions), left out of
                the regressors, the Lipschitz constants and the covering radius.
            max_generators: see the class docstring.
            n_neighbors: neighbours per point for the Lipschitz estimate.
            lipschitz_margin: factor (>= 1) applied to the estimated constants; default 1.5 for
                ``method="local"`` (a safety factor on constants estimated from data: with 1.0,
                no sampled state of the example systems fell outside in 1.07 million, but a
                first version of the cells let 2 of 39,000 out) and 1.0 for ``"global"``.
            domain: ``(low, high)``, each ``[n + m]`` bounds on ``(x, u)`` (``±inf`` for none):
                the transitions outside are dropped and the model claims nothing outside
                (see the class docstring). ``"data"``: the bounding box of the data's
                ``(x_minus, u_minus)``, unbounded on the translation-invariant dims and a body
                frame's heading (a model of low-speed data then claims nothing at speeds it
                never saw). ``None``: no restriction.
            method: ``"local"`` (default): affine models on regression-tree leaves of the data
                with set-membership error bounds (:mod:`torchrl_brsl.reach.cells`), chosen per
                step by the set itself; ``"global"``: one affine fit for the whole data region
                (plan-independent generators; much wider on nonlinear robots).
            leaf_size, overlap, extend: the cells of ``method="local"`` (see :func:`fit_cells`).
            features: offer the local model hinge features for saturating inputs and products of a
                state and an action input (``use_features`` of :func:`fit_cells`); ``False`` for
                comparison.
            body_frame: for a yaw-invariant planar robot, its position and heading dims
                (:class:`~torchrl_brsl.reach.body_frame.BodyFrame`): the local model then fits the
                position step (and a heading vector) in the body frame, without the heading among
                its inputs, and rotates it by the heading set at every step. ``method="local"`` only.
                ``"auto"`` (default): the frame the data show (:meth:`BodyFrame.detect
                <torchrl_brsl.reach.body_frame.BodyFrame.detect>`; the fitted model's ``body_frame``
                says which, ``None`` where none), none for ``method="global"``; ``None``: the world frame.
            held_out_folds: ``method="local"``: after the fit, bound each of this many parts of the data
                with cells fitted on the rest (:func:`~torchrl_brsl.reach.cells.held_out_factors`) and
                widen the error bound of each leaf that holds a held-out transition outside its bound by
                the factor it needed (a warning says how many fell outside); costs this many extra
                fits. 0 (default): no check. A partial remedy: on hinges free in every input (before
                :data:`~torchrl_brsl.reach.hinges.SPARSE_SHARE`), from 500 random steps, 5 folds cut the
                sampled states outside the example bicycle's sets from starts near the data's edges from
                182 to 0 of 60,000 in one draw (at 1.1x their width) and from 259 to 174 in three others,
                and left the capped quadrotor's (6 of 4,389): most lie where no held-out transition does.
            progress: ``method="local"``: show a progress bar over the outputs' fits.
            dtype: computation dtype (float64 by default).
        """
        if method not in METHODS:
            raise ValueError(f"`method` must be one of {METHODS}, got {method!r}")
        if isinstance(body_frame, str) and body_frame != "auto":
            raise ValueError(f"`body_frame` must be a BodyFrame, 'auto' or None, got {body_frame!r}")
        if body_frame is not None and body_frame != "auto" and method != "local":
            raise ValueError(f"`body_frame` needs method='local' (the global model is one affine map), got {method!r}")
        x_minus = _rows("x_minus", x_minus, dtype)
        x_plus = _rows("x_plus", x_plus, dtype)
        u_minus = _rows("u_minus", u_minus, dtype)
        n, m = x_minus.shape[1], u_minus.shape[1]
        if x_plus.shape != x_minus.shape:
            raise ValueError(f"`x_plus` {tuple(x_plus.shape)} must match `x_minus` {tuple(x_minus.shape)}")
        if u_minus.shape[0] != x_minus.shape[0]:
            raise ValueError(f"`u_minus` has {u_minus.shape[0]} rows but `x_minus` has {x_minus.shape[0]}")
        if not isinstance(noise, Zonotope) or noise.batch_size != torch.Size([]) or noise.dim != n:
            raise ValueError(f"`noise` must be an unbatched {n}-dimensional Zonotope")
        if lipschitz_margin is None:
            lipschitz_margin = 1.5 if method == "local" else 1.0
        if lipschitz_margin < 1:
            raise ValueError(f"`lipschitz_margin` must be >= 1, got {lipschitz_margin}")
        if held_out_folds and (method != "local" or int(held_out_folds) < 2):
            raise ValueError(f"`held_out_folds` must be 0, or >= 2 with method='local'; got {held_out_folds} "
                             f"with method={method!r}")
        fixed = sorted({int(d) % n for d in translation_invariant_dims})
        dims = tuple(translation_invariant_dims)
        if len(fixed) != len(dims) or any(not -n <= d < n for d in dims):
            raise ValueError(f"`translation_invariant_dims`={dims} must be distinct state indices < {n}")
        if body_frame == "auto":
            body_frame = BodyFrame.detect(x_minus, x_plus, u_minus, fixed) if method == "local" else None
        if body_frame is not None:
            body_frame.check(n, tuple(fixed))
        heading = () if body_frame is None else body_frame.heading_dims
        identity = fixed + ([body_frame.heading] if body_frame is not None and body_frame.angle else [])
        free = [d for d in range(n) if d not in fixed and d not in heading]
        if isinstance(domain, str):
            domain = _data_domain(domain, x_minus, u_minus, fixed + list(heading))
        domain_low, domain_high = _domain(domain, n + m, dtype)
        if domain is not None:
            points = torch.cat((x_minus, u_minus), dim=1)
            keep = ((points >= domain_low) & (points <= domain_high)).all(-1)
            x_minus, x_plus, u_minus = x_minus[keep], x_plus[keep], u_minus[keep]
        n_samples = x_minus.shape[0]
        needed = (1 + len(free) + m) * (2 if method == "local" else 1)
        if n_samples < needed:
            where = " in `domain`" if domain is not None else ""
            raise ValueError(f"need at least {needed} transitions{where} to fit (method={method!r}), got {n_samples}")

        w_c = noise.center.to(dtype)
        w_g = noise.generators.to(dtype)
        select = torch.zeros(n, n, dtype=dtype)
        select[identity, identity] = 1.0
        inputs = torch.cat((x_minus[:, free], u_minus), dim=1)  # [N, d]
        regressors = torch.cat((torch.ones(n_samples, 1, dtype=dtype), inputs), dim=1)
        target = x_plus - w_c - x_minus @ select.T
        theta = torch.linalg.lstsq(regressors, target, driver="gelsd").solution  # [1 + d, n]
        residual = target - regressors @ theta
        r_lo, r_hi = residual.amin(0), residual.amax(0)

        scale = (inputs.amax(0) - inputs.amin(0)).clamp_min(1e-9)
        scaled = inputs / scale
        delta = covering_radius(scaled)
        lipschitz = residual_lipschitz(scaled, residual, 2 * w_g.abs().sum(-1), n_neighbors) * lipschitz_margin

        state_matrix = select.clone()
        state_matrix[:, free] += theta[1:1 + len(free)].T
        params = TensorDict(
            state_matrix=state_matrix,  # Ā [n, n]
            input_matrix=theta[1 + len(free):].T.contiguous(),  # B [n, m]
            offset=theta[0] + w_c + (r_lo + r_hi) / 2,  # k [n]
            error_generators=torch.cat((torch.diag((r_hi - r_lo) / 2 + lipschitz * delta), 2 * w_g), dim=1),
            lipschitz=lipschitz,
            input_scale=scale,
            residual_low=r_lo,
            residual_high=r_hi,
            noise_center=w_c,
            noise_generators=w_g,
            domain_low=domain_low,
            domain_high=domain_high,
            x_minus=x_minus,
            x_plus=x_plus,
            u_minus=u_minus,
        )
        if method == "local":
            noise_radius, local_select = w_g.abs().sum(-1), select
            if body_frame is not None:
                target = body_frame.body_targets(x_minus, x_plus, w_c, target)
                noise_radius = body_frame.body_noise_radius(x_minus, w_g, noise_radius)
                local_select = select.clone()
                local_select[[d for pair in body_frame.rotated_pairs for d in pair]] = 0.0  # added after the rotation
            options = dict(scale=scale, leaf_size=leaf_size, overlap=overlap, extend=extend,
                           lipschitz_margin=lipschitz_margin, use_features=features)
            cells = fit_cells(scaled, target, noise_radius, m, progress=progress, **options)
            if held_out_folds:
                cells = _widened(cells, *held_out_factors(cells, scaled, target, noise_radius, m, held_out_folds,
                                                          torch.Generator().manual_seed(0), **options))
            params.update(_local_params(cells, scale, free, local_select, w_c))
        return cls(params, fixed, delta, max_generators, body_frame)

    @classmethod
    def from_data(cls, data, noise: Zonotope, **kwargs) -> DataDrivenReach:
        """Fit from a TensorDict with ``x_minus``, ``x_plus``, ``u_minus`` (see
        :func:`collect_offline_data`); ``kwargs`` go to :meth:`fit`."""
        return cls.fit(data["x_minus"], data["x_plus"], data["u_minus"], noise, **kwargs)

    @classmethod
    def from_env(cls, env, noise: Zonotope, steps: int = 500, *, state_key="state", action_key="action",
                 progress: bool = False, generator: torch.Generator | None = None, **kwargs) -> DataDrivenReach:
        """Collect ``steps`` random-input transitions in ``env`` (an empty copy of the task) and fit.

        ``generator`` draws the random inputs (:func:`collect_offline_data`); ``progress`` shows the collection's and
        the fit's progress; ``kwargs`` go to :meth:`fit`.

        Examples:
            >>> info = envs.safety_info("diffdrive_nav")
            >>> W = Zonotope(info.noise_center, info.noise_generators)
            >>> reach = DataDrivenReach.from_env(envs.make("diffdrive_nav", empty=True), W,
            ...                                  translation_invariant_dims=info.position_dims)
        """
        from torchrl_brsl.reach.offline import collect_offline_data

        data = collect_offline_data(env, steps, state_key=state_key, action_key=action_key, progress=progress,
                                    generator=generator)
        return cls.from_data(data, noise, progress=progress, **kwargs)

    # ----------------------------------------------------------------- properties
    @property
    def state_dim(self) -> int:
        return self.state_matrix.shape[0]

    @property
    def action_dim(self) -> int:
        return self.input_matrix.shape[1]

    @property
    def free_dims(self) -> list[int]:
        """State dims that enter the regressors (all but the translation-invariant ones and a body
        frame's heading)."""
        heading = () if self.body_frame is None else self.body_frame.heading_dims
        return [d for d in range(self.state_dim) if d not in self.translation_invariant_dims and d not in heading]

    @property
    def noise(self) -> Zonotope:
        return Zonotope(self.noise_center, self.noise_generators)

    @property
    def method(self) -> str:
        """``"local"`` (cells, plan-dependent generators) or ``"global"`` (see :meth:`fit`)."""
        return "local" if hasattr(self, "cell_low") else "global"

    @property
    def plan_dependent(self) -> bool:
        """Whether the sets' generators depend on the plan (``method="local"``)."""
        return self.method == "local"

    # ----------------------------------------------------------------- reachability
    def reach_centers(self, x0: Tensor, actions: Tensor) -> Tensor:
        """Centres of ``R_1 .. R_H``, affine in the plan (the hot path).

        Args:
            x0: ``[..., n]`` centre of the initial set.
            actions: ``[..., H, m]``.

        Returns:
            ``[..., H, n]`` in the model's dtype.
        """
        if self.plan_dependent:
            return self.reach_covered(Zonotope.from_point(x0.to(self.state_matrix.dtype)), actions)[0].center
        horizon = actions.shape[-2]
        powers, transfer, drift = self._transfer(horizon)
        x0 = x0.to(powers.dtype)
        flat = actions.to(powers.dtype).flatten(-2)  # [..., H m]
        free = (powers @ x0.unsqueeze(-2).unsqueeze(-1)).squeeze(-1)  # [..., H, n]
        forced = (transfer @ flat.unsqueeze(-1)).squeeze(-1).unflatten(-1, (horizon, self.state_dim))
        return free + forced + drift

    def error_generators_sequence(self, horizon: int) -> Tensor:
        """Plan-independent generators of ``R_1 .. R_H`` from a point initial set: ``[H, n, p]``.

        ``E_1 = G_E``, ``E_{j+1} = reduce([Ā E_j, G_E])`` (Girard, to ``max_generators`` when
        set, else zero-padded to the final width). Cached per horizon.
        """
        key = ("errors", horizon)
        if key not in self._cache:
            g_e = self.error_generators
            width = self.max_generators or horizon * g_e.shape[1]
            if width < self.state_dim:
                raise ValueError(f"`max_generators`={width} must be at least the state dimension {self.state_dim}")
            current, out = g_e, []
            for _ in range(horizon):
                if current.shape[1] > width:
                    current = reduce_girard(current, width)
                out.append(pad_generators(current, width))
                current = torch.cat((self.state_matrix @ current, g_e), dim=1)
            self._cache[key] = torch.stack(out)
        return self._cache[key]

    def reach(self, initial: Zonotope, actions: Tensor) -> Zonotope:
        """Reachable sets ``R_1 .. R_H`` of a batch of plans.

        Args:
            initial: initial sets, batch ``[...]`` (``Zonotope.from_point(x)`` for a measured
                state).
            actions: ``[..., H, m]`` plans (broadcast with ``initial``'s batch).

        Returns:
            A :class:`Zonotope` of batch ``[..., H]``, differentiable w.r.t. ``actions`` and the
            initial centre and generators.
        """
        if self.plan_dependent:  # which checks the arguments
            return self.reach_covered(initial, actions)[0]
        actions = self._check_reach_args(initial, actions)
        horizon = actions.shape[-2]
        centers = self.reach_centers(initial.center, actions)
        batch = centers.shape[:-1]
        errors = self.error_generators_sequence(horizon).expand(*batch, self.state_dim, -1)
        if initial.n_generators:
            powers = self._transfer(horizon)[0]
            g0 = powers @ initial.generators.to(powers.dtype).unsqueeze(-3)  # [..., H, n, p0]
            errors = torch.cat((g0.expand(*batch, *g0.shape[-2:]), errors), dim=-1)
        with skip_value_checks():  # built from the validated model and finite inputs
            return Zonotope(centers, errors)

    def _check_reach_args(self, initial: Zonotope, actions: Tensor) -> Tensor:
        actions = check_tensor("actions", actions, min_ndim=2)
        if not isinstance(initial, Zonotope) or initial.dim != self.state_dim:
            raise ValueError(f"`initial` must be a {self.state_dim}-dimensional Zonotope")
        if actions.shape[-1] != self.action_dim:
            raise ValueError(f"`actions` must end in {self.action_dim} (the action dim), got {tuple(actions.shape)}")
        return actions

    def reach_covered(self, initial: Zonotope, actions: Tensor, tangents: tuple[Tensor, Tensor] | None = None,
                      brake: tuple | None = None, finish: tuple | None = None
                      ) -> tuple[Zonotope, Tensor] | tuple[Zonotope, ...]:
        """:meth:`reach` and whether every step lies in the region the data cover.

        For ``method="local"`` each step ``R_j -> R_{j+1}`` is :meth:`step_sets`; a step whose
        regressor set ``(R_j on the free dims, u_j)`` reaches beyond the leaves (the data's
        region, extended) is *not covered*: the data say nothing there and no guarantee is
        claimed (the safety layer treats such a plan as unverified and flags it
        ``out_of_data``). The global model covers everything (its claims rest on
        :meth:`data_distance`).

        Args:
            tangents: a local model only: ``(dc [..., n, k], du [..., H, m, k])``, directions of the
                initial centre and the actions, mapped to the centres' directions to first order with
                each step's leaf models and relaxations held fixed (a linearisation for the adjusters).
            brake: a local model only: ``(policy, steps)``, ``steps`` more steps after the plan, each under
                ``policy(centre)`` (``[..., n] -> [..., m]``, e.g. a braking policy's actions as the robot
                receives them), in the plan's compiled loop when the model is compiled. With ``tangents``,
                ``(policy, steps, policy_tangent)``: ``policy_tangent(centre [..., n], directions [..., n, k])``
                maps the centre's directions to the action's ``[..., m, k]``.
            finish: a local model only: ``(function, batched, args)``, what is computed from the sets, in the plan's
                compiled loop when the model is compiled (one graph: a check of the sets costs one call):
                ``function(centers [..., H, n], generators [..., H, n, p], covered [...], *batched, *args)``
                (:meth:`~torchrl_brsl.reach.local_step.LocalStep.plan_sets`). Its results replace ``(sets,
                covered)``.

        Returns:
            ``(sets [..., H], covered [...])``; with ``tangents`` also the centres' directions
            ``[..., H, n, k]``; with ``brake`` also (last) every step's action ``[..., H + steps, m]`` (and
            ``H + steps`` sets).
        """
        actions = self._check_reach_args(initial, actions)
        for name, value in (("tangents", tangents), ("brake", brake), ("finish", finish)):
            if value is not None and not self.plan_dependent:
                raise ValueError(f"`{name}` is for a local model (method='local'); a global model's centres are "
                                 "affine in the plan (see `reach_centers`)")
        if not self.plan_dependent:
            sets = self.reach(initial, actions)
            return sets, torch.ones(sets.batch_size[:-1], dtype=torch.bool, device=sets.center.device)
        return self._covered_sets(initial.center, initial.generators, actions, tangents, brake, finish)

    def _covered_sets(self, center: Tensor, generators: Tensor | None, actions: Tensor,
                      tangents: tuple[Tensor, Tensor] | None = None, brake: tuple | None = None,
                      finish: tuple | None = None) -> tuple:
        """:meth:`reach_covered` of a local model from ``Z(center [..., n], generators [..., n, p])`` (``None``: the
        point ``center``), its arguments unchecked: the safety layer's path, whose checker checks its own start and
        plan (:meth:`~torchrl_brsl.safety.PlanChecker.rollout_sets`; a ``Zonotope`` of the start and the checks
        of :meth:`reach_covered` cost a tenth of a compiled check)."""
        center, generators, actions = self._plan_start(center, generators, actions)
        return self._local_step().plan_sets(center, generators, actions, tangents, brake, finish)

    def _plan_start(self, center: Tensor, generators: Tensor | None, actions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """A local model's plan inputs in its dtype: the start ``Z(center, generators)`` (``None``: the point) expanded
        to the plans' batch, the actions ``[..., T, m]`` as given."""
        dtype = self.state_matrix.dtype
        actions, center = actions.to(dtype), center.to(dtype)
        generators = center.new_zeros(*center.shape, 0) if generators is None else generators.to(dtype)
        batch = broadcast_shapes(center.shape[:-1], generators.shape[:-2], actions.shape[:-2])
        return center.expand(*batch, self.state_dim), generators.expand(*batch, *generators.shape[-2:]), actions

    def error_budget(self, initial: Zonotope, actions: Tensor) -> TensorDict:
        """Where a local model's sets get their width, step by step: what to change where the layer holds a robot.

        The sets of :meth:`reach`, computed eagerly and without gradients (a compiled model's agree up to rounding,
        :meth:`compile_steps`), each step's interval radius split into the previous set's width mapped through the
        step and the width the step adds, and the model error it adds split by its cause. Per step ``j`` and state
        dim:

        - ``radius``: the set's interval radius, ``carried + added``;
        - ``carried``: the previous set's width mapped through the step (how the step's slopes grow it);
        - ``added``: the step's own width: its model error and the noise ``W`` (in a body frame also the rotation's
          remainder, :class:`~torchrl_brsl.reach.BodyFrame`);
        - ``noise``: ``W``'s radius (``added`` cannot fall below it);
        - the model error per output, in the frame of the model's outputs (a body frame's position and heading
          outputs are body-frame steps), the leaf that sets it: ``leaf``, the error on its data (the residuals'
          envelope, ``L δ``, a hidden noise: more or better spread data, or a state that holds what the step depends
          on); ``far``, ``L (D - δ)_+`` where the set reaches beyond the leaf's data (data where the plans go);
          ``between``, the gap between the models of the leaves the set meets; and ``relaxation``, the hinges' and
          products' relaxations over the set (both grow with the set: shorter plans, tighter starts);
        - ``covered`` ``[..., T]``: the step lies in the data's region (:meth:`reach_covered`).

        Args:
            initial: initial sets, batch ``[...]``.
            actions: ``[..., T, m]`` plans.

        Returns:
            A :class:`~tensordict.TensorDict` of batch ``[..., T]``, entries ``[..., T, n]`` but ``covered``.

        Examples:
            >>> budget = reach.error_budget(Zonotope.from_point(x0), plan)  # a plan the layer does not verify
            >>> budget["added"].median(0).values, budget["far"].median(0).values  # noise, or data off the plan?
        """
        if not self.plan_dependent:
            raise ValueError("`error_budget` is for a local model (method='local'); a global model's sets add the "
                             "same error every step (see `error_generators_sequence`)")
        center, generators, actions = self._plan_start(initial.center, initial.generators,
                                                       self._check_reach_args(initial, actions))
        with torch.no_grad():  # the steps take the plans' batch whole
            parts = self._local_step().error_budget(center, generators, actions.expand(*center.shape[:-1], -1, -1))
        parts["noise"] = torch.zeros_like(parts["radius"]) + self.noise.generators.abs().sum(-1)
        return TensorDict(parts, batch_size=parts["covered"].shape)

    def step_sets(self, center: Tensor, generators: Tensor, action: Tensor,
                  tangents: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, ...]:
        """One step of a local model: ``R_j = Z(center, generators)`` under ``action`` ``[..., m]``
        (:class:`~torchrl_brsl.reach.local_step.LocalStep`, which also maps ``tangents``).

        Returns:
            ``(center [..., n], generators [..., n, p'], covered [...])`` of ``R_{j+1}``
            (generators reduced to ``max_generators`` when set), and the mapped tangents if given.
        """
        return self._local_step()(center, generators, action, tangents)

    def _local_step(self) -> LocalStep:
        """The local model's step, built once (and again after :meth:`compile_steps` or ``.to()``)."""
        if ("step",) not in self._cache:
            self._cache[("step",)] = LocalStep(self, *(self._compile[:2] if self._compile else ()))
        return self._cache[("step",)]

    def compile_steps(self, enabled: bool = True, warm_up: bool = True, loop: bool = True,
                      **compile_kwargs) -> DataDrivenReach:
        """Run the local model's steps (:meth:`step_sets`) through :func:`torch.compile`; returns ``self``.

        The same operations, fused, and each step's set the eager one up to rounding (over a plan a
        rounding difference can flip a discrete choice, a leaf or the columns Girard's reduction
        keeps: on the Turtlebot's 6-D model, random plans' radii differed by up to 4 %; both are
        sound bounds of their inputs). A plan's sets without
        gradients (checking and both adjusters' linearisation, with a braking policy's tail too) run as
        one compiled loop, 7-9x faster than eager at batch 1; single steps (gradients) 2-5x
        (``benchmarks/bench_compiled_step.py``). The warm-up's five graphs take minutes with an empty
        on-disk cache (the bicycle's body-frame model: 193 s on one CPU core) and about 20 s in a later
        process: every graph, the plans' loops included (:data:`~torchrl_brsl._compiling.CACHEABLE_LOOPS`),
        then comes from inductor's cache, and each process only traces them again. ``warm_up``
        compiles the steps' and the plans' graphs (with and without tangents) here, on two offline
        states, so that no call of :meth:`reach_covered` stalls on it (the graphs of gradients through
        the steps, which the adjusters take only for obstacles checked by the LP, compile on first
        use). The safety layer's checks and its adjusters' linearisation run in graphs of their own,
        the plan's loop with the check (``finish``), compiled when the layer is appended
        (:meth:`~torchrl_brsl.safety.PlanChecker.prepare_checks`). A global model's steps are
        one affine map and stay eager: it records the choice for the rollout of a braking policy's
        tail (:class:`~torchrl_brsl.safety.PlanChecker`), which follows it (:attr:`compile_options`).

        Calling it again with the same arguments keeps the compiled graphs. The graphs hold torch's thread count
        (:func:`torch.set_num_threads`): set it before this call and before the layer is appended, or the first
        steps after a change compile again.

        Args:
            enabled: ``False`` returns to eager steps.
            warm_up: compile now rather than at the first steps.
            loop: a plan's sets without gradients run as one compiled loop; ``False``: as compiled
                steps called one by one (a smaller graph to compile; for comparison).
            **compile_kwargs: passed to :func:`torch.compile` (e.g. ``backend="aot_eager"``).

        Raises:
            ValueError: a local model without ``max_generators`` (the compiled step keeps the generator matrix
                at that width).

        Examples:
            >>> reach = DataDrivenReach.fit(x, xp, u, noise, translation_invariant_dims=(0, 1), max_generators=30)
            >>> reach = reach.compile_steps()
        """
        if enabled and self.plan_dependent and self.max_generators is None:
            raise ValueError("`compile_steps` needs `max_generators` (a fixed width of the sets' generator "
                             "matrices keeps one compiled graph); fit the model with `max_generators=...`")
        if enabled and self._compile is not None and self._compile[::2] == (compile_kwargs, loop):
            return self  # already compiled so: keep the graphs
        functions = LocalStep.compiled_functions(loop) if enabled else None
        self._compile = (dict(compile_kwargs), functions, loop) if enabled else None
        self._cache.pop(("step",), None)
        if enabled and warm_up and self.plan_dependent:
            self._warm_up()
        return self

    @quick_tracing
    def _warm_up(self) -> None:
        """Compile the steps' and the plans' graphs (with and without tangents) on two offline states."""
        center, action = self.x_minus[:2], self.u_minus[:2]
        generators = center.new_zeros(*center.shape, self.max_generators)
        tangents = (center.new_zeros(*center.shape, 2), action.new_zeros(*action.shape, 2))
        with torch.no_grad():
            self.step_sets(center, generators, action)
            self.step_sets(center, generators, action, tangents)
            plan = action.unsqueeze(-2).expand(-1, 2, -1)
            plan_tangents = tangents[1].unsqueeze(-3).expand(-1, 2, -1, -1)
            self._local_step().plan_sets(center, generators, plan)
            self._local_step().plan_sets(center[:1], generators[:1], plan[:1])  # one plan: a graph of its own
            self._local_step().plan_sets(center, generators, plan, (tangents[0], plan_tangents))

    @property
    def compile_options(self) -> dict | None:
        """The :func:`torch.compile` arguments given to :meth:`compile_steps`, or ``None`` for eager steps."""
        return None if self._compile is None else dict(self._compile[0])

    @property
    def _leaf_rows(self) -> Tensor:
        """Per (output, leaf), flattened: ``[A row, B row, offset, feature slopes]`` ``[n M, n + m + 1 + H + Q]``."""
        key = ("leaf rows",)
        if key not in self._cache:
            d = self.cell_directions.shape[1]
            parts = (self.cell_state_rows, self.cell_input_rows, self.cell_offset.unsqueeze(-1),
                     self.cell_slopes[..., d:])
            self._cache[key] = torch.cat(parts, dim=-1).flatten(0, 1)
        return self._cache[key]

    @property
    def _cells(self) -> Cells:
        key = ("cells",)
        if key not in self._cache:
            self._cache[key] = Cells(self.cell_directions, self.cell_weights, self.cell_low, self.cell_high,
                                     self.cell_slopes, self.cell_intercepts, self.cell_errors, self.cell_lipschitz,
                                     self.cell_delta, self.cell_score, self.cell_hinge_directions,
                                     self.cell_hinge_knots, self.cell_product_directions, self.cell_product_knots,
                                     self.cell_members)
        return self._cache[key]

    @property
    def _scaled_data(self) -> Tensor:
        """The offline regressors in scaled units: ``[N, d]``."""
        key = ("scaled data",)
        if key not in self._cache:
            self._cache[key] = torch.cat((self.x_minus[:, self.free_dims], self.u_minus), dim=1) / self.input_scale
        return self._cache[key]

    @property
    def _weighted_data(self) -> Tensor:
        """:attr:`_scaled_data` in each output's metric of the cells: ``[n, N, d]``."""
        key = ("weighted data",)
        if key not in self._cache:
            self._cache[key] = self._scaled_data * self.cell_weights[:, None, :]
        return self._cache[key]

    @property
    def _free_index(self) -> list[int]:
        if ("free",) not in self._cache:
            self._cache[("free",)] = self.free_dims
        return self._cache[("free",)]

    @property
    def _diagonal_noise(self) -> Tensor | None:
        """The noise radius per dim when ``W``'s generators form a diagonal matrix, else ``None``."""
        if ("diagonal_noise",) not in self._cache:
            gens = self.noise_generators
            diagonal = gens.shape[-1] == gens.shape[-2] and bool((gens == torch.diag_embed(gens.diagonal())).all())
            self._cache[("diagonal_noise",)] = gens.diagonal().abs() if diagonal else None
        return self._cache[("diagonal_noise",)]

    def reach_literal(self, initial: Zonotope, actions: Tensor) -> Zonotope:
        """Reference: the paper's literal per-step form, one pseudo-inverse per step.

        Unbatched (``initial`` batch ``[]``, ``actions`` ``[H, m]``), no order reduction,
        linearised at each set's centre. Agrees with :meth:`reach` (``max_generators=None``)
        to rounding; kept for tests and benchmarks.
        """
        dtype = self.state_matrix.dtype
        free, fixed = self.free_dims, list(self.translation_invariant_dims)
        x_minus, u_minus = self.x_minus, self.u_minus
        target = self.x_plus - self.noise_center
        target[:, fixed] -= x_minus[:, fixed]
        center, gens = initial.center.to(dtype), initial.generators.to(dtype)
        centers, generators = [], []
        for u in actions.to(dtype):
            regressors = torch.cat((torch.ones(len(x_minus), 1, dtype=dtype), x_minus[:, free] - center[free],
                                    u_minus - u), dim=1)
            M = target.T @ torch.linalg.pinv(regressors.T)  # [n, 1 + d]
            residual = target - regressors @ M.T
            r_lo, r_hi = residual.amin(0), residual.amax(0)
            slope = torch.zeros(self.state_dim, self.state_dim, dtype=dtype)
            slope[fixed, fixed] = 1.0
            slope[:, free] += M[:, 1:1 + len(free)]
            box = torch.diag((r_hi - r_lo) / 2 + self.lipschitz * self.covering_radius)
            shifted = torch.zeros_like(center)
            shifted[fixed] = center[fixed]
            center = shifted + M[:, 0] + self.noise_center + (r_lo + r_hi) / 2
            gens = torch.cat((slope @ gens, box, 2 * self.noise_generators), dim=1)
            centers.append(center)
            generators.append(gens)
        width = generators[-1].shape[1]
        return Zonotope(torch.stack(centers), torch.stack([pad_generators(g, width) for g in generators]))

    # ----------------------------------------------------------------- domain and data region
    @property
    def bounded_domain(self) -> bool:
        """Whether the model was fitted on a restricted domain (see :meth:`fit`)."""
        if ("bounded",) not in self._cache:  # read at every check
            self._cache[("bounded",)] = bool(torch.isfinite(self.domain_low).any() or
                                             torch.isfinite(self.domain_high).any())
        return self._cache[("bounded",)]

    def in_domain(self, sets: Zonotope, actions: Tensor) -> Tensor:
        """Whether the steps from ``sets`` under ``actions`` stay in the model's domain.

        Args:
            sets: the sets each step starts from, batch ``[..., H]`` (``R_0 .. R_{H-1}``);
                their interval hulls are tested.
            actions: ``[..., H, m]``.

        Returns:
            ``[...]`` bool: every set and action of the sequence lies in the domain.
        """
        return self._boxes_in_domain(sets.center, sets.generators.abs().sum(-1), actions)

    def _boxes_in_domain(self, centers: Tensor, radius: Tensor, actions: Tensor) -> Tensor:
        """:meth:`in_domain` for boxes ``centers ± radius`` ``[..., H, n]``."""
        n = self.state_dim
        low, high = self.domain_low.to(centers), self.domain_high.to(centers)
        inside = ((centers - radius >= low[:n]) & (centers + radius <= high[:n])).all(-1)
        inside &= ((actions >= low[n:].to(actions)) & (actions <= high[n:].to(actions))).all(-1)
        return inside.all(-1)

    def _data_distance_scaled(self, z: Tensor) -> Tensor:
        """Distance ``[...]`` of scaled regressors ``z`` ``[..., d]`` to the nearest data point."""
        data = self._scaled_data.to(z)
        return torch.cdist(z.reshape(-1, z.shape[-1]), data).amin(-1).reshape(z.shape[:-1])

    def data_distance(self, states: Tensor, actions: Tensor) -> Tensor:
        """Scaled distance from ``(states, actions)`` to the nearest data point: ``[...]``.

        Queries with a distance above :attr:`covering_radius` lie outside the region the
        offline data cover, where the error bound is not backed by data.
        """
        query = torch.cat((states[..., self.free_dims].to(self.input_scale.dtype),
                           actions.to(self.input_scale.dtype)), dim=-1) / self.input_scale
        return self._data_distance_scaled(query.detach())

    # ----------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> None:
        """Write the fitted model (parameters, data and settings) to ``path``."""
        params = {name: buf for name, buf in self.named_buffers()}
        frame = None if self.body_frame is None else (self.body_frame.position, self.body_frame.heading)
        torch.save({"params": params, "translation_invariant_dims": self.translation_invariant_dims,
                    "covering_radius": self.covering_radius, "max_generators": self.max_generators,
                    "body_frame": frame}, path)

    @classmethod
    def load(cls, path: str | Path, map_location=None) -> DataDrivenReach:
        """Read a model written by :meth:`save`."""
        state = torch.load(path, map_location=map_location, weights_only=True)
        params = TensorDict(state["params"])
        if "domain_low" not in params.keys():  # written before domains existed: unrestricted
            size = params["state_matrix"].shape[0] + params["input_matrix"].shape[1]
            params["domain_low"], params["domain_high"] = _domain(None, size, params["state_matrix"].dtype)
        if "cell_low" in params.keys() and "cell_product_knots" not in params.keys():  # written before products
            n, d = params["cell_hinge_directions"].shape[0], params["cell_directions"].shape[1]
            params["cell_product_directions"] = params["cell_low"].new_zeros(n, 0, 2, d)
            params["cell_product_knots"] = params["cell_low"].new_zeros(n, 0, 2)
        frame = state.get("body_frame")
        return cls(params, state["translation_invariant_dims"], state["covering_radius"], state["max_generators"],
                   None if frame is None else BodyFrame(*frame))

    def _apply(self, fn, recurse=True):
        self._cache.clear()
        return super()._apply(fn, recurse)

    def _load_from_state_dict(self, *args, **kwargs):
        """``load_state_dict`` copies into the buffers in place: what is derived from them (the global model's transfer
        matrices, the local model's step and its tables) is rebuilt from the loaded values, its compiled graphs
        warmed up again."""
        super()._load_from_state_dict(*args, **kwargs)
        self._cache.clear()
        if self._compile is not None and self.plan_dependent:
            self._warm_up()

    def _transfer(self, horizon: int) -> tuple[Tensor, Tensor, Tensor]:
        """``Ā^1..Ā^H`` ``[H, n, n]``, the block-Toeplitz input map ``[H n, H m]`` and the drift ``[H, n]``."""
        key = ("transfer", horizon)
        if key not in self._cache:
            A, B, k = self.state_matrix, self.input_matrix, self.offset
            n, m = B.shape
            powers = [torch.eye(n, dtype=A.dtype, device=A.device)]
            for _ in range(horizon):
                powers.append(A @ powers[-1])
            transfer = A.new_zeros(horizon, n, horizon, m)
            drift = A.new_zeros(horizon, n)
            for j in range(horizon):
                for i in range(j + 1):
                    transfer[j, :, i] = powers[j - i] @ B
                drift[j] = sum(powers[i] @ k for i in range(j + 1))
            self._cache[key] = (torch.stack(powers[1:]), transfer.reshape(horizon * n, horizon * m), drift)
        return self._cache[key]


def _widened(cells: Cells, factors: Tensor, outside: int) -> Cells:
    """``cells`` with each leaf's error and Lipschitz constant times its held-out factor ``[n, M]``."""
    if outside:
        per_output = [round(float(f), 2) for f in factors.amax(-1)]
        warnings.warn(f"{outside} held-out transitions fell outside their one-step bounds: the data are sparse for "
                      f"the Lipschitz constants they gave; {int((factors > 1).sum())} leaves' error bounds are "
                      f"widened, by up to {per_output} per output "
                      f"(more offline data would keep them tighter)", stacklevel=3)
    return cells._replace(errors=cells.errors * factors, lipschitz=cells.lipschitz * factors)


def _local_params(cells: Cells, scale: Tensor, free: list[int], select: Tensor, noise_center: Tensor) -> dict:
    """The cells' models in state units: output ``k`` of cell ``c`` is
    ``x+_k = A_kc x + B_kc u + k_kc + [-e_kc, e_kc] + W_k``."""
    n_free, d = len(free), scale.shape[0]
    slopes = cells.slopes[..., :d] / scale  # [n, M, d] per unscaled input
    state_rows = select.unsqueeze(1).expand(-1, slopes.shape[1], -1).clone()  # [n, M, n]
    state_rows[:, :, free] += slopes[..., :n_free]
    return dict(cell_directions=cells.directions, cell_weights=cells.weights, cell_low=cells.low,
                cell_high=cells.high, cell_state_rows=state_rows, cell_input_rows=slopes[..., n_free:].contiguous(),
                cell_offset=cells.intercepts + noise_center.unsqueeze(-1), cell_errors=cells.errors,
                cell_lipschitz=cells.lipschitz, cell_delta=cells.delta, cell_score=cells.score,
                cell_slopes=cells.slopes, cell_intercepts=cells.intercepts,
                cell_hinge_directions=cells.hinge_directions, cell_hinge_knots=cells.hinge_knots,
                cell_product_directions=cells.product_directions, cell_product_knots=cells.product_knots,
                cell_members=cells.members)


def _data_domain(domain: str, x_minus: Tensor, u_minus: Tensor, fixed: list[int]) -> tuple[Tensor, Tensor]:
    """``domain="data"``: the data's bounding box on ``(x, u)``, unbounded on the invariant dims ``fixed``."""
    if domain != "data":
        raise ValueError(f"`domain` must be a pair (low, high), 'data' or None, got {domain!r}")
    points = torch.cat((x_minus, u_minus), dim=1)
    low, high = points.amin(0), points.amax(0)
    low[fixed], high[fixed] = -torch.inf, torch.inf
    flat = (low >= high).nonzero().flatten().tolist()
    if flat:
        raise ValueError(f"`domain='data'`: the data do not vary on dims {flat} of (state, action), so their box is "
                         "empty there; give the domain as (low, high)")
    return low, high


def _domain(domain, size: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``(low, high)`` ``[size]`` of a ``fit(domain=...)`` argument (``±inf`` for ``None``)."""
    if domain is None:
        return torch.full((size,), -torch.inf, dtype=dtype), torch.full((size,), torch.inf, dtype=dtype)
    if not isinstance(domain, (tuple, list)) or len(domain) != 2:
        raise ValueError("`domain` must be a pair (low, high) of bounds on (state, action)")
    low, high = (torch.as_tensor(bound, dtype=dtype) for bound in domain)
    if low.shape != (size,) or high.shape != (size,):
        raise ValueError(f"`domain` bounds must have shape [{size}] (state dims then action dims), "
                         f"got {tuple(low.shape)} and {tuple(high.shape)}")
    if torch.isnan(low).any() or torch.isnan(high).any() or bool((low >= high).any()):
        raise ValueError("`domain` needs low < high in every dim (use ±inf for no bound)")
    return low, high


def _rows(name: str, value, dtype: torch.dtype) -> Tensor:
    if isinstance(value, (list, tuple)):
        value = torch.cat([check_tensor(f"{name}[{i}]", v, min_ndim=2) for i, v in enumerate(value)])
    value = check_tensor(name, value, min_ndim=2)
    if value.ndim != 2:
        raise ValueError(f"`{name}` must be [N, dim] (samples along the first dimension), got {tuple(value.shape)}")
    return value.to(dtype)
