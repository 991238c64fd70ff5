"""One collision API over the closed form and the LP back end.

Every function takes a batch of sets and a batch of obstacles, each a
:class:`~torchrl_brsl.sets.Zonotope` or :class:`~torchrl_brsl.sets.ConstrainedZonotope` of
the same dimension, dtype and device, and checks each set against each obstacle *elementwise
over the broadcast batch shape*. To check every set against every obstacle, give them
different singleton axes: reachable sets ``[B, H, 1]`` (``B`` environments, ``H`` plan steps)
against obstacles ``[B, 1, K]`` give ``[B, H, K]``.

Back ends (``backend=``):

* ``"closed_form"``: exact for zonotope pairs in 1-3 D whose ``Z(0, [G1, G2])`` is
  full-dimensional (:mod:`torchrl_brsl.collision.closed_form`); differentiable w.r.t.
  centres and generators, no solver.
* ``"lp"``: the program of Selim et al. (2022), eq. (10), through ``CvxpyLayer``
  (:mod:`torchrl_brsl.collision.lp`) for constrained zonotopes in any dimension;
  differentiable w.r.t. centres, generators and constraints, about milliseconds per pair.
* ``"auto"`` (default): ``"closed_form"`` when it applies to every pair, else ``"lp"``.

Values are ``v*``: the sets intersect iff ``v* <= 1``. The signed ``clearance`` (units of
the state space) is positive iff ``v* > 1``:

* closed form: ``max_k (|u_k . dc| - s_k)`` over the unit facet normals of
  ``Z(0, [G1, G2])``: minus the penetration depth (exact) when intersecting, a lower bound
  on the Euclidean distance when disjoint;
* LP: the exact Euclidean distance (distance SOCP) when disjoint; when intersecting,
  ``(v* - 1) * s_min([G1, G2])`` with ``s_min`` the smallest singular value. For zonotopes
  (no constraints) this lies in ``[-depth, 0]`` (the ball of radius ``s_min`` fits in
  ``Z(0, [G1, G2])``); for constrained zonotopes it is a scaled gauge without metric meaning.

Failures never raise in :func:`check_collision`: non-finite data, an empty constrained
zonotope, a constrained zonotope with inconsistent constraints or a solver failure give
``value = 0`` and ``clearance = 0`` (colliding) with a :class:`CollisionStatus` per pair.
Two non-empty sets whose intersection equations have no solution at all (e.g. parallel
segments) are disjoint and get ``v* = inf``. Malformed arguments
(types, dimensions, dtypes, batch shapes, backend names) raise ``ValueError`` naming the
argument.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchrl_brsl.collision.closed_form import (
    CLOSED_FORM_DIMS,
    _broadcast,
    facet_clearances,
    facet_table,
    finite_offsets,
    gauge_values,
    is_full_dimensional,
)
from torchrl_brsl.collision.lp import solve_distance, solve_gauge
from torchrl_brsl.collision.result import CollisionResult, CollisionStatus
from torchrl_brsl.sets import ConstrainedZonotope, Zonotope
from torchrl_brsl.sets._checks import default_tol

BACKENDS = ("auto", "closed_form", "lp")

LP_TOL = 1e-6
"""Default slack of :func:`intersects` on LP values (the solver is accurate to ~1e-8)."""


def check_collision(sets, obstacles, *, backend: str = "auto", with_clearance: bool = True,
                    solver_args: dict | None = None) -> CollisionResult:
    """Collision values, clearances and per-pair status; never raises on bad numbers.

    Args:
        sets: a :class:`Zonotope` or :class:`ConstrainedZonotope` batch ``[...]``.
        obstacles: the same kinds, batch shape broadcastable with ``sets``.
        backend: ``"auto"``, ``"closed_form"`` or ``"lp"`` (see the module docstring).
        with_clearance: also compute the signed clearance (for the LP back end this adds
            one distance SOCP per disjoint pair).
        solver_args: overrides of :data:`torchrl_brsl.collision.lp.SOLVER_ARGS`.

    Returns:
        A :class:`CollisionResult` of the broadcast batch shape.

    Raises:
        ValueError: naming the argument, for malformed arguments (see the module docstring),
            or ``backend="closed_form"`` where it does not apply.

    Examples:
        >>> box = Zonotope.from_interval(-torch.ones(2), torch.ones(2))
        >>> far = box.translate(torch.tensor([[1.5, 0.0], [5.0, 0.0]]))
        >>> result = check_collision(box, far)
        >>> result.value, result.clearance, result.reason_names()
        (tensor([0.7500, 2.5000]), tensor([-0.5000,  3.0000]), ['OK', 'OK'])
    """
    return _check(sets, obstacles, backend, with_clearance, solver_args)[0]


def collision_value(sets, obstacles, backend: str = "auto", *, solver_args: dict | None = None) -> Tensor:
    """``v*`` of every (set, obstacle) pair; the pair intersects iff ``v* <= 1``.

    ``0`` (colliding) for pairs that cannot be certified; see :func:`check_collision` for
    the arguments and the reasons.

    Returns:
        ``[...]`` the broadcast batch shape, in the sets' dtype.

    Examples:
        >>> box = Zonotope.from_interval(-torch.ones(2), torch.ones(2))
        >>> collision_value(box, box.translate(torch.tensor([3.0, 0.0])))
        tensor(1.5000)
    """
    return _check(sets, obstacles, backend, False, solver_args)[0].value


def intersects(sets, obstacles, *, margin: float = 0.0, tol: float | None = None, backend: str = "auto",
               solver_args: dict | None = None) -> Tensor:
    """Whether each pair intersects, i.e. ``v* <= 1 + margin + tol``: bool ``[...]``.

    Both slacks count borderline pairs as intersecting, the safe side for collision
    avoidance. Pairs that cannot be certified (see :func:`check_collision`) are ``True``.

    Args:
        sets: see :func:`check_collision`.
        obstacles: see :func:`check_collision`.
        margin: safety margin on the gauge (a relative inflation of both sets' generators).
        tol: numerical slack; default :func:`~torchrl_brsl.sets._checks.default_tol` of the
            dtype (1e-9 in float64, 1e-5 otherwise) for the closed form, :data:`LP_TOL`
            for the LP.
        backend: see :func:`check_collision`.
        solver_args: see :func:`check_collision`.

    Examples:
        >>> box = Zonotope.from_interval(-torch.ones(2), torch.ones(2))
        >>> intersects(box, box.translate(torch.tensor([[2.0, 0.0], [2.1, 0.0]])))
        tensor([ True, False])
    """
    result, used = _check(sets, obstacles, backend, False, solver_args)
    if tol is None:
        tol = default_tol(result.value.dtype) if used == "closed_form" else LP_TOL
    return result.value <= 1 + margin + tol


def clearance(sets, obstacles, *, backend: str = "auto", solver_args: dict | None = None) -> Tensor:
    """Signed clearance of every pair (negative when intersecting, positive when disjoint).

    See the module docstring for what it is under each back end, and
    :func:`check_collision` for the arguments; ``0`` for pairs that cannot be certified.

    Examples:
        >>> box = Zonotope.from_interval(-torch.ones(2), torch.ones(2))
        >>> clearance(box, box.translate(torch.tensor([[1.5, 0.0], [3.0, 4.0]])))
        tensor([-0.5000,  2.0000])
    """
    return _check(sets, obstacles, backend, True, solver_args)[0].clearance


def _check(sets, obstacles, backend: str, with_clearance: bool, solver_args: dict | None
           ) -> tuple[CollisionResult, str]:
    batch = _validate(sets, obstacles, backend)
    if backend != "lp" and isinstance(sets, Zonotope) and isinstance(obstacles, Zonotope) \
            and sets.dim in CLOSED_FORM_DIMS:
        result = _closed_form(sets, obstacles, batch, with_clearance, required=backend == "closed_form")
        if result is not None:
            return result, "closed_form"
    elif backend == "closed_form":
        raise ValueError("`backend`='closed_form' needs two Zonotope batches of dimension 1, 2 or 3")
    return _lp(sets, obstacles, batch, with_clearance, solver_args), "lp"


def _validate(sets, obstacles, backend: str) -> torch.Size:
    kinds = (Zonotope, ConstrainedZonotope)
    for name, value in (("sets", sets), ("obstacles", obstacles)):
        if not isinstance(value, kinds):
            raise ValueError(f"`{name}` must be a Zonotope or ConstrainedZonotope, got {type(value).__name__}")
    if backend not in BACKENDS:
        raise ValueError(f"`backend` must be one of {BACKENDS}, got {backend!r}")
    if obstacles.dim != sets.dim:
        raise ValueError(f"`obstacles` are {obstacles.dim}-dimensional but `sets` are {sets.dim}-dimensional")
    if obstacles.center.dtype != sets.center.dtype:
        raise ValueError(f"`obstacles` have dtype {obstacles.center.dtype} but `sets` have {sets.center.dtype}")
    if obstacles.center.device != sets.center.device:
        raise ValueError(f"`obstacles` are on {obstacles.center.device} but `sets` are on {sets.center.device}")
    return _broadcast("obstacles", obstacles.batch_size, sets.batch_size)


def _closed_form(sets: Zonotope, obstacles: Zonotope, batch: torch.Size, with_clearance: bool, required: bool
                 ) -> CollisionResult | None:
    """The closed form on the broadcast batch, or ``None`` if some pair is not full-dimensional."""
    g1, g2 = sets.generators, obstacles.generators
    generators = torch.cat((g1.expand(*batch, *g1.shape[-2:]), g2.expand(*batch, *g2.shape[-2:])), dim=-1)
    offsets, finite = finite_offsets((obstacles.center - sets.center).expand(*batch, sets.dim))
    finite = finite & torch.isfinite(generators).flatten(-2).all(-1)
    generators = torch.where(finite[..., None, None], generators, 0.0)
    offsets = torch.where(finite.unsqueeze(-1), offsets, 0.0)
    if not bool((is_full_dimensional(generators) | ~finite).all()):
        if required:
            raise ValueError("`sets` and `obstacles`: Z(0, [G1, G2]) is not full-dimensional for some pair, "
                             "so `backend`='closed_form' does not apply")
        return None
    table = facet_table(generators)
    value = torch.where(finite, gauge_values(offsets, table), 0.0)
    clear = torch.where(finite, facet_clearances(offsets, table), 0.0) if with_clearance else None
    reason = torch.where(finite, int(CollisionStatus.OK), int(CollisionStatus.NONFINITE)).to(torch.int8)
    return CollisionResult(value, clear, finite, reason)


def _lp(sets, obstacles, batch: torch.Size, with_clearance: bool, solver_args: dict | None) -> CollisionResult:
    """Emptiness of each constrained zonotope, the intersection LP and, if asked, the distance SOCP."""
    s, o = _constrained_parts(sets, batch), _constrained_parts(obstacles, batch)
    reason = torch.full(batch, int(CollisionStatus.OK), dtype=torch.int8, device=sets.center.device)
    for cz in (sets, obstacles):  # an empty set never collides, but it is a broken description
        if isinstance(cz, ConstrainedZonotope) and cz.n_constraints:
            own, own_reason = solve_gauge(cz.A, cz.b, solver_args=solver_args)
            own_reason = torch.where((own_reason == CollisionStatus.OK) & (own > 1 + LP_TOL),
                                     int(CollisionStatus.EMPTY_SET), own_reason)
            reason = torch.where(reason == CollisionStatus.OK, own_reason.expand(batch), reason)
    finite = torch.stack([torch.isfinite(t).flatten(len(batch)).all(-1) for t in (*s, *o)]).all(0)
    reason = torch.where(finite | (reason != CollisionStatus.OK), reason, int(CollisionStatus.NONFINITE))
    safe = [torch.where(finite.reshape(*batch, *[1] * (t.ndim - len(batch))), t, 0.0) for t in (*s, *o)]
    inter = ConstrainedZonotope(*safe[:4]).intersect(ConstrainedZonotope(*safe[4:]))
    value, lp_reason = solve_gauge(inter.A, inter.b, active=reason == CollisionStatus.OK, solver_args=solver_args)
    # both sets are non-empty here, so equations without any solution mean disjoint sets: v* = inf
    lp_reason = torch.where(lp_reason == CollisionStatus.INFEASIBLE, int(CollisionStatus.OK), lp_reason)
    reason = torch.where(reason == CollisionStatus.OK, lp_reason, reason)
    clear = None
    if with_clearance:
        nc = inter.A.shape[-2] - sets.dim  # constraint rows of the pair; the last n rows hold [G1, -G2] z = dc
        disjoint = (reason == CollisionStatus.OK) & (value > 1)
        dist, dist_reason = solve_distance(inter.A[..., nc:, :], inter.b[..., nc:], inter.A[..., :nc, :],
                                           inter.b[..., :nc], active=disjoint, solver_args=solver_args)
        reason = torch.where(reason == CollisionStatus.OK, dist_reason, reason)
        generators = torch.cat((safe[1], safe[5]), dim=-1)
        s_min = (torch.linalg.svdvals(generators)[..., -1] if generators.shape[-1] >= sets.dim
                 else torch.zeros_like(value))
        inside = (torch.where(disjoint, 1.0, value) - 1) * s_min  # no inf * 0 in the backward of disjoint pairs
        clear = torch.where(disjoint, dist, inside)
    ok = reason == CollisionStatus.OK
    value = torch.where(ok, value, 0.0)
    clear = torch.where(ok, clear, 0.0) if with_clearance else None
    return CollisionResult(value, clear, ok, reason)


def _constrained_parts(cz, batch: torch.Size) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(c, G, A, b)`` of a (constrained) zonotope, expanded to ``batch``."""
    c, g = cz.center, cz.generators
    if isinstance(cz, ConstrainedZonotope):
        a, b = cz.A, cz.b
    else:
        a, b = g.new_zeros(*g.shape[:-2], 0, g.shape[-1]), g.new_zeros(*g.shape[:-2], 0)
    return (c.expand(*batch, *c.shape[-1:]), g.expand(*batch, *g.shape[-2:]),
            a.expand(*batch, *a.shape[-2:]), b.expand(*batch, *b.shape[-1:]))


__all__ = ["BACKENDS", "LP_TOL", "check_collision", "clearance", "collision_value", "intersects"]
