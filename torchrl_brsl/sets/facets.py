"""Facet normals and the exact gauge of a zero-centred zonotope in 1-, 2- and 3-D.

A full-dimensional zonotope ``Z(0, G)`` in R^n (n <= 3) is the polytope
``{x : |h_k . x| <= sigma_k}`` whose facet normals ``h_k`` are perpendicular to n - 1 of
its generators, with ``sigma_k = sum_j |h_k . g_j|`` its support. Its gauge (Minkowski
functional) is therefore the closed form

    gauge(x) = min {t >= 0 : x in t Z(0, G)} = max_k |h_k . x| / sigma_k.

Candidate normals built from every (n-1)-subset of generators include all facet normals and
otherwise only valid supporting directions, so the maximum is exact. Zero candidates
(padding columns, parallel pairs) are masked out.
"""
from __future__ import annotations

import itertools

import torch
from torch import Tensor

_EPS = 1e-12


def facet_normals(generators: Tensor) -> Tensor:
    """Candidate facet normals of ``Z(0, generators)``.

    Args:
        generators: ``[..., n, p]`` with ``n`` in {1, 2, 3}.

    Returns:
        ``[..., K, n]`` with ``K = 1`` (n = 1), ``p`` (n = 2) or ``p (p - 1) / 2`` (n = 3).
        Rows may be zero (padding generators or parallel pairs); :func:`facet_supports`
        marks them.
    """
    n, p = generators.shape[-2], generators.shape[-1]
    if n == 1:
        return torch.ones(*generators.shape[:-2], 1, 1, dtype=generators.dtype, device=generators.device)
    if n == 2:
        gx, gy = generators[..., 0, :], generators[..., 1, :]
        return torch.stack((-gy, gx), dim=-1)
    if n == 3:
        i, j = _pairs(p, generators.device)
        g = generators.transpose(-1, -2)
        return torch.linalg.cross(g[..., i, :], g[..., j, :], dim=-1)
    raise ValueError(f"`generators` must be [..., n, p] with n in (1, 2, 3) for closed-form facets, got n={n}")


def facet_supports(normals: Tensor, generators: Tensor) -> Tensor:
    """Support ``sigma_k = sum_j |h_k . g_j|`` of ``Z(0, generators)`` along each normal.

    Args:
        normals: ``[..., K, n]``.
        generators: ``[..., n, p]``.

    Returns:
        ``[..., K]``.
    """
    return (normals @ generators).abs().sum(-1)


def gauge_from_facets(x: Tensor, normals: Tensor, supports: Tensor) -> Tensor:
    """Gauge ``max_k |h_k . x| / sigma_k`` from precomputed facet data.

    Normals whose support is (numerically) zero are ignored, which is exact for
    full-dimensional zonotopes, the only case this closed form serves.

    Args:
        x: ``[..., n]`` points relative to the zonotope centre.
        normals: ``[..., K, n]``.
        supports: ``[..., K]``.

    Returns:
        ``[...]`` the gauge value (<= 1 iff ``x`` lies in the zonotope).
    """
    valid = supports > _EPS * supports.amax(-1, keepdim=True).clamp_min(_EPS)
    ratio = (normals @ x.unsqueeze(-1)).squeeze(-1).abs() / torch.where(valid, supports, torch.ones_like(supports))
    return torch.where(valid, ratio, torch.zeros_like(ratio)).amax(-1)


def zonotope_gauge(x: Tensor, generators: Tensor) -> Tensor:
    """Exact gauge of the full-dimensional zonotope ``Z(0, generators)`` at ``x`` (n <= 3).

    Args:
        x: ``[..., n]``.
        generators: ``[..., n, p]`` of rank ``n``.

    Returns:
        ``[...]``.

    Examples:
        >>> G = torch.eye(2)
        >>> zonotope_gauge(torch.tensor([0.5, -2.0]), G)
        tensor(2.)
    """
    if generators.ndim < 2:
        raise ValueError(f"`generators` must be [..., n, p], got shape {tuple(generators.shape)}")
    if x.ndim < 1 or x.shape[-1] != generators.shape[-2]:
        raise ValueError(f"`x` must be [..., {generators.shape[-2]}] to match `generators`, got shape {tuple(x.shape)}")
    normals = facet_normals(generators)
    return gauge_from_facets(x, normals, facet_supports(normals, generators))


_PAIR_CACHE: dict[tuple[int, str], tuple[Tensor, Tensor]] = {}


def _pairs(p: int, device: torch.device) -> tuple[Tensor, Tensor]:
    key = (p, str(device))
    if key not in _PAIR_CACHE:
        pairs = list(itertools.combinations(range(p), 2))
        idx = torch.tensor(pairs, dtype=torch.long, device=device).reshape(-1, 2)
        _PAIR_CACHE[key] = (idx[:, 0], idx[:, 1])
    return _PAIR_CACHE[key]
