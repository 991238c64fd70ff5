"""Checking fitted reachable sets against sampled trajectories of the true system."""
from __future__ import annotations

import itertools
from copy import deepcopy
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from torchrl_brsl.reach.data_driven import DataDrivenReach
from torchrl_brsl.reach.offline import collect_offline_data
from torchrl_brsl.sets import Zonotope


class SampledReach(NamedTuple):
    """Sets of ``P`` plans against ``S`` sampled true trajectories each, over ``H`` steps.

    Attributes:
        outside: ``[P, H]`` sampled states outside their set.
        width_ratio: ``[P, H]`` the sets' interval widths over the samples' spread (max - min),
            geometric mean over the state dims the samples spread in (:data:`SPREAD_FLOOR`; ``inf`` where none).
        covered: ``[P]`` whether the model claims the plan (see :meth:`DataDrivenReach.reach_covered`).
        samples: ``S``.
        dim_ratio: ``[P, H, n]`` the same per state dim (``nan`` where the samples do not spread).
        starts, plans: ``[P, n]`` and ``[P, H, m]``, the plans and their starts (e.g. for
            :meth:`DataDrivenReach.error_budget`).
    """

    outside: Tensor
    width_ratio: Tensor
    covered: Tensor
    samples: int
    dim_ratio: Tensor
    starts: Tensor
    plans: Tensor

    @property
    def violations(self) -> int:
        """Sampled states outside their sets, over the plans the model claims."""
        return int(self.outside[self.covered].sum())

    @property
    def checked(self) -> int:
        """Sampled states of the plans the model claims."""
        return int(self.covered.sum()) * self.outside.shape[1] * self.samples

    @property
    def median_ratio(self) -> float:
        """Median width ratio over the steps of the plans the model claims (``nan`` if none)."""
        ratios = self.width_ratio[self.covered]
        return float(ratios.median()) if ratios.numel() else float("nan")

    @property
    def median_dim_ratio(self) -> Tensor:
        """``[n]`` each dim's median width ratio over the steps of the claimed plans where it spreads (``nan``: none)."""
        ratios = self.dim_ratio[self.covered].flatten(0, -2)
        return ratios.nanmedian(0).values if ratios.numel() else ratios.new_full(ratios.shape[-1:], torch.nan)


def sample_reach(reach: DataDrivenReach, step: Callable[[Tensor, Tensor], Tensor], x0: Tensor, plans: Tensor,
                 samples: int = 300) -> SampledReach:
    """Roll ``samples`` noisy trajectories of the true system along each plan and compare.

    Args:
        reach: the fitted model.
        step: the true system, ``step(x [S, n], u [m]) -> x+ [S, n]`` with its own noise.
        x0: ``[P, n]`` initial states (measured exactly).
        plans: ``[P, H, m]``.
        samples: trajectories per plan.

    Examples:
        >>> system = KinematicBicycle()
        >>> reach = DataDrivenReach.fit(*system.offline_data(2000), system.noise, translation_invariant_dims=(0, 1))
        >>> result = sample_reach(reach, system.step, x0, plans)
        >>> result.violations, result.median_ratio
    """
    if x0.ndim != 2 or plans.ndim != 3 or plans.shape[0] != x0.shape[0]:
        raise ValueError(f"`x0` must be [P, n] and `plans` [P, H, m]; got {tuple(x0.shape)} and {tuple(plans.shape)}")
    sets, covered = reach.reach_covered(Zonotope.from_point(x0), plans)
    compared = []
    for p in range(x0.shape[0]):
        x, states = x0[p].expand(samples, -1), []
        for action in plans[p]:
            x = step(x, action)
            states.append(x)
        compared.append(_compare(sets[p], torch.stack(states, 1)))
    return _sampled(compared, covered, samples, x0, plans)


def _compare(sets: Zonotope, states: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(outside [H], width_ratio [H], dim_ratio [H, n])`` of one plan's sets ``[H]`` against its sampled states
    ``[S, H, n]``."""
    states = states.to(sets.center.dtype)
    spread = states.amax(0) - states.amin(0)
    spreads = spread > SPREAD_FLOOR
    per_dim = torch.where(spreads, 2 * sets.generators.abs().sum(-1) / spread.clamp_min(SPREAD_FLOOR), torch.nan)
    count = spreads.sum(-1)
    ratio = torch.where(count > 0, (per_dim.log().nan_to_num(0.0).sum(-1) / count.clamp_min(1)).exp(), torch.inf)
    return points_outside(sets, states).sum(0), ratio, per_dim


def _sampled(compared: list[tuple[Tensor, Tensor, Tensor]], covered: Tensor, samples: int, starts: Tensor,
             plans: Tensor) -> SampledReach:
    """The plans' :func:`_compare` results, stacked."""
    outside, ratios, per_dim = (torch.stack(parts) for parts in zip(*compared))
    return SampledReach(outside, ratios, covered, samples, per_dim, starts, plans)


SPREAD_FLOOR = 1e-12
"""A dim whose samples spread less than this is left out of the width ratio's mean: e.g. a position one step after
the start, when the noise enters through the velocities."""


def env_sample_reach(reach: DataDrivenReach, env, plans: int, horizon: int, action_low: Tensor, action_high: Tensor,
                     braking_action: Tensor, samples: int = 100, warmup: int = 6, state_key: str = "state",
                     seed: int = 0, noise: str = "uniform") -> SampledReach:
    """:func:`sample_reach` on a simulated robot: ``samples`` true trajectories along each plan from one reached state.

    Plans and their starts are drawn as :func:`env_trajectories` draws them (random actions, every other plan one
    action then the braking action, from a state ``0 .. warmup - 1`` random steps after a reset). At each start
    the env is copied ``samples`` times, each copy's noise re-seeded (``seed`` plus the sample's index, the same
    seeds for every plan), and every copy runs the plan: the trajectories differ only by the task's process noise,
    so their spread is what the sets would ideally cover. A plan whose episode ends in any copy is dropped and
    another drawn. Uniform noise seldom reaches the sets' edges (a sample's spread grows like the square root of the
    steps, the worst case linearly): with ``noise="vertices"`` each copy's noise stays at one random vertex of ``W``
    for the whole plan, a constant worst case whose spread approaches the reachable set's extent, so the width ratio
    says how far the sets are from the true reachable sets rather than from typical noise.

    Args:
        reach: the fitted model.
        env: an unbatched TorchRL env of a task of ``envs`` (typically its empty variant, with a long time limit),
            whose task draws its noise from ``env.task.random``.
        plans, horizon, action_low, action_high, braking_action, warmup, state_key: as :func:`env_trajectories`.
        samples: trajectories per plan.
        seed: of the copies' noise.
        noise: ``"uniform"`` (the task's noise) or ``"vertices"`` (each copy's at a random vertex of ``W`` throughout,
            the task's ``noise_signs``).

    Examples:
        >>> env = envs.make("diffdrive_nav", empty=True, robot="wheeled", episode_steps=10_000)
        >>> result = env_sample_reach(reach, env, 20, info.n_brk + 1, info.action_low, info.action_high,
        ...                           info.braking_action)
        >>> result.violations, result.median_ratio
    """
    if not hasattr(getattr(getattr(env, "task", None), "random", None), "seed"):
        raise TypeError(f"`env` must be a task of `envs`, whose task draws its noise from `env.task.random`; got "
                        f"{type(env).__name__}")
    if noise not in ("uniform", "vertices"):
        raise ValueError(f"`noise` must be 'uniform' or 'vertices', got {noise!r}")
    uniform = _uniform(action_low, action_high)
    starts, chosen, outcomes = [], [], []
    while len(starts) < plans:
        td = _reached_state(env, uniform, warmup)
        plan = _random_plan(uniform, horizon, braking_action, brakes=len(starts) % 2 == 1)
        runs = []
        for sample in range(samples):
            copy = deepcopy(env)
            copy.task.random.seed(seed + sample)
            if noise == "vertices":
                copy.task.noise_signs = copy.task.random.choice([-1.0, 1.0], copy.task.noise_generators.shape[1])
            runs.append(_run_plan(copy, td.clone(), plan, state_key))
        if not any(done for _, done in runs):
            starts.append(td[state_key].double())
            chosen.append(plan)
            outcomes.append(torch.stack([states for states, _ in runs]))  # [S, H, n]
    x0, chosen = torch.stack(starts), torch.stack(chosen)
    sets, covered = reach.reach_covered(Zonotope.from_point(x0), chosen)
    return _sampled([_compare(sets[p], states) for p, states in enumerate(outcomes)], covered, samples, x0, chosen)


MAX_VERTEX_GENERATORS = 12
"""Noise zonotopes with up to this many generators have every vertex checked by :func:`worst_noise_outside`;
larger ones get this many random sign vectors' worth (``2 ** 12``)."""


def worst_noise_outside(reach: DataDrivenReach, dynamics: Callable[[Tensor, Tensor], Tensor] | Tensor, states: Tensor,
                        actions: Tensor, chunk: int = 2048, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Whether a true successor with its noise at a vertex of ``W`` leaves the model's one-step set.

    The model claims ``f(x, u) + W ⊆ S(x, u)`` for the one-step set ``S`` from a point. A successor
    drawn with uniform noise seldom reaches ``W``'s edge, and along a plan each set's over-approximation
    hides an error bound too small at one step; so a model can pass :func:`sample_reach` while its bound
    is short at some inputs. Here every vertex of ``W`` (a random :data:`MAX_VERTEX_GENERATORS`-th power of 2
    of them for larger ones) is added to the noiseless successor (a convex set holds ``f + W`` iff it holds
    its vertices), which checks the claim itself at each query.

    Args:
        reach: the fitted model; its noise ``W`` is the one checked.
        dynamics: the true system without noise, ``dynamics(x [q, n], u [q, m]) -> [q, n]`` (called per chunk), or
            the noiseless successors ``[Q, n]`` themselves (:func:`noiseless_transitions`).
        states, actions: ``[Q, n]`` and ``[Q, m]`` the queries.
        chunk: queries per batch of one-step sets.
        seed: for the random vertices of a noise zonotope with more than :data:`MAX_VERTEX_GENERATORS` generators.

    Returns:
        ``(outside [Q], claimed [Q])``: a vertex outside (:func:`points_outside`), and whether the model claims the
        query's set (only those count).

    Examples:
        >>> system = SaturatedThrustPoint()
        >>> reach = DataDrivenReach.fit(*system.offline_data(500), system.noise, translation_invariant_dims=(0, 1))
        >>> gen = torch.Generator().manual_seed(1)
        >>> outside, claimed = worst_noise_outside(reach, system.dynamics, system.sample_states(1000, gen),
        ...                                        system.sample_actions(1000, generator=gen))
        >>> int(outside[claimed].sum())
        0
    """
    if states.ndim != 2 or actions.ndim != 2 or states.shape[0] != actions.shape[0]:
        raise ValueError(f"`states` must be [Q, n] and `actions` [Q, m]; got {tuple(states.shape)} and "
                         f"{tuple(actions.shape)}")
    if isinstance(dynamics, Tensor) and dynamics.shape != states.shape:
        raise ValueError(f"`dynamics` as successors must be [Q, n] like `states` {tuple(states.shape)}; got "
                         f"{tuple(dynamics.shape)}")
    noise = reach.noise
    generators = noise.generators.to(states.dtype)
    p = generators.shape[-1]
    if p <= MAX_VERTEX_GENERATORS:
        signs = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=p)), dtype=states.dtype).reshape(-1, p)
    else:
        gen = torch.Generator().manual_seed(seed)
        signs = torch.randint(0, 2, (2 ** MAX_VERTEX_GENERATORS, p), generator=gen).to(states.dtype) * 2 - 1
    vertices = noise.center.to(states.dtype) + signs @ generators.T  # [V, n]
    outside, claimed = [], []
    given = dynamics.split(chunk) if isinstance(dynamics, Tensor) else None
    for index, (x, u) in enumerate(zip(states.split(chunk), actions.split(chunk))):
        sets, covered = reach.reach_covered(Zonotope.from_point(x), u.unsqueeze(1))
        nominal = given[index] if given is not None else dynamics(x, u)
        successors = nominal.to(sets.center.dtype) + vertices.unsqueeze(1)  # [V, q, n]
        outside.append(points_outside(sets[:, 0], successors).any(0))
        claimed.append(covered)
    return torch.cat(outside), torch.cat(claimed)


def noiseless_transitions(env, queries: int, generator: torch.Generator | None = None,
                          state_key: str = "state") -> tuple[Tensor, Tensor, Tensor]:
    """Transitions of a random walk through a task, with their successors less the noise: for
    :func:`worst_noise_outside` on a simulated robot.

    The walk of the offline data (:func:`~torchrl_brsl.reach.collect_offline_data`, uniform actions from
    ``generator``), each next state less the noise the task reports it added (``env.task.last_noise``, which the
    tasks of ``envs`` keep).

    Args:
        env: an unbatched TorchRL env of such a task (typically its empty variant).
        queries: how many transitions to keep.
        generator: the source of the random actions.
        state_key: where the state is.

    Returns:
        ``(states [Q, n], actions [Q, m], successors [Q, n])``, float64; the actions as the env applied them.

    Examples:
        >>> x, u, clean = noiseless_transitions(envs.make("point_boxes", empty=True), 1000)
        >>> outside, claimed = worst_noise_outside(reach, clean, x, u)
    """
    if not hasattr(getattr(env, "task", None), "last_noise"):
        raise TypeError(f"`env` must be a task of `envs`, whose task reports the noise of its last step "
                        f"(`env.task.last_noise`); got {type(env).__name__}")
    data = collect_offline_data(env, queries, state_key=state_key, generator=generator,
                                record=lambda walked: walked.task.last_noise)
    return data["x_minus"], data["u_minus"], data["x_plus"] - data["recorded"]


def env_trajectories(env, plans: int, horizon: int, action_low: Tensor, action_high: Tensor, braking_action: Tensor,
                     warmup: int = 6, state_key: str = "state") -> tuple[Tensor, Tensor, Tensor]:
    """True trajectories of an env along random plans from reachable states, for checking sets against.

    Each plan starts after ``0 .. warmup - 1`` uniformly random actions from a reset (a state of the
    operating regime); its actions are uniform in the bounds, every other plan one action then the
    braking action. A plan whose episode ends on the way (e.g. the robot left the data region) is
    dropped and another drawn. Random numbers come from the global torch RNG, the env's own from its seed.

    Args:
        env: an unbatched TorchRL env (typically a task's empty variant, with a long time limit).
        plans: how many plans to keep.
        horizon: ``H``, steps per plan.
        action_low, action_high, braking_action: ``[m]``.
        state_key: where the state is.

    Returns:
        ``(x0 [P, n], plans [P, H, m], states [P, H, n])``, float64 (the plans' values are float32's, as the env
        applies them); ``states[:, j]`` follows action ``j``.

    Examples:
        >>> x0, plans, states = env_trajectories(envs.make("point_boxes", empty=True, episode_steps=10_000), 40, 11,
        ...                                      info.action_low, info.action_high, info.braking_action)
        >>> sets, claimed = reach.reach_covered(Zonotope.from_point(x0), plans)
        >>> bool(sets.contains(states)[claimed].all())
    """
    uniform = _uniform(action_low, action_high)
    starts, chosen, visited = [], [], []
    while len(starts) < plans:
        td = _reached_state(env, uniform, warmup)
        plan = _random_plan(uniform, horizon, braking_action, brakes=len(starts) % 2 == 1)
        x0 = td[state_key].double()
        states, done = _run_plan(env, td, plan, state_key)
        if not done:
            starts.append(x0)
            chosen.append(plan)
            visited.append(states)
    return torch.stack(starts), torch.stack(chosen), torch.stack(visited)


def _uniform(action_low: Tensor, action_high: Tensor) -> Callable[..., Tensor]:
    """``uniform(*shape) -> [*shape, m]`` float64 actions uniform in the bounds (the global torch RNG)."""
    low, high = action_low.double(), action_high.double()
    return lambda *shape: low + (high - low) * torch.rand(*shape, low.shape[-1], dtype=torch.float64)


def _reached_state(env, uniform: Callable[..., Tensor], warmup: int):
    """The TensorDict of a state ``0 .. warmup - 1`` random steps after a reset."""
    td = env.reset()
    for _ in range(int(torch.randint(0, warmup, ()))):
        td["action"] = uniform().float()
        td = env.step_mdp(env.step(td))
    return td


def _random_plan(uniform: Callable[..., Tensor], horizon: int, braking_action: Tensor, brakes: bool) -> Tensor:
    """``[H, m]`` random actions, or (``brakes``) one random action then the braking action, as the env applies them
    (float32 values, in float64): a set of the unrounded plan misses the robot's exact dims by the rounding."""
    plan = uniform(horizon)
    if brakes:
        plan[1:] = braking_action.double()
    return plan.float().double()


def _run_plan(env, td, plan: Tensor, state_key: str) -> tuple[Tensor, bool]:
    """``(states [H, n] float64, whether the episode ended)``: ``plan`` run in ``env`` from ``td``."""
    states = []
    for action in plan:
        td["action"] = action.float()
        td = env.step(td)
        states.append(td["next", state_key].double())
        td = env.step_mdp(td)
    return torch.stack(states), bool(td["done"])


def points_outside(sets: Zonotope, points: Tensor, directions: int = 64, seed: int = 0) -> Tensor:
    """Whether ``points`` ``[S, ...]`` lie outside ``sets`` (batch ``[...]``): ``[S, ...]`` bool.

    Exact in every 2-D coordinate projection (closed form) and along the coordinate axes and random
    directions (support function); a point outside either test is outside the set. A point passing both
    may still be outside in ``n > 2`` dimensions, so this is a lower bound on violations. A pair with a dim
    of zero width in every set is left to the axes, which are exact for it (its projection is a segment or a
    point along them, for which the closed form does not hold and an LP per point would be slow: a rotor
    hexarotor's one-step sets are exact on its three offsets, 21 of 36 pairs).
    """
    outside = torch.zeros(points.shape[:-1], dtype=torch.bool, device=points.device)
    flat = (sets.generators == 0).all(-1).reshape(-1, sets.dim).all(0)  # [n]
    for dims in itertools.combinations(range(sets.dim), 2):
        if not flat[list(dims)].any():
            outside |= ~sets.project(dims).contains(points[..., list(dims)])
    gen = torch.Generator(device="cpu").manual_seed(seed)
    random = torch.randn(directions, sets.dim, generator=gen, dtype=points.dtype).to(points.device)
    axes = torch.eye(sets.dim, dtype=points.dtype, device=points.device)
    direction = torch.cat((axes, -axes, random))
    support = (sets.generators.transpose(-1, -2) @ direction.T).abs().sum(-2)  # [..., D]
    offset = (points - sets.center) @ direction.T  # [S, ..., D]
    return outside | (offset > support * (1 + 1e-9) + 1e-12).any(-1)
