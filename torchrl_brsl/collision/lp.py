"""Batched, differentiable collision programs of constrained zonotopes through ``CvxpyLayer``.

Two convex programs, each compiled once per problem size and cached:

* the gauge LP of Selim et al. (2022), eq. (10): ``v* = min v s.t. A z = b, |z| <= v``
  (:func:`solve_gauge`), used on the intersection data of Scott et al. (2016), Prop. 1,
  and on a single constrained zonotope's own constraints to test emptiness;
* the distance SOCP ``min ||G z - d||_2 s.t. A z = b, ||z||_inf <= 1``
  (:func:`solve_distance`): the Euclidean distance between two constrained zonotopes.

Both run on the CPU in float64 (results come back on the inputs' device and dtype) with
Clarabel through diffcp, one problem after another on one thread (:data:`SOLVER_ARGS`),
and are differentiated by diffcp's implicit differentiation of the
solution map. That derivative is the true gradient wherever the primal and dual solutions
are unique; at degenerate points (ties between active constraints, e.g. exactly symmetric
configurations) the value is only directionally differentiable and diffcp returns one
least-squares element. No regulariser is added, so the values are those of the exact
programs.

Nothing here raises on bad numbers: every element gets a :class:`CollisionStatus`. Elements
with NaN or infinite data and elements whose equality constraints have no solution at all
(checked by least squares before solving; ``v* = inf``) are not sent to the solver; a
solver exception for the batch is retried element by element; every returned point is
checked against the constraints and rejected (``SOLVER_FAILED``) if it violates them.
"""
from __future__ import annotations

import functools

import cvxpy as cp
import torch
from cvxpylayers.torch import CvxpyLayer
from torch import Tensor

from torchrl_brsl.collision.result import CollisionStatus

SOLVER_ARGS = {"solve_method": "Clarabel", "n_jobs_forward": 1, "tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10,
               "tol_feas": 1e-10}
"""Default ``solver_args`` of the layers (overridable per call); the backward pass also runs
on one thread (``n_jobs_backward=1``) unless overridden."""

FEASIBILITY_RTOL = 1e-6
"""Relative constraint violation above which a returned solution is rejected."""


@functools.lru_cache(maxsize=64)
def gauge_layer(n_rows: int, n_cols: int) -> CvxpyLayer:
    """``min v s.t. A z = b, |z| <= v`` with parameters ``(A [n_rows, n_cols], b [n_rows])``.

    Returns a layer whose outputs are ``(v, z)``; cached per size.
    """
    A = cp.Parameter((n_rows, n_cols))
    b = cp.Parameter(n_rows)
    z = cp.Variable(n_cols)
    v = cp.Variable()
    problem = cp.Problem(cp.Minimize(v), [A @ z == b, cp.abs(z) <= v])
    return CvxpyLayer(problem, parameters=[A, b], variables=[v, z])


@functools.lru_cache(maxsize=64)
def distance_layer(n: int, n_cols: int, n_rows: int) -> CvxpyLayer:
    """``min t s.t. ||G z - d||_2 <= t, A z = b, ||z||_inf <= 1``.

    Parameters ``(G [n, n_cols], d [n], A [n_rows, n_cols], b [n_rows])``, or ``(G, d)``
    when ``n_rows == 0``. Returns a layer whose outputs are ``(t, z)``; cached per size.
    """
    G = cp.Parameter((n, n_cols))
    d = cp.Parameter(n)
    z = cp.Variable(n_cols)
    t = cp.Variable()
    constraints = [cp.norm(G @ z - d, 2) <= t, cp.abs(z) <= 1]
    parameters = [G, d]
    if n_rows:
        A = cp.Parameter((n_rows, n_cols))
        b = cp.Parameter(n_rows)
        constraints.append(A @ z == b)
        parameters += [A, b]
    return CvxpyLayer(cp.Problem(cp.Minimize(t), constraints), parameters=parameters, variables=[t, z])


def solve_gauge(A: Tensor, b: Tensor, active: Tensor | None = None, solver_args: dict | None = None
                ) -> tuple[Tensor, Tensor]:
    """Batched ``v* = min ||z||_inf s.t. A z = b``, differentiable w.r.t. ``A`` and ``b``.

    Args:
        A: ``[..., m, p]``.
        b: ``[..., m]`` (same batch shape).
        active: optional bool ``[...]``; inactive elements are not solved (value 0,
            reason ``OK``).
        solver_args: overrides of :data:`SOLVER_ARGS`.

    Returns:
        ``(value, reason)``, each ``[...]``: ``v*`` in the dtype of ``A`` and ``torch.int8``
        :class:`CollisionStatus` codes. Where ``A z = b`` has no solution at all the value is
        ``inf`` (the optimum of an infeasible minimisation) and the reason ``INFEASIBLE``;
        the caller decides what that means. Other failures give value 0.

    Examples:
        >>> A = torch.tensor([[[1.0, 1.0]], [[0.0, 0.0]]], dtype=torch.float64)
        >>> b = torch.tensor([[1.0], [1.0]], dtype=torch.float64)
        >>> value, reason = solve_gauge(A, b)
        >>> value.round(decimals=6), reason
        (tensor([0.5000,    inf], dtype=torch.float64), tensor([0, 3], dtype=torch.int8))
    """
    batch, (m, p) = A.shape[:-2], A.shape[-2:]
    if p == 0:  # a zero column leaves the program unchanged and gives cvxpy a variable
        A = torch.nn.functional.pad(A, (0, 1))
        p = 1
    rows = batch.numel()
    flat_A, flat_b = A.reshape(rows, m, p).double().cpu(), b.reshape(rows, m).double().cpu()
    reason = _status_of_data(flat_A, flat_b)
    feasible = _has_solution(flat_A, flat_b)
    reason = torch.where((reason == CollisionStatus.OK) & ~feasible, int(CollisionStatus.INFEASIBLE), reason)
    todo = reason == CollisionStatus.OK
    if active is not None:
        todo &= active.reshape(rows).cpu()
    value = flat_A.new_zeros(rows)
    if m and bool(todo.any()):
        idx = todo.nonzero().squeeze(-1)
        sub_A, sub_b = flat_A[idx], flat_b[idx]
        (v, z), solved = _solve(gauge_layer(m, p), (sub_A, sub_b), p, solver_args)
        z, v_ = z.detach(), v.detach()
        bounded = z.abs().amax(-1) <= v_ + FEASIBILITY_RTOL * (1 + v_.abs())
        good = solved & torch.isfinite(v_) & _satisfies(sub_A, sub_b, z) & bounded
        value = value.index_put((idx,), torch.where(good, v, 0.0))
        reason = reason.index_put((idx,), torch.where(good, reason[idx], int(CollisionStatus.SOLVER_FAILED)))
    value = torch.where(reason == CollisionStatus.INFEASIBLE, float("inf"), value)
    return value.to(A.device, A.dtype).reshape(batch), reason.to(A.device).reshape(batch)


def solve_distance(G: Tensor, d: Tensor, A: Tensor, b: Tensor, active: Tensor | None = None,
                   solver_args: dict | None = None) -> tuple[Tensor, Tensor]:
    """Batched ``min ||G z - d||_2 s.t. A z = b, ||z||_inf <= 1``, differentiable in all data.

    With ``G = [G1, -G2]``, ``d = c2 - c1`` and ``A = blkdiag(A1, A2)``, ``b = [b1; b2]``
    this is the Euclidean distance between ``Z(c1, G1, A1, b1)`` and ``Z(c2, G2, A2, b2)``.

    Args:
        G: ``[..., n, p]``.
        d: ``[..., n]``.
        A: ``[..., nc, p]`` (``nc`` may be 0).
        b: ``[..., nc]``.
        active: optional bool ``[...]``; inactive elements are not solved (distance 0,
            reason ``OK``).
        solver_args: overrides of :data:`SOLVER_ARGS`.

    Returns:
        ``(distance, reason)`` as in :func:`solve_gauge`. Elements whose constraints are
        infeasible within ``||z||_inf <= 1`` (empty sets) come back ``SOLVER_FAILED``.
    """
    batch, (n, p), nc = G.shape[:-2], G.shape[-2:], A.shape[-2]
    if p == 0:
        G, A = torch.nn.functional.pad(G, (0, 1)), torch.nn.functional.pad(A, (0, 1))
        p = 1
    rows = batch.numel()
    flat = [G.reshape(rows, n, p), d.reshape(rows, n), A.reshape(rows, nc, p), b.reshape(rows, nc)]
    flat = [t.double().cpu() for t in flat]
    reason = _status_of_data(*flat)
    todo = reason == CollisionStatus.OK
    if active is not None:
        todo &= active.reshape(rows).cpu()
    dist = flat[0].new_zeros(rows)
    if bool(todo.any()):
        idx = todo.nonzero().squeeze(-1)
        sub = [t[idx] for t in flat]
        (t, z), solved = _solve(distance_layer(n, p, nc), tuple(sub if nc else sub[:2]), p, solver_args)
        z = z.detach()
        bounded = z.abs().amax(-1) <= 1 + FEASIBILITY_RTOL
        good = solved & torch.isfinite(t.detach()) & _satisfies(sub[2], sub[3], z) & bounded
        dist = dist.index_put((idx,), torch.where(good, t.clamp_min(0), 0.0))
        reason = reason.index_put((idx,), torch.where(good, reason[idx], int(CollisionStatus.SOLVER_FAILED)))
    return dist.to(G.device, G.dtype).reshape(batch), reason.to(G.device).reshape(batch)


def _solve(layer: CvxpyLayer, params: tuple[Tensor, ...], z_size: int, solver_args: dict | None
           ) -> tuple[tuple[Tensor, Tensor], Tensor]:
    """Run ``layer`` (outputs: a scalar and ``z [z_size]``) on a batch; on an exception retry
    element by element.

    Returns the two outputs (zeros where an element failed) and a bool mask of the elements
    the solver returned without raising.
    """
    args = {**SOLVER_ARGS, **(solver_args or {})}
    if torch.is_grad_enabled() and any(p.requires_grad for p in params):
        args.setdefault("n_jobs_backward", 1)  # only the differentiating solve accepts it
    try:
        return layer(*params, solver_args=args), torch.ones(len(params[0]), dtype=torch.bool)
    except Exception:  # noqa: BLE001 - any solver error becomes a per-element status
        pass
    scalars, points, solved = [], [], []
    for i in range(len(params[0])):
        try:
            scalar, point = layer(*(p[i:i + 1] for p in params), solver_args=args)
            solved.append(True)
        except Exception:  # noqa: BLE001
            scalar, point = params[0].new_zeros(1), params[0].new_zeros(1, z_size)
            solved.append(False)
        scalars.append(scalar.reshape(1))
        points.append(point.reshape(1, z_size))
    return (torch.cat(scalars), torch.cat(points)), torch.tensor(solved)


def _satisfies(A: Tensor, b: Tensor, z: Tensor, rtol: float = FEASIBILITY_RTOL) -> Tensor:
    """Whether ``A z = b`` holds to relative tolerance ``rtol``.

    ``A`` is ``[rows, m, p]``, ``b`` ``[rows, m]`` and ``z`` ``[rows, p]``; returns bool ``[rows]``.
    """
    if A.shape[-2] == 0:
        return torch.ones(A.shape[0], dtype=torch.bool, device=A.device)
    residual = ((A @ z.unsqueeze(-1)).squeeze(-1) - b).abs().amax(-1)
    scale = 1 + b.abs().amax(-1) + A.abs().amax((-2, -1)) * z.abs().amax(-1)
    return residual <= rtol * scale


def _status_of_data(*tensors: Tensor) -> Tensor:
    """``NONFINITE`` where any of the ``[rows, ...]`` tensors has a NaN/inf entry, else ``OK``."""
    finite = torch.ones(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    for t in tensors:
        finite &= torch.isfinite(t.detach()).reshape(t.shape[0], -1).all(-1)
    return torch.where(finite, int(CollisionStatus.OK), int(CollisionStatus.NONFINITE)).to(torch.int8)


def _has_solution(A: Tensor, b: Tensor) -> Tensor:
    """Whether ``A z = b`` has any solution, by a least-squares residual test: bool ``[rows]``."""
    if A.shape[-2] == 0:
        return torch.ones(A.shape[0], dtype=torch.bool, device=A.device)
    finite = torch.isfinite(A).flatten(1).all(-1) & torch.isfinite(b).all(-1)
    A = torch.where(finite[:, None, None], A.detach(), 0.0)
    b = torch.where(finite[:, None], b.detach(), 0.0)
    z = torch.linalg.lstsq(A, b.unsqueeze(-1), driver="gelsd").solution.squeeze(-1)
    return _satisfies(A, b, z, rtol=1e-9)


__all__ = ["SOLVER_ARGS", "distance_layer", "gauge_layer", "solve_distance", "solve_gauge"]
