"""Obstacle zonotopes for the safety layer: boxes, discs and polygons inflated by the robot footprint.

The layer checks the robot's *position* (a point of the obstacle space) against obstacles, so
every obstacle is inflated by the robot's footprint first. The footprint here is a disc (2-D)
or a ball (3-D) of radius ``rho`` around the robot position: the robot touches an obstacle
``O`` exactly when its position lies in ``O ⊕ B(rho)``. Each helper returns a zonotope that
*contains* that Minkowski sum, so a set that avoids the zonotope keeps the robot off the
obstacle:

* ``B(rho)`` in the plane lies inside the regular octagon of inradius ``rho`` (4 generators),
  so a box (rotated too) becomes ``box ⊕ octagon`` (2 + 4 generators) and a convex polygon its
  smallest-area bounding rectangle ``⊕ octagon``.
* a disc of radius ``R`` becomes the regular 12-gon of inradius ``R + rho`` (6 generators).
* in 3-D, ``B(rho) ⊆ octagon(rho) × [-rho, rho]``: boxes and upright cylinders get one more
  generator along z, of half-length ``h + rho``.

:func:`obstacle_batch` pads a list of them into the ``obstacles`` entry the layer reads
(``center [K, d]``, ``generators [K, d, p]``, ``mask [K]``).

Examples:
    >>> wall = inflate_box(torch.tensor([2.0, 0.0]), torch.tensor([0.1, 1.0]), robot_radius=0.2)
    >>> post = inflate_disc(torch.tensor([0.5, 0.5]), radius=0.1, robot_radius=0.2)
    >>> rock = inflate_polygon(torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.3, 0.8]]), robot_radius=0.2)
    >>> obstacles = obstacle_batch([wall, post, rock], capacity=5)
    >>> obstacles["center"].shape, obstacles["generators"].shape, obstacles["mask"].tolist()
    (torch.Size([5, 2]), torch.Size([5, 2, 6]), [True, True, True, False, False])
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict import TensorDict
from torch import Tensor

from torchrl_brsl.sets.constrained_zonotope import ConstrainedZonotope
from torchrl_brsl.sets.reduction import pad_generators
from torchrl_brsl.sets.zonotope import Zonotope

__all__ = ["Obstacles", "inflate_box", "inflate_disc", "inflate_polygon", "obstacle_batch",
           "regular_polygon_generators"]


@dataclass(frozen=True)
class Obstacles:
    """A padded batch of ``K`` obstacles per env: what the safety layer checks sets against.

    Zonotopes ``{c + G ξ : ||ξ||_∞ <= 1}``, or, with ``constraint_matrix`` and
    ``constraint_offset``, constrained zonotopes ``{c + G ξ : ||ξ||_∞ <= 1, A ξ = b}``: any
    convex polytope (:meth:`~torchrl_brsl.sets.ConstrainedZonotope.from_polytope`), which only
    the LP collision check handles (:class:`~torchrl_brsl.safety.PlanChecker`'s ``collision``).
    Its batch ``[...]`` (the envs) is ``center.shape[:-2]``; it indexes, expands and reshapes
    over that batch like a tensor (``obstacles[idx]`` selects envs). Empty slots have
    ``mask=False``; their centre and generators are never used. A plain frozen dataclass rather
    than a tensorclass: the safety path reads its fields many times per step.

    Args:
        center: ``[..., K, d]``.
        generators: ``[..., K, d, p]``.
        mask: ``[..., K]`` bool, ``True`` for real obstacles.
        constraint_matrix: ``[..., K, c, p]`` or ``None``.
        constraint_offset: ``[..., K, c]`` or ``None``.

    Examples:
        >>> obstacles = Obstacles(**obstacle_batch([inflate_disc(torch.zeros(2), 0.3, 0.1)], capacity=4))
        >>> obstacles.batch_size, obstacles.n_obstacles, obstacles.dim, obstacles.constrained
        (torch.Size([]), 4, 2, False)
        >>> obstacles.expand(3)[torch.tensor([0, 2])].center.shape
        torch.Size([2, 4, 2])
    """

    center: Tensor
    generators: Tensor
    mask: Tensor
    constraint_matrix: Tensor | None = None
    constraint_offset: Tensor | None = None

    def __post_init__(self):
        c, g, m = self.center, self.generators, self.mask
        if c.ndim < 2 or g.shape[:-1] != c.shape or m.shape != c.shape[:-1]:
            raise ValueError(f"obstacles need `center` [..., K, d], `generators` [..., K, d, p] and `mask` [..., K]; "
                             f"got {tuple(c.shape)}, {tuple(g.shape)} and {tuple(m.shape)}")
        if m.dtype is not torch.bool:
            raise ValueError(f"the obstacles' `mask` must be bool (True for real obstacles), got {m.dtype}")
        a, b = self.constraint_matrix, self.constraint_offset
        if (a is None) != (b is None) or (a is not None and (a.shape[:-2] != m.shape or a.shape[-1] != g.shape[-1]
                                                           or b.shape != a.shape[:-1])):
            raise ValueError(f"`constraint_matrix` [..., K, c, p] and `constraint_offset` [..., K, c] come together, "
                             f"matching `generators` {tuple(g.shape)}; got "
                             f"{None if a is None else tuple(a.shape)} and {None if b is None else tuple(b.shape)}")

    @property
    def batch_size(self) -> torch.Size:
        """The envs' batch shape ``[...]``."""
        return self.center.shape[:-2]

    @property
    def n_obstacles(self) -> int:
        """``K``, the number of slots."""
        return self.center.shape[-2]

    @property
    def dim(self) -> int:
        """``d``, the dimension of the obstacle space."""
        return self.center.shape[-1]

    @property
    def constrained(self) -> bool:
        """Whether the obstacles carry equality constraints (constrained zonotopes)."""
        return self.constraint_matrix is not None and self.constraint_matrix.shape[-2] > 0

    def _map(self, fn) -> Obstacles:
        """``fn(tensor, trailing dims)`` applied to every field over the batch."""
        fields = (self.center, self.generators, self.mask, self.constraint_matrix, self.constraint_offset)
        trailing = (2, 3, 1, 3, 2)
        return Obstacles(*(None if t is None else fn(t, k) for t, k in zip(fields, trailing)))

    def __getitem__(self, index) -> Obstacles:
        """The envs ``index`` (any tensor index over the batch)."""
        return self._map(lambda t, _: t[index])

    def expand(self, *shape: int) -> Obstacles:
        """The batch expanded to ``shape`` (views, as :meth:`torch.Tensor.expand`)."""
        return self._map(lambda t, k: t.expand(*shape, *t.shape[t.ndim - k:]))

    def repeat(self, count: int) -> Obstacles:
        """The batch ``[B, ...]`` repeated ``count`` times along its first dim: ``[count B, ...]``, copy after copy
        (one copy per plan of a batch of candidates, as :meth:`torch.Tensor.repeat`; by ``torch.cat``, about a sixth
        of ``repeat``'s cost on a control step's small tensors)."""
        return self._map(lambda t, _: torch.cat((t,) * count))

    def reshape(self, *shape: int) -> Obstacles:
        """The batch reshaped to ``shape``."""
        return self._map(lambda t, k: t.reshape(*shape, *t.shape[t.ndim - k:]))

    def to_dtype(self, dtype: torch.dtype) -> Obstacles:
        """The centres, generators and constraints in ``dtype`` (the mask stays bool)."""
        if self.center.dtype == dtype and self.generators.dtype == dtype:
            return self
        return self._map(lambda t, _: t if t.dtype is torch.bool else t.to(dtype))

    def as_sets(self) -> Zonotope | ConstrainedZonotope:
        """The obstacles as one set batch ``[..., K]`` (constrained when they carry constraints)."""
        if self.constrained:
            return ConstrainedZonotope(self.center, self.generators, self.constraint_matrix, self.constraint_offset)
        return Zonotope(self.center, self.generators)


def regular_polygon_generators(n: int, inradius: float, dtype: torch.dtype = torch.float64) -> Tensor:
    """Generators ``[2, n]`` of the regular ``2n``-gon with the given inradius (it contains the
    disc of that radius).

    Examples:
        >>> regular_polygon_generators(4, 1.0).shape  # the octagon
        torch.Size([2, 4])
    """
    if int(n) < 2:
        raise ValueError(f"`n` must be at least 2 (a square), got {n}")
    if not inradius >= 0:
        raise ValueError(f"`inradius` must be non-negative, got {inradius}")
    angles = torch.arange(int(n), dtype=dtype) * (math.pi / int(n))
    half_side = float(inradius) * math.tan(math.pi / (2 * int(n)))
    return half_side * torch.stack((torch.cos(angles), torch.sin(angles)))


def _as_vector(name: str, value, sizes: tuple[int, ...]) -> Tensor:
    value = torch.as_tensor(value, dtype=torch.float64)
    if value.ndim != 1 or value.shape[0] not in sizes:
        raise ValueError(f"`{name}` must be a vector of {' or '.join(map(str, sizes))} values, got shape "
                         f"{tuple(value.shape)}")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"`{name}` must be finite, got {value.tolist()}")
    return value


def _check_radius(name: str, value: float) -> float:
    value = float(value)
    if not value >= 0 or not math.isfinite(value):
        raise ValueError(f"`{name}` must be a finite non-negative number, got {value}")
    return value


def _with_height(planar: Tensor, half_height: float, robot_radius: float) -> Tensor:
    """Planar generators ``[2, p]`` extended to 3-D with one z generator ``h + rho``: ``[3, p + 1]``."""
    generators = planar.new_zeros(3, planar.shape[1] + 1)
    generators[:2, :-1] = planar
    generators[2, -1] = half_height + robot_radius
    return generators


def inflate_box(center, half_size, robot_radius: float, yaw: float = 0.0) -> Zonotope:
    """A box (rotated by ``yaw`` about z) inflated by a disc/ball footprint of radius ``robot_radius``.

    Args:
        center: ``[2]`` or ``[3]`` the box centre.
        half_size: the box half-extents along its own axes, ``[2]`` (``hx, hy``) or, in 3-D, ``[3]``.
        robot_radius: ``rho``.
        yaw: rotation of the box about z (rad).

    Returns:
        A :class:`Zonotope` ``[d]`` with 6 generators (2-D) or 7 (3-D).

    Examples:
        >>> z = inflate_box(torch.zeros(2), torch.tensor([1.0, 0.5]), 0.1, yaw=0.3)
        >>> z.generators.shape
        torch.Size([2, 6])
    """
    center = _as_vector("center", center, (2, 3))
    half = _as_vector("half_size", half_size, (center.shape[0],))
    rho = _check_radius("robot_radius", robot_radius)
    if bool((half < 0).any()):
        raise ValueError(f"`half_size` must be non-negative, got {half.tolist()}")
    cos, sin = math.cos(float(yaw)), math.sin(float(yaw))
    hx, hy = float(half[0]), float(half[1])
    box = torch.tensor([[hx * cos, -hy * sin], [hx * sin, hy * cos]], dtype=torch.float64)
    planar = torch.cat((box, regular_polygon_generators(4, rho)), dim=1)
    if center.shape[0] == 2:
        return Zonotope(center.clone(), planar)
    return Zonotope(center.clone(), _with_height(planar, float(half[2]), rho))


def inflate_disc(center, radius: float, robot_radius: float, half_height: float | None = None) -> Zonotope:
    """A disc of ``radius`` (in 3-D an upright cylinder of ``half_height``) inflated by the footprint.

    Args:
        center: ``[2]``, or ``[3]`` with ``half_height``.
        radius: ``R``.
        robot_radius: ``rho``.
        half_height: the cylinder's half-height (3-D only).

    Returns:
        A :class:`Zonotope`: the regular 12-gon of inradius ``R + rho`` (6 generators), with one
        z generator ``half_height + rho`` in 3-D.
    """
    center = _as_vector("center", center, (2, 3))
    rho = _check_radius("robot_radius", robot_radius)
    planar = regular_polygon_generators(6, _check_radius("radius", radius) + rho)
    if center.shape[0] == 2:
        if half_height is not None:
            raise ValueError("`half_height` is for 3-D cylinders: give a 3-D `center`")
        return Zonotope(center.clone(), planar)
    if half_height is None:
        raise ValueError("a 3-D `center` needs the cylinder's `half_height`")
    return Zonotope(center.clone(), _with_height(planar, _check_radius("half_height", half_height), rho))


def inflate_polygon(vertices, robot_radius: float) -> Zonotope:
    """A planar polygon (its convex hull) inflated by the footprint.

    A general polygon is not a zonotope: it is enclosed by its smallest-area bounding rectangle
    (one of the hull's edge directions is a side of it), then inflated like a box. Exact for
    rectangles; conservative otherwise.

    Args:
        vertices: ``[V, 2]`` (any order, ``V >= 1``; only the convex hull matters).
        robot_radius: ``rho``.

    Returns:
        A 2-D :class:`Zonotope` with 6 generators.

    Examples:
        >>> z = inflate_polygon(torch.tensor([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]]), 0.0)
        >>> z.center.tolist(), z.interval()[1].tolist()
        ([1.0, 0.5], [2.0, 1.0])
    """
    points = torch.as_tensor(vertices, dtype=torch.float64)
    if points.ndim != 2 or points.shape[-1] != 2 or points.shape[0] < 1:
        raise ValueError(f"`vertices` must be [V, 2] with V >= 1, got shape {tuple(points.shape)}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError("`vertices` must be finite")
    hull = _convex_hull(points)
    edges = hull.roll(-1, 0) - hull
    lengths = edges.norm(dim=-1)
    directions = edges[lengths > 0] / lengths[lengths > 0].unsqueeze(-1) if bool((lengths > 0).any()) else \
        torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    best = None
    for axis in directions:
        normal = torch.stack((-axis[1], axis[0]))
        along, across = hull @ axis, hull @ normal
        area = float((along.max() - along.min()) * (across.max() - across.min()))
        if best is None or area < best[0]:
            best = (area, axis, normal, along, across)
    _, axis, normal, along, across = best
    mid_along, mid_across = (along.max() + along.min()) / 2, (across.max() + across.min()) / 2
    center = mid_along * axis + mid_across * normal
    box = torch.stack((axis * (along.max() - along.min()) / 2, normal * (across.max() - across.min()) / 2), dim=1)
    planar = torch.cat((box, regular_polygon_generators(4, _check_radius("robot_radius", robot_radius))), dim=1)
    return Zonotope(center, planar)


def _convex_hull(points: Tensor) -> Tensor:
    """Vertices of the convex hull, counter-clockwise (Andrew's monotone chain): ``[H, 2]``."""
    unique = sorted(set(map(tuple, points.tolist())))
    if len(unique) <= 2:
        return torch.tensor(unique, dtype=torch.float64)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in unique:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(unique):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return torch.tensor(lower[:-1] + upper[:-1], dtype=torch.float64)


def obstacle_batch(zonotopes: Sequence[Zonotope | ConstrainedZonotope], capacity: int | None = None,
                   n_generators: int | None = None) -> TensorDict:
    """The ``obstacles`` entry the safety layer reads, from a list of obstacle sets.

    Args:
        zonotopes: obstacles of one dimension ``d`` (e.g. from :func:`inflate_box`);
            :class:`~torchrl_brsl.sets.ConstrainedZonotope` s (polytopes) are allowed and make
            every slot a constrained zonotope (checked by the LP).
        capacity: ``K``, the number of slots (default: as many as obstacles); unused slots are
            zeros with ``mask=False``. Keep ``K`` fixed over an env's episodes (the specs do not
            change); ``K = 0`` is allowed.
        n_generators: ``p`` (default: the most any obstacle has); obstacles with fewer are
            padded with zero generators.

    Returns:
        A TensorDict with ``center [K, d]``, ``generators [K, d, p]`` and ``mask [K]`` (float64
        and bool), and with polytopes ``constraint_matrix [K, c, p]`` and ``constraint_offset [K, c]``.
    """
    zonotopes = list(zonotopes)
    capacity = len(zonotopes) if capacity is None else int(capacity)
    if len(zonotopes) > capacity:
        raise ValueError(f"{len(zonotopes)} obstacles exceed the capacity {capacity}")
    dims = {z.center.shape[-1] for z in zonotopes}
    if len(dims) > 1 or any(z.center.ndim != 1 for z in zonotopes):
        raise ValueError(f"the obstacles must be single zonotopes of one dimension, got dimensions {sorted(dims)}")
    d = dims.pop() if dims else 2
    widest = max((z.generators.shape[-1] for z in zonotopes), default=1)
    p = widest if n_generators is None else int(n_generators)
    if p < widest:
        raise ValueError(f"`n_generators`={p} is below an obstacle's {widest} generators")
    constrained = [z if isinstance(z, ConstrainedZonotope) else None for z in zonotopes]
    rows = max((z.n_constraints for z in constrained if z is not None), default=0)
    center = torch.zeros(capacity, d, dtype=torch.float64)
    generators = torch.zeros(capacity, d, p, dtype=torch.float64)
    matrix = torch.zeros(capacity, rows, p, dtype=torch.float64)
    offset = torch.zeros(capacity, rows, dtype=torch.float64)
    mask = torch.zeros(capacity, dtype=torch.bool)
    for i, z in enumerate(zonotopes):
        center[i] = z.center.to(torch.float64)
        generators[i] = pad_generators(z.generators.to(torch.float64), p)
        if constrained[i] is not None:
            padded = constrained[i].pad(p, rows)
            matrix[i], offset[i] = padded.A.to(torch.float64), padded.b.to(torch.float64)
        mask[i] = True
    if any(z is not None for z in constrained):
        return TensorDict(center=center, generators=generators, mask=mask, constraint_matrix=matrix,
                          constraint_offset=offset, batch_size=[])
    return TensorDict(center=center, generators=generators, mask=mask, batch_size=[])
