"""Zonotope algebra checked against dense sampling, closed forms and HiGHS."""
from __future__ import annotations

import doctest
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

import torchrl_brsl.sets.zonotope as zonotope_module
from torchrl_brsl.sets import ConstrainedZonotope, Zonotope, zonotope_gauge

F64 = torch.float64


def scaled(z: Zonotope, points: torch.Tensor, level: float) -> torch.Tensor:
    """Move ``points`` along rays from the centre so their gauge is exactly ``level`` (n <= 3)."""
    offset = points - z.center
    g = zonotope_gauge(offset, z.generators).unsqueeze(-1)
    return z.center + offset / g * level


def polygon_contains(vertices: torch.Tensor, points: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
    """Whether ``points`` ``[N, 2]`` lie in the convex CCW polygon ``vertices`` ``[k, 2]``."""
    edges = vertices.roll(-1, dims=0) - vertices  # [k, 2]
    rel = points.unsqueeze(-2) - vertices  # [N, k, 2]
    cross = edges[:, 0] * rel[..., 1] - edges[:, 1] * rel[..., 0]
    scale = edges.norm(dim=-1)
    return (cross >= -tol * scale).all(-1)


def shoelace(vertices: torch.Tensor) -> torch.Tensor:
    x, y = vertices[..., 0], vertices[..., 1]
    return 0.5 * (x * y.roll(-1, dims=-1) - x.roll(-1, dims=-1) * y).sum(-1)


# --------------------------------------------------------------------------- constructors
def test_constructor_sets_batch_shape_and_sizes(gen, oracle):
    z = oracle.random_zonotope(gen, 3, 5, batch=(2, 4))
    assert z.batch_size == torch.Size([2, 4])
    assert z.dim == 3 and z.n_generators == 5
    assert torch.equal(z.radius(), z.generators.abs().sum(-1))


def test_constructor_accepts_lists_as_float_tensors():
    z = Zonotope([0.0, 1.0], [[1.0, 0.0], [0.0, 2.0]])
    assert isinstance(z.center, torch.Tensor) and z.center.is_floating_point()
    assert z.contains(torch.tensor([1.0, 3.0])) and not z.contains(torch.tensor([1.0, 3.1]))


def test_from_interval_is_the_box(gen, oracle):
    lo = torch.tensor([-1.0, 0.5, 2.0], dtype=F64)
    hi = torch.tensor([0.0, 0.5, 5.0], dtype=F64)
    z = Zonotope.from_interval(lo, hi)
    got_lo, got_hi = z.interval()
    torch.testing.assert_close(got_lo, lo)
    torch.testing.assert_close(got_hi, hi)
    inside = oracle.box_points(gen, lo, hi, 200)
    assert z.contains(inside).all()
    outside = inside.clone()
    outside[:, 2] = hi[2] + 0.01
    assert not z.contains(outside).any()


def test_from_box_oriented(gen, oracle):
    angle = torch.tensor(0.7, dtype=F64)
    rot = torch.stack([torch.stack([angle.cos(), -angle.sin()]), torch.stack([angle.sin(), angle.cos()])])
    center = torch.tensor([1.0, -2.0], dtype=F64)
    half = torch.tensor([2.0, 0.5], dtype=F64)
    z = Zonotope.from_box(center, half, rot)
    u = torch.rand(300, 2, generator=gen, dtype=F64) * 2 - 1  # box coordinates
    assert z.contains(center + (u * half) @ rot.T).all()
    u_out = u.clone()
    u_out[:, 0] = torch.where(u[:, 0] >= 0, 1.02, -1.02)
    assert not z.contains(center + (u_out * half) @ rot.T).any()
    # the axes are the rotated columns, scaled by the half extents
    torch.testing.assert_close(z.generators, rot * half)
    # without rotation: axis aligned
    lo, hi = Zonotope.from_box(center, half).interval()
    torch.testing.assert_close(lo, center - half)
    torch.testing.assert_close(hi, center + half)


def test_from_box_broadcasts_center_over_batched_extents():
    z = Zonotope.from_box(torch.zeros(2), torch.ones(3, 2))
    assert z.batch_size == torch.Size([3])
    assert z.center.shape == (3, 2)


def test_from_point_is_a_singleton():
    x = torch.tensor([0.3, -0.2, 1.0, 4.0], dtype=F64)
    z = Zonotope.from_point(x)
    assert z.n_generators == 0
    assert z.contains(x)
    assert not z.contains(x + 1e-3)
    assert not z.is_empty()


# --------------------------------------------------------------------------- interval, support
def test_interval_is_tight_and_contains_samples(gen, oracle):
    z = oracle.random_zonotope(gen, 3, 4)
    lo, hi = z.interval()
    pts = z.sample(2000, generator=gen)
    assert ((pts >= lo - 1e-12) & (pts <= hi + 1e-12)).all()
    # 4 generators: 16 sign patterns, the snapped half of the samples hits every one
    torch.testing.assert_close(pts.amax(0), hi)
    torch.testing.assert_close(pts.amin(0), lo)


def test_support_matches_lp_and_samples(gen, oracle):
    z = oracle.random_zonotope(gen, 3, 6)
    dirs = torch.randn(20, 3, generator=gen, dtype=F64)
    got = z.support(dirs)
    assert got.shape == (20,)
    expected = torch.tensor([oracle.support(d, z.center, z.generators) for d in dirs], dtype=F64)
    torch.testing.assert_close(got, expected, rtol=1e-7, atol=1e-7)
    pts = z.sample(500, generator=gen)
    assert ((pts @ dirs.T) <= got + 1e-9).all()


def test_support_is_attained_by_samples(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3)
    dirs = torch.randn(10, 2, generator=gen, dtype=F64)
    pts = z.sample(400, generator=gen)
    torch.testing.assert_close((pts @ dirs.T).amax(0), z.support(dirs))


# --------------------------------------------------------------------------- algebra
def test_linear_map_maps_members_and_non_members(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 4)
    M = torch.tensor([[2.0, 1.0], [-0.5, 1.5]], dtype=F64)
    mz = z.linear_map(M)
    assert isinstance(mz, Zonotope)
    pts = z.sample(300, generator=gen)
    assert mz.contains(pts @ M.T).all()
    out = scaled(z, pts, 1.05)  # M is invertible: images of non-members are non-members
    assert not mz.contains(out @ M.T).any()
    mz2 = M @ z
    torch.testing.assert_close(mz2.center, mz.center)
    torch.testing.assert_close(mz2.generators, mz.generators)


def test_linear_map_to_higher_dimension_uses_lp_path(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3)
    M = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=F64)  # image is a 2-D slab in R^3
    mz = z.linear_map(M)
    pts = z.sample(40, generator=gen)
    assert mz.contains(pts @ M.T).all()
    off_plane = pts @ M.T + torch.tensor([0.0, 0.0, 1e-3], dtype=F64)
    assert not mz.contains(off_plane).any()


def test_minkowski_sum_contains_sums_and_adds_supports(gen, oracle):
    z1 = oracle.random_zonotope(gen, 2, 3)
    z2 = oracle.random_zonotope(gen, 2, 2)
    s = z1 + z2
    assert s.n_generators == 5
    x1, x2 = z1.sample(300, generator=gen), z2.sample(300, generator=gen)
    assert s.contains(x1 + x2).all()
    dirs = torch.randn(50, 2, generator=gen, dtype=F64)
    torch.testing.assert_close(s.support(dirs), z1.support(dirs) + z2.support(dirs))
    # points just beyond the boundary of the sum are not in it
    assert not s.contains(scaled(s, s.sample(200, generator=gen), 1.01)).any()


def test_translate_and_negation(gen, oracle):
    z = oracle.random_zonotope(gen, 3, 4)
    t = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    pts = z.sample(200, generator=gen)
    out = scaled(z, pts, 1.02)
    for moved, shift in ((z.translate(t), t), (z + t, t), (t + z, t), (z - t, -t)):
        assert moved.contains(pts + shift).all()
        assert not moved.contains(out + shift).any()
    neg = -z
    assert neg.contains(-pts).all()
    assert not neg.contains(-out).any()


def test_cartesian_product(gen, oracle):
    z1 = oracle.random_zonotope(gen, 2, 3)
    z2 = oracle.random_zonotope(gen, 1, 2)
    prod = z1.cartesian_product(z2)
    assert prod.dim == 3 and prod.n_generators == 5
    x1, x2 = z1.sample(200, generator=gen), z2.sample(200, generator=gen)
    assert prod.contains(torch.cat((x1, x2), -1)).all()
    assert not prod.contains(torch.cat((scaled(z1, x1, 1.02), x2), -1)).any()
    assert not prod.contains(torch.cat((x1, scaled(z2, x2, 1.02)), -1)).any()


def test_project_keeps_supports_of_the_chosen_coordinates(gen, oracle):
    z = oracle.random_zonotope(gen, 4, 6)
    proj = z.project([2, 0])
    assert proj.dim == 2
    pts = z.sample(300, generator=gen)
    assert proj.contains(pts[:, [2, 0]]).all()
    dirs = torch.randn(30, 2, generator=gen, dtype=F64)
    lifted = torch.zeros(30, 4, dtype=F64)
    lifted[:, 2], lifted[:, 0] = dirs[:, 0], dirs[:, 1]
    torch.testing.assert_close(proj.support(dirs), z.support(lifted))
    torch.testing.assert_close(z.project([-1]).center, z.center[..., 3:])


def test_reduce_and_pad_methods(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 9)
    red = z.reduce(4)
    assert red.n_generators == 4
    assert red.contains(z.sample(500, generator=gen)).all()
    padded = z.pad(12)
    assert padded.n_generators == 12
    dirs = torch.randn(20, 2, generator=gen, dtype=F64)
    torch.testing.assert_close(padded.support(dirs), z.support(dirs))


def test_to_constrained_is_the_same_set(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3)
    cz = z.to_constrained()
    assert isinstance(cz, ConstrainedZonotope) and cz.n_constraints == 0
    pts = torch.cat((z.sample(20, generator=gen), scaled(z, z.sample(20, generator=gen), 1.02)))
    assert torch.equal(cz.contains(pts), z.contains(pts))


# --------------------------------------------------------------------------- containment
@pytest.mark.parametrize("n, p", [(1, 3), (2, 2), (2, 6), (3, 3), (3, 7), (4, 6)])
def test_contains_matches_highs(gen, oracle, n, p):
    z = oracle.random_zonotope(gen, n, p)
    lo, hi = z.interval()
    pad = 0.2 * (hi - lo)
    pts = torch.cat((oracle.box_points(gen, lo - pad, hi + pad, 60), z.sample(20, generator=gen)))
    truth = torch.tensor([oracle.gauge(z.generators, x - z.center) for x in pts], dtype=F64)
    keep = (truth - 1).abs() > 1e-6
    got = z.contains(pts)
    assert torch.equal(got[keep], truth[keep] <= 1)
    assert (truth <= 1).any() and (truth > 1).any()


def test_contains_rank_deficient_segment():
    z = Zonotope(torch.zeros(2, dtype=F64), torch.tensor([[1.0, 2.0], [1.0, 2.0]], dtype=F64))  # the segment y = x
    assert z.contains(torch.tensor([[2.9, 2.9], [-3.0, -3.0]], dtype=F64)).all()
    assert not z.contains(torch.tensor([[1.0, 1.01], [3.1, 3.1]], dtype=F64)).any()


@pytest.mark.parametrize("n", [2, 4])
def test_contains_an_empty_batch_is_an_empty_bool_tensor(n):
    """Both paths (closed form, LP beyond 3-D): a mask that selects no set still gives a mask."""
    z = Zonotope(torch.zeros(0, 3, n, dtype=F64), torch.eye(n, dtype=F64).expand(0, 3, n, n))
    inside = z.contains(torch.zeros(0, 3, n, dtype=F64))
    assert inside.dtype == torch.bool and inside.shape == (0, 3)


def test_contains_tolerance_argument():
    z = Zonotope.from_interval(-torch.ones(2, dtype=F64), torch.ones(2, dtype=F64))
    x = torch.tensor([1.0 + 1e-4, 0.0], dtype=F64)
    assert not z.contains(x)
    assert z.contains(x, tol=1e-3)


def test_contains_float32(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 4, dtype=torch.float32)
    pts = z.sample(300, generator=gen)
    assert z.contains(pts).all()
    assert not z.contains(scaled(z, pts, 1.01)).any()


def test_contains_mixed_precision():
    z32 = Zonotope.from_interval(-torch.ones(2), torch.ones(2))
    z64 = z32.to(F64)
    pts = torch.tensor([[0.5, 1.0], [1.001, 0.0]], dtype=F64)
    assert z32.contains(pts).tolist() == [True, False]
    assert z64.contains(pts.float()).tolist() == [True, False]


def test_is_empty_is_false(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3, batch=(4,))
    assert z.is_empty().shape == (4,)
    assert not z.is_empty().any()


# --------------------------------------------------------------------------- sample, vertices
def test_sample_shape_membership_boundary_and_seed(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 5, batch=(3,))
    pts = z.sample(100, generator=torch.Generator().manual_seed(7))
    assert pts.shape == (100, 3, 2) and pts.dtype == F64
    assert z.contains(pts).all()
    gauges = zonotope_gauge(pts - z.center, z.generators)
    assert (gauges > 0.999).any()  # the snapped half reaches the boundary
    assert (gauges < 0.9).any()  # and the other half fills the interior
    again = z.sample(100, generator=torch.Generator().manual_seed(7))
    assert torch.equal(pts, again)


def test_vertices_lie_on_the_boundary_and_bound_the_samples(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 5)
    v = z.vertices()
    assert v.shape == (10, 2)
    gauges = zonotope_gauge(v - z.center, z.generators)
    torch.testing.assert_close(gauges, torch.ones_like(gauges))
    assert polygon_contains(v, z.sample(2000, generator=gen)).all()
    # counter-clockwise, and the area of a zonotope: 4 * sum_{i<j} |det(g_i, g_j)|
    G = z.generators
    dets = sum(abs(torch.linalg.det(G[:, [i, j]])) for i in range(5) for j in range(i + 1, 5))
    torch.testing.assert_close(shoelace(v), 4 * dets)


def test_vertices_batched_with_degenerate_generators():
    G = torch.tensor([[[1.0, -1.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, -2.0], [1.0, 0.0, -2.0]]], dtype=F64)
    z = Zonotope(torch.zeros(2, 2, dtype=F64), G)  # both flat: a segment each (with zero and parallel columns)
    v = z.vertices()
    assert v.shape == (2, 6, 2)
    torch.testing.assert_close(v[0, :, 0].abs().amax(), torch.tensor(2.0, dtype=F64))
    torch.testing.assert_close(v[1].abs().amax(-2), torch.tensor([3.0, 3.0], dtype=F64))
    torch.testing.assert_close(shoelace(v), torch.zeros(2, dtype=F64))


def test_vertices_needs_two_dimensions(gen, oracle):
    with pytest.raises(ValueError, match="2-D"):
        oracle.random_zonotope(gen, 3, 4).vertices()


# --------------------------------------------------------------------------- batching
def test_batched_operations_match_elementwise(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3, batch=(2, 3))
    M = torch.randn(2, 3, 2, 2, generator=gen, dtype=F64)
    mz = z.linear_map(M)
    assert mz.batch_size == (2, 3)
    for i in range(2):
        for j in range(3):
            single = z[i, j].linear_map(M[i, j])
            torch.testing.assert_close(mz[i, j].generators, single.generators)
            torch.testing.assert_close(mz[i, j].center, single.center)
    pts = z.sample(50, generator=gen)  # [50, 2, 3, 2]
    assert z.contains(pts).all()
    assert z.contains(pts).shape == (50, 2, 3)


def test_broadcast_batches(gen, oracle):
    a = oracle.random_zonotope(gen, 2, 2, batch=(3, 1))
    b = oracle.random_zonotope(gen, 2, 3, batch=(1, 4))
    for out in (a + b, a.cartesian_product(b)):
        assert out.batch_size == (3, 4)
    s, prod = a + b, a.cartesian_product(b)
    for i in range(3):
        for j in range(4):
            single = a[i, 0] + b[0, j]
            torch.testing.assert_close(s[i, j].generators, single.generators)
            torch.testing.assert_close(s[i, j].center, single.center)
            torch.testing.assert_close(prod[i, j].generators, a[i, 0].cartesian_product(b[0, j]).generators)
    moved = a.translate(torch.zeros(1, 4, 2, dtype=F64))
    assert moved.batch_size == (3, 4)
    pts = a.sample(10, generator=gen) + b.sample(10, generator=gen)  # [10, 3, 4, 2]
    assert s.contains(pts).all()
    assert a.support(torch.randn(1, 4, 2, generator=gen, dtype=F64)).shape == (3, 4)


def test_tensordict_storage_index_stack_and_dtype(gen, oracle):
    z = oracle.random_zonotope(gen, 2, 3, batch=(5,), dtype=torch.float32)
    td = TensorDict({"z": z, "r": torch.zeros(5)}, batch_size=[5])
    item = td[2]["z"]
    assert isinstance(item, Zonotope) and item.batch_size == ()
    assert torch.equal(item.center, z.center[2]) and torch.equal(item.generators, z.generators[2])
    sub = td[torch.tensor([True, False, True, False, False])]["z"]
    assert torch.equal(sub.generators, z.generators[[0, 2]])
    stacked = torch.stack([td, td], 0)
    assert stacked["z"].batch_size == (2, 5)
    assert isinstance(stacked["z"], Zonotope)
    zs = torch.stack([z[0], z[1]])
    assert zs.batch_size == (2,) and torch.equal(zs.generators, z.generators[:2])
    z64 = z.to(F64)
    assert z64.center.dtype == F64 and z64.generators.dtype == F64
    assert z64.contains(z64.sample(20, generator=gen)).all()
    assert z.contains(z.sample(20, generator=gen)).all()


# --------------------------------------------------------------------------- gradients
def test_gradients_flow_through_the_algebra():
    c = torch.randn(2, dtype=F64, requires_grad=True)
    G = torch.randn(2, 5, dtype=F64, requires_grad=True)
    M = torch.randn(2, 2, dtype=F64, requires_grad=True)
    d = torch.randn(2, dtype=F64)

    def f(c, G, M):
        z = (M @ Zonotope(c, G)) + Zonotope.from_point(c)
        return z.reduce(3).support(d)

    assert torch.autograd.gradcheck(f, (c, G, M))
    lo, hi = Zonotope(c, G).interval()
    (hi - lo).sum().backward()
    torch.testing.assert_close(G.grad, 2 * G.detach().sign())


def test_support_gradient_wrt_center_is_the_direction():
    c = torch.zeros(3, requires_grad=True)
    d = torch.tensor([1.0, -2.0, 0.5])
    Zonotope(c, torch.eye(3)).support(d).backward()
    torch.testing.assert_close(c.grad, d)


# --------------------------------------------------------------------------- bad input
_nan2 = torch.tensor([float("nan"), 0.0])
_Z2 = Zonotope(torch.zeros(2), torch.eye(2))

BAD = [
    (lambda: Zonotope(torch.zeros(2), torch.zeros(3, 2)), "`generators`"),
    (lambda: Zonotope(torch.zeros(2), torch.zeros(2)), "`generators`"),
    (lambda: Zonotope(torch.zeros(2, dtype=torch.long), torch.eye(2)), "`center`"),
    (lambda: Zonotope(torch.zeros(2), torch.eye(2, dtype=torch.int32)), "`generators`"),
    (lambda: Zonotope(_nan2, torch.eye(2)), "`center`"),
    (lambda: Zonotope(torch.zeros(2), torch.eye(2) * math.inf), "`generators`"),
    (lambda: Zonotope(torch.zeros(2), torch.eye(2, dtype=F64)), "`generators`"),
    (lambda: Zonotope(torch.zeros(3, 2), torch.zeros(4, 2, 1)), "`generators`"),
    (lambda: Zonotope.from_interval(torch.ones(2), torch.zeros(2)), "`lo`"),
    (lambda: Zonotope.from_interval(torch.zeros(2), torch.ones(3)), "`lo`"),
    (lambda: Zonotope.from_interval(torch.zeros(2), torch.tensor([1.0, math.nan])), "`hi`"),
    (lambda: Zonotope.from_box(torch.zeros(2), -torch.ones(2)), "`half_extents`"),
    (lambda: Zonotope.from_box(torch.zeros(3), torch.ones(2)), "`center`"),
    (lambda: Zonotope.from_box(torch.zeros(2), torch.ones(2), torch.eye(3)), "`rotation`"),
    (lambda: Zonotope.from_box(torch.zeros(2), torch.ones(2), torch.eye(2, dtype=F64)), "`rotation`"),
    (lambda: Zonotope.from_point(torch.zeros(2, dtype=torch.long)), "`point`"),
    (lambda: _Z2.linear_map(torch.eye(3)), "`matrix`"),
    (lambda: _Z2.linear_map(torch.ones(2)), "`matrix`"),
    (lambda: _Z2.linear_map(torch.eye(2) * math.nan), "`matrix`"),
    (lambda: Zonotope(torch.zeros(3, 2), torch.ones(3, 2, 2)).linear_map(torch.ones(4, 2, 2)), "`matrix`"),
    (lambda: _Z2.translate(torch.ones(3)), "`offset`"),
    (lambda: _Z2.translate(torch.tensor([math.inf, 0.0])), "`offset`"),
    (lambda: _Z2.minkowski_sum(torch.ones(2)), "`other`"),
    (lambda: _Z2.minkowski_sum(Zonotope(torch.zeros(3), torch.eye(3))), "`other`"),
    (lambda: Zonotope(torch.zeros(3, 2), torch.ones(3, 2, 2)) + Zonotope(torch.zeros(4, 2), torch.ones(4, 2, 1)), "`other`"),
    (lambda: _Z2.cartesian_product(torch.ones(2)), "`other`"),
    (lambda: _Z2.project([2]), "`dims`"),
    (lambda: _Z2.project([-3]), "`dims`"),
    (lambda: _Z2.project([]), "`dims`"),
    (lambda: _Z2.contains(torch.ones(3)), "`points`"),
    (lambda: _Z2.contains(_nan2), "`points`"),
    (lambda: _Z2.contains(torch.ones(2, dtype=torch.long)), "`points`"),
    (lambda: Zonotope(torch.zeros(3, 2), torch.ones(3, 2, 2)).contains(torch.ones(4, 2)), "`points`"),
    (lambda: _Z2.support(torch.ones(3)), "`direction`"),
    (lambda: _Z2.support(torch.ones(2, dtype=F64)), "`direction`"),
    (lambda: _Z2.linear_map(torch.eye(2, dtype=F64)), "`matrix`"),
    (lambda: _Z2.reduce(1), "`n_generators`"),
    (lambda: _Z2.pad(1), "`n_generators`"),
    (lambda: _Z2.plot(dims=(0, 1, 1)), "`dims`"),
]


@pytest.mark.parametrize("call, name", BAD, ids=[f"{i}-{n.strip('`')}" for i, (_, n) in enumerate(BAD)])
def test_bad_input_raises_value_error_naming_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


# --------------------------------------------------------------------------- properties
@settings(max_examples=25, deadline=None, derandomize=True, database=None)
@given(n=st.integers(1, 3), p1=st.integers(0, 4), p2=st.integers(0, 4), seed=st.integers(0, 2**31 - 1))
def test_support_of_sum_and_map(n, p1, p2, seed):
    g = torch.Generator().manual_seed(seed)
    z1 = Zonotope(torch.randn(n, generator=g, dtype=F64), torch.randn(n, p1, generator=g, dtype=F64))
    z2 = Zonotope(torch.randn(n, generator=g, dtype=F64), torch.randn(n, p2, generator=g, dtype=F64))
    M = torch.randn(n, n, generator=g, dtype=F64)
    d = torch.randn(8, n, generator=g, dtype=F64)
    torch.testing.assert_close((z1 + z2).support(d), z1.support(d) + z2.support(d))
    torch.testing.assert_close(z1.linear_map(M).support(d), z1.support(d @ M))


@settings(max_examples=20, deadline=None, derandomize=True, database=None)
@given(n=st.integers(1, 3), extra=st.integers(0, 4), seed=st.integers(0, 2**31 - 1))
def test_contains_closed_form_agrees_with_lp(oracle, n, extra, seed):
    g = torch.Generator().manual_seed(seed)
    z = Zonotope(torch.zeros(n, dtype=F64), torch.randn(n, n + extra, generator=g, dtype=F64))
    pts = torch.randn(6, n, generator=g, dtype=F64) * z.radius()
    truth = torch.tensor([oracle.gauge(z.generators, x) for x in pts], dtype=F64)
    keep = (truth - 1).abs() > 1e-6
    assert torch.equal(z.contains(pts)[keep], truth[keep] <= 1)


def test_docstring_examples():
    result = doctest.testmod(zonotope_module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0


def test_skip_value_checks_only_skips_the_nan_scan():
    from torchrl_brsl.sets._checks import skip_value_checks

    with skip_value_checks():
        z = Zonotope(torch.tensor([float("nan"), 0.0]), torch.eye(2))
        assert torch.isnan(z.center[0])
        with pytest.raises(ValueError, match="generators"):
            Zonotope(torch.zeros(2), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="center"):
        Zonotope(torch.tensor([float("nan"), 0.0]), torch.eye(2))


@pytest.mark.parametrize("shapes", [((3, 1), (3, 1), (3, 1)), ((2, 1), (3,)), ((), (4,)), ((1,), ()),
                                    ((5, 1, 2), (1, 3, 1))])
def test_the_fast_broadcast_agrees_with_torch(shapes):
    from torchrl_brsl.sets._checks import broadcast_shapes

    assert broadcast_shapes(*map(torch.Size, shapes)) == torch.broadcast_shapes(*shapes)
    with pytest.raises(RuntimeError):
        broadcast_shapes(torch.Size([2]), torch.Size([3]))
