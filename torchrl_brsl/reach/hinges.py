"""Hinge features ``relu(a · z - c)`` (the kinks of saturating actuators) and state-action products, fitted once.

A servo that saturates (``v+ = v + sat(u - v)``) is affine on either side of a few
hyperplanes; a tree of affine leaves can only cut around such a kink, and a leaf that holds
the narrow linear ramp between two kinks needs more points than random data put there. A
hinge ``relu(a · z - c)`` at each kink makes the whole function affine in ``(z, h(z))``, so the
leaves' fits leave noise instead of the kink. The hinges are chosen by greedy forward
selection, as in multivariate adaptive regression splines (Friedman, "Multivariate adaptive
regression splines", Ann. Statist. 1991), starting from the split directions and a grid of
knots, each hinge's direction and knot then moved to the kink (a hinging-hyperplane fit); their
coefficients are fitted once on all data: a leaf then fits its share of what the hinges leave,
so no leaf extrapolates a hinge its own data never showed bending.

Over a reachable set the hinge is replaced by its zonotope relaxation (Singh et al., "Fast and
effective robustness certification", NeurIPS 2018): with ``s = a · z - c ∈ [l, u]`` and
``l < 0 < u``, ``relu(s) ∈ λ s + μ ± μ`` with ``λ = u / (u - l)``, ``μ = -λ l / 2``; ``λ = 1``
(``0``) when the set lies beyond (before) the knot.

Products ``(z_i - m_i)(u_j - m_j)`` of a state input and an action input join the same greedy
selection: a bicycle's heading step ``v tan(steer)`` is bilinear, and leaves of a few dozen
points cannot see a curvature of the noise's size. Over a set the action is a point, so the
product is affine in the state there (:func:`product_relaxation` adds ``r_i r_j = 0``).
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

MAX_HINGES = 12
"""Most hinges per output. A velocity servo whose force saturates, integrated in 5 substeps a control step, kinks its
position step at 10 values of ``u - v`` (where one more substep saturates): the capped quadrotor's position steps
(500 offline steps) kept up to 6e-4 m of error with 8 hinges, 3e-5 m with the 10 that 12 allow (and :data:`KNOTS`)."""

KNOTS = 50
"""Candidate knots per direction (quantiles of the data from 3 % to 97 %). The servo's 10 kinks lie in a band of
``u - v`` that holds about a tenth of random data: 25 quantiles put two or three candidates there, and the
refinement from them ended at 8 hinges, a ninth no longer lowering the held-out residual, where 50 found all 10."""

MIN_GAIN = 0.05
"""A feature is added while it removes at least this share of the squared residual beyond the noise's.

Measured against the excess over the noise, not the whole residual: a servo whose saturation
sets in over a physics step's few substeps bends smoothly, and the hinges that fit the bend
remove little squared residual (the bend holds few points) but most of its largest error,
which is what the leaves' bounds pay for (capped ``quadrotor_nav``: final-set radius 0.31 m
with 10 % of the whole residual, 0.12 m with 5 % of the excess). For the same reason selection
does not stop once the whole residual is down to the noise's variance (only :data:`NOISE_GAIN`
guards it there): the capped quadrotor's vertical servo (500 offline steps, torch seed 2) got there
with four hinges, two of them cutting its bend (``u_z - v_z`` from 0.4 to 1.1 m/s) into pieces
that left 0.046 m/s of error at 0.91 against a bound of 0.027, and 2 of 4,389 sampled states fell
outside their sets; selecting on, a fifth hinge was refined jointly with the four, the backward
pass dropped one again, and none did (the example black boxes' sets the same or up to 3 % narrower)."""

STOP_SHARE = 0.0
"""Selection stops once the whole squared residual is within this share of the noise's variance (0: never;
:data:`MIN_GAIN` and :data:`NOISE_GAIN` stop it). At 1, as before, the capped quadrotor's bend was left
under-fitted (see :data:`MIN_GAIN`)."""

STARTS = 3
"""Grid directions a new hinge's refinement starts from (their best knots); the best refined one is judged. From
the single best, one of two offline data sets of the wheeled Turtlebot found none of its wheel clips."""

SPARSE_SHARE = 0.2
"""A refined hinge keeps only the inputs that weigh at least this share of its direction's largest entry, and is
refined again on them. A kink of a real robot lies along few inputs (a servo's ``u - v``, four for a differential
drive's wheel clips); the small components the free refinement adds fit the sparse data's accidents, and the
leaves' slopes cancel them where the hinge is active but not where it is not: a bicycle's speed hinge tilted
2 % into the steering left the leaf holding full braking from rest with a steering slope the true speed does
not have (0.053 m/s predicted at -0.49 rad, 0.007 at +0.49, 0 true). From 500 offline steps, with this pruning
no sampled state fell outside the bicycle's sets from starts near the data's edges (6, 11 and 243 of 10,000 in
three seeds without), nor outside the capped quadrotor's (6 and 5 of 4,389 in two seeds without); at 0.1, 6, 0
and 11 of the bicycle's did."""

NOISE_GAIN = 10.0
"""Nor does a feature join that removes less than this many times the noise's variance ``w̄² / 3``:
the best of a few hundred candidates fitted to noise alone removes about ``2 ln(candidates)``
times it (measured on a capped servo whose two kinks were fitted: 4-8 times)."""


class Features(NamedTuple):
    """The features of one output: hinges ``relu(a · z - c)`` then products ``(a1 · z - c1)(a2 · z - c2)``.

    Attributes:
        hinge_directions: ``[H, d]``; hinge_knots: ``[H]``.
        product_directions: ``[Q, 2, d]`` the two factors' directions (a state input, an action input);
        product_knots: ``[Q, 2]`` their centres.
        coefficients: ``[H + Q]`` in the least-squares fit on ``[1, z, hinges, products]``.
    """

    hinge_directions: Tensor
    hinge_knots: Tensor
    product_directions: Tensor
    product_knots: Tensor
    coefficients: Tensor


def fit_features(features: Tensor, directions: Tensor, inputs: Tensor, target: Tensor, noise_radius: Tensor,
                 max_features: int | None = None, n_actions: int = 0) -> Features:
    """Hinges (and products) of one output by greedy forward selection, the hinges' directions and knots refined.

    Each step adds the candidate that most reduces the squared residual of the least-squares
    fit of ``target`` on ``[1, inputs, features so far]`` (computed for all candidates at once
    by projecting them off the current regressors). The candidates are ``relu(features_f -
    knot)`` (the grid: the given directions and quantiles of the data) and the products of a
    state input and an action input (the last ``n_actions`` columns), centred at the data's
    mean: a bicycle's heading step ``v tan(steer)`` is bilinear, which leaves cannot fit with few
    points per leaf when its curvature is of the noise's size. A product with an action is linear
    in the state over a set (the action is exact), so its relaxation adds no error; products of
    two states would add the product of their radii at every step.

    When a hinge is best, every hinge's direction and knot move off the grid together
    (:func:`refine_hinges`), from each of the :data:`STARTS` best grid directions and from the best hinge
    halfway between two parallel fitted ones of one sign (:func:`midpoint_hinges`; where its gain beats the best
    product's, the step is a hinge's): a kink between
    grid knots, or along a direction no candidate follows (a differential drive's wheel speeds
    clip along ``(u_v - v) ± (track / 2)(u_ω - ω)``, four kinks that each remove little alone),
    ends up fitted by one hinge. The best refined hinge is judged on held-out data (two-fold
    cross-validation). Selection stops when a step removes less than :data:`MIN_GAIN` of the
    residual beyond the noise's variance, or less than :data:`NOISE_GAIN` times the variance (not
    when the residual is down to that variance, :data:`STOP_SHARE`); then hinges that the others
    made redundant are dropped (:func:`prune_hinges`). The coefficients are the features' in the
    final least-squares fit.

    Args:
        features: ``[N, f]`` ``inputs @ directions.T``.
        directions: ``[f, d]`` the candidate hinge directions.
        inputs: ``[N, d]`` scaled regressors.
        target: ``[N]`` the output.
        noise_radius: the output's noise radius ``w̄`` (uniform noise has variance ``w̄² / 3``).
        max_features: the most features (``None``: :data:`MAX_HINGES`).
        n_actions: the action columns of ``inputs`` (0: no products).
    """
    n_points, d = inputs.shape
    max_features = MAX_HINGES if max_features is None else max_features
    quantiles = torch.linspace(0.03, 0.97, KNOTS, dtype=features.dtype)
    knots = torch.quantile(features, quantiles, dim=0).T  # [f, K]
    grid = (features.unsqueeze(-1) - knots).clamp_min(0).flatten(1)  # [N, f K]
    states, actions = torch.arange(d - n_actions), torch.arange(d - n_actions, d) if n_actions else torch.arange(0)
    pairs = torch.cartesian_prod(states, actions).T.reshape(2, -1)  # [2, C] (state, action)
    eye, mean = torch.eye(d, dtype=inputs.dtype), inputs.mean(0)
    pair_directions, pair_knots = torch.stack((eye[pairs[0]], eye[pairs[1]]), 1), mean[pairs.T]  # [C, 2, d], [C, 2]
    products = product_features(inputs, pair_directions, pair_knots)
    candidates = torch.cat((grid, products), dim=1)
    base = torch.cat((torch.ones(n_points, 1, dtype=inputs.dtype), inputs), dim=1)  # constant, inputs, products
    hinge_dirs, hinge_knots, chosen_products = inputs.new_zeros(0, d), inputs.new_zeros(0), []
    floor = n_points * float(noise_radius) ** 2 / 3
    for _ in range(max_features):
        regressors = torch.cat((base, hinge_features(inputs, hinge_dirs, hinge_knots)), dim=1)
        mid_dirs, mid_knots = hinge_dirs[:0], hinge_knots[:0]
        if not chosen_products:  # after a product (a smooth, bilinear bend) a hinge between two splits a curve
            signs = _coefficients(regressors, target)[base.shape[1]:].sign()
            mid_dirs, mid_knots = midpoint_hinges(hinge_dirs, hinge_knots, signs)
        gain, remaining = _gains(regressors, torch.cat((candidates, hinge_features(inputs, mid_dirs, mid_knots)), 1),
                                 target)
        if remaining <= STOP_SHARE * floor:
            break
        gain, mid_gain = gain.split((candidates.shape[1], len(mid_knots)))
        best = int(gain.argmax())
        if best >= grid.shape[1] and not (len(mid_knots) and mid_gain.max() > gain[best]):  # a product: exact gain
            if float(gain[best]) < _least_gain(remaining, floor, n_points):
                break
            chosen_products.append(best - grid.shape[1])
            base = torch.cat((base, products[:, best - grid.shape[1], None]), dim=1)
            continue
        # a hinge is judged once refined (a kink off the grid's directions gains little before), on held-out data
        # (a direction free in d dims can fit structure of sparse data that the next points do not share); the
        # refinement starts from the best knot of each of the STARTS best grid directions, and the best result counts
        per_direction = gain[:grid.shape[1]].view(-1, KNOTS).max(-1)
        trials = [refine_hinges(inputs, torch.cat((hinge_dirs, directions[f, None])),
                                torch.cat((hinge_knots, knots[f, per_direction.indices[f], None])), base, target)
                  for f in per_direction.values.argsort(descending=True)[:STARTS].tolist()]
        if len(mid_knots):  # and from the best knot halfway between two parallel fitted ones
            mid = int(mid_gain.argmax())
            trials.append(refine_hinges(inputs, torch.cat((hinge_dirs, mid_dirs[mid, None])),
                                        torch.cat((hinge_knots, mid_knots[mid, None])), base, target))
        left, trial = min(((_held_out_residual(torch.cat((base, hinge_features(inputs, *t)), dim=1), target), t)
                           for t in trials), key=lambda pair: pair[0])
        held_out = _held_out_residual(regressors, target)
        if held_out - left < _least_gain(held_out, floor, n_points):
            break
        hinge_dirs, hinge_knots = trial
    hinge_dirs, hinge_knots = prune_hinges(inputs, hinge_dirs, hinge_knots, base, target, floor)
    regressors = torch.cat((base[:, :1 + d], hinge_features(inputs, hinge_dirs, hinge_knots), base[:, 1 + d:]), dim=1)
    coefficients = torch.linalg.lstsq(regressors, target.unsqueeze(-1), driver="gelsd").solution[1 + d:, 0]
    product = torch.tensor(chosen_products, dtype=torch.long)
    return Features(hinge_dirs, hinge_knots, pair_directions[product], pair_knots[product], coefficients)


CHAIN_COSINE = 0.95
"""Hinges whose directions have at least this ``|cosine|`` are parallel (:func:`parallel_knots`)."""


def parallel_knots(directions: Tensor, knots: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Where the hinges ``relu(a · z - k)`` ``[H, d]``, ``[H]`` kink along each other's directions.

    Returns:
        ``(unit [H, d], length [H], own [H, 1], other [H, H], gap [H, H])``: the unit directions ``â = a / |a|`` and
        ``|a|``; knot ``i``'s position ``k / |a|`` along ``â_i``, and knot ``j``'s along ``â_i`` (an opposite hinge's
        knot lies at ``-k / |a|``); ``other - own`` where hinges ``i != j`` are parallel (:data:`CHAIN_COSINE`), else
        NaN.
    """
    length = directions.norm(dim=-1).clamp_min(1e-300)
    unit = directions / length.unsqueeze(-1)
    cosine = unit @ unit.T  # [H, H]
    own = (knots / length).unsqueeze(1)
    other = (knots / length).unsqueeze(0) * cosine.sign()
    parallel = (cosine.abs() >= CHAIN_COSINE) & ~torch.eye(len(knots), dtype=torch.bool, device=knots.device)
    return unit, length, own, other, torch.where(parallel, other - own, torch.nan)


def midpoint_hinges(directions: Tensor, knots: Tensor, signs: Tensor) -> tuple[Tensor, Tensor]:
    """A hinge halfway between each two parallel hinges (:func:`parallel_knots`) with no parallel knot between them
    and coefficients of one sign (``signs`` ``[H]``: the two cut a bend, whose stray :func:`~torchrl_brsl.reach.cells.
    bend_error` pays for), along the first one's direction: ``([P, d], [P])``.

    A servo saturating over a step's substeps kinks at several values of ``u - v``; a greedy step
    whose grid holds no knot between two fitted kinks can miss the one between (the capped quadrotor's
    y velocity, 2,000 steps: kinks fitted at 0.58 and 0.98 m/s of ``u - v``, where the true ones lie
    0.16 apart from 0.4 to 1.04), and the bend term then pays for the wide gap."""
    if len(knots) < 2:
        return directions[:0], knots[:0]
    _, length, own, _, gap = parallel_knots(directions, knots)
    above = torch.where(gap > 0, gap, torch.inf)
    nearest, index = above.min(-1)  # [H]: the next parallel knot above
    pairs = (torch.isfinite(nearest) & (signs == signs[index])).nonzero().flatten()
    return directions[pairs], (own[pairs, 0] + nearest[pairs] / 2) * length[pairs]


def refine_hinges(inputs: Tensor, directions: Tensor, knots: Tensor, base: Tensor, target: Tensor,
                  iterations: int = 50) -> tuple[Tensor, Tensor]:
    """Move hinges ``relu(a · z - c)`` (directions and knots together) to the least squared residual.

    The residual of the least-squares fit of ``target`` on ``[base, hinges]`` is a function of
    the hinges' parameters alone once the linear coefficients are solved for (variable
    projection, Golub & Pereyra 1973); it is minimised by L-BFGS from the given hinges, then
    again on the inputs each hinge weighs most (:data:`SPARSE_SHARE`), and the result is kept
    only where it lowers the residual. A refined hinge is dropped unless it leaves more data points on
    either side of its knot than it has parameters (``d + 2`` at least: a direction, a knot, a
    coefficient), as the end span of multivariate adaptive regression splines keeps knots off the data's
    last few points (Friedman 1991, section 3.8): the refinement otherwise moved a bicycle's speed hinge
    (500 offline steps, data seed 5) to leave a few points on its side, in the corner where the speed clips
    at 0 under hard braking, and extrapolated from them the model put the stopped bicycle up to 0.06 m/s
    beyond its bound: 144, 131 and 912 of 10,000 sampled states fell outside its sets from edge starts in
    three plan seeds, 27, 0 and 0 with the rule (the 27 at the heading's step, which the rule does not
    touch). This is a hinging-hyperplane fit
    (Breiman, "Hinging hyperplanes for regression, classification, and function approximation",
    IEEE Trans. Inf. Theory 1993) started from the grid.

    Args:
        inputs: ``[N, d]``; directions: ``[H, d]``; knots: ``[H]``.
        base: ``[N, r]`` the regressors kept as they are (constant, inputs, products).
        target: ``[N]``.

    Returns:
        ``(directions [H', d], knots [H'])``, each direction of unit norm (``H' < H`` where hinges were dropped).
    """
    start = _residual(torch.cat((base, hinge_features(inputs, directions, knots)), 1), target)
    params = _descend(inputs, torch.cat((directions, knots.unsqueeze(-1)), dim=1), base, target, iterations)
    if bool(torch.isfinite(params).all()):  # the inputs each hinge keeps (SPARSE_SHARE), refined again on them
        weights = params[:, :-1].abs()
        kept = weights >= SPARSE_SHARE * weights.amax(-1, keepdim=True)
        support = torch.cat((kept, torch.ones_like(kept[:, :1])), dim=1)  # knots stay free
        params = _descend(inputs, params * support, base, target, iterations, support)
    norm = params[:, :-1].norm(dim=1, keepdim=True)
    if not bool(torch.isfinite(params).all() and (norm > 0).all()):
        return directions, knots
    refined = params / norm
    refined = refined[_spans_ends(inputs, refined[:, :-1], refined[:, -1])]
    if _residual(torch.cat((base, hinge_features(inputs, refined[:, :-1], refined[:, -1])), 1), target) >= start:
        return directions, knots
    return refined[:, :-1], refined[:, -1]


def _spans_ends(inputs: Tensor, directions: Tensor, knots: Tensor) -> Tensor:
    """Which hinges ``[H]`` leave more of the ``inputs`` ``[N, d]`` on either side of their knot than they have
    parameters (:func:`refine_hinges`)."""
    active = (inputs @ directions.T > knots).sum(0)  # [H]
    return torch.minimum(active, len(inputs) - active) >= inputs.shape[1] + 2


def _descend(inputs: Tensor, params: Tensor, base: Tensor, target: Tensor, iterations: int,
             support: Tensor | None = None) -> Tensor:
    """L-BFGS on the hinges' ``[direction, knot]`` rows ``params`` ``[H, d + 1]`` to the least squared residual of
    ``target`` on ``[base, hinges]``, the entries outside ``support`` (a mask like ``params``) held at zero."""
    mask = torch.ones_like(params) if support is None else support.to(params.dtype)
    free = params.detach().clone()
    optimizer = torch.optim.LBFGS([free], max_iter=iterations, line_search_fn="strong_wolfe")

    def closure():
        loss, free.grad = _residual_gradient(inputs, free * mask, base, target)
        free.grad.mul_(mask)
        return loss

    optimizer.step(closure)
    return free * mask


def _residual_gradient(inputs: Tensor, params: Tensor, base: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_residual` of ``target`` on ``[base, relu(inputs @ a - c)]`` and its gradient in the hinges' rows
    ``params = [a, c]`` ``[H, d + 1]``. With the coefficients ``θ`` solved for, the gradient in a column ``h`` of
    the regressors is ``-2 e θ_h`` (``e`` the residual; variable projection, Golub & Pereyra 1973: the coefficients'
    own change does not count at their optimum), through ``relu`` onto ``a`` and ``c``: a closed form, equal to
    autograd through the solve up to the tiny ridge's share, which halves the refinement's time (a 2,000-step
    bicycle fit's 18 s of refinement took 9)."""
    before = inputs @ params[:, :-1].T - params[:, -1]  # [N, H]
    regressors = torch.cat((base, before.clamp_min(0)), 1)
    coefficients = _coefficients(regressors, target)
    residual = target - regressors @ coefficients
    slope = (-2 * residual).unsqueeze(-1) * coefficients[base.shape[1]:] * (before > 0)  # [N, H]
    return residual.square().sum(), torch.cat((slope.T @ inputs, -slope.sum(0).unsqueeze(-1)), dim=1)


def prune_hinges(inputs: Tensor, directions: Tensor, knots: Tensor, base: Tensor, target: Tensor,
                 floor: float) -> tuple[Tensor, Tensor]:
    """Drop the hinges the others make redundant (the backward pass of MARS).

    One at a time, the hinge whose removal costs least goes while it removes less than
    :data:`MIN_GAIN` of what the residual it would leave exceeds the noise's ``floor`` by (or
    less than :data:`NOISE_GAIN` times the noise's variance), or that residual is within the
    floor. Returns the kept ``(directions [H', d], knots [H'])``.
    """
    keep = torch.ones(len(knots), dtype=torch.bool)
    while keep.any():
        costs = []
        for h in keep.nonzero()[:, 0].tolist():
            others = keep.clone()
            others[h] = False
            gain, remaining = _gains(torch.cat((base, hinge_features(inputs, directions[others], knots[others])), 1),
                                     hinge_features(inputs, directions[h, None], knots[h, None]), target)
            costs.append((float(gain[0]), remaining, h))
        gain, remaining, h = min(costs)
        if remaining > floor and gain >= _least_gain(remaining, floor, len(target)):
            break
        keep[h] = False
    return directions[keep], knots[keep]


def _least_gain(remaining: float, floor: float, n_points: int) -> float:
    """The least a feature must remove from the squared residual ``remaining`` to join (or stay)."""
    return max(MIN_GAIN * (remaining - floor), NOISE_GAIN * floor / n_points)


def _held_out_residual(regressors: Tensor, target: Tensor) -> float:
    """The squared residual of ``target`` ``[N]`` on ``regressors`` ``[N, r]`` predicted by two-fold cross-validation
    (each half by the least-squares fit of the other; the halves interleave the points in a fixed random order)."""
    order = torch.randperm(len(target), generator=torch.Generator().manual_seed(0))
    total = 0.0
    for fit, held in ((order[0::2], order[1::2]), (order[1::2], order[0::2])):
        coefficients = torch.linalg.lstsq(regressors[fit], target[fit].unsqueeze(-1), driver="gelsd").solution
        total += float((target[held] - regressors[held] @ coefficients[:, 0]).square().sum())
    return total


def _residual(regressors: Tensor, target: Tensor) -> Tensor:
    """The squared residual of the least-squares fit of ``target`` ``[N]`` on ``regressors`` ``[N, r]``."""
    return (target - regressors @ _coefficients(regressors, target)).square().sum()


def _coefficients(regressors: Tensor, target: Tensor, ridge: float = 1e-10) -> Tensor:
    """The least-squares coefficients ``[r]`` of ``target`` on ``regressors``, by the normal equations with a tiny
    ridge (hinges that coincide or never activate leave them singular)."""
    gram = regressors.T @ regressors
    gram = gram + ridge * gram.diagonal().mean().clamp_min(1.0) * torch.eye(gram.shape[0], dtype=gram.dtype)
    return torch.linalg.solve(gram, regressors.T @ target)


def _gains(regressors: Tensor, candidates: Tensor, target: Tensor) -> tuple[Tensor, float]:
    """How much each candidate column ``[N, C]`` would lower the squared residual of the least-squares fit of
    ``target`` on ``regressors`` ``[N, r]``: ``([C], the residual's squared norm now)``."""
    basis = torch.linalg.qr(regressors).Q
    residual = target - basis @ (basis.T @ target)
    projected = candidates - basis @ (basis.T @ candidates)
    norm = projected.square().sum(0)
    gain = torch.where(norm > 1e-12 * target.shape[0], (residual @ projected).square() / norm.clamp_min(1e-300), 0.0)
    return gain, float(residual.square().sum())


def fit_hinges(features: Tensor, directions: Tensor, inputs: Tensor, target: Tensor, noise_radius: Tensor,
               max_hinges: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Hinges only (:func:`fit_features` without products): ``(directions [H, d], knots [H], coefficients [H])``."""
    fitted = fit_features(features, directions, inputs, target, noise_radius, max_hinges)
    return fitted.hinge_directions, fitted.hinge_knots, fitted.coefficients


def product_features(z: Tensor, directions: Tensor, knots: Tensor) -> Tensor:
    """``(directions[:, 0] @ z - knots[:, 0]) (directions[:, 1] @ z - knots[:, 1])``: ``[..., Q]``."""
    factors = torch.einsum("...d,qkd->...qk", z, directions) - knots
    return factors.prod(-1)


def product_relaxation(center: Tensor, radius: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The relaxation of ``s1 s2`` for factors ``s_k ∈ center_k ± radius_k`` (``[..., 2]`` each).

    With ``s_k = c_k + δ_k`` (``δ`` affine in a set's generators),
    ``s1 s2 = c2 s1 + c1 s2 - c1 c2 + δ1 δ2`` and ``|δ1 δ2| <= r1 r2`` (0 when a factor is an
    action, exact over the set).

    Args:
        center, radius: ``[..., Q, 2]``.

    Returns:
        ``(λ [..., Q, 2], κ [..., Q], ε [..., Q], low, high)``: ``s1 s2 ∈ λ1 s1 + λ2 s2 + κ ± ε``
        and ``[low, high]`` its range over the box of factors (``[..., Q]`` each).
    """
    c1, c2 = center.unbind(-1)
    r1, r2 = radius.unbind(-1)
    corners = torch.stack(((c1 - r1) * (c2 - r2), (c1 - r1) * (c2 + r2), (c1 + r1) * (c2 - r2), (c1 + r1) * (c2 + r2)))
    return torch.stack((c2, c1), -1), -c1 * c2, r1 * r2, corners.amin(0), corners.amax(0)


def hinge_features(z: Tensor, directions: Tensor, knots: Tensor) -> Tensor:
    """``relu(directions @ z - knots)``: ``[..., H]`` for ``z`` ``[..., d]``."""
    return (z @ directions.T - knots).clamp_min(0)


def relu_relaxation(center: Tensor, radius: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The relaxation of ``relu(s)`` for ``s ∈ center ± radius`` (module docstring).

    Returns:
        ``(λ, μ, low, high)``, each of ``center``'s shape: ``relu(s) ∈ λ s + μ ± μ`` for every
        ``s`` of the interval, and ``[low, high]`` the exact range of ``relu`` over it.
    """
    low, high = center - radius, center + radius
    straddles = (low < 0) & (high > 0)
    slope = torch.where(straddles, high / (high - low).clamp_min(1e-300), (low >= 0).to(center.dtype))
    offset = torch.where(straddles, -slope * low / 2, torch.zeros_like(center))
    return slope, offset, low.clamp_min(0), high.clamp_min(0)


def feature_values(z: Tensor, features: Features) -> Tensor:
    """The hinges' then the products' values: ``[..., H + Q]``."""
    return torch.cat((hinge_features(z, features.hinge_directions, features.hinge_knots),
                      product_features(z, features.product_directions, features.product_knots)), dim=-1)

