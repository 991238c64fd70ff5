"""Batched constrained zonotopes ``Z(c, G, A, b) = {c + G z : A z = b, ||z||_inf <= 1}``."""
from __future__ import annotations

from typing import Sequence

import numpy as np
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
from torchrl_brsl.sets.lp import gauge_lp, polytope_bounds, support_lp
from torchrl_brsl.sets.zonotope import Zonotope


@documented_tensorclass
class ConstrainedZonotope:
    """A batch of constrained zonotopes (Scott et al., 2016).

    Every convex compact polytope is one. Batch shape ``center.shape[:-1]``; operations
    broadcast over it and are differentiable. Queries that need a linear program
    (:meth:`contains`, :meth:`is_empty`, :meth:`interval`, :meth:`plot`) run HiGHS per batch
    element; the differentiable collision check lives in :mod:`torchrl_brsl.collision`.

    Args:
        center: ``[..., n]``.
        generators: ``[..., n, p]``.
        A: ``[..., nc, p]`` constraint matrix (``nc`` may be 0).
        b: ``[..., nc]``.

    Examples:
        >>> box = Zonotope.from_interval(-torch.ones(2), torch.ones(2)).to_constrained()
        >>> tri = box.intersect_halfspace(torch.tensor([1.0, 1.0]), torch.tensor(0.0))
        >>> tri.contains(torch.tensor([[0.9, -0.9], [0.9, 0.9]]))
        tensor([ True, False])
    """

    center: Tensor
    generators: Tensor
    A: Tensor
    b: Tensor

    def __post_init__(self):
        c = check_tensor("center", self.center, min_ndim=1)
        g = check_tensor("generators", self.generators, min_ndim=2)
        a = check_tensor("A", self.A, min_ndim=2)
        b = check_tensor("b", self.b, min_ndim=1)
        check_same_dtype_device(center=c, generators=g, A=a, b=b)
        if g.shape[:-1] != c.shape:
            raise ValueError(f"`generators` {tuple(g.shape)} must be [..., n, p] matching `center` {tuple(c.shape)}")
        if a.shape[:-2] != c.shape[:-1] or a.shape[-1] != g.shape[-1]:
            raise ValueError(f"`A` {tuple(a.shape)} must be [..., nc, p] with p={g.shape[-1]} and batch {tuple(c.shape[:-1])}")
        if b.shape != a.shape[:-1]:
            raise ValueError(f"`b` {tuple(b.shape)} must be [..., nc] matching `A` {tuple(a.shape)}")
        self.batch_size = c.shape[:-1]

    # ----------------------------------------------------------------- constructors
    @classmethod
    def from_zonotope(cls, zonotope: Zonotope) -> ConstrainedZonotope:
        """The zonotope as a constrained zonotope with ``nc = 0``."""
        g = zonotope.generators
        return cls(zonotope.center, g, g.new_zeros(*g.shape[:-2], 0, g.shape[-1]), g.new_zeros(*g.shape[:-2], 0))

    @classmethod
    def from_polytope(cls, H: Tensor, h: Tensor) -> ConstrainedZonotope:
        """Exact conversion of the bounded polytope ``{x : H x <= h}``.

        Bounding box by linear programming, then one halfspace intersection per row
        (Raghuraman & Koeln, 2022). Single (unbatched) polytope.

        Args:
            H: ``[m, n]``.
            h: ``[m]``.
        """
        H = check_tensor("H", H, min_ndim=2)
        h = check_tensor("h", h, min_ndim=1)
        if H.ndim != 2 or h.shape != H.shape[:1]:
            raise ValueError(f"`H` must be [m, n] and `h` [m]; got {tuple(H.shape)} and {tuple(h.shape)}")
        lo, hi = polytope_bounds(H.detach().double().cpu().numpy(), h.detach().double().cpu().numpy())
        box = Zonotope.from_interval(H.new_tensor(lo), H.new_tensor(hi)).to_constrained()
        return box.intersect_halfspace(H, h)

    @classmethod
    def from_box(cls, center: Tensor, half_extents: Tensor, rotation: Tensor | None = None) -> ConstrainedZonotope:
        """An (oriented) box; see :meth:`Zonotope.from_box`."""
        return cls.from_zonotope(Zonotope.from_box(center, half_extents, rotation))

    # ----------------------------------------------------------------- properties
    @property
    def dim(self) -> int:
        """Ambient dimension ``n``."""
        return self.center.shape[-1]

    @property
    def n_generators(self) -> int:
        """Number of generator columns ``p``."""
        return self.generators.shape[-1]

    @property
    def n_constraints(self) -> int:
        """Number of equality constraints ``nc``."""
        return self.A.shape[-2]

    # ----------------------------------------------------------------- algebra
    def linear_map(self, matrix: Tensor) -> ConstrainedZonotope:
        """``M Z`` for ``matrix`` ``[..., k, n]``."""
        matrix = check_tensor("matrix", matrix, min_ndim=2)
        if matrix.shape[-1] != self.dim:
            raise ValueError(f"`matrix` has {matrix.shape[-1]} columns but the set is {self.dim}-dimensional")
        broadcast_batch("matrix", matrix.shape[:-2], self.batch_size)
        check_same_dtype_device(center=self.center, matrix=matrix)
        g = matrix @ self.generators
        batch = g.shape[:-2]
        return ConstrainedZonotope(
            (matrix @ self.center.unsqueeze(-1)).squeeze(-1),
            g,
            self.A.expand(*batch, *self.A.shape[-2:]),
            self.b.expand(*batch, self.n_constraints),
        )

    def __rmatmul__(self, matrix: Tensor) -> ConstrainedZonotope:
        return self.linear_map(matrix)

    def minkowski_sum(self, other) -> ConstrainedZonotope:
        """``Z1 + Z2`` with block-diagonal constraints (batch shapes broadcast)."""
        other = _as_constrained("other", other)
        if other.dim != self.dim:
            raise ValueError(f"`other` is {other.dim}-dimensional but the set is {self.dim}-dimensional")
        s, o = _broadcast_pair(self, other)
        return ConstrainedZonotope(
            s.center + o.center,
            torch.cat((s.generators, o.generators), dim=-1),
            _block_diag(s.A, o.A),
            torch.cat((s.b, o.b), dim=-1),
        )

    def translate(self, offset: Tensor) -> ConstrainedZonotope:
        """``Z + offset`` for ``offset`` ``[..., n]``."""
        offset = check_tensor("offset", offset, min_ndim=1)
        check_last_dim("offset", offset, self.dim)
        broadcast_batch("offset", offset.shape[:-1], self.batch_size)
        center = self.center + offset
        batch = center.shape[:-1]
        return ConstrainedZonotope(
            center,
            self.generators.expand(*batch, *self.generators.shape[-2:]),
            self.A.expand(*batch, *self.A.shape[-2:]),
            self.b.expand(*batch, self.n_constraints),
        )

    def __add__(self, other):
        if isinstance(other, (Zonotope, ConstrainedZonotope)):
            return self.minkowski_sum(other)
        if isinstance(other, Tensor):
            return self.translate(other)
        return NotImplemented

    __radd__ = __add__

    def __sub__(self, other):
        if isinstance(other, Tensor):
            return self.translate(-other)
        return NotImplemented

    def cartesian_product(self, other) -> ConstrainedZonotope:
        """``Z1 x Z2`` (batch shapes broadcast)."""
        s, o = _broadcast_pair(self, _as_constrained("other", other))
        return ConstrainedZonotope(
            torch.cat((s.center, o.center), dim=-1),
            _block_diag(s.generators, o.generators),
            _block_diag(s.A, o.A),
            torch.cat((s.b, o.b), dim=-1),
        )

    def project(self, dims: Sequence[int]) -> ConstrainedZonotope:
        """Projection onto the coordinates ``dims``."""
        dims = check_dims("dims", dims, self.dim)
        return ConstrainedZonotope(self.center[..., dims], self.generators[..., dims, :], self.A, self.b)

    def intersect(self, other) -> ConstrainedZonotope:
        """``Z1 ∩ Z2`` by Scott et al. (2016), Prop. 1 (batch shapes broadcast).

        ``Z(c1, [G1, 0], [[A1, 0], [0, A2], [G1, -G2]], [b1; b2; c2 - c1])``.
        """
        other = _as_constrained("other", other)
        if other.dim != self.dim:
            raise ValueError(f"`other` is {other.dim}-dimensional but the set is {self.dim}-dimensional")
        s, o = _broadcast_pair(self, other)
        g = torch.cat((s.generators, torch.zeros_like(o.generators)), dim=-1)
        A = torch.cat((_block_diag(s.A, o.A), torch.cat((s.generators, -o.generators), dim=-1)), dim=-2)
        b = torch.cat((s.b, o.b, o.center - s.center), dim=-1)
        return ConstrainedZonotope(s.center, g, A, b)

    def intersect_halfspace(self, H: Tensor, h: Tensor) -> ConstrainedZonotope:
        """Intersection with ``{x : H x <= h}`` (Raghuraman & Koeln, 2022).

        Each row adds one slack generator and one constraint
        ``H_i G z + d_i/2 s = h_i - H_i c - d_i/2`` with
        ``d_i = max(h_i - H_i c + ||H_i G||_1, 0)``; ``d_i = 0`` (the halfspace misses the
        set's bounding zonotope) leaves an infeasible constraint, i.e. an empty set.

        Args:
            H: ``[..., m, n]`` or ``[n]`` (one halfspace); batch dimensions broadcast with the set's.
            h: ``[..., m]`` or scalar.
        """
        H = check_tensor("H", H, min_ndim=1)
        if not isinstance(h, Tensor):
            h = torch.as_tensor(h, dtype=H.dtype, device=H.device)
        h = check_tensor("h", h)
        check_same_dtype_device(center=self.center, H=H, h=h)
        if H.ndim == 1:
            H, h = H.unsqueeze(0), h.reshape(1)
        if H.shape[-1] != self.dim:
            raise ValueError(f"`H` must be [..., m, {self.dim}], got {tuple(H.shape)}")
        if h.shape != H.shape[:-1]:
            raise ValueError(f"`h` must be [..., m] matching `H` {tuple(H.shape)}; got {tuple(h.shape)}")
        batch = broadcast_batch("H", H.shape[:-2], self.batch_size)
        m, n, p, nc = H.shape[-2], self.dim, self.n_generators, self.n_constraints
        hc = (H @ self.center.unsqueeze(-1)).squeeze(-1).expand(*batch, m)  # [..., m]
        hg = (H @ self.generators).expand(*batch, m, p)  # [..., m, p]
        h = h.expand(*batch, m)
        d = (h - hc + hg.abs().sum(-1)).clamp_min(0)  # [..., m]
        gens = self.generators.expand(*batch, n, p)
        g = torch.cat((gens, gens.new_zeros(*batch, n, m)), dim=-1)
        A = self.A.expand(*batch, nc, p)
        A_old = torch.cat((A, A.new_zeros(*batch, nc, m)), dim=-1)
        A_new = torch.cat((hg, torch.diag_embed(d / 2)), dim=-1)
        return ConstrainedZonotope(self.center.expand(*batch, n), g, torch.cat((A_old, A_new), dim=-2),
                                   torch.cat((self.b.expand(*batch, nc), h - hc - d / 2), dim=-1))

    def pad(self, n_generators: int, n_constraints: int) -> ConstrainedZonotope:
        """Append zero generators / zero constraint rows (the set is unchanged)."""
        dp, dc = n_generators - self.n_generators, n_constraints - self.n_constraints
        if dp < 0:
            raise ValueError(f"`n_generators`={n_generators} is smaller than the {self.n_generators} generators present")
        if dc < 0:
            raise ValueError(f"`n_constraints`={n_constraints} is smaller than the {self.n_constraints} constraints present")
        pad = torch.nn.functional.pad
        return ConstrainedZonotope(self.center, pad(self.generators, (0, dp)), pad(self.A, (0, dp, 0, dc)),
                                   pad(self.b, (0, dc)))

    # ----------------------------------------------------------------- LP queries (HiGHS)
    def contains(self, points: Tensor, tol: float | None = None) -> Tensor:
        """Whether ``points`` ``[..., n]`` lie in the set: bool ``[...]`` (one LP each)."""
        points = check_tensor("points", points, min_ndim=1)
        tol = max(default_tol(points.dtype) if tol is None else tol, 1e-7)
        if points.shape[-1] != self.dim:
            raise ValueError(f"`points` must have last dimension {self.dim}, got {tuple(points.shape)}")
        batch = broadcast_batch("points", points.shape[:-1], self.batch_size)
        s = self.expand(batch)
        out = [gauge_lp(np.vstack([A, G]), np.concatenate([b, x - c])) <= 1 + tol
               for c, G, A, b, x in _numpy_rows(s, points.expand(*batch, self.dim))]
        return torch.tensor(out, device=points.device).reshape(batch)

    def is_empty(self, tol: float | None = None) -> Tensor:
        """Whether each set is empty: bool ``[...]`` (Scott et al., Prop. 2)."""
        tol = max(default_tol(self.center.dtype) if tol is None else tol, 1e-7)
        out = [gauge_lp(A, b) > 1 + tol for _, _, A, b in _numpy_rows(self)]
        return torch.tensor(out, device=self.center.device).reshape(self.batch_size)

    def interval(self) -> tuple[Tensor, Tensor]:
        """Tight interval hull ``(lo, hi)`` by ``2 n`` LPs per set; raises on an empty set."""
        lo, hi = [], []
        eye = np.eye(self.dim)
        for c, G, A, b in _numpy_rows(self):
            hi.append([support_lp(e, c, G, A, b)[0] for e in eye])
            lo.append([-support_lp(-e, c, G, A, b)[0] for e in eye])
        shape = (*self.batch_size, self.dim)
        return self.center.new_tensor(lo).reshape(shape), self.center.new_tensor(hi).reshape(shape)

    def vertices(self, n_directions: int = 64) -> Tensor:
        """Support points of a 2-D set in ``n_directions`` directions, counter-clockwise.

        Every support point is a vertex, so the polygon is an inner approximation that is exact
        once every vertex is hit. Returns ``[..., n_directions, 2]``.
        """
        if self.dim != 2:
            raise ValueError(f"vertices() needs a 2-D set, got n={self.dim}; project() first")
        angles = np.linspace(0, 2 * np.pi, n_directions, endpoint=False)
        dirs = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
        pts = [[support_lp(d, c, G, A, b)[1] for d in dirs] for c, G, A, b in _numpy_rows(self)]
        return self.center.new_tensor(np.asarray(pts)).reshape(*self.batch_size, n_directions, 2)

    def plot(self, ax=None, dims: Sequence[int] = (0, 1), n_directions: int = 64, **kwargs):
        """Draw every set of the batch, projected onto ``dims``; see :meth:`Zonotope.plot`."""
        from torchrl_brsl.sets.plotting import plot_polygons

        if len(dims) != 2:
            raise ValueError(f"`dims` must name two coordinates, got {list(dims)}")
        verts = self.project(dims).vertices(n_directions).detach().cpu().reshape(-1, n_directions, 2)
        return plot_polygons([v.numpy() for v in verts], ax=ax, **kwargs)


def _as_constrained(name: str, value) -> ConstrainedZonotope:
    if isinstance(value, Zonotope):
        return ConstrainedZonotope.from_zonotope(value)
    if isinstance(value, ConstrainedZonotope):
        return value
    raise ValueError(f"`{name}` must be a Zonotope or ConstrainedZonotope, got {type(value).__name__}")


def _broadcast_pair(a: ConstrainedZonotope, b: ConstrainedZonotope):
    batch = broadcast_batch("other", b.batch_size, a.batch_size)
    return a.expand(batch), b.expand(batch)


def _block_diag(x: Tensor, y: Tensor) -> Tensor:
    """Batched ``blkdiag(x, y)`` for ``x`` ``[..., r1, c1]`` and ``y`` ``[..., r2, c2]``."""
    batch = x.shape[:-2]
    top = torch.cat((x, x.new_zeros(*batch, x.shape[-2], y.shape[-1])), dim=-1)
    bottom = torch.cat((y.new_zeros(*batch, y.shape[-2], x.shape[-1]), y), dim=-1)
    return torch.cat((top, bottom), dim=-2)


def _numpy_rows(cz: ConstrainedZonotope, points: Tensor | None = None):
    """Yield ``(c, G, A, b[, x])`` float64 numpy arrays for each batch element."""
    n, p, nc = cz.dim, cz.n_generators, cz.n_constraints
    rows = cz.batch_size.numel()
    arrays = [cz.center.reshape(rows, n), cz.generators.reshape(rows, n, p), cz.A.reshape(rows, nc, p),
              cz.b.reshape(rows, nc)]
    if points is not None:
        arrays.append(points.reshape(rows, n))
    arrays = [a.detach().double().cpu().numpy() for a in arrays]
    return zip(*arrays)


__all__ = ["ConstrainedZonotope"]
