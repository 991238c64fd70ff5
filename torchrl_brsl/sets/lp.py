"""Small linear programs on constrained zonotopes, solved one at a time with HiGHS.

These are the slow, obvious reference paths (not differentiable, CPU, float64): point
containment, emptiness, support values and bounding boxes of constrained zonotopes.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import linprog


def gauge_lp(A: np.ndarray, b: np.ndarray) -> float:
    """Solve ``min v s.t. A z = b, |z| <= v`` and return ``v*`` (``inf`` if infeasible).

    Args:
        A: ``[m, p]`` equality matrix.
        b: ``[m]`` right-hand side.
    """
    m, p = A.shape
    if p == 0:
        return 0.0 if np.allclose(b, 0.0) else float("inf")
    # variables (z, v); |z_i| <= v  <=>  z_i - v <= 0, -z_i - v <= 0
    cost = np.zeros(p + 1)
    cost[-1] = 1.0
    eye = np.eye(p)
    ones = np.ones((p, 1))
    A_ub = np.block([[eye, -ones], [-eye, -ones]])
    b_ub = np.zeros(2 * p)
    A_eq = np.hstack([A, np.zeros((m, 1))])
    res = _linprog(cost, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b, bounds=[(None, None)] * p + [(0, None)])
    if res.status == 2:
        return float("inf")
    if res.status != 0:
        raise RuntimeError(f"HiGHS failed: {res.message}")
    return float(res.fun)


def support_lp(direction: np.ndarray, center: np.ndarray, G: np.ndarray, A: np.ndarray, b: np.ndarray
               ) -> tuple[float, np.ndarray]:
    """Support value and maximiser of ``Z(c, G, A, b)`` along ``direction``.

    Returns:
        ``(max_x d.x, argmax x)``; raises ``ValueError`` if the set is empty.
    """
    p = G.shape[1]
    res = _linprog(-(direction @ G), A_eq=A if A.shape[0] else None, b_eq=b if A.shape[0] else None,
                   bounds=[(-1.0, 1.0)] * p)
    if res.status == 2:
        raise ValueError("the constrained zonotope is empty")
    if res.status != 0:
        raise RuntimeError(f"HiGHS failed: {res.message}")
    x = center + G @ res.x
    return float(direction @ x), x


def polytope_bounds(H: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box of ``{x : H x <= h}``; raises ``ValueError`` if empty or unbounded."""
    n = H.shape[1]
    lo, hi = np.empty(n), np.empty(n)
    for i in range(n):
        for sign, out in ((1.0, lo), (-1.0, hi)):
            cost = np.zeros(n)
            cost[i] = sign
            res = _linprog(cost, A_ub=H, b_ub=h, bounds=[(None, None)] * n)
            if res.status == 2:
                raise ValueError("the polytope `H x <= h` is empty")
            if res.status == 3:
                raise ValueError("the polytope `H x <= h` is unbounded")
            if res.status != 0:
                raise RuntimeError(f"HiGHS failed: {res.message}")
            out[i] = res.x[i]
    return lo, hi


NUMERICAL_DIFFICULTIES = 4
""":func:`scipy.optimize.linprog`'s status where the solver gave up on the problem's numerics."""


def _linprog(cost: np.ndarray, **problem):
    """:func:`scipy.optimize.linprog` with HiGHS's choice of method, and its interior-point method where that gives up
    on the numerics (a capped quadrotor's 6 x 30 gauge problem with two zero generators: the dual simplex stopped with
    "Not Set", the interior point solved it)."""
    res = linprog(cost, method="highs", **problem)
    if res.status == NUMERICAL_DIFFICULTIES:
        res = linprog(cost, method="highs-ipm", **problem)
    return res
