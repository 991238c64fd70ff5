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
    res = linprog(cost, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b, bounds=[(None, None)] * p + [(0, None)],
                  method="highs")
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
    res = linprog(-(direction @ G), A_eq=A if A.shape[0] else None, b_eq=b if A.shape[0] else None,
                  bounds=[(-1.0, 1.0)] * p, method="highs")
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
            res = linprog(cost, A_ub=H, b_ub=h, bounds=[(None, None)] * n, method="highs")
            if res.status == 2:
                raise ValueError("the polytope `H x <= h` is empty")
            if res.status == 3:
                raise ValueError("the polytope `H x <= h` is unbounded")
            if res.status != 0:
                raise RuntimeError(f"HiGHS failed: {res.message}")
            out[i] = res.x[i]
    return lo, hi
