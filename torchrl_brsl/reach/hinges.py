"""Hinge features ``relu(a · z - c)`` (the kinks of saturating actuators) and state-action products, fitted once.

A servo that saturates (``v+ = v + sat(u - v)``) is affine on either side of a few
hyperplanes; a tree of affine leaves can only cut around such a kink, and a leaf that holds
the narrow linear ramp between two kinks needs more points than random data put there. A
hinge ``relu(a · z - c)`` at each kink makes the whole function affine in ``(z, h(z))``, so the
leaves' fits leave noise instead of the kink. The hinges are chosen by greedy forward
selection, as in multivariate adaptive regression splines (Friedman, "Multivariate adaptive
regression splines", Ann. Statist. 1991), over the split directions and a grid of knots, and
their coefficients are fitted once on all data: a leaf then fits its share of what the hinges
leave, so no leaf extrapolates a hinge its own data never showed bending.

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

MAX_HINGES = 8
"""Most hinges per output."""

KNOTS = 25
"""Candidate knots per direction (quantiles of the data from 3 % to 97 %)."""

MIN_GAIN = 0.1
"""A hinge is added while it removes at least this share of the remaining squared residual."""


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
                 max_features: int = MAX_HINGES, n_actions: int = 0) -> Features:
    """Hinges (and products) of one output by greedy forward selection.

    Each step adds the candidate that most reduces the squared residual of the least-squares
    fit of ``target`` on ``[1, inputs, features so far]`` (computed for all candidates at once
    by projecting them off the current regressors), until it removes less than
    :data:`MIN_GAIN` of it or the residual is down to the noise's variance. The candidates are
    ``relu(features_f - knot)`` and the products of a state input and an action input (the
    last ``n_actions`` columns), centred at the data's mean: a bicycle's heading step
    ``v tan(steer)`` is bilinear, which leaves cannot fit with few points per leaf when its
    curvature is of the noise's size. A product with an action is linear in the state over a
    set (the action is exact), so its relaxation adds no error; products of two states would
    add the product of their radii at every step. The coefficients are the features' in the
    final least-squares fit.

    Args:
        features: ``[N, f]`` ``inputs @ directions.T``.
        directions: ``[f, d]`` the candidate hinge directions.
        inputs: ``[N, d]`` scaled regressors.
        target: ``[N]`` the output.
        noise_radius: the output's noise radius ``w̄`` (uniform noise has variance ``w̄² / 3``).
        n_actions: the action columns of ``inputs`` (0: no products).
    """
    n_points, d = inputs.shape
    quantiles = torch.linspace(0.03, 0.97, KNOTS, dtype=features.dtype)
    knots = torch.quantile(features, quantiles, dim=0).T  # [f, K]
    hinges = (features.unsqueeze(-1) - knots).clamp_min(0).flatten(1)  # [N, f K]
    states, actions = torch.arange(d - n_actions), torch.arange(d - n_actions, d) if n_actions else torch.arange(0)
    pairs = torch.cartesian_prod(states, actions).T.reshape(2, -1)  # [2, C] (state, action)
    eye, mean = torch.eye(d, dtype=inputs.dtype), inputs.mean(0)
    pair_directions, pair_knots = torch.stack((eye[pairs[0]], eye[pairs[1]]), 1), mean[pairs.T]  # [C, 2, d], [C, 2]
    candidates = torch.cat((hinges, product_features(inputs, pair_directions, pair_knots)), dim=1)
    regressors = torch.cat((torch.ones(n_points, 1, dtype=inputs.dtype), inputs), dim=1)
    floor = n_points * float(noise_radius) ** 2 / 3
    chosen: list[int] = []
    for _ in range(max_features):
        gain, remaining = _gains(regressors, candidates, target)
        best = int(gain.argmax())
        if remaining <= floor or float(gain[best]) < MIN_GAIN * remaining:
            break
        chosen.append(best)
        regressors = torch.cat((regressors, candidates[:, best:best + 1]), dim=1)
    index = torch.tensor(sorted(chosen), dtype=torch.long)  # the hinges first
    hinge, product = index[index < hinges.shape[1]], index[index >= hinges.shape[1]] - hinges.shape[1]
    base = torch.cat((regressors[:, :1 + d], candidates[:, hinges.shape[1] + product]), dim=1)
    spacing = (knots[:, -1] - knots[:, 0]) / (KNOTS - 1)
    hinge_knots = refine_knots(features[:, hinge // KNOTS], knots.flatten()[hinge], spacing[hinge // KNOTS], base,
                               target, floor)
    kept = torch.isfinite(hinge_knots)
    hinge, hinge_knots = hinge[kept], hinge_knots[kept]
    regressors = torch.cat((regressors[:, :1 + d], (features[:, hinge // KNOTS] - hinge_knots).clamp_min(0),
                            base[:, 1 + d:]), dim=1)
    coefficients = torch.linalg.lstsq(regressors, target.unsqueeze(-1), driver="gelsd").solution[1 + d:, 0]
    return Features(directions[hinge // KNOTS], hinge_knots, pair_directions[product], pair_knots[product],
                    coefficients)


REFINE_STEPS = 33
"""Knot positions tried per hinge and sweep, across one candidate spacing on either side."""


def refine_knots(values: Tensor, knots: Tensor, spacing: Tensor, base: Tensor, target: Tensor, floor: float,
                 sweeps: int = 3) -> Tensor:
    """Move each selected hinge's knot off the candidate grid, then drop the hinges the others make redundant.

    The greedy selection places knots on quantiles of the data, so a kink between two of them
    is fitted by several hinges around it, leaving a residual a few times the noise (a capped
    velocity servo: 2-3.6 times). Each sweep moves one hinge at a time to the knot within
    ``± spacing`` that leaves the smallest squared residual of the least-squares fit on
    ``[base, all hinges]``, the others held fixed (coordinate descent: the residual never
    grows). Then, as in the backward pass of MARS, hinges are removed one by one while the
    one whose removal costs least removes less than :data:`MIN_GAIN` of the residual it would
    leave, or that residual is within the noise's ``floor``.

    Args:
        values: ``[N, H]`` each hinge's direction ``a · z`` on the data; knots, spacing: ``[H]``.
        base: ``[N, r]`` the regressors kept fixed (constant, inputs, products).
        target: ``[N]``.

    Returns:
        ``[H]`` the knots, ``inf`` where a hinge was dropped.
    """
    knots = knots.clone()
    offsets = torch.linspace(-1.0, 1.0, REFINE_STEPS, dtype=knots.dtype)
    for _ in range(sweeps if knots.numel() else 0):
        for h in range(knots.numel()):
            others = torch.cat((base, (values - knots).clamp_min(0)[:, torch.arange(knots.numel()) != h]), dim=1)
            trial = knots[h] + offsets * spacing[h]
            gain, _ = _gains(others, (values[:, h:h + 1] - trial).clamp_min(0), target)
            knots[h] = trial[int(gain.argmax())]
    alive = torch.ones_like(knots, dtype=torch.bool)
    while alive.any():
        costs = []
        for h in alive.nonzero()[:, 0].tolist():
            keep = alive.clone()
            keep[h] = False
            gain, remaining = _gains(torch.cat((base, (values - knots).clamp_min(0)[:, keep]), dim=1),
                                     (values[:, h:h + 1] - knots[h]).clamp_min(0), target)
            costs.append((float(gain[0]), remaining, h))
        gain, remaining, h = min(costs)
        if remaining > floor and gain >= MIN_GAIN * remaining:
            break
        alive[h] = False
    return torch.where(alive, knots, torch.inf)


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
               max_hinges: int = MAX_HINGES) -> tuple[Tensor, Tensor, Tensor]:
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

