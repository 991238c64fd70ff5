"""Helpers shared by the collision tests: random set pairs and independent HiGHS oracles.

The oracles are written from the definitions with ``scipy.optimize.linprog(method="highs")``
and numpy, independently of ``torchrl_brsl.collision`` and of ``ConstrainedZonotope.intersect``.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linprog

from torchrl_brsl.sets import ConstrainedZonotope, Zonotope


def np64(x) -> np.ndarray:
    return x.detach().double().cpu().numpy()


def parts(cz) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(c, G, A, b)`` numpy arrays of a single (unbatched) set."""
    c, g = np64(cz.center), np64(cz.generators)
    if isinstance(cz, ConstrainedZonotope):
        return c, g, np64(cz.A), np64(cz.b)
    return c, g, np.zeros((0, g.shape[1])), np.zeros(0)


def highs_gauge(A: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
    """``min v s.t. A z = b, |z| <= v`` by HiGHS: ``(v*, z*)``, ``(inf, None)`` if infeasible."""
    m, p = A.shape
    cost = np.r_[np.zeros(p), 1.0]
    A_ub = np.block([[np.eye(p), -np.ones((p, 1))], [-np.eye(p), -np.ones((p, 1))]])
    res = linprog(cost, A_ub=A_ub, b_ub=np.zeros(2 * p), A_eq=np.hstack([A, np.zeros((m, 1))]), b_eq=b,
                  bounds=[(None, None)] * p + [(0, None)], method="highs",
                  options={"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10})
    if res.status == 2:
        return float("inf"), None
    assert res.status == 0, res.message
    return float(res.fun), res.x[:p]


def intersection_program(set_, obstacle) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` of eq. (10) for one pair: ``[[A1, 0], [0, A2], [G1, -G2]] z = [b1; b2; c2 - c1]``."""
    c1, g1, a1, b1 = parts(set_)
    c2, g2, a2, b2 = parts(obstacle)
    p1, p2 = g1.shape[1], g2.shape[1]
    A = np.vstack([np.hstack([a1, np.zeros((a1.shape[0], p2))]),
                   np.hstack([np.zeros((a2.shape[0], p1)), a2]),
                   np.hstack([g1, -g2])])
    return A, np.concatenate([b1, b2, c2 - c1])


def highs_values(sets, obstacles) -> np.ndarray:
    """Eq. (10) by HiGHS for every pair of two equally batched 1-D set batches: ``[N]``."""
    return np.array([highs_gauge(*intersection_program(s, o))[0] for s, o in zip(sets, obstacles)])


def random_zonotope_pairs(seed: int, n: int, num: int, p1: int, p2: int, dtype=torch.float64):
    """``num`` random pairs: sets with ``p1`` generators (the last one zero, as padding), boxes
    rotated at random with ``p2`` generators, centres spread so that about half intersect."""
    gen = torch.Generator().manual_seed(seed)
    c1 = torch.randn(num, n, generator=gen, dtype=dtype)
    g1 = 0.4 * torch.randn(num, n, p1, generator=gen, dtype=dtype)
    g1[..., -1] = 0.0
    c2 = c1 + 2.0 * torch.randn(num, n, generator=gen, dtype=dtype)
    g2 = 0.5 * torch.randn(num, n, p2, generator=gen, dtype=dtype)
    return Zonotope(c1, g1), Zonotope(c2, g2)


def to_boundary(sets: Zonotope, obstacles: Zonotope, targets: np.ndarray) -> Zonotope:
    """Move each obstacle along ``c2 - c1`` so that the pair's ``v*`` becomes ``targets`` (the gauge
    of a zonotope pair is positively homogeneous in the centre offset)."""
    values = highs_values(sets, obstacles)
    scale = torch.as_tensor(targets / values, dtype=sets.center.dtype).unsqueeze(-1)
    offsets = obstacles.center - sets.center
    return Zonotope(sets.center + scale * offsets, obstacles.generators)


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances from points ``p [..., 2]`` to the segment ``[a, b]``."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def polygon_distance(P: np.ndarray, Q: np.ndarray) -> float:
    """Euclidean distance between two disjoint convex polygons given by vertices ``[k, 2]``."""
    best = np.inf
    for X, Y in ((P, Q), (Q, P)):
        for i in range(len(Y)):
            best = min(best, segment_distance(X, Y[i], Y[(i + 1) % len(Y)]).min())
    return float(best)


def random_polytope(gen: torch.Generator, n: int, m: int, dtype=torch.float64) -> ConstrainedZonotope:
    """A random bounded polytope ``{x : H x <= h}`` around the origin with ``n + 1 + m`` facets, as a
    constrained zonotope (``ConstrainedZonotope.from_polytope``).

    The first ``n + 1`` normals are a randomly rotated ``[I; -1/sqrt(n)]`` (which bounds the set),
    the other ``m`` are random; no facet is axis-aligned, so no constraint is tangent to the
    bounding box and the programs are non-degenerate with probability one.
    """
    rotation, _ = torch.linalg.qr(torch.randn(n, n, generator=gen, dtype=dtype))
    simplex = torch.cat([torch.eye(n, dtype=dtype), -torch.ones(1, n, dtype=dtype) / n ** 0.5])
    H = torch.cat([simplex @ rotation.T, torch.randn(m, n, generator=gen, dtype=dtype)])
    H = H / H.norm(dim=-1, keepdim=True)
    h = 0.5 + torch.rand(n + 1 + m, generator=gen, dtype=dtype)
    return ConstrainedZonotope.from_polytope(H, h)


def support_points(cz, directions: np.ndarray) -> np.ndarray:
    """Maximisers of ``d . x`` over a single set for each row ``d`` of ``directions``: ``[k, n]``."""
    c, g, A, b = parts(cz)
    kwargs = {"A_eq": A, "b_eq": b} if A.shape[0] else {}
    points = []
    for d in directions:
        res = linprog(-(d @ g), bounds=[(-1, 1)] * g.shape[1], method="highs", **kwargs)
        assert res.status == 0, res.message
        points.append(c + g @ res.x)
    return np.array(points)


def stack_sets(items):
    """Stack single sets of one kind and equal sizes into a ``[N]`` batch."""
    first = items[0]
    if isinstance(first, ConstrainedZonotope):
        keys = ("center", "generators", "A", "b")
        return ConstrainedZonotope(*(torch.stack([getattr(s, k) for s in items]) for k in keys))
    return Zonotope(torch.stack([s.center for s in items]), torch.stack([s.generators for s in items]))
