"""Order reduction of zonotope generator matrices with a fixed output width."""
from __future__ import annotations

import torch
from torch import Tensor

from torchrl_brsl.sets._checks import check_tensor


def pad_generators(generators: Tensor, n_generators: int) -> Tensor:
    """Append zero columns so ``generators`` has exactly ``n_generators`` columns.

    Args:
        generators: ``[..., n, p]`` with ``p <= n_generators``.
        n_generators: the target column count.

    Returns:
        ``[..., n, n_generators]``.
    """
    generators = check_tensor("generators", generators, min_ndim=2)
    p = generators.shape[-1]
    if p > n_generators:
        raise ValueError(f"`n_generators`={n_generators} is smaller than the {p} generators present")
    if p == n_generators:
        return generators
    return torch.nn.functional.pad(generators, (0, n_generators - p))


def reduce_girard(generators: Tensor, n_generators: int) -> Tensor:
    """Girard's order reduction to exactly ``n_generators`` columns (zero-padded if fewer).

    The ``p - n_generators + n`` generators with the smallest ``||g||_1 - ||g||_inf`` are
    replaced by their interval hull ``diag(sum_j |g_j|)`` (``n`` columns); the others are
    kept. The result's zonotope contains the input's (same centre). Batched and
    differentiable.

    Args:
        generators: ``[..., n, p]``.
        n_generators: target width, at least ``n``.

    Returns:
        ``[..., n, n_generators]``.

    Examples:
        >>> G = torch.randn(4, 2, 30)
        >>> reduce_girard(G, 6).shape
        torch.Size([4, 2, 6])
    """
    generators = check_tensor("generators", generators, min_ndim=2)
    n, p = generators.shape[-2], generators.shape[-1]
    if n_generators < n:
        raise ValueError(f"`n_generators`={n_generators} must be at least the dimension n={n}")
    if p <= n_generators:
        return pad_generators(generators, n_generators)
    return girard_columns(generators, n_generators)


def girard_columns(generators: Tensor, n_generators: int) -> Tensor:
    """:func:`reduce_girard`'s reduction without its checks, for ``p > n_generators >= n`` columns of
    finite entries (library code whose inputs hold that by construction, e.g. a traced loop body,
    which may have no side effects such as the checks' switch)."""
    n_keep = n_generators - generators.shape[-2]
    score = generators.abs().sum(-2) - generators.abs().amax(-2)
    kept = score.topk(n_keep, dim=-1).indices  # [..., n_keep], largest first
    boxed = torch.ones_like(score).scatter(-1, kept, 0.0)  # [..., p]: 1 for the columns boxed
    box = torch.diag_embed((generators.abs() * boxed.unsqueeze(-2)).sum(-1))
    return torch.cat((generators.gather(-1, kept.unsqueeze(-2).expand(*generators.shape[:-1], n_keep)), box), dim=-1)
