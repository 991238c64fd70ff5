"""Batched zonotopes ``Z(c, G) = {c + G z : ||z||_inf <= 1}``."""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from torchrl_brsl.sets._checks import (
    broadcast_batch,
    check_dims,
    check_last_dim,
    check_same_dtype_device,
    check_tensor,
    default_tol,
)
from torchrl_brsl.sets._tensorclass import documented_tensorclass
from torchrl_brsl.sets.facets import facet_normals, facet_supports, gauge_from_facets
from torchrl_brsl.sets.lp import gauge_lp
from torchrl_brsl.sets.reduction import pad_generators, reduce_girard


@documented_tensorclass
class Zonotope:
    """A batch of zonotopes ``{c + G z : ||z||_inf <= 1}``.

    A tensorclass: it indexes, stacks, moves across devices and sits inside a TensorDict like
    any tensor collection. Its batch shape is ``center.shape[:-1]``. All operations broadcast
    over batch dimensions and are differentiable.

    Args:
        center: ``[..., n]``.
        generators: ``[..., n, p]`` (``p`` may be 0).

    Examples:
        >>> z = Zonotope(torch.zeros(2), torch.tensor([[1.0, 0.5], [0.0, 0.5]]))
        >>> z.interval()
        (tensor([-1.5000, -0.5000]), tensor([1.5000, 0.5000]))
        >>> (torch.eye(2) * 2 @ z).generators
        tensor([[2., 1.],
                [0., 1.]])
        >>> z.contains(torch.tensor([1.4, 0.4]))
        tensor(True)
    """

    center: Tensor
    generators: Tensor

    def __post_init__(self):
        c = check_tensor("center", self.center, min_ndim=1)
        g = check_tensor("generators", self.generators, min_ndim=2)
        check_same_dtype_device(center=c, generators=g)
        if g.shape[:-1] != c.shape:
            raise ValueError(
                f"`generators` must have shape [..., n, p] matching `center` [..., n]; got center "
                f"{tuple(c.shape)} and generators {tuple(g.shape)}"
            )
        self.batch_size = c.shape[:-1]

    # ----------------------------------------------------------------- constructors
    @classmethod
    def from_interval(cls, lo: Tensor, hi: Tensor) -> Zonotope:
        """The axis-aligned box ``[lo, hi]`` (``[..., n]`` each, ``lo <= hi``)."""
        lo = check_tensor("lo", lo, min_ndim=1)
        hi = check_tensor("hi", hi, min_ndim=1)
        if lo.shape != hi.shape:
            raise ValueError(f"`lo` {tuple(lo.shape)} and `hi` {tuple(hi.shape)} must have the same shape")
        if bool((lo > hi).any()):
            raise ValueError("`lo` must be elementwise <= `hi`")
        return cls((lo + hi) / 2, torch.diag_embed((hi - lo) / 2))

    @classmethod
    def from_box(cls, center: Tensor, half_extents: Tensor, rotation: Tensor | None = None) -> Zonotope:
        """An oriented box ``center + rotation @ diag(half_extents) z``.

        Args:
            center: ``[..., n]``.
            half_extents: ``[..., n]`` (non-negative).
            rotation: optional ``[..., n, n]`` whose columns are the box axes.
        """
        half_extents = check_tensor("half_extents", half_extents, min_ndim=1)
        if bool((half_extents < 0).any()):
            raise ValueError("`half_extents` must be non-negative")
        n = half_extents.shape[-1]
        center = check_tensor("center", center, min_ndim=1)
        check_last_dim("center", center, n)
        generators = torch.diag_embed(half_extents)
        if rotation is not None:
            rotation = check_tensor("rotation", rotation, min_ndim=2)
            if rotation.shape[-2:] != (n, n):
                raise ValueError(f"`rotation` must be [..., {n}, {n}], got shape {tuple(rotation.shape)}")
            broadcast_batch("rotation", rotation.shape[:-2], half_extents.shape[:-1])
            check_same_dtype_device(half_extents=half_extents, rotation=rotation)
            generators = rotation @ generators
        broadcast_batch("center", center.shape[:-1], generators.shape[:-2])
        center, generators = _broadcast_set(center, generators)
        return cls(center, generators)

    @classmethod
    def from_point(cls, point: Tensor) -> Zonotope:
        """The singleton ``{point}`` (no generators)."""
        point = check_tensor("point", point, min_ndim=1)
        return cls(point, point.new_zeros(*point.shape, 0))

    # ----------------------------------------------------------------- properties
    @property
    def dim(self) -> int:
        """Ambient dimension ``n``."""
        return self.center.shape[-1]

    @property
    def n_generators(self) -> int:
        """Number of generator columns ``p``."""
        return self.generators.shape[-1]

    def radius(self) -> Tensor:
        """Half-widths of the interval hull, ``sum_j |g_j|``: ``[..., n]``."""
        return self.generators.abs().sum(-1)

    def interval(self) -> tuple[Tensor, Tensor]:
        """Tight interval hull ``(lo, hi)``, each ``[..., n]``."""
        r = self.radius()
        return self.center - r, self.center + r

    def support(self, direction: Tensor) -> Tensor:
        """Support function ``max_{x in Z} d . x`` for ``direction`` ``[..., n]``: ``[...]``."""
        direction = check_tensor("direction", direction, min_ndim=1)
        check_last_dim("direction", direction, self.dim)
        broadcast_batch("direction", direction.shape[:-1], self.batch_size)
        check_same_dtype_device(center=self.center, direction=direction)
        return (direction * self.center).sum(-1) + (direction.unsqueeze(-2) @ self.generators).abs().sum(-1).squeeze(-1)

    # ----------------------------------------------------------------- algebra
    def linear_map(self, matrix: Tensor) -> Zonotope:
        """``M Z = Z(M c, M G)`` for ``matrix`` ``[..., k, n]``."""
        matrix = check_tensor("matrix", matrix, min_ndim=2)
        if matrix.shape[-1] != self.dim:
            raise ValueError(f"`matrix` has {matrix.shape[-1]} columns but the set is {self.dim}-dimensional")
        broadcast_batch("matrix", matrix.shape[:-2], self.batch_size)
        check_same_dtype_device(center=self.center, matrix=matrix)
        return Zonotope((matrix @ self.center.unsqueeze(-1)).squeeze(-1), matrix @ self.generators)

    def __rmatmul__(self, matrix: Tensor) -> Zonotope:
        return self.linear_map(matrix)

    def minkowski_sum(self, other: Zonotope) -> Zonotope:
        """``Z1 + Z2 = Z(c1 + c2, [G1, G2])`` (batch shapes broadcast)."""
        if not isinstance(other, Zonotope):
            raise ValueError(f"`other` must be a Zonotope, got {type(other).__name__}")
        _check_same_dim(self, other)
        batch = broadcast_batch("other", other.batch_size, self.batch_size)
        g1 = self.generators.expand(*batch, *self.generators.shape[-2:])
        g2 = other.generators.expand(*batch, *other.generators.shape[-2:])
        return Zonotope(self.center + other.center, torch.cat((g1, g2), dim=-1))

    def translate(self, offset: Tensor) -> Zonotope:
        """``Z + offset`` for ``offset`` ``[..., n]``."""
        offset = check_tensor("offset", offset, min_ndim=1)
        check_last_dim("offset", offset, self.dim)
        broadcast_batch("offset", offset.shape[:-1], self.batch_size)
        center, generators = _broadcast_set(self.center + offset, self.generators)
        return Zonotope(center, generators)

    def __add__(self, other):
        if isinstance(other, Zonotope):
            return self.minkowski_sum(other)
        if isinstance(other, Tensor):
            return self.translate(other)
        return NotImplemented

    __radd__ = __add__

    def __sub__(self, other):
        if isinstance(other, Tensor):
            return self.translate(-other)
        return NotImplemented

    def __neg__(self) -> Zonotope:
        return Zonotope(-self.center, -self.generators)

    def cartesian_product(self, other: Zonotope) -> Zonotope:
        """``Z1 x Z2 = Z([c1; c2], blkdiag(G1, G2))`` (batch shapes broadcast)."""
        if not isinstance(other, Zonotope):
            raise ValueError(f"`other` must be a Zonotope, got {type(other).__name__}")
        batch = broadcast_batch("other", other.batch_size, self.batch_size)
        c1 = self.center.expand(*batch, self.dim)
        c2 = other.center.expand(*batch, other.dim)
        g1 = self.generators.expand(*batch, *self.generators.shape[-2:])
        g2 = other.generators.expand(*batch, *other.generators.shape[-2:])
        top = torch.cat((g1, g1.new_zeros(*batch, self.dim, other.n_generators)), dim=-1)
        bottom = torch.cat((g2.new_zeros(*batch, other.dim, self.n_generators), g2), dim=-1)
        return Zonotope(torch.cat((c1, c2), dim=-1), torch.cat((top, bottom), dim=-2))

    def project(self, dims: Sequence[int]) -> Zonotope:
        """Projection onto the coordinates ``dims``."""
        dims = check_dims("dims", dims, self.dim)
        return Zonotope(self.center[..., dims], self.generators[..., dims, :])

    def reduce(self, n_generators: int) -> Zonotope:
        """Girard order reduction to exactly ``n_generators`` columns (an outer approximation)."""
        return Zonotope(self.center, reduce_girard(self.generators, n_generators))

    def pad(self, n_generators: int) -> Zonotope:
        """Append zero generators up to ``n_generators`` columns (the set is unchanged)."""
        return Zonotope(self.center, pad_generators(self.generators, n_generators))

    def to_constrained(self):
        """The same set as a :class:`ConstrainedZonotope` with no constraints."""
        from torchrl_brsl.sets.constrained_zonotope import ConstrainedZonotope

        return ConstrainedZonotope.from_zonotope(self)

    # ----------------------------------------------------------------- queries
    def is_empty(self) -> Tensor:
        """Zonotopes are never empty: ``False`` for every batch element."""
        return torch.zeros(self.batch_size, dtype=torch.bool, device=self.center.device)

    def contains(self, points: Tensor, tol: float | None = None) -> Tensor:
        """Whether ``points`` ``[..., n]`` lie in the set (broadcast with the batch).

        Exact closed form for full-dimensional sets in 1-3 D, HiGHS otherwise. ``tol`` is
        the slack on the gauge (default: 1e-9 in float64, 1e-5 otherwise).
        Returns a bool tensor of the broadcast batch shape.
        """
        points = check_tensor("points", points, min_ndim=1)
        if points.shape[-1] != self.dim:
            raise ValueError(f"`points` must have last dimension {self.dim}, got {tuple(points.shape)}")
        broadcast_batch("points", points.shape[:-1], self.batch_size)
        dtype = torch.promote_types(points.dtype, self.center.dtype)
        if tol is None:  # the looser tolerance when either side is in lower precision
            tol = max(default_tol(points.dtype), default_tol(self.center.dtype))
        offset = points.to(dtype) - self.center.to(dtype)
        generators = self.generators.to(dtype)
        if self.dim <= 3 and _full_rank(self.generators):
            # facet data once per set; the points broadcast against it
            normals = facet_normals(generators)
            gauge = gauge_from_facets(offset, normals, facet_supports(normals, generators))
            return gauge <= 1 + tol
        generators = generators.expand(*offset.shape[:-1], *generators.shape[-2:])
        rows = offset.shape[:-1].numel()
        flat_x = offset.detach().reshape(rows, self.dim).double().cpu().numpy()
        flat_g = generators.detach().reshape(rows, *generators.shape[-2:]).double().cpu().numpy()
        inside = [gauge_lp(g, x) <= 1 + max(tol, 1e-7) for g, x in zip(flat_g, flat_x)]
        return torch.tensor(inside, dtype=torch.bool, device=points.device).reshape(offset.shape[:-1])

    def sample(self, num: int, generator: torch.Generator | None = None) -> Tensor:
        """``num`` points ``c + G z`` with ``z`` uniform in the unit cube: ``[num, ..., n]``.

        The second half of the samples has every coefficient snapped to +-1 (the zonotope's
        vertices are among these points), so the samples also reach the boundary.
        """
        shape = (num, *self.generators.shape[:-2], self.n_generators)
        z = torch.rand(shape, generator=generator, dtype=self.center.dtype, device=self.center.device) * 2 - 1
        z[num // 2:] = z[num // 2:].sign()
        return self.center + (self.generators @ z.unsqueeze(-1)).squeeze(-1)

    def vertices(self) -> Tensor:
        """Counter-clockwise polygon vertices of a 2-D zonotope: ``[..., 2p, 2]``."""
        if self.dim != 2:
            raise ValueError(f"vertices() needs a 2-D set, got n={self.dim}; project() first")
        g = self.generators.transpose(-1, -2)  # [..., p, 2]
        flip = (g[..., 1] < 0) | ((g[..., 1] == 0) & (g[..., 0] < 0))
        g = torch.where(flip.unsqueeze(-1), -g, g)
        angle = torch.atan2(g[..., 1], g[..., 0])
        g = g.gather(-2, angle.argsort(-1).unsqueeze(-1).expand_as(g))
        start = self.center - g.sum(-2)
        steps = torch.cat((2 * g, -2 * g), dim=-2)
        return start.unsqueeze(-2) + torch.cumsum(steps, dim=-2)

    def plot(self, ax=None, dims: Sequence[int] = (0, 1), **kwargs):
        """Draw every set of the batch, projected onto ``dims``, as a filled polygon.

        Args:
            ax: a matplotlib axis (a new figure when ``None``).
            dims: the two coordinates to draw.
            **kwargs: passed to ``matplotlib.patches.Polygon`` (e.g. ``facecolor``, ``alpha``).

        Returns:
            The axis.
        """
        from torchrl_brsl.sets.plotting import plot_polygons

        if len(dims) != 2:
            raise ValueError(f"`dims` must name two coordinates, got {list(dims)}")
        verts = self.project(dims).vertices().detach().cpu().reshape(-1, 2 * self.n_generators, 2)
        return plot_polygons([v.numpy() for v in verts], ax=ax, **kwargs)


def _check_same_dim(a, b) -> None:
    if a.dim != b.dim:
        raise ValueError(f"`other` is {b.dim}-dimensional but the set is {a.dim}-dimensional")


def _broadcast_set(center: Tensor, generators: Tensor) -> tuple[Tensor, Tensor]:
    batch = torch.broadcast_shapes(center.shape[:-1], generators.shape[:-2])
    return center.expand(*batch, center.shape[-1]), generators.expand(*batch, *generators.shape[-2:])


def _full_rank(generators: Tensor) -> bool:
    n = generators.shape[-2]
    if generators.shape[-1] < n:
        return False
    flat = generators.detach().reshape(-1, *generators.shape[-2:])
    return bool((torch.linalg.matrix_rank(flat) == n).all())


__all__ = ["Zonotope"]
