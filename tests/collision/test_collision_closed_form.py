"""The closed-form back end: exactness against HiGHS and the LP, geometry, gradients, caching."""
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
    random_zonotope_pairs,
    to_boundary,
)

from torchrl_brsl.collision import (
    ZonotopeCollisionChecker,
    check_collision,
    clearance,
    collision_value,
    facet_table,
    intersects,
    is_full_dimensional,
    pair_facets,
    pair_gauge,
)
from torchrl_brsl.collision import closed_form
from torchrl_brsl.collision.closed_form import _PAIR_FACETS, facet_clearances, gauge_values
from torchrl_brsl.collision.lp import SOLVER_ARGS, gauge_layer
from torchrl_brsl.sets import Zonotope

SIZES = {2: (8, 2), 3: (11, 3)}  # reachable-set and obstacle generator counts


@pytest.mark.parametrize("n", [2, 3])
def test_closed_form_agrees_with_lp_and_highs(n):
    p1, p2 = SIZES[n]
    sets, obstacles = random_zonotope_pairs(seed=n, n=n, num=60, p1=p1, p2=p2)
    # a third of the pairs within 1 % of the boundary, both sides
    targets = np.random.default_rng(n).uniform(0.99, 1.01, size=20)
    near = to_boundary(sets[:20], obstacles[:20], targets)
    obstacles = Zonotope(torch.cat([near.center, obstacles.center[20:]]), obstacles.generators)
    ref = highs_values(sets, obstacles)
    closed = check_collision(sets, obstacles, backend="closed_form", with_clearance=False)
    lp = check_collision(sets, obstacles, backend="lp", with_clearance=False)
    assert closed.ok.all() and lp.ok.all()
    np.testing.assert_allclose(np64(closed.value), ref, rtol=1e-8)
    np.testing.assert_allclose(np64(lp.value), ref, rtol=1e-6)
    np.testing.assert_allclose(np64(closed.value[:20]), targets, rtol=1e-8)
    # the near-boundary pairs are classified as HiGHS classifies them
    assert (intersects(sets, obstacles).numpy() == (ref <= 1)).all()
    assert collision_value(sets, obstacles).dtype == torch.float64


@pytest.mark.parametrize("n", [2, 3])
def test_degenerate_generators(n):
    """Zero columns, repeated and parallel generators leave the value exact."""
    gen = torch.Generator().manual_seed(10 + n)
    g = torch.randn(40, n, 4, generator=gen, dtype=torch.float64)
    g1 = torch.cat([g, 2 * g[..., :1], -g[..., 1:2], torch.zeros(40, n, 2, dtype=torch.float64)], dim=-1)
    g2 = torch.cat([torch.diag_embed(torch.rand(40, n, generator=gen, dtype=torch.float64)), g[..., 2:3]], dim=-1)
    sets = Zonotope(torch.zeros(40, n, dtype=torch.float64), g1)
    obstacles = Zonotope(3 * torch.randn(40, n, generator=gen, dtype=torch.float64), g2)
    ref = highs_values(sets, obstacles)
    np.testing.assert_allclose(np64(collision_value(sets, obstacles, backend="closed_form")), ref, rtol=1e-8)
    checker = ZonotopeCollisionChecker(g1, g2)
    assert checker.n_facets < facet_table(torch.cat([g1, g2], -1)).weights.shape[-2]
    np.testing.assert_allclose(np64(checker.value(sets.center, obstacles.center)), ref, rtol=1e-8)


def test_auto_falls_back_to_lp_when_not_full_dimensional():
    # two segments on one line in 2-D: Z(0, [G1, G2]) is flat
    seg = torch.tensor([[1.0], [0.0]], dtype=torch.float64)
    sets = Zonotope(torch.zeros(2, 2, dtype=torch.float64), seg.expand(2, 2, 1))
    obstacles = Zonotope(torch.tensor([[1.5, 0.0], [1.0, 0.5]], dtype=torch.float64), 0.5 * seg.expand(2, 2, 1))
    value = collision_value(sets, obstacles)
    np.testing.assert_allclose(np64(value)[0], 1.0, rtol=1e-6)  # touching end to end
    assert value[1] == float("inf")  # parallel lines never meet: the equations have no solution
    assert clearance(sets, obstacles)[1] == pytest.approx(0.5, rel=1e-6)
    with pytest.raises(ValueError, match="backend"):
        collision_value(sets, obstacles, backend="closed_form")
    # v* = inf must not turn into NaN gradients
    g1 = sets.generators.clone().requires_grad_()
    c1 = sets.center.clone().requires_grad_()
    result = check_collision(Zonotope(c1, g1), obstacles)
    grads = torch.autograd.grad(result.value.sum() + result.clearance.sum(), (c1, g1), allow_unused=True)
    assert all(torch.isfinite(g).all() for g in grads if g is not None)


@pytest.mark.parametrize("n", [2, 3])
def test_intersection_truth_by_sampling(n):
    p1, p2 = SIZES[n]
    sets, obstacles = random_zonotope_pairs(seed=20 + n, n=n, num=40, p1=p1, p2=p2)
    value = collision_value(sets, obstacles)
    gen = torch.Generator().manual_seed(0)
    points = sets.sample(2000, generator=gen)  # [2000, N, n]
    inside_both = obstacles.contains(points)  # [2000, N]
    separate = value > 1
    assert separate.any() and (~separate).any()
    assert not inside_both[:, separate].any()
    # v* <= 1: the LP solution z* is a point of both sets
    for i in torch.nonzero(~separate).squeeze(-1).tolist():
        A, b = intersection_program(sets[i], obstacles[i])
        v, z = gauge_layer(*A.shape)(torch.from_numpy(A), torch.from_numpy(b), solver_args=SOLVER_ARGS)
        assert abs(float(v) - float(value[i])) < 1e-6
        point = sets.center[i] + sets.generators[i] @ z[:p1]
        assert sets[i].contains(point, tol=1e-6) and obstacles[i].contains(point, tol=1e-6)


@pytest.mark.parametrize("n", [2, 3])
def test_gradients_match_finite_differences(n):
    p1, p2 = SIZES[n]
    sets, obstacles = random_zonotope_pairs(seed=30 + n, n=n, num=6, p1=p1, p2=p2)
    tensors = (sets.center, sets.generators, obstacles.center, obstacles.generators)
    inputs = [t.clone().requires_grad_() for t in tensors]

    def value(c1, g1, c2, g2):
        return collision_value(Zonotope(c1, g1), Zonotope(c2, g2), backend="closed_form")

    def clear(c1, g1, c2, g2):
        return clearance(Zonotope(c1, g1), Zonotope(c2, g2), backend="closed_form")

    assert torch.autograd.gradcheck(value, inputs, eps=1e-7, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradcheck(clear, inputs, eps=1e-7, atol=1e-6, fast_mode=True)
    checker = ZonotopeCollisionChecker(sets.generators, obstacles.generators)
    assert torch.autograd.gradcheck(checker.value, (inputs[0], inputs[2]), eps=1e-7, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradcheck(checker.clearance, (inputs[0], inputs[2]), eps=1e-7, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("n", [2, 3])
def test_checker_broadcasts_steps_against_obstacles(n):
    p1, p2 = SIZES[n]
    gen = torch.Generator().manual_seed(40 + n)
    H, K, B = 5, 4, 3
    g_sets = 0.3 * torch.randn(H, 1, n, p1, generator=gen, dtype=torch.float64)
    g_obs = torch.diag_embed(0.2 + torch.rand(1, K, n, generator=gen, dtype=torch.float64))
    c_sets = torch.randn(B, H, 1, n, generator=gen, dtype=torch.float64)
    c_obs = torch.randn(B, 1, K, n, generator=gen, dtype=torch.float64)
    checker = ZonotopeCollisionChecker(g_sets, g_obs)
    result = checker.check(c_sets, c_obs)
    assert result.value.shape == (B, H, K) and result.ok.all()
    reference = check_collision(Zonotope(c_sets, g_sets.expand(B, H, 1, n, p1)),
                                Zonotope(c_obs, g_obs.expand(B, 1, K, n, n)))
    torch.testing.assert_close(result.value, reference.value, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(result.clearance, reference.clearance, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [2, 3])
def test_clearance_is_depth_inside_and_a_lower_bound_outside(n):
    p1, p2 = SIZES[n]
    sets, obstacles = random_zonotope_pairs(seed=50 + n, n=n, num=40, p1=p1, p2=p2)
    result = check_collision(sets, obstacles)
    value, clear = result.value, result.clearance
    assert ((clear > 0) == (value > 1)).all()
    touching = to_boundary(sets[:5], obstacles[:5], np.ones(5))
    assert clearance(sets[:5], touching).abs().max() < 1e-9

    gen = torch.Generator().manual_seed(0)
    directions = torch.randn(200, n, generator=gen, dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    offsets = obstacles.center - sets.center
    generators = torch.cat([sets.generators, obstacles.generators], -1)
    table = facet_table(generators)
    for i in torch.nonzero(value < 1).squeeze(-1).tolist():
        depth = -float(clear[i])
        # moving the obstacle by less than the depth in any direction keeps the contact ...
        moved = Zonotope(sets.center[i] + offsets[i] + (depth - 1e-7) * directions,
                         obstacles.generators[i].expand(200, n, p2))
        assert (collision_value(sets[i], moved) <= 1).all()
        # ... and moving it just past the depth along the deepest facet normal separates
        scores = (table.normals[i] @ offsets[i]).abs() - table.supports[i]
        k = int(scores.argmax())
        u = table.normals[i, k] * torch.sign(table.normals[i, k] @ offsets[i])
        escaped = Zonotope(sets.center[i] + offsets[i] + (depth + 1e-7) * u, obstacles.generators[i])
        assert collision_value(sets[i], escaped) > 1

    if n == 2:  # outside: a lower bound on the exact polygon distance
        for i in torch.nonzero(value > 1).squeeze(-1).tolist():
            exact = polygon_distance(np64(sets[i].vertices()), np64(obstacles[i].vertices()))
            assert 0 < float(clear[i]) <= exact + 1e-9


def test_intersects_margin_and_tolerance():
    box = Zonotope.from_interval(-torch.ones(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    offsets = torch.tensor([[2.0, 0.0], [2.0 + 1e-12, 0.0], [2.1, 0.0], [2.3, 0.0]], dtype=torch.float64)
    others = box.translate(offsets)  # v* = 1, 1 + 5e-13, 1.05, 1.15
    assert intersects(box, others).tolist() == [True, True, False, False]
    assert intersects(box, others, tol=0.0).tolist() == [True, False, False, False]
    assert intersects(box, others, margin=0.1).tolist() == [True, True, True, False]


def test_closed_form_float32_matches_float64():
    sets, obstacles = random_zonotope_pairs(seed=60, n=3, num=50, p1=10, p2=3)
    v64 = collision_value(sets, obstacles)
    v32 = collision_value(Zonotope(sets.center.float(), sets.generators.float()),
                          Zonotope(obstacles.center.float(), obstacles.generators.float()))
    assert v32.dtype == torch.float32
    torch.testing.assert_close(v32.double(), v64, rtol=1e-4, atol=1e-5)


def test_highs_oracle_is_independent_of_the_sets_module():
    """The oracle's program is eq. (10) built by hand; it agrees with ConstrainedZonotope.intersect."""
    sets, obstacles = random_zonotope_pairs(seed=70, n=2, num=3, p1=4, p2=2)
    for i in range(3):
        A, b = intersection_program(sets[i], obstacles[i])
        inter = sets[i].to_constrained().intersect(obstacles[i].to_constrained())
        np.testing.assert_allclose(A, np64(inter.A))
        np.testing.assert_allclose(b, np64(inter.b))
        assert np.isfinite(highs_gauge(A, b)[0])


def test_a_flat_pair_is_widened_on_request_and_only_stricter():
    """A 2 km flat wall beside a set of 1e-6: Z(0, [G1, G2]) is numerically flat. Without ``widen`` the
    checker refuses it; with it the pair gets a tiny box, and its values are never above the LP's."""
    D = torch.float64
    tiny = 1e-6 * torch.eye(2, dtype=D).view(1, 1, 2, 2)
    wall = torch.tensor([[1e3], [0.0]], dtype=D).view(1, 1, 2, 1)
    with pytest.raises(ValueError, match="not full-dimensional"):
        ZonotopeCollisionChecker(tiny, wall)
    checker = ZonotopeCollisionChecker(tiny, wall, widen=True)
    centers = torch.tensor([[0.0, 0.5], [0.0, 1e-9], [5.0, 0.0]], dtype=D).view(3, 1, 2)
    values = checker.value(centers, torch.zeros(1, 1, 2, dtype=D))
    sets = Zonotope(centers.squeeze(1), tiny[0, 0].expand(3, 2, 2))
    exact = collision_value(sets, Zonotope(torch.zeros(2, dtype=D), wall[0, 0]), backend="lp")
    assert (values.squeeze(-1) <= exact * (1 + 1e-6)).all()
    assert values[0, 0] > 1 and values[2, 0] <= 1


@pytest.mark.parametrize("n", [2, 3])
def test_pair_tables_split_the_support_products_exactly(n):
    """The checker's tables from the sets' and the obstacles' own products and the per-pair crosses give the
    values and clearances of each pair's own table and the values of HiGHS, parallel and zero columns included."""
    gen = torch.Generator().manual_seed(60 + n)
    H, K, B, p = 6, 5, 4, 9
    g = 0.3 * torch.randn(H, 1, n, p, generator=gen, dtype=torch.float64)
    g_sets = torch.cat((g, -2 * g[..., :1], torch.zeros(H, 1, n, 1, dtype=torch.float64)), -1)
    g_obs = torch.cat((torch.diag_embed(0.1 + torch.rand(1, K, n, generator=gen, dtype=torch.float64)),
                       g_sets[:1, :, :, 1:2].expand(1, K, n, 1)), -1)  # one column parallel to a set's
    full = _PAIR_FACETS[n](g_sets, g_obs).full
    assert full.shape == (H, K) and full.all()
    split = ZonotopeCollisionChecker(g_sets, g_obs, deduplicate=False)
    own = facet_table(torch.cat((g_sets.expand(H, K, n, p + 2), g_obs.expand(H, K, n, n + 1)), -1))
    assert split.n_facets == own.weights.shape[-2]
    if n == 2:  # the same rows in the same order
        torch.testing.assert_close(split.table, own, rtol=1e-13, atol=1e-13)
    c_sets = torch.randn(B, H, 1, n, generator=gen, dtype=torch.float64)
    c_obs = torch.randn(B, 1, K, n, generator=gen, dtype=torch.float64)
    offsets = c_obs - c_sets
    torch.testing.assert_close(split.value(c_sets, c_obs), gauge_values(offsets, own), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(split.clearance(c_sets, c_obs), facet_clearances(offsets, own), rtol=1e-12,
                               atol=1e-12)
    values = ZonotopeCollisionChecker(g_sets, g_obs).value(c_sets, c_obs)
    sets = Zonotope(c_sets.expand(B, H, K, n).reshape(-1, n), g_sets.expand(B, H, K, n, p + 2).reshape(-1, n, p + 2))
    obstacles = Zonotope(c_obs.expand(B, H, K, n).reshape(-1, n), g_obs.expand(B, H, K, n, n + 1).reshape(-1, n, n + 1))
    np.testing.assert_allclose(np64(values).ravel(), highs_values(sets, obstacles), rtol=1e-8)


@pytest.mark.parametrize("n", [2, 3])
def test_pair_gauge_gives_the_tables_values_and_attaining_rows_without_forming_them(n):
    """``pair_gauge`` on ``pair_facets`` (normals per owner, 3-D mixed supports by the triple product) gives
    the values of each pair's own table and of HiGHS, parallel and zero columns included, and the row it
    picks attains the value: ``|picked| = value`` and ``picked = weights . offset``."""
    gen = torch.Generator().manual_seed(70 + n)
    H, K, B, p = 6, 5, 4, 9
    g = 0.3 * torch.randn(H, 1, n, p, generator=gen, dtype=torch.float64)
    g_sets = torch.cat((g, -2 * g[..., :1], torch.zeros(H, 1, n, 1, dtype=torch.float64)), -1)
    g_obs = torch.cat((torch.diag_embed(0.1 + torch.rand(1, K, n, generator=gen, dtype=torch.float64)),
                       g_sets[:1, :, :, 1:2].expand(1, K, n, 1)), -1)
    offsets = torch.randn(B, H, K, n, generator=gen, dtype=torch.float64)
    values, picked, weights = pair_gauge(offsets, pair_facets(g_sets, g_obs))
    own = facet_table(torch.cat((g_sets.expand(H, K, n, p + 2), g_obs.expand(H, K, n, n + 1)), -1))
    torch.testing.assert_close(values, gauge_values(offsets, own), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(picked.abs(), values, rtol=0, atol=0)
    torch.testing.assert_close((weights * offsets).sum(-1), picked, rtol=1e-12, atol=1e-12)
    sets = Zonotope(torch.zeros(B * H * K, n, dtype=torch.float64), g_sets.expand(B, H, K, n, p + 2).reshape(
        -1, n, p + 2))
    obstacles = Zonotope(offsets.reshape(-1, n), g_obs.expand(B, H, K, n, n + 1).reshape(-1, n, n + 1))
    np.testing.assert_allclose(np64(values).ravel(), highs_values(sets, obstacles), rtol=1e-8)


def test_mixed_rows_rounding_bound_keeps_every_value_below_the_gauge(monkeypatch):
    """3-D set generators exactly or nearly (1e-12) parallel to an obstacle's: their crosses are rounding
    noise, whose supports the triple products do not measure. With the rounding bound every value stays
    at or below HiGHS's gauge (a collision is never missed); without it (teeth) some pair claims more."""
    gen = torch.Generator().manual_seed(72)
    N, p = 64, 6
    shared = torch.randn(N, 3, 1, generator=gen, dtype=torch.float64)
    g_obs = torch.cat((torch.diag_embed(0.1 + torch.rand(N, 3, generator=gen, dtype=torch.float64)), shared), -1)
    tilt = 1e-12 * torch.randn(N, 3, 1, generator=gen, dtype=torch.float64)
    g_sets = torch.cat((torch.randn(N, 3, p, generator=gen, dtype=torch.float64), shared, -2 * shared,
                        shared + tilt), -1)
    offsets = 3 * torch.randn(N, 3, generator=gen, dtype=torch.float64)
    sets = Zonotope(torch.zeros(N, 3, dtype=torch.float64), g_sets)
    reference = torch.as_tensor(highs_values(sets, Zonotope(offsets, g_obs)))
    values = pair_gauge(offsets, pair_facets(g_sets, g_obs))[0]
    assert (values <= reference * (1 + 1e-8)).all()
    monkeypatch.setattr(closed_form, "_triple_rounding", lambda g1, g2: 0.0)
    unbounded = pair_gauge(offsets, pair_facets(g_sets, g_obs))[0]
    assert (unbounded > reference * (1 + 1e-6)).any()


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("ratio", [0.0, 1e-12, 1e-9, 1e-8, 3e-8, 6e-8, 1e-7, 1e-6, 1e-4, 1.0])
def test_pair_full_dimensional_test_never_accepts_what_the_singular_values_reject(n, ratio):
    """Near-flat pairs at singular-value ratios around the threshold ``sqrt(eps) ≈ 1.5e-8``: the determinant
    test accepts only pairs the SVD test accepts (4x inside it), and accepts clearly full ones."""
    gen = torch.Generator().manual_seed(61)
    turn = torch.linalg.qr(torch.randn(32, n, n, generator=gen, dtype=torch.float64)).Q
    scales = torch.tensor([3.0] * (n - 1) + [3.0 * ratio], dtype=torch.float64)
    g1 = turn @ torch.diag(scales) @ torch.randn(32, n, 5, generator=gen, dtype=torch.float64).sign()
    eye = torch.eye(n, dtype=torch.float64)
    g2 = turn @ torch.diag(scales) @ (eye + 0.5 * eye.roll(1, 1))
    full = _PAIR_FACETS[n](g1, g2).full
    svd = is_full_dimensional(torch.cat((g1, g2), -1))
    assert not (full & ~svd).any()
    if ratio >= (1e-6 if n == 2 else 1e-4):
        assert full.all()
    if ratio <= 1e-9:
        assert not svd.any()
