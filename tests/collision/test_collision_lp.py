"""The CvxpyLayer back end: constrained zonotopes in 2-4 D, gradients, clearance, caching."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from collision_support import (
    highs_gauge,
    highs_values,
    intersection_program,
    np64,
    polygon_distance,
    random_polytope,
    random_zonotope_pairs,
    stack_sets,
    support_points,
)

from torchrl_brsl.collision import check_collision, clearance, collision_value, solve_gauge
from torchrl_brsl.collision.lp import SOLVER_ARGS, distance_layer, gauge_layer
from torchrl_brsl.sets import ConstrainedZonotope, Zonotope


def polytope_pairs(seed: int, n: int, num: int):
    """``num`` pairs of random polytopes (constrained zonotopes) with centres spread apart."""
    gen = torch.Generator().manual_seed(seed)
    sets = stack_sets([random_polytope(gen, n, m=3) for _ in range(num)])
    obstacles = stack_sets([random_polytope(gen, n, m=2) for _ in range(num)])
    shift = 1.6 * torch.randn(num, n, generator=gen, dtype=torch.float64)
    return sets, obstacles.translate(shift)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_constrained_zonotopes_agree_with_highs(n):
    sets, obstacles = polytope_pairs(seed=n, n=n, num=16)
    ref = highs_values(sets, obstacles)
    assert (ref <= 1).any() and (ref > 1).any()
    result = check_collision(sets, obstacles, with_clearance=False)
    assert result.ok.all(), result.reason_names()
    np.testing.assert_allclose(np64(result.value), ref, rtol=1e-6)


def test_mixed_kinds_and_broadcasting():
    """A zonotope batch [H, 1] against constrained obstacles [1, K] gives [H, K] pairs."""
    gen = torch.Generator().manual_seed(5)
    H, K = 3, 4
    sets = Zonotope(torch.randn(H, 1, 2, generator=gen, dtype=torch.float64),
                    0.5 * torch.randn(H, 1, 2, 5, generator=gen, dtype=torch.float64))
    obstacles = stack_sets([random_polytope(gen, 2, m=3) for _ in range(K)])
    obstacles = ConstrainedZonotope(obstacles.center.unsqueeze(0), obstacles.generators.unsqueeze(0),
                                    obstacles.A.unsqueeze(0), obstacles.b.unsqueeze(0))
    value = collision_value(sets, obstacles)
    assert value.shape == (H, K)
    for h in range(H):
        for k in range(K):
            A, b = intersection_program(sets[h, 0], obstacles[0, k])
            assert float(value[h, k]) == pytest.approx(highs_gauge(A, b)[0], rel=1e-6)


@pytest.mark.parametrize("n", [2, 3])
def test_common_point_from_the_lp_solution(n):
    sets, obstacles = polytope_pairs(seed=10 + n, n=n, num=12)
    value = collision_value(sets, obstacles)
    for i in torch.nonzero(value <= 1).squeeze(-1).tolist():
        A, b = intersection_program(sets[i], obstacles[i])
        v, z = gauge_layer(*A.shape)(torch.from_numpy(A), torch.from_numpy(b), solver_args=SOLVER_ARGS)
        point = sets.center[i] + sets.generators[i] @ z[: sets.n_generators]
        assert sets[i].contains(point, tol=1e-6) and obstacles[i].contains(point, tol=1e-6)
    directions = np.random.default_rng(n).standard_normal((24, n))
    for i in torch.nonzero(value > 1).squeeze(-1).tolist():
        points = torch.from_numpy(support_points(sets[i], directions))
        assert not obstacles[i].expand(24).contains(points).any()


def _finite_difference(fn, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    grad = torch.zeros_like(x)
    flat = grad.view(-1)
    for j in range(x.numel()):
        e = torch.zeros_like(x).view(-1)
        e[j] = h
        e = e.view_as(x)
        flat[j] = (fn(x + e) - fn(x - e)) / (2 * h)
    return grad


def test_lp_gradients_match_finite_differences():
    """d v*/d centres, d v*/d b and d v*/d generators of eq. (10) against HiGHS central differences."""
    sets, obstacles = polytope_pairs(seed=20, n=2, num=2)
    c1, g1, b1 = (t.clone().requires_grad_() for t in (sets.center, sets.generators, sets.b))
    c2 = obstacles.center.clone().requires_grad_()
    value = collision_value(ConstrainedZonotope(c1, g1, sets.A, b1),
                            ConstrainedZonotope(c2, obstacles.generators, obstacles.A, obstacles.b))
    grads = torch.autograd.grad(value.sum(), (c1, c2, b1, g1))

    def highs(c1_=c1, c2_=c2, b1_=b1, g1_=g1):
        s = ConstrainedZonotope(c1_.detach(), g1_.detach(), sets.A, b1_.detach())
        o = ConstrainedZonotope(c2_.detach(), obstacles.generators, obstacles.A, obstacles.b)
        return torch.from_numpy(highs_values(s, o)).sum()

    expected = (
        _finite_difference(lambda x: highs(c1_=x), c1.detach()),
        _finite_difference(lambda x: highs(c2_=x), c2.detach()),
        _finite_difference(lambda x: highs(b1_=x), b1.detach()),
        _finite_difference(lambda x: highs(g1_=x), g1.detach()),
    )
    for got, want in zip(grads, expected):
        assert want.abs().max() > 0
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_lp_and_closed_form_gradients_agree_for_zonotopes():
    sets, obstacles = random_zonotope_pairs(seed=21, n=3, num=8, p1=10, p2=3)
    grads = {}
    for backend in ("closed_form", "lp"):
        c1 = sets.center.clone().requires_grad_()
        value = collision_value(Zonotope(c1, sets.generators), obstacles, backend=backend)
        grads[backend] = torch.autograd.grad(value.sum(), c1)[0]
    torch.testing.assert_close(grads["lp"], grads["closed_form"], rtol=1e-5, atol=1e-6)


def test_lp_clearance_is_the_distance_outside_and_bounded_inside_for_zonotopes():
    sets, obstacles = random_zonotope_pairs(seed=30, n=2, num=30, p1=6, p2=2)
    lp = check_collision(sets, obstacles, backend="lp")
    closed = check_collision(sets, obstacles, backend="closed_form")
    assert lp.ok.all()
    assert ((lp.clearance > 0) == (lp.value > 1)).all()
    # closed form: lower bound outside, exact depth inside; LP: exact outside, within the depth inside
    assert (closed.clearance <= lp.clearance + 1e-7).all()
    assert (lp.clearance <= 1e-12).eq(lp.value <= 1).all()
    for i in torch.nonzero(lp.value > 1).squeeze(-1).tolist():
        exact = polygon_distance(np64(sets[i].vertices()), np64(obstacles[i].vertices()))
        assert float(lp.clearance[i]) == pytest.approx(exact, rel=1e-6, abs=1e-8)


@pytest.mark.parametrize("n", [2, 3])
def test_lp_clearance_invariants_for_constrained_zonotopes(n):
    sets, obstacles = polytope_pairs(seed=40 + n, n=n, num=8)
    result = check_collision(sets, obstacles)
    assert result.ok.all()
    assert ((result.clearance > 0) == (result.value > 1)).all()
    assert ((result.clearance < 0) == (result.value < 1)).all()
    directions = np.random.default_rng(n).standard_normal((48, n))
    for i in torch.nonzero(result.value > 1).squeeze(-1).tolist():
        # support points are points of the sets, so their distance bounds the true one from above
        a, b = support_points(sets[i], directions), support_points(obstacles[i], directions)
        bound = np.linalg.norm(a[:, None] - b[None], axis=-1).min()
        if n == 2:  # the convex hulls of the support points are inner polygons: a tighter bound
            bound = min(bound, polygon_distance(a[_hull_order(a)], b[_hull_order(b)]))
        assert 0 < float(result.clearance[i]) <= bound + 1e-7


def _hull_order(points: np.ndarray) -> np.ndarray:
    """Angular order of support points around their mean (they are in convex position)."""
    d = points - points.mean(0)
    return np.argsort(np.arctan2(d[:, 1], d[:, 0]))


def test_layers_are_cached_per_size():
    assert gauge_layer(3, 7) is gauge_layer(3, 7)
    assert gauge_layer(3, 7) is not gauge_layer(3, 8)
    assert distance_layer(2, 7, 0) is distance_layer(2, 7, 0)


def test_solve_gauge_batches_and_skips_inactive():
    gen = torch.Generator().manual_seed(50)
    A = torch.randn(2, 3, 2, 6, generator=gen, dtype=torch.float64)
    b = torch.randn(2, 3, 2, generator=gen, dtype=torch.float64)
    active = torch.tensor([[True, False, True], [True, True, False]])
    value, reason = solve_gauge(A, b, active=active)
    assert value.shape == reason.shape == (2, 3)
    assert (value[~active] == 0).all() and (reason == 0).all()
    for i, j in torch.nonzero(active).tolist():
        assert float(value[i, j]) == pytest.approx(highs_gauge(np64(A[i, j]), np64(b[i, j]))[0], rel=1e-6)


def test_float32_sets_use_the_lp_in_float64():
    gen = torch.Generator().manual_seed(60)
    s = random_polytope(gen, 2, m=3)
    o = random_polytope(gen, 2, m=3).translate(torch.tensor([0.5, 0.2], dtype=torch.float64))
    v64 = collision_value(s, o)
    s32 = ConstrainedZonotope(*(t.float() for t in (s.center, s.generators, s.A, s.b)))
    o32 = ConstrainedZonotope(*(t.float() for t in (o.center, o.generators, o.A, o.b)))
    v32 = collision_value(s32, o32)
    assert v32.dtype == torch.float32
    assert float(v32) == pytest.approx(float(v64), rel=1e-5)
    assert clearance(s32, o32).dtype == torch.float32
