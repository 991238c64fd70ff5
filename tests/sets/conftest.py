"""Shared fixtures for the set-algebra tests: seeded generators and independent HiGHS oracles.

The oracles are written from the definitions, independently of ``torchrl_brsl.sets.lp``:
membership is a feasibility LP with box bounds, the gauge and support are LPs over the
generator coefficients.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.optimize import linprog


def _np(x) -> np.ndarray:
    return x.detach().double().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=float)


def _empty_constraints(p: int):
    return np.zeros((0, p)), np.zeros(0)


def lp_member(c, G, x, A=None, b=None) -> bool:
    """Whether ``x`` is in ``{c + G z : A z = b, -1 <= z <= 1}`` (one feasibility LP)."""
    c, G, x = _np(c), _np(G), _np(x)
    p = G.shape[1]
    A, b = _empty_constraints(p) if A is None else (_np(A), _np(b))
    A_eq, b_eq = np.vstack([G, A]), np.concatenate([x - c, b])
    if p == 0:
        return bool(np.allclose(b_eq, 0.0, atol=1e-9))
    res = linprog(np.zeros(p), A_eq=A_eq, b_eq=b_eq, bounds=[(-1.0, 1.0)] * p, method="highs")
    assert res.status in (0, 2), res.message
    return res.status == 0


def lp_gauge(G, x) -> float:
    """Gauge of ``Z(0, G)`` at ``x``: ``min t`` such that ``G z = x`` and ``|z_i| <= t``."""
    G, x = _np(G), _np(x)
    n, p = G.shape
    # variables (z, t): G z = x, -t <= z_i <= t
    cost = np.r_[np.zeros(p), 1.0]
    A_ub = np.block([[np.eye(p), -np.ones((p, 1))], [-np.eye(p), -np.ones((p, 1))]])
    res = linprog(cost, A_ub=A_ub, b_ub=np.zeros(2 * p), A_eq=np.hstack([G, np.zeros((n, 1))]), b_eq=x,
                  bounds=[(None, None)] * p + [(0, None)], method="highs")
    if res.status == 2:
        return float("inf")
    assert res.status == 0, res.message
    return float(res.fun)


def lp_support(d, c, G, A=None, b=None) -> float:
    """``max d . x`` over ``{c + G z : A z = b, |z| <= 1}``."""
    d, c, G = _np(d), _np(c), _np(G)
    p = G.shape[1]
    kwargs = {} if A is None or _np(A).shape[0] == 0 else {"A_eq": _np(A), "b_eq": _np(b)}
    res = linprog(-(d @ G), bounds=[(-1.0, 1.0)] * p, method="highs", **kwargs)
    assert res.status == 0, res.message
    return float(d @ c - res.fun)


def random_zonotope(gen: torch.Generator, n: int, p: int, batch=(), dtype=torch.float64):
    """A random zonotope with centre in ``[-1, 1]^n`` and standard normal generators."""
    from torchrl_brsl.sets import Zonotope

    center = torch.rand(*batch, n, generator=gen, dtype=dtype) * 2 - 1
    generators = torch.randn(*batch, n, p, generator=gen, dtype=dtype)
    return Zonotope(center, generators)


def box_points(gen: torch.Generator, lo, hi, num: int) -> torch.Tensor:
    """``num`` uniform points in the box ``[lo, hi]`` (``[n]`` each): ``[num, n]``."""
    u = torch.rand(num, lo.shape[-1], generator=gen, dtype=lo.dtype)
    return lo + u * (hi - lo)


@pytest.fixture(scope="session")
def oracle():
    """Independent reference computations (HiGHS LPs and random set factories)."""
    return SimpleNamespace(member=lp_member, gauge=lp_gauge, support=lp_support,
                           random_zonotope=random_zonotope, box_points=box_points)


@pytest.fixture
def gen():
    """A seeded ``torch.Generator`` so every test draws the same data on every run."""
    return torch.Generator().manual_seed(1234)
