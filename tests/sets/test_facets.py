"""Closed-form gauge of 1-3-D zonotopes against HiGHS."""
from __future__ import annotations

import doctest

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchrl_brsl.sets.facets as facets_module
from torchrl_brsl.sets import facet_normals, facet_supports, gauge_from_facets, zonotope_gauge

F64 = torch.float64


def test_gauge_of_the_unit_box():
    x = torch.tensor([[0.5, -2.0], [0.0, 0.0], [1.0, 1.0], [-0.25, 0.1]], dtype=F64)
    torch.testing.assert_close(zonotope_gauge(x, torch.eye(2, dtype=F64)), x.abs().amax(-1))


def test_gauge_in_one_dimension():
    G = torch.tensor([[0.5, -1.0, 0.0]], dtype=F64)
    x = torch.tensor([[3.0], [-0.75], [0.0]], dtype=F64)
    torch.testing.assert_close(zonotope_gauge(x, G), torch.tensor([2.0, 0.5, 0.0], dtype=F64))


@pytest.mark.parametrize("n, p", [(1, 1), (1, 4), (2, 2), (2, 7), (3, 3), (3, 8)])
def test_gauge_matches_highs(gen, oracle, n, p):
    G = torch.randn(n, p, generator=gen, dtype=F64)
    x = torch.randn(40, n, generator=gen, dtype=F64) * G.abs().sum(-1)
    expected = torch.tensor([oracle.gauge(G, xi) for xi in x], dtype=F64)
    torch.testing.assert_close(zonotope_gauge(x, G), expected, rtol=1e-7, atol=1e-9)


def test_gauge_near_the_boundary_decides_membership(gen, oracle):
    G = torch.randn(3, 6, generator=gen, dtype=F64)
    z = torch.rand(50, 6, generator=gen, dtype=F64) * 2 - 1
    z[:, 0] = 1.0  # a face of the coefficient cube: often, not always, a boundary point
    x = z @ G.T
    for scale in (0.999, 1.001):
        expected = torch.tensor([oracle.gauge(G, xi) for xi in scale * x], dtype=F64)
        got = zonotope_gauge(scale * x, G)
        torch.testing.assert_close(got, expected, rtol=1e-8, atol=1e-10)
        keep = (expected - 1).abs() > 1e-9
        assert torch.equal((got <= 1)[keep], (expected <= 1)[keep])


def test_zero_and_parallel_generators_do_not_change_the_gauge(gen):
    G = torch.randn(3, 4, generator=gen, dtype=F64)
    x = torch.randn(20, 3, generator=gen, dtype=F64)
    base = zonotope_gauge(x, G)
    padded = torch.cat((G, torch.zeros(3, 3, dtype=F64)), -1)
    torch.testing.assert_close(zonotope_gauge(x, padded), base)
    # a duplicated column is the same as doubling it
    dup = torch.cat((G, G[:, :1]), -1)
    doubled = G.clone()
    doubled[:, 0] *= 2
    torch.testing.assert_close(zonotope_gauge(x, dup), zonotope_gauge(x, doubled))
    G2 = torch.randn(2, 3, generator=gen, dtype=F64)
    x2 = torch.randn(20, 2, generator=gen, dtype=F64)
    torch.testing.assert_close(zonotope_gauge(x2, torch.cat((G2, torch.zeros(2, 2, dtype=F64)), -1)),
                               zonotope_gauge(x2, G2))


@pytest.mark.parametrize("n, p, k", [(1, 3, 1), (2, 5, 5), (3, 5, 10)])
def test_facet_normals_shape_and_orthogonality(gen, n, p, k):
    G = torch.randn(4, n, p, generator=gen, dtype=F64)
    h = facet_normals(G)
    assert h.shape == (4, k, n)
    if n == 2:  # h_k is perpendicular to g_k
        torch.testing.assert_close((h * G.transpose(-1, -2)).sum(-1), torch.zeros(4, p, dtype=F64))
    if n == 3:  # each normal is perpendicular to the two generators it came from
        prod = (h @ G).abs()  # [4, K, p]
        assert (prod < 1e-12).sum(-1).eq(2).all()
    sigma = facet_supports(h, G)
    torch.testing.assert_close(sigma, (h @ G).abs().sum(-1))


def test_gauge_from_precomputed_facets_and_broadcasting(gen):
    G = torch.randn(3, 3, 5, generator=gen, dtype=F64)  # 3 zonotopes
    h = facet_normals(G)
    sigma = facet_supports(h, G)
    x = torch.randn(7, 3, 3, generator=gen, dtype=F64)  # 7 points per zonotope
    got = gauge_from_facets(x, h, sigma)
    assert got.shape == (7, 3)
    torch.testing.assert_close(got, zonotope_gauge(x, G))
    for i in range(3):
        torch.testing.assert_close(got[:, i], zonotope_gauge(x[:, i], G[i]))


def test_gauge_is_float32_friendly(gen, oracle):
    G = torch.randn(2, 4, generator=gen)
    x = torch.randn(30, 2, generator=gen)
    expected = torch.tensor([oracle.gauge(G, xi) for xi in x])
    torch.testing.assert_close(zonotope_gauge(x, G), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_gradcheck(gen, n):
    G = torch.randn(n, n + 2, generator=gen, dtype=F64, requires_grad=True)
    x = torch.randn(5, n, generator=gen, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(zonotope_gauge, (x, G))


def test_gradient_on_a_facet_is_the_scaled_normal():
    G = torch.tensor([[2.0, 0.0], [0.0, 1.0]], dtype=F64)
    x = torch.tensor([1.0, 0.2], dtype=F64, requires_grad=True)  # the active facet is x_0 = 2
    zonotope_gauge(x, G).backward()
    torch.testing.assert_close(x.grad, torch.tensor([0.5, 0.0], dtype=F64))


BAD = [
    (lambda: zonotope_gauge(torch.zeros(4), torch.eye(4)), "`generators`"),
    (lambda: facet_normals(torch.eye(4)), "`generators`"),
    (lambda: zonotope_gauge(torch.zeros(3), torch.eye(2)), "`x`"),
    (lambda: zonotope_gauge(torch.zeros(2), torch.ones(2)), "`generators`"),
]


@pytest.mark.parametrize("call, name", BAD)
def test_bad_input_raises_value_error_naming_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


@settings(max_examples=30, deadline=None, derandomize=True, database=None)
@given(n=st.integers(1, 3), extra=st.integers(0, 4), t=st.floats(0.0, 10.0), seed=st.integers(0, 2**31 - 1))
def test_gauge_is_homogeneous_and_bounded_by_coefficients(n, extra, t, seed):
    g = torch.Generator().manual_seed(seed)
    G = torch.randn(n, n + extra, generator=g, dtype=F64)
    z = torch.rand(n + extra, generator=g, dtype=F64) * 2 - 1
    x = G @ z
    gx = zonotope_gauge(x, G)
    assert gx <= z.abs().amax() + 1e-9  # x = G z is reached with ||z||_inf
    torch.testing.assert_close(zonotope_gauge(t * x, G), t * gx)
    torch.testing.assert_close(zonotope_gauge(-x, G), gx)


def test_docstring_examples():
    result = doctest.testmod(facets_module)
    assert result.attempted > 0 and result.failed == 0
