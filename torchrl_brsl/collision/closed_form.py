"""Exact collision check of zonotope pairs in 1-, 2- and 3-D, with cacheable facet data.

For zonotopes ``Z1 = Z(c1, G1)`` and ``Z2 = Z(c2, G2)`` the program of Selim et al. (2022),
eq. (10), ``v* = min ||z||_inf s.t. [G1, -G2] z = c2 - c1``, is the gauge of the
zero-centred zonotope ``M = Z(0, [G1, G2])`` at ``dc = c2 - c1``. When ``M`` is
full-dimensional and ``n <= 3`` that gauge has the closed form

    v* = max_k |h_k . dc| / sigma_k,        sigma_k = sum_j |h_k . g_j|,

over the candidate facet normals ``h_k`` of :func:`torchrl_brsl.sets.facet_normals`. The
same facet data gives a signed clearance ``max_k (|u_k . dc| - s_k)`` with unit normals
``u_k`` and supports ``s_k`` of ``M`` along them: the exact signed distance (minus the
penetration depth) when the sets intersect, and a lower bound on the Euclidean distance
between the sets when they do not. Both are maxima of linear functions of the centres,
hence differentiable almost everywhere.

The facet data depends on the generators only. Reachable-set generators do not depend on
the plan, so :class:`ZonotopeCollisionChecker` computes it once and each control step only
evaluates one batched product with the centre offsets.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchrl_brsl._compiling import small_matmul
from torchrl_brsl.collision.result import CollisionResult, CollisionStatus
from torchrl_brsl.sets._checks import check_same_dtype_device, check_tensor
from torchrl_brsl.sets.facets import _pairs, facet_normals, facet_supports

CLOSED_FORM_DIMS = (1, 2, 3)


class FacetTable(NamedTuple):
    """Facet data of zero-centred zonotopes ``Z(0, G)``, one row per candidate normal.

    Rows that are not valid directions (zero normals from padding or parallel generators,
    and rows added to pad a batch to a common length) have zero ``weights`` and
    ``normals`` and an infinite ``supports``, so they never attain a maximum.

    Attributes:
        weights: ``[..., K, n]`` normals scaled by their support, ``h_k / sigma_k``: the gauge
            at ``x`` is ``max_k |weights_k . x|``.
        normals: ``[..., K, n]`` unit normals ``u_k``.
        supports: ``[..., K]`` supports ``s_k = max_{x in Z} u_k . x``.
    """

    weights: Tensor
    normals: Tensor
    supports: Tensor


def facet_table(generators: Tensor, deduplicate: bool = False) -> FacetTable:
    """Facet data of ``Z(0, generators)`` (differentiable w.r.t. ``generators``).

    Args:
        generators: ``[..., n, p]`` with ``n`` in {1, 2, 3}; the zonotopes must be
            full-dimensional (see :func:`is_full_dimensional`).
        deduplicate: drop zero normals and all but one of each group of parallel normals,
            and shorten ``K`` to the largest count left in the batch. Exact (a dropped row
            repeats a kept one up to rounding) and worth it when the table is reused, e.g.
            for padded generator matrices or axis-aligned boxes; it costs ``O(K^2)`` and
            one device synchronisation.

    Returns:
        A :class:`FacetTable` with ``K = 1`` (n = 1), ``p`` (n = 2) or ``p (p - 1) / 2``
        (n = 3) rows, fewer after deduplication.

    Examples:
        >>> G = torch.tensor([[1.0, 0.0, 2.0, 0.0], [0.0, 1.0, 0.0, 0.0]])  # parallel and zero columns
        >>> facet_table(G).weights.shape, facet_table(G, deduplicate=True).weights.shape
        (torch.Size([4, 2]), torch.Size([2, 2]))
        >>> gauge_values(torch.tensor([6.0, 0.5]), facet_table(G))  # Z(0, G) = [-3, 3] x [-1, 1]
        tensor(2.)
    """
    h = facet_normals(generators)  # [..., K, n]
    return _table(h, facet_supports(h, generators), deduplicate)


def _table(h: Tensor, sigma: Tensor, deduplicate: bool) -> FacetTable:
    """The :class:`FacetTable` of candidate normals ``h`` ``[..., K, n]`` with supports ``sigma`` ``[..., K]``."""
    norm = h.norm(dim=-1)
    valid = sigma > 0
    one = torch.ones_like(sigma)
    sigma_safe = torch.where(valid, sigma, one)
    norm_safe = torch.where(valid, norm, one)
    zero = torch.zeros_like(h)
    weights = torch.where(valid.unsqueeze(-1), h / sigma_safe.unsqueeze(-1), zero)
    normals = torch.where(valid.unsqueeze(-1), h / norm_safe.unsqueeze(-1), zero)
    supports = torch.where(valid, sigma / norm_safe, torch.full_like(sigma, float("inf")))
    if deduplicate:
        keep = valid & ~_parallel_to_earlier(normals, valid)
        k_max = max(int(keep.sum(-1).amax()) if keep.numel() else 1, 1)
        order = torch.argsort((~keep).to(torch.int8), dim=-1, stable=True)[..., :k_max]
        rows = order.unsqueeze(-1).expand(*order.shape, h.shape[-1])
        kept = keep.gather(-1, order)
        weights = torch.where(kept.unsqueeze(-1), weights.gather(-2, rows), 0.0)
        normals = torch.where(kept.unsqueeze(-1), normals.gather(-2, rows), 0.0)
        supports = torch.where(kept, supports.gather(-1, order), float("inf"))
    return FacetTable(weights, normals, supports)


class PairFacets(NamedTuple):
    """Candidate facet data of ``Z(0, [G1, G2])`` for every (set, obstacle) pair, kept by owner.

    The rows come in groups: the normals of the sets' own generators, in 3-D those of a set and an
    obstacle generator, and those of the obstacles' own. Normals are stored once per owner and
    broadcast over the other's batch, so that a check never materialises every pair's ``[K, n]``
    table (:func:`pair_gauge`).

    Attributes:
        normals: per group ``[..., N_g, n]``, broadcastable to the pair batch; ``None`` for the
            group of the crosses ``g1_i × g2_j`` of ``crossed`` (``i`` major), never formed.
        supports: per group ``[..., N_g]`` over the pair batch, ``sigma_k >= sum_j |h_k . g_j|``
            (``0``: a row that is no direction).
        full: ``[...]`` whether each pair is surely full-dimensional, which the closed form needs.
        crossed: ``(G1 [..., 3, p1], G2 [..., 3, p2])`` for the group ``None``, else ``None``.
    """

    normals: tuple[Tensor | None, ...]
    supports: tuple[Tensor, ...]
    full: Tensor
    crossed: tuple[Tensor, Tensor] | None = None

    def joined(self) -> tuple[Tensor, Tensor]:
        """Every pair's normals ``[..., K, n]`` and supports ``[..., K]``, groups in order."""
        batch = self.full.shape
        normals = [self._crosses() if h is None else h for h in self.normals]
        normals = torch.cat([h.expand(*batch, *h.shape[-2:]) for h in normals], -2)
        return normals, torch.cat([s.expand(*batch, s.shape[-1]) for s in self.supports], -1)

    def _crosses(self) -> Tensor:
        g1, g2 = self.crossed
        return torch.linalg.cross(g1.mT.unsqueeze(-2), g2.mT.unsqueeze(-3), dim=-1).flatten(-3, -2)


def _planar_pair_facets(set_generators: Tensor, obstacle_generators: Tensor) -> PairFacets:
    """The :class:`PairFacets` of every pair of a 2-D batch, from the sets' own products.

    In 2-D the normals are the generators turned by 90°, ``h(g) . g' = g × g'``, so the pair's
    ``[p, p]`` support product splits into ``G1 × G1`` and ``G2 × G2`` (computed once per set and
    per obstacle, whatever the other's batch) and one ``[p1, p2]`` product ``G1 × G2`` per pair
    (its transpose, negated, is ``G2 × G1``): with ``K`` obstacles, ``p1 p1 + K 2 p1 p2`` products
    instead of ``K (p1 + p2)^2``. The same crosses give ``det(G G^T) = sum_{i<j} (g_i × g_j)^2``
    (Cauchy–Binet, a sum of squares without cancellation); a pair is reported full-dimensional
    when ``det > 16 eps tr(G G^T)^2``, which implies ``s_min^2 = det / s_max^2 > 16 eps s_max^2``
    (``s_max^2 <= tr``): at least 4x inside the test of :func:`is_full_dimensional`, so it never
    accepts a pair that test rejects (a pair it declines goes through that test).

    Args:
        set_generators: ``[..., 2, p1]``.
        obstacle_generators: ``[..., 2, p2]``; batch shapes broadcast.

    Returns:
        Two groups, the sets' ``p1`` normals then the obstacles' ``p2`` (the rows of
        ``facet_normals(cat(G1, G2))`` in their order).
    """
    g1, g2 = set_generators, obstacle_generators
    h1, h2 = facet_normals(g1), facet_normals(g2)
    own1, own2 = small_matmul(h1, g1), small_matmul(h2, g2)  # [S1, p1, p1], [S2, p2, p2]
    if torch.compiler.is_compiling():  # summed by hand: fused into the kernels around it, no BLAS call per check
        cross = small_matmul(h1, g2).abs()
    else:  # einsum: one product per owner
        cross = torch.einsum("...in,...nj->...ij", h1, g2).abs_()  # [..., p1, p2]
    supports = (own1.abs().sum(-1) + cross.sum(-1), own2.abs().sum(-1) + cross.sum(-2))
    floor = 16 * torch.finfo(g1.dtype).eps * _squared_norm(g1, g2).square()  # tr(G G^T) >= lambda_max
    full = _full_pairs((_squared_norm(own1) + _squared_norm(own2)) / 2, (cross,), floor)
    return PairFacets((h1, h2), supports, full.expand(cross.shape[:-2]))


def _spatial_pair_facets(set_generators: Tensor, obstacle_generators: Tensor) -> PairFacets:
    """:func:`_planar_pair_facets` in 3-D. The normals ``g1_i × g1_k`` of two set generators are the
    set's own (their supports over ``G1`` computed once per set), those of two obstacle generators
    the obstacle's own; per pair only the products ``X = (g1_i × g1_k) . g2_j`` and ``Z = (g2_j ×
    g2_l) . g1_i`` are formed (``p1 (p1 - 1) p2 / 2 + p2 (p2 - 1) p1 / 2``). The mixed normals
    ``g1_i × g2_j`` need neither a vector nor products of their own: by the triple product
    ``|(g1_i × g2_j) . g1_k| = |X_{ik,j}|`` and ``|(g1_i × g2_j) . g2_l| = |Z_{jl,i}|``, so their supports
    are sums of the same entries (one product with each side's pair incidence). Those supports are
    raised by a bound on the rounding of the identity, ``(p1 + p2 + 32) eps |g1_i| |g2_j| sum_k |g_k|``:
    a nearly parallel ``g1_i, g2_j`` has a crossed vector of rounding size whose support the triple
    products do not measure, and without the bound its row could claim a gauge above the true one
    (a collision missed); with it every row's value is a lower bound of the gauge, and the bound is
    ``1e-13`` of a well-conditioned row's support. Every triple's determinant appears once in ``X``
    or ``Z`` or three times in the own products, which gives ``det(G G^T)`` by Cauchy–Binet; a pair
    is full when ``det > 16 eps tr^3``: then ``s_min^2 >= det / tr^2 > 16 eps s_max^2``.

    Returns:
        Three groups: the sets' ``p1 (p1 - 1) / 2`` normals, the pairs' ``p1 p2`` crosses (``None``,
        see :class:`PairFacets`) and the obstacles' ``p2 (p2 - 1) / 2``: the rows of
        ``facet_normals(cat(G1, G2))`` in another order.
    """
    g1, g2 = set_generators, obstacle_generators
    p1, p2 = g1.shape[-1], g2.shape[-1]
    h11, h22 = facet_normals(g1), facet_normals(g2)  # [S1, N1, 3], [S2, N2, 3]
    own1, own2 = h11 @ g1, h22 @ g2  # [S1, N1, p1], [S2, N2, p2]
    # einsum: one product per owner, not per pair; contiguous: the reductions below run along rows
    x = torch.einsum("...fn,...nj->...jf", h11, g2).contiguous().abs_()  # [..., p2, N1]
    z = torch.einsum("...fn,...ni->...if", h22, g1).contiguous().abs_()  # [..., p1, N2]
    mixed = (x @ _incidence(p1, g1)).mT + z @ _incidence(p2, g2)  # [..., p1, p2]
    mixed = mixed + _triple_rounding(g1, g2)
    supports = (own1.abs().sum(-1) + x.sum(-2), mixed.flatten(-2), own2.abs().sum(-1) + z.sum(-2))
    floor = 16 * torch.finfo(g1.dtype).eps * _squared_norm(g1, g2) ** 3
    full = _full_pairs((_squared_norm(own1) + _squared_norm(own2)) / 3, (x, z), floor)
    return PairFacets((h11, None, h22), supports, full.expand(mixed.shape[:-2]), (g1, g2))


def _triple_rounding(g1: Tensor, g2: Tensor) -> Tensor:
    """``(p1 + p2 + 32) eps |g1_i| |g2_j| sum_k |g_k|`` ``[..., p1, p2]``: what rounding may take from a mixed row's
    support computed by the triple product (the crossed vector's, the products' and the sums' rounding)."""
    norms1, norms2 = g1.norm(dim=-2), g2.norm(dim=-2)  # [S1, p1], [S2, p2]
    total = norms1.sum(-1) + norms2.sum(-1)
    units = (g1.shape[-1] + g2.shape[-1] + 32) * torch.finfo(g1.dtype).eps
    return units * norms1.unsqueeze(-1) * norms2.unsqueeze(-2) * total[..., None, None]


def _full_pairs(own: Tensor, mixed: tuple[Tensor, ...], floor: Tensor) -> Tensor:
    """``det(G G^T) > floor`` per pair, ``det = own + sum ||M||_F^2`` over ``mixed`` (Cauchy–Binet: ``own`` the
    squared minors of each side's own generators, computed per set and per obstacle, ``mixed`` the pairs' mixed
    products). The mixed terms only add, so where ``own`` alone clears the floor for every pair (a set that is
    full-dimensional on its own, as the sets with noise are) the mixed products, the pairs' largest tensors, are
    not summed: the same answer without a pass over them. Compiled (a graph cannot branch on values), ``own > floor``
    alone: it may decline a pair the mixed terms would clear, which the caller then checks eagerly
    (:meth:`~torchrl_brsl.safety.PlanChecker.evaluate_with_gauge`)."""
    full = own > floor
    if torch.compiler.is_compiling() or bool(full.all()):
        return full
    for matrix in mixed:
        own = own + _squared_norm(matrix)
    return own > floor


def _squared_norm(*matrices: Tensor) -> Tensor:
    """``sum ||M||_F^2`` over the last two dims of each, broadcast: ``[...]`` (one reduction, no squares formed)."""
    return sum(torch.linalg.vector_norm(m, dim=(-2, -1)).square() for m in matrices)


_INCIDENCE: dict[tuple[int, torch.dtype, str], Tensor] = {}


def _incidence(p: int, like: Tensor) -> Tensor:
    """``[p (p - 1) / 2, p]``: 1 where generator ``i`` is in the pair (pairs in :func:`facet_normals`'s order)."""
    key = (p, like.dtype, str(like.device))
    if key not in _INCIDENCE:
        i, k = _pairs(p, like.device)
        rows = torch.arange(len(i), device=like.device)
        incidence = torch.zeros(len(i), p, dtype=like.dtype, device=like.device)
        incidence[rows, i] = 1.0
        incidence[rows, k] = 1.0
        _INCIDENCE[key] = incidence
    return _INCIDENCE[key]


#: per dimension, the normals and supports of every (set, obstacle) pair from the sets' own products
_PAIR_FACETS = {2: _planar_pair_facets, 3: _spatial_pair_facets}


def pair_facets(set_generators: Tensor, obstacle_generators: Tensor, widen: bool = False) -> PairFacets:
    """The :class:`PairFacets` of ``Z(0, [G1, G2])`` for every pair of the broadcast batch (unchecked input).

    In 2-D and 3-D by owner (:data:`_PAIR_FACETS`) when every pair is surely full-dimensional;
    otherwise one group from each pair's own products, where the singular values decide and flat
    pairs are widened (``widen``, see :class:`ZonotopeCollisionChecker`) or refused.

    Args:
        set_generators: ``[..., n, p1]``, ``n`` in {1, 2, 3}.
        obstacle_generators: ``[..., n, p2]``.
    """
    g1, g2 = set_generators, obstacle_generators
    n = g1.shape[-2]
    if n in _PAIR_FACETS:
        split = split_pair_facets(g1, g2)
        if bool(split.full.all()):
            return split
    batch = torch.broadcast_shapes(g1.shape[:-2], g2.shape[:-2])
    generators = widened_pairs(g1, g2, batch, widen)
    normals = facet_normals(generators)
    full = torch.ones(batch, dtype=torch.bool, device=g1.device)
    return PairFacets((normals,), (facet_supports(normals, generators),), full)


def split_pair_facets(set_generators: Tensor, obstacle_generators: Tensor) -> PairFacets:
    """:func:`pair_facets` by owner in 2-D and 3-D, without its fallback: valid for the pairs its ``full`` marks
    (no branch on values, so it traces into one compiled graph).

    Args:
        set_generators: ``[..., n, p1]``, ``n`` in {2, 3}.
        obstacle_generators: ``[..., n, p2]``.
    """
    return _PAIR_FACETS[set_generators.shape[-2]](set_generators, obstacle_generators)


def widened_pairs(g1: Tensor, g2: Tensor, batch: torch.Size, widen: bool) -> Tensor:
    """``[G1, G2]`` of every pair, :data:`WIDEN_SHARE` boxes on the flat ones (``widen``), else a ``ValueError``."""
    generators = torch.cat((g1.expand(*batch, *g1.shape[-2:]), g2.expand(*batch, *g2.shape[-2:])), dim=-1)
    full = is_full_dimensional(generators)
    if bool(full.all()):
        return generators
    if not widen:
        raise ValueError(
            "`set_generators` and `obstacle_generators`: Z(0, [G1, G2]) is not full-dimensional for some "
            "pair; the closed form does not apply (use collision_value(..., backend='lp'))"
        )
    n = generators.shape[-2]
    radius = torch.where(full, 0.0, WIDEN_SHARE * generators.norm(dim=(-2, -1)))
    return torch.cat((generators, torch.diag_embed(radius.unsqueeze(-1).expand(*radius.shape, n))), -1)


def pair_gauge(offsets: Tensor, facets: PairFacets) -> tuple[Tensor, Tensor, Tensor]:
    """The closed-form value of every pair at ``offsets`` ``[..., n]`` (obstacle centre minus set centre)
    and its attaining row, without forming any pair's table.

    Returns:
        ``(values [...], picked [...], weights [..., n])``: ``v* = max_k |h_k . x| / sigma_k``, the
        signed ``h_k . x / sigma_k`` of the row attaining it and that row's ``h_k / sigma_k``
        (zeros where no row is a direction). Differentiable w.r.t. ``offsets``.
    """
    ratios = []
    for normals, supports in zip(facets.normals, facets.supports):
        if normals is None:  # (g1_i × g2_j) . x = g1_i . (g2_j × x)
            g1, g2 = facets.crossed
            turned = torch.linalg.cross(*torch.broadcast_tensors(g2.mT, offsets.unsqueeze(-2)))  # [..., p2, 3]
            products = torch.einsum("...ni,...jn->...ij", g1, turned).flatten(-2)
        elif torch.compiler.is_compiling():  # summed by hand, as in :func:`_planar_pair_facets`
            products = small_matmul(normals, offsets.unsqueeze(-1)).squeeze(-1)
        else:
            products = torch.einsum("...fn,...n->...f", normals, offsets)
        valid = supports > 0
        ratios.append(torch.where(valid, products / torch.where(valid, supports, 1.0), 0.0))
    ratios = torch.cat(ratios, -1)
    values, best = ratios.abs().max(-1)
    picked = ratios.gather(-1, best.unsqueeze(-1)).squeeze(-1)
    return values, picked, _picked_weights(facets, best, offsets.shape[-1])


def _picked_weights(facets: PairFacets, best: Tensor, n: int) -> Tensor:
    """``h_k / sigma_k`` ``[..., n]`` of the rows ``best`` ``[...]`` (indices into the groups in order)."""
    weights = torch.zeros(*best.shape, n, dtype=facets.supports[0].dtype, device=best.device)
    start = 0
    for normals, supports in zip(facets.normals, facets.supports):
        count = supports.shape[-1]
        index = (best - start).clamp(0, count - 1)
        if normals is None:
            g1, g2 = (g.mT.expand(*best.shape, *g.mT.shape[-2:]) for g in facets.crossed)
            p2 = g2.shape[-2]
            rows = torch.linalg.cross(rows_at(g1, index // p2), rows_at(g2, index % p2))
        else:
            rows = rows_at(normals.expand(*best.shape, count, n), index)
        sigma = supports.expand(*best.shape, count).gather(-1, index.unsqueeze(-1))
        valid = (best >= start) & (best < start + count) & (sigma.squeeze(-1) > 0)
        weights = torch.where(valid.unsqueeze(-1), rows / torch.where(sigma > 0, sigma, 1.0), weights)
        start += count
    return weights


def rows_at(matrix: Tensor, index: Tensor) -> Tensor:
    """``matrix[..., index, :]`` for ``matrix`` ``[..., R, n]`` and ``index`` ``[...]``: ``[..., n]`` (one row per
    batch entry, e.g. the facet attaining each value)."""
    return matrix.gather(-2, index[..., None, None].expand(*index.shape, 1, matrix.shape[-1])).squeeze(-2)


def is_full_dimensional(generators: Tensor) -> Tensor:
    """Whether each ``Z(0, generators)`` has a non-empty interior: bool ``[...]``.

    The test is ``s_min(G) > sqrt(eps) * s_max(G)`` on the singular values of ``G``. It
    also certifies the closed form: every unit direction ``u`` then has the support
    ``||G^T u||_1 >= s_min(G) > 0``.

    Args:
        generators: ``[..., n, p]``.

    Examples:
        >>> is_full_dimensional(torch.tensor([[[1.0, 1.0], [0.0, 1.0]], [[1.0, 2.0], [1.0, 2.0]]]))
        tensor([ True, False])
    """
    if generators.shape[-1] < generators.shape[-2]:
        return torch.zeros(generators.shape[:-2], dtype=torch.bool, device=generators.device)
    s = torch.linalg.svdvals(generators.detach())
    rtol = torch.finfo(generators.dtype).eps ** 0.5
    return s[..., -1] > rtol * s[..., 0]


def gauge_values(offsets: Tensor, table: FacetTable) -> Tensor:
    """``v* = max_k |weights_k . offsets|``: ``[...]`` for ``offsets`` ``[..., n]``."""
    return (table.weights @ offsets.unsqueeze(-1)).squeeze(-1).abs().amax(-1)


def facet_clearances(offsets: Tensor, table: FacetTable) -> Tensor:
    """``max_k (|normals_k . offsets| - supports_k)``: ``[...]`` for ``offsets`` ``[..., n]``."""
    return ((table.normals @ offsets.unsqueeze(-1)).squeeze(-1).abs() - table.supports).amax(-1)


def finite_offsets(offsets: Tensor) -> tuple[Tensor, Tensor]:
    """Zero the offsets that hold a NaN or infinity; also return the finite mask ``[...]``."""
    finite = torch.isfinite(offsets).all(-1)
    return torch.where(finite.unsqueeze(-1), offsets, torch.zeros_like(offsets)), finite


WIDEN_SHARE = 1e-7
"""Half-width of the box (a share of ``||[G1, G2]||_F``) that makes a flat pair full-dimensional: above
the ``sqrt(eps) ≈ 1.5e-8`` of :func:`is_full_dimensional`, since ``s_max <= ||[G1, G2]||_F``."""


class ZonotopeCollisionChecker:
    """Exact collision values of zonotope pairs with fixed generators, for many centres.

    Computes the facet table of ``Z(0, [G1, G2])`` once for every (set, obstacle) pair of
    the broadcast generator batch (in 2-D and 3-D from each set's and each obstacle's own
    products and the pairs' crosses, :data:`_PAIR_FACETS`); afterwards :meth:`value`, :meth:`clearance` and
    :meth:`check` cost one batched product with the centre offsets, have no Python loop
    over pairs, do not synchronise with the device, and are differentiable w.r.t. both
    centres. The table is detached: for gradients w.r.t. generators use
    :func:`torchrl_brsl.collision.collision_value`.

    A typical safety-layer use: the generators of the ``H`` reachable sets of a plan, shaped
    ``[H, 1, n, p1]``, against the ``K`` obstacles of an episode, ``[1, K, n, p2]``; then at
    every step the centres ``[B, H, 1, n]`` and ``[B, 1, K, n]`` give ``[B, H, K]`` values.

    Non-finite centres never raise and never pass as safe: their pairs get ``value = 0``
    and ``clearance = 0`` (colliding), and :meth:`check` reports them.

    Args:
        set_generators: ``[..., n, p1]`` with ``n`` in {1, 2, 3}.
        obstacle_generators: ``[..., n, p2]``; batch shapes broadcast with ``set_generators``.
        deduplicate: see :func:`facet_table` (default ``True``).
        widen: a pair whose ``Z(0, [G1, G2])`` is not full-dimensional (numerically: a 100 m
            flat obstacle beside a set of 1e-6 m) gets a box of :data:`WIDEN_SHARE` of its size
            added instead of raising; its value can then only be smaller (a larger set is
            stricter), so a safety check stays sound and never fails mid-episode.

    Raises:
        ValueError: naming the argument, for non-tensors, non-floating or non-finite
            entries, mismatched dimensions or dtypes, batch shapes that do not broadcast,
            ``n > 3``, or (without ``widen``) a pair whose ``Z(0, [G1, G2])`` is not full-dimensional.

    Examples:
        >>> box = torch.eye(2)
        >>> checker = ZonotopeCollisionChecker(box.expand(3, 1, 2, 2), box.expand(1, 2, 2, 2))
        >>> set_centers = torch.tensor([[0.0, 0.0], [3.0, 0.0], [10.0, 0.0]]).unsqueeze(1)
        >>> obstacle_centers = torch.tensor([[1.0, 0.0], [4.0, 1.0]]).unsqueeze(0)
        >>> checker.value(set_centers, obstacle_centers)
        tensor([[0.5000, 2.0000],
                [1.0000, 0.5000],
                [4.5000, 3.0000]])
        >>> checker.clearance(set_centers, obstacle_centers)
        tensor([[-1.,  2.],
                [ 0., -1.],
                [ 7.,  4.]])
    """

    def __init__(self, set_generators: Tensor, obstacle_generators: Tensor, *, deduplicate: bool = True,
                 widen: bool = False):
        g1 = check_tensor("set_generators", set_generators, min_ndim=2).detach()
        g2 = check_tensor("obstacle_generators", obstacle_generators, min_ndim=2).detach()
        check_same_dtype_device(set_generators=g1, obstacle_generators=g2)
        n = g1.shape[-2]
        if n not in CLOSED_FORM_DIMS:
            raise ValueError(f"`set_generators` must be [..., n, p1] with n in {CLOSED_FORM_DIMS}, got n={n}")
        if g2.shape[-2] != n:
            raise ValueError(
                f"`obstacle_generators` must be [..., {n}, p2] like `set_generators`, got {tuple(g2.shape)}")
        self.batch_shape = _broadcast("obstacle_generators", g2.shape[:-2], g1.shape[:-2])
        self.table = _table(*pair_facets(g1, g2, widen).joined(), deduplicate)
        self.dim = n

    @property
    def n_facets(self) -> int:
        """Rows of the facet table per pair (after deduplication)."""
        return self.table.weights.shape[-2]

    def offsets(self, set_centers: Tensor, obstacle_centers: Tensor) -> Tensor:
        """``obstacle_centers - set_centers`` (broadcast), checked for shape only: ``[..., n]``."""
        for name, value in (("set_centers", set_centers), ("obstacle_centers", obstacle_centers)):
            if value.ndim < 1 or value.shape[-1] != self.dim:
                raise ValueError(f"`{name}` must be [..., {self.dim}], got shape {tuple(value.shape)}")
        return obstacle_centers - set_centers

    def value(self, set_centers: Tensor, obstacle_centers: Tensor) -> Tensor:
        """``v*`` of every pair; ``<= 1`` iff the sets intersect.

        Args:
            set_centers: ``[..., n]``.
            obstacle_centers: ``[..., n]``; batch shapes broadcast with each other and with
                the checker's generator batch.

        Returns:
            ``[...]`` the broadcast batch shape.
        """
        offsets, finite = finite_offsets(self.offsets(set_centers, obstacle_centers))
        return torch.where(finite, gauge_values(offsets, self.table), 0.0)

    def clearance(self, set_centers: Tensor, obstacle_centers: Tensor) -> Tensor:
        """Signed clearance of every pair (see the module docstring); arguments as in :meth:`value`."""
        offsets, finite = finite_offsets(self.offsets(set_centers, obstacle_centers))
        return torch.where(finite, facet_clearances(offsets, self.table), 0.0)

    def check(self, set_centers: Tensor, obstacle_centers: Tensor, with_clearance: bool = True) -> CollisionResult:
        """Values, clearances and status codes of every pair (no device synchronisation).

        Args:
            set_centers: see :meth:`value`.
            obstacle_centers: see :meth:`value`.
            with_clearance: also compute the clearance (otherwise ``clearance`` is ``None``).
        """
        offsets, finite = finite_offsets(self.offsets(set_centers, obstacle_centers))
        value = torch.where(finite, gauge_values(offsets, self.table), 0.0)
        clear = torch.where(finite, facet_clearances(offsets, self.table), 0.0) if with_clearance else None
        reason = torch.where(finite, int(CollisionStatus.OK), int(CollisionStatus.NONFINITE)).to(torch.int8)
        return CollisionResult(value, clear, finite.expand(value.shape), reason.expand(value.shape))


def _parallel_to_earlier(normals: Tensor, valid: Tensor) -> Tensor:
    """Rows whose unit normal is (anti)parallel to a valid earlier row, up to rounding."""
    cos = (normals @ normals.transpose(-1, -2)).abs()
    tol = 1 - 8 * torch.finfo(normals.dtype).eps
    k = normals.shape[-2]
    earlier = torch.ones(k, k, dtype=torch.bool, device=normals.device).tril(-1)
    return ((cos >= tol) & earlier & valid.unsqueeze(-2)).any(-1)


def _broadcast(name: str, shape, batch) -> torch.Size:
    """``broadcast_shapes(shape, batch)`` or a ``ValueError`` naming the argument ``name``."""
    try:
        return torch.broadcast_shapes(torch.Size(shape), torch.Size(batch))
    except RuntimeError as err:
        raise ValueError(
            f"`{name}` has batch shape {tuple(shape)}, which does not broadcast with {tuple(batch)}") from err


__all__ = [
    "FacetTable",
    "PairFacets",
    "ZonotopeCollisionChecker",
    "facet_clearances",
    "facet_table",
    "finite_offsets",
    "gauge_values",
    "is_full_dimensional",
    "pair_facets",
    "pair_gauge",
    "rows_at",
    "split_pair_facets",
    "widened_pairs",
]
