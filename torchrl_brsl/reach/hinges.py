"""Hinge features ``relu(a · z - c)``: the kinks of saturating actuators, fitted once over all data.

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
"""
from __future__ import annotations

import torch
from torch import Tensor

MAX_HINGES = 8
"""Most hinges per output."""

KNOTS = 25
"""Candidate knots per direction (quantiles of the data from 3 % to 97 %)."""

MIN_GAIN = 0.1
"""A hinge is added while it removes at least this share of the remaining squared residual."""


def fit_hinges(features: Tensor, directions: Tensor, inputs: Tensor, target: Tensor, noise_radius: Tensor,
               max_hinges: int = MAX_HINGES) -> tuple[Tensor, Tensor, Tensor]:
    """Hinges of one output by greedy forward selection: ``(directions [H, d], knots [H], coefficients [H])``.

    Each step adds the candidate ``relu(features_f - knot)`` that most reduces the squared
    residual of the least-squares fit of ``target`` on ``[1, inputs, hinges so far]`` (computed
    for all candidates at once by projecting them off the current regressors), until it
    removes less than :data:`MIN_GAIN` of it or the residual is down to the noise's variance.
    The coefficients are the hinges' in the final least-squares fit.

    Args:
        features: ``[N, f]`` ``inputs @ directions.T``.
        directions: ``[f, d]`` the candidate directions.
        inputs: ``[N, d]`` scaled regressors.
        target: ``[N]`` the output.
        noise_radius: the output's noise radius ``w̄`` (uniform noise has variance ``w̄² / 3``).
    """
    n_points = inputs.shape[0]
    quantiles = torch.linspace(0.03, 0.97, KNOTS, dtype=features.dtype)
    knots = torch.quantile(features, quantiles, dim=0).T  # [f, K]
    candidates = (features.unsqueeze(-1) - knots).clamp_min(0).flatten(1)  # [N, f K]
    regressors = torch.cat((torch.ones(n_points, 1, dtype=inputs.dtype), inputs), dim=1)
    floor = n_points * float(noise_radius) ** 2 / 3
    chosen: list[int] = []
    for _ in range(max_hinges):
        basis = torch.linalg.qr(regressors).Q
        residual = target - basis @ (basis.T @ target)
        remaining = float(residual.square().sum())
        if remaining <= floor:
            break
        projected = candidates - basis @ (basis.T @ candidates)
        norm = projected.square().sum(0)
        gain = torch.where(norm > 1e-12 * n_points, (residual @ projected).square() / norm.clamp_min(1e-300), 0.0)
        best = int(gain.argmax())
        if float(gain[best]) < MIN_GAIN * remaining:
            break
        chosen.append(best)
        regressors = torch.cat((regressors, candidates[:, best:best + 1]), dim=1)
    index = torch.tensor(chosen, dtype=torch.long)
    coefficients = torch.linalg.lstsq(regressors, target.unsqueeze(-1), driver="gelsd").solution[1 + inputs.shape[1]:]
    return directions[index // KNOTS], knots.flatten()[index], coefficients[:, 0]


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
