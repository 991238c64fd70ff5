"""Constrained-zonotope algebra checked against closed-form membership of its pieces and HiGHS."""
from __future__ import annotations

import doctest
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

import torchrl_brsl.sets.constrained_zonotope as cz_module
from torchrl_brsl.sets import ConstrainedZonotope, Zonotope, zonotope_gauge

F64 = torch.float64
MARGIN = 1e-6  # points this close to a boundary are not used to judge membership


def gauge(z: Zonotope, pts: torch.Tensor) -> torch.Tensor:
    return zonotope_gauge(pts - z.center, z.generators)


def overlapping_pair(gen, oracle, n=2):
    """Two zonotopes that overlap without one containing the other.

    The centre of the second is a vertex of the first and its generators are smaller, so part
    of each lies outside the other.
    """
    z1 = oracle.random_zonotope(gen, n, 3)
    vertex = z1.center + z1.generators.sum(-1)
    z2 = Zonotope(vertex, 0.6 * torch.randn(n, 4, generator=gen, dtype=F64))
    return z1, z2


def test_from_zonotope_is_the_same_set(gen, oracle):
    z = oracle.random_zonotope(gen, 3, 5)
    cz = ConstrainedZonotope.from_zonotope(z)
    assert cz.n_constraints == 0 and cz.n_generators == 5 and cz.dim == 3
    lo, hi = z.interval()
    pts = oracle.box_points(gen, lo, hi, 80)
    g = gauge(z, pts)
    keep = (g - 1).abs() > MARGIN
    assert torch.equal(cz.contains(pts)[keep], (g <= 1)[keep])
    assert (g[keep] <= 1).any() and (g[keep] > 1).any()


def test_from_box_oriented():
    rot = torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=F64)
    cz = ConstrainedZonotope.from_box(torch.zeros(2, dtype=F64), torch.tensor([2.0, 0.5], dtype=F64), rot)
    assert cz.contains(torch.tensor([[0.49, 1.99], [-0.49, -1.99]], dtype=F64)).all()
    assert not cz.contains(torch.tensor([[1.99, 0.49], [0.51, 0.0]], dtype=F64)).any()


# --------------------------------------------------------------------------- polytopes
def _polygon_halfspaces(gen, m):
    angles = torch.arange(m, dtype=F64) * 2 * math.pi / m + torch.rand(m, generator=gen, dtype=F64) * 0.3
    H = torch.stack((angles.cos(), angles.sin()), -1)
    h = 0.5 + torch.rand(m, generator=gen, dtype=F64)
    return H, h


def _polytope_3d(gen):
    H = torch.cat((torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64), torch.randn(6, 3, generator=gen, dtype=F64)))
    h = torch.cat((torch.ones(6, dtype=F64) * 2, 0.5 + torch.rand(6, generator=gen, dtype=F64)))
    return H, h


@pytest.mark.parametrize("dim", [2, 3])
def test_from_polytope_membership(gen, oracle, dim):
    H, h = _polygon_halfspaces(gen, 7) if dim == 2 else _polytope_3d(gen)
    cz = ConstrainedZonotope.from_polytope(H, h)
    lo, hi = cz.interval()
    pts = oracle.box_points(gen, lo - 0.3, hi + 0.3, 120)
    violation = (pts @ H.T - h).amax(-1)
    keep = violation.abs() > MARGIN
    got = cz.contains(pts)
    assert got[violation <= -MARGIN].all()  # every point with H x <= h is in the set
    assert not got[violation >= MARGIN].any()  # and no point violating a row is
    assert keep.sum() > 100 and (violation < 0).sum() > 3


def test_from_polytope_bounding_box_is_tight(gen):
    H, h = _polygon_halfspaces(gen, 5)
    lo, hi = ConstrainedZonotope.from_polytope(H, h).interval()
    from scipy.optimize import linprog

    for i in range(2):
        e = torch.zeros(2, dtype=F64)
        e[i] = 1.0
        low = linprog(e.numpy(), A_ub=H.numpy(), b_ub=h.numpy(), bounds=[(None, None)] * 2, method="highs").fun
        high = -linprog(-e.numpy(), A_ub=H.numpy(), b_ub=h.numpy(), bounds=[(None, None)] * 2, method="highs").fun
        assert lo[i].item() == pytest.approx(low, abs=1e-7)
        assert hi[i].item() == pytest.approx(high, abs=1e-7)


def test_from_polytope_rejects_unbounded_and_empty():
    with pytest.raises(ValueError, match="unbounded"):
        ConstrainedZonotope.from_polytope(torch.tensor([[1.0, 0.0], [0.0, 1.0]]), torch.ones(2))
    with pytest.raises(ValueError, match="empty"):
        ConstrainedZonotope.from_polytope(torch.tensor([[1.0], [-1.0]]), torch.tensor([-1.0, -1.0]))


# --------------------------------------------------------------------------- intersection
def test_intersect_membership_by_sampling(gen, oracle):
    z1, z2 = overlapping_pair(gen, oracle)
    inter = z1.to_constrained().intersect(z2)
    assert inter.n_generators == 7 and inter.n_constraints == 2
    pts = z1.sample(150, generator=gen)
    g2 = gauge(z2, pts)
    keep = (g2 - 1).abs() > MARGIN
    got = inter.contains(pts)
    assert got[keep & (g2 <= 1)].all()  # samples of Z1 in Z2 are in Z1 ∩ Z2
    assert not got[keep & (g2 > 1)].any()  # samples of Z1 outside Z2 are not
    assert (keep & (g2 <= 1)).sum() > 3 and (keep & (g2 > 1)).sum() > 3
    # points of Z2 outside Z1 are not in it either
    pts2 = z2.sample(60, generator=gen)
    g1 = gauge(z1, pts2)
    assert not inter.contains(pts2[g1 > 1 + MARGIN]).any()


def test_intersect_of_constrained_operands(gen, oracle):
    z1, z2 = overlapping_pair(gen, oracle)
    H = torch.tensor([1.0, 1.0], dtype=F64)
    h = H @ z2.center - 0.1 * H @ z1.generators.sum(-1)  # cuts Z1 ∩ Z2 but keeps part of it
    x = z1.to_constrained().intersect_halfspace(H, h).intersect(z2.to_constrained())
    lo, hi = x.interval()  # only where the points are drawn: a region around the set
    pad = 0.2 * (hi - lo)
    pts = oracle.box_points(gen, lo - pad, hi + pad, 150)
    score = torch.stack((gauge(z1, pts) - 1, gauge(z2, pts) - 1, pts @ H - h), -1).amax(-1)
    keep = score.abs() > MARGIN
    assert torch.equal(x.contains(pts)[keep], (score <= 0)[keep])
    assert (score[keep] <= 0).sum() > 5


def test_intersect_of_disjoint_sets_is_empty():
    a = Zonotope.from_interval(torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    b = a.translate(torch.tensor([1.5, 0.0], dtype=F64))
    touching = a.translate(torch.tensor([1.0, 1.0], dtype=F64))
    assert a.to_constrained().intersect(b).is_empty()
    assert not a.to_constrained().intersect(touching).is_empty()  # they share the corner (1, 1)
    assert a.to_constrained().intersect(touching).contains(torch.ones(2, dtype=F64))


def test_intersect_halfspace_forms(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 4)
    cz = z.to_constrained()
    H = torch.tensor([[1.0, -0.5], [0.2, 1.0]], dtype=F64)
    h = H @ z.center + torch.tensor([0.3, -0.2], dtype=F64)
    both = cz.intersect_halfspace(H, h)
    assert both.n_constraints == 2 and both.n_generators == 6
    one = cz.intersect_halfspace(H[0], h[0])
    float_h = cz.intersect_halfspace(H[0], float(h[0]))
    pts = z.sample(120, generator=gen)
    slack = pts @ H.T - h
    keep = slack.abs().amin(-1) > MARGIN
    assert torch.equal(both.contains(pts)[keep], (slack <= 0).all(-1)[keep])
    assert torch.equal(one.contains(pts)[keep], (slack[:, 0] <= 0)[keep])
    assert torch.equal(float_h.b, one.b)
    assert ((slack <= 0).all(-1) & keep).sum() > 5 and ((slack > 0).any(-1) & keep).sum() > 5


def test_intersect_halfspace_missing_the_set_is_empty():
    box = Zonotope.from_interval(-torch.ones(2, dtype=F64), torch.ones(2, dtype=F64)).to_constrained()
    far = box.intersect_halfspace(torch.tensor([1.0, 0.0], dtype=F64), torch.tensor(-5.0, dtype=F64))
    assert far.is_empty()
    assert not far.contains(torch.tensor([[-1.0, 0.0], [-1.0, 1.0], [0.0, 0.0]], dtype=F64)).any()
    edge = box.intersect_halfspace(torch.tensor([1.0, 0.0], dtype=F64), torch.tensor(-1.0, dtype=F64))
    assert not edge.is_empty()  # the halfspace touches the left edge
    assert edge.contains(torch.tensor([-1.0, 0.5], dtype=F64))
    assert not edge.contains(torch.tensor([-0.99, 0.5], dtype=F64))


def test_intersect_halfspace_that_contains_the_set_changes_nothing(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3)
    d = torch.tensor([0.6, 0.8], dtype=F64)
    cut = z.to_constrained().intersect_halfspace(d, z.support(d) + 1.0)
    lo, hi = cut.interval()
    torch.testing.assert_close(lo, z.interval()[0])
    torch.testing.assert_close(hi, z.interval()[1])


def test_intersect_halfspace_batched(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3, batch=(3,))
    H = torch.randn(3, 2, 2, generator=gen, dtype=F64)
    h = (H @ z.center.unsqueeze(-1)).squeeze(-1)  # both halfspaces through each centre
    out = z.to_constrained().intersect_halfspace(H, h)
    assert out.batch_size == (3,)
    for i in range(3):
        single = z[i].to_constrained().intersect_halfspace(H[i], h[i])
        torch.testing.assert_close(out[i].A, single.A)
        torch.testing.assert_close(out[i].b, single.b)
    shared = z.to_constrained().intersect_halfspace(H[0], h[0])  # one H for the whole batch
    assert shared.batch_size == (3,)
    assert not out.is_empty().any()


# --------------------------------------------------------------------------- other algebra
@pytest.fixture
def lens(gen, oracle):
    """A constrained zonotope with constraints and the closed-form truth of its membership."""
    z1, z2 = overlapping_pair(gen, oracle)

    def truth(pts):
        return torch.maximum(gauge(z1, pts), gauge(z2, pts)) - 1  # <= 0 inside

    def samples(num):
        """Uniform points of Z1's bounding box that lie in Z1 ∩ Z2 (``num`` drawn before filtering)."""
        lo, hi = z1.interval()
        pts = oracle.box_points(gen, lo, hi, num)
        return pts[truth(pts) <= 0]

    return z1.to_constrained().intersect(z2), truth, samples


def test_linear_map(lens, gen):
    x, truth, samples = lens
    M = torch.tensor([[1.5, 0.5], [-1.0, 2.0]], dtype=F64)
    mx = x.linear_map(M)
    assert torch.equal((M @ x).generators, mx.generators)
    lo, hi = x.interval()
    pts = torch.rand(120, 2, generator=gen, dtype=F64) * (hi - lo) * 1.4 + lo - 0.2 * (hi - lo)
    t = truth(pts)
    keep = t.abs() > MARGIN
    assert torch.equal(mx.contains(pts @ M.T)[keep], (t <= 0)[keep])
    batched = x.linear_map(torch.stack([M, 2 * M]))
    assert batched.batch_size == (2,)
    assert batched.A.shape[:-2] == (2,)


def test_minkowski_sum(lens, gen, oracle):
    x, _, samples = lens
    y = oracle.random_zonotope(gen, 2, 2)
    for s in (x + y, y + x, x.minkowski_sum(y.to_constrained()), x + x):
        assert isinstance(s, ConstrainedZonotope)
    s = x + y
    xs = samples(3000)[:40]
    assert len(xs) >= 10
    assert s.contains(xs + y.sample(len(xs), generator=gen)).all()
    xx = x + x
    assert xx.contains(xs + xs.flip(0)).all()
    # the interval hull of a sum is the sum of the hulls: exact non-membership information
    (lo_x, hi_x), (lo_y, hi_y), (lo_s, hi_s) = x.interval(), y.interval(), s.interval()
    torch.testing.assert_close(lo_s, lo_x + lo_y, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(hi_s, hi_x + hi_y, rtol=1e-7, atol=1e-7)
    assert not s.contains(hi_s + torch.tensor([1e-4, 0.0], dtype=F64))


def test_translate(lens, gen):
    x, truth, samples = lens
    t = torch.tensor([3.0, -1.0], dtype=F64)
    pts = samples(3000)[:20]
    assert len(pts) >= 10
    for moved, shift in ((x.translate(t), t), (x + t, t), (x - t, -t)):
        assert moved.contains(pts + shift).all()
        assert not moved.contains(pts).all()
    lo, hi = x.interval()
    torch.testing.assert_close(x.translate(t).interval()[1], hi + t, rtol=1e-7, atol=1e-7)


def test_cartesian_product(lens, gen, oracle):
    x, truth, samples = lens
    y = oracle.random_zonotope(gen, 1, 2)
    prod = x.cartesian_product(y)
    assert prod.dim == 3 and prod.n_constraints == x.n_constraints
    xs = samples(3000)[:20]
    assert len(xs) >= 10
    ys = y.sample(len(xs), generator=gen)
    assert prod.contains(torch.cat((xs, ys), -1)).all()
    outside_y = y.center + 1.01 * y.radius()
    assert not prod.contains(torch.cat((xs, outside_y.expand(len(xs), 1)), -1)).any()
    far_x = xs + 10.0
    assert not prod.contains(torch.cat((far_x, ys), -1)).any()


def test_project(gen, oracle):
    z = oracle.random_zonotope(gen, 3, 4)
    x = z.to_constrained().intersect_halfspace(torch.tensor([1.0, 1.0, 1.0], dtype=F64), z.center.sum())
    proj = x.project([2, 0])
    lo, hi = x.interval()
    plo, phi = proj.interval()
    torch.testing.assert_close(plo, lo[[2, 0]], rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(phi, hi[[2, 0]], rtol=1e-7, atol=1e-7)
    pts = z.sample(100, generator=gen)
    inside = pts[pts.sum(-1) <= z.center.sum()][:20]
    assert proj.contains(inside[:, [2, 0]]).all()


def test_interval_is_tight_and_contains_samples(lens, gen, oracle):
    x, truth, samples = lens
    lo, hi = x.interval()
    width = hi - lo
    # members among dense points of a box 10 % wider than the hull on every side
    pts = oracle.box_points(gen, lo - 0.1 * width, hi + 0.1 * width, 20000)
    pts = pts[truth(pts) <= 0]
    assert len(pts) > 1000
    assert ((pts >= lo - 1e-9) & (pts <= hi + 1e-9)).all()
    assert ((pts.amax(0) - hi).abs() < 0.05 * width).all()
    assert ((pts.amin(0) - lo).abs() < 0.05 * width).all()
    # attained exactly: the support points along +-e_i are members with those coordinates
    v = x.vertices(4)  # directions +e_0, +e_1, -e_0, -e_1
    assert (truth(v) <= 1e-7).all()
    torch.testing.assert_close(torch.stack((v[0, 0], v[1, 1], v[2, 0], v[3, 1])),
                               torch.stack((hi[0], hi[1], lo[0], lo[1])))
    # exact for a zonotope
    z = Zonotope(torch.zeros(2, dtype=F64), torch.tensor([[1.0, 2.0], [0.5, -1.0]], dtype=F64))
    zlo, zhi = z.to_constrained().interval()
    torch.testing.assert_close(zhi, torch.tensor([3.0, 1.5], dtype=F64))
    torch.testing.assert_close(zlo, -zhi)


def test_interval_of_an_empty_set_raises():
    box = Zonotope.from_interval(-torch.ones(2, dtype=F64), torch.ones(2, dtype=F64)).to_constrained()
    with pytest.raises(ValueError, match="empty"):
        box.intersect_halfspace(torch.tensor([1.0, 0.0], dtype=F64), torch.tensor(-2.0, dtype=F64)).interval()


def test_vertices_on_the_boundary(lens, gen):
    x, truth, samples = lens
    v = x.vertices(32)
    assert v.shape == (32, 2)
    t = truth(v)
    assert (t.abs() < 1e-7).all()  # every support point is on the boundary of Z1 ∩ Z2
    angles = torch.arange(32, dtype=F64) * 2 * math.pi / 32
    dirs = torch.stack((angles.cos(), angles.sin()), -1)
    assert not x.contains(v + 1e-4 * dirs).any()


def test_vertices_of_a_zonotope_are_exact():
    angles = torch.tensor([0.1, 1.2, 2.2], dtype=F64)  # every normal cone is wider than 2 pi / 64
    G = torch.stack((angles.cos(), angles.sin())) * torch.tensor([1.0, 0.5, 2.0], dtype=F64)
    z = Zonotope(torch.tensor([0.3, -1.0], dtype=F64), G)
    v = z.to_constrained().vertices(64)
    assert z.contains(v).all()
    unique = torch.unique(v.round(decimals=6), dim=0)
    assert len(unique) == 6  # all 2p vertices are hit by 64 directions
    zv = z.vertices()
    dist = torch.cdist(unique, zv).amin(-1)
    assert (dist < 1e-6).all()


def test_vertices_needs_two_dimensions(gen, oracle):
    with pytest.raises(ValueError, match="2-D"):
        oracle.random_zonotope(gen, 3, 3).to_constrained().vertices()


def test_pad_keeps_the_set(lens, gen):
    x, truth, samples = lens
    padded = x.pad(x.n_generators + 3, x.n_constraints + 2)
    assert padded.n_generators == x.n_generators + 3 and padded.n_constraints == x.n_constraints + 2
    lo, hi = x.interval()
    pts = torch.rand(60, 2, generator=gen, dtype=F64) * (hi - lo) + lo
    keep = truth(pts).abs() > MARGIN
    assert torch.equal(padded.contains(pts)[keep], x.contains(pts)[keep])
    plo, phi = padded.interval()
    torch.testing.assert_close(plo, lo, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(phi, hi, rtol=1e-7, atol=1e-7)


def test_singleton_and_unconstrained_queries():
    pt = Zonotope.from_point(torch.tensor([1.0, 2.0], dtype=F64)).to_constrained()
    assert pt.contains(torch.tensor([1.0, 2.0], dtype=F64))
    assert not pt.contains(torch.tensor([1.0, 2.001], dtype=F64))
    assert not pt.is_empty()
    lo, hi = Zonotope.from_interval(torch.zeros(3, dtype=F64), torch.ones(3, dtype=F64)).to_constrained().interval()
    torch.testing.assert_close(hi, torch.ones(3, dtype=F64))


# --------------------------------------------------------------------------- emptiness
def test_is_empty_cases():
    g = torch.eye(2, dtype=F64)
    infeasible = ConstrainedZonotope(torch.zeros(2, dtype=F64), g, torch.tensor([[1.0, 0.0]], dtype=F64),
                                     torch.tensor([2.0], dtype=F64))  # z_1 = 2 is out of [-1, 1]
    boundary = ConstrainedZonotope(torch.zeros(2, dtype=F64), g, torch.tensor([[1.0, 1.0]], dtype=F64),
                                   torch.tensor([2.0], dtype=F64))  # only z = (1, 1)
    assert infeasible.is_empty()
    assert not boundary.is_empty()
    assert boundary.contains(torch.ones(2, dtype=F64))
    assert not boundary.contains(torch.tensor([1.0, 0.9], dtype=F64))
    batch = torch.stack([infeasible, boundary, infeasible])
    assert batch.is_empty().tolist() == [True, False, True]
    assert not infeasible.contains(torch.zeros(2, dtype=F64))


def test_is_empty_batched_intersections(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3)
    shifts = torch.tensor([[0.0, 0.0], [100.0, 0.0], [0.1, -0.2], [0.0, -100.0]], dtype=F64)
    inter = z.to_constrained().intersect(z.translate(shifts))
    assert inter.batch_size == (4,)
    assert inter.is_empty().tolist() == [False, True, False, True]


# --------------------------------------------------------------------------- batching
def test_broadcast_batches(gen, oracle):
    a = oracle.random_zonotope(gen, 2, 2, batch=(3, 1)).to_constrained()
    b = oracle.random_zonotope(gen, 2, 3, batch=(1, 4))
    for out in (a.intersect(b), a + b, a.cartesian_product(b)):
        assert out.batch_size == (3, 4)
    inter = a.intersect(b)
    for i in range(3):
        for j in range(4):
            single = a[i, 0].intersect(b[0, j])
            torch.testing.assert_close(inter[i, j].A, single.A)
            torch.testing.assert_close(inter[i, j].b, single.b)
            torch.testing.assert_close(inter[i, j].generators, single.generators)
    moved = a.translate(torch.zeros(1, 4, 2, dtype=F64))
    assert moved.batch_size == (3, 4)
    assert a.contains(torch.zeros(1, 4, 2, dtype=F64)).shape == (3, 4)


def test_tensordict_storage_index_stack_and_dtype(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3, batch=(4,), dtype=torch.float32)
    cz = z.to_constrained().intersect_halfspace(torch.tensor([1.0, 0.0]), torch.tensor(0.0))
    td = TensorDict({"obstacle": cz}, batch_size=[4])
    item = td[1]["obstacle"]
    assert isinstance(item, ConstrainedZonotope) and item.batch_size == ()
    assert torch.equal(item.A, cz.A[1]) and torch.equal(item.b, cz.b[1])
    stacked = torch.stack([td, td])
    assert stacked["obstacle"].batch_size == (2, 4)
    cz64 = cz.to(F64)
    assert all(t.dtype == F64 for t in (cz64.center, cz64.generators, cz64.A, cz64.b))
    assert cz64.contains(cz64.center).shape == (4,)


# --------------------------------------------------------------------------- gradients
def test_gradients_of_the_constructions():
    c1 = torch.randn(2, dtype=F64, requires_grad=True)
    G1 = torch.randn(2, 3, dtype=F64, requires_grad=True)
    c2 = torch.randn(2, dtype=F64, requires_grad=True)
    G2 = torch.randn(2, 2, dtype=F64, requires_grad=True)
    H = torch.randn(2, 2, dtype=F64, requires_grad=True)

    h = (H @ c1).detach() + 10.0  # far enough that d > 0 stays smooth

    def f(c1, G1, c2, G2, H):
        x = Zonotope(c1, G1).to_constrained().intersect(Zonotope(c2, G2)).intersect_halfspace(H, h)
        x = torch.eye(2, dtype=F64) * 2 @ x + Zonotope(c2, G2)
        return x.A, x.b, x.generators, x.center

    assert torch.autograd.gradcheck(f, (c1, G1, c2, G2, H))


# --------------------------------------------------------------------------- bad input
_CZ = Zonotope(torch.zeros(2), torch.eye(2)).to_constrained()
BAD = [
    (lambda: ConstrainedZonotope(torch.zeros(2), torch.eye(2), torch.zeros(1, 3), torch.zeros(1)), "`A`"),
    (lambda: ConstrainedZonotope(torch.zeros(2), torch.eye(2), torch.zeros(1, 2), torch.zeros(2)), "`b`"),
    (lambda: ConstrainedZonotope(torch.zeros(2), torch.eye(2), torch.zeros(1, 2, dtype=torch.long), torch.zeros(1)), "`A`"),
    (lambda: ConstrainedZonotope(torch.zeros(2), torch.eye(2), torch.zeros(1, 2), torch.tensor([math.nan])), "`b`"),
    (lambda: ConstrainedZonotope(torch.zeros(2), torch.eye(2), torch.zeros(1, 2), torch.zeros(1, dtype=F64)), "`b`"),
    (lambda: ConstrainedZonotope(torch.zeros(2), torch.eye(3), torch.zeros(1, 3), torch.zeros(1)), "`generators`"),
    (lambda: ConstrainedZonotope.from_polytope(torch.ones(2), torch.ones(2)), "`H`"),
    (lambda: ConstrainedZonotope.from_polytope(torch.ones(3, 2), torch.ones(2)), "`H`"),
    (lambda: ConstrainedZonotope.from_polytope(torch.ones(3, 2, dtype=torch.long), torch.ones(3)), "`H`"),
    (lambda: ConstrainedZonotope.from_polytope(torch.ones(3, 2), torch.tensor([1.0, math.inf, 1.0])), "`h`"),
    (lambda: _CZ.intersect_halfspace(torch.ones(3), torch.tensor(1.0)), "`H`"),
    (lambda: _CZ.intersect_halfspace(torch.ones(2, 2), torch.ones(3)), "`h`"),
    (lambda: _CZ.intersect_halfspace(torch.ones(2, dtype=F64), torch.tensor(1.0, dtype=F64)), "`H`"),
    (lambda: _CZ.intersect_halfspace(torch.ones(2) * math.nan, torch.tensor(1.0)), "`H`"),
    (lambda: _CZ.expand(3).intersect_halfspace(torch.ones(4, 1, 2), torch.ones(4, 1)), "`H`"),
    (lambda: _CZ.intersect(torch.ones(2)), "`other`"),
    (lambda: _CZ.intersect(Zonotope(torch.zeros(3), torch.eye(3))), "`other`"),
    (lambda: _CZ.expand(3).intersect(_CZ.expand(4)), "`other`"),
    (lambda: _CZ.minkowski_sum(Zonotope(torch.zeros(3), torch.eye(3))), "`other`"),
    (lambda: _CZ.minkowski_sum("box"), "`other`"),
    (lambda: _CZ.cartesian_product(3.0), "`other`"),
    (lambda: _CZ.linear_map(torch.eye(3)), "`matrix`"),
    (lambda: _CZ.linear_map(torch.eye(2, dtype=F64)), "`matrix`"),
    (lambda: _CZ.expand(3).linear_map(torch.ones(4, 2, 2)), "`matrix`"),
    (lambda: _CZ.translate(torch.ones(3)), "`offset`"),
    (lambda: _CZ.translate(torch.tensor([math.nan, 0.0])), "`offset`"),
    (lambda: _CZ.project([5]), "`dims`"),
    (lambda: _CZ.contains(torch.ones(3)), "`points`"),
    (lambda: _CZ.contains(torch.ones(2, dtype=torch.int64)), "`points`"),
    (lambda: _CZ.contains(torch.tensor([math.inf, 0.0])), "`points`"),
    (lambda: _CZ.expand(3).contains(torch.ones(4, 2)), "`points`"),
    (lambda: _CZ.pad(1, 0), "`n_generators`"),
    (lambda: _CZ.intersect_halfspace(torch.ones(2), torch.tensor(1.0)).pad(5, 0), "`n_constraints`"),
    (lambda: _CZ.plot(dims=(0,)), "`dims`"),
]


@pytest.mark.parametrize("call, name", BAD, ids=[f"{i}-{n.strip('`')}" for i, (_, n) in enumerate(BAD)])
def test_bad_input_raises_value_error_naming_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


# --------------------------------------------------------------------------- properties
@settings(max_examples=15, deadline=None, derandomize=True, database=None)
@given(lo1=st.lists(st.floats(-2, 2), min_size=2, max_size=2), w1=st.lists(st.floats(0.1, 2), min_size=2, max_size=2),
       lo2=st.lists(st.floats(-2, 2), min_size=2, max_size=2), w2=st.lists(st.floats(0.1, 2), min_size=2, max_size=2))
def test_intersection_of_boxes_is_the_box_of_bounds(lo1, w1, lo2, w2):
    lo1, lo2 = torch.tensor(lo1, dtype=F64), torch.tensor(lo2, dtype=F64)
    hi1, hi2 = lo1 + torch.tensor(w1, dtype=F64), lo2 + torch.tensor(w2, dtype=F64)
    inter = Zonotope.from_interval(lo1, hi1).to_constrained().intersect(Zonotope.from_interval(lo2, hi2))
    lo, hi = torch.maximum(lo1, lo2), torch.minimum(hi1, hi2)
    gap = (lo - hi).amax()
    if gap.abs() < 1e-6:
        return  # touching boxes: emptiness is decided by the tolerance
    assert bool(inter.is_empty()) == bool(gap > 0)
    if gap < 0:
        got_lo, got_hi = inter.interval()
        torch.testing.assert_close(got_lo, lo, rtol=1e-7, atol=1e-7)
        torch.testing.assert_close(got_hi, hi, rtol=1e-7, atol=1e-7)


def test_docstring_examples():
    tests = doctest.DocTestFinder().find(cz_module)
    examples = sum(len(t.examples) for t in tests)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    for t in tests:
        runner.run(t)
    assert examples > 0 and runner.failures == 0
