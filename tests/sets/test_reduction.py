"""Girard order reduction: containment, exact width, padding, batching, gradients."""
from __future__ import annotations

import doctest
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchrl_brsl.sets.reduction as reduction_module
from torchrl_brsl.sets import Zonotope, pad_generators, reduce_girard, zonotope_gauge

F64 = torch.float64


@pytest.mark.parametrize("n, p, target", [(2, 20, 4), (2, 9, 2), (3, 15, 6), (3, 4, 3)])
def test_reduced_set_contains_dense_samples(gen, n, p, target):
    G = torch.randn(n, p, generator=gen, dtype=F64)
    R = reduce_girard(G, target)
    assert R.shape == (n, target)
    z = Zonotope(torch.zeros(n, dtype=F64), G)
    pts = z.sample(4000, generator=gen)
    assert (zonotope_gauge(pts, R) <= 1 + 1e-9).all()
    # vertices of the original (all sign patterns of the coefficients, for small p) too
    if p <= 9:
        signs = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * p)
        assert (zonotope_gauge(signs @ G.T, R) <= 1 + 1e-9).all()


def test_reduction_keeps_the_interval_hull_and_the_strongest_generators(gen):
    G = torch.randn(2, 12, generator=gen, dtype=F64)
    R = reduce_girard(G, 5)
    torch.testing.assert_close(R.abs().sum(-1), G.abs().sum(-1))
    score = G.abs().sum(0) - G.abs().amax(0)
    kept = G[:, score.argsort(descending=True)[:3]]
    torch.testing.assert_close(R[:, :3], kept)
    box = R[:, 3:]
    torch.testing.assert_close(box, torch.diag(box.diagonal()))
    assert (box.diagonal() >= 0).all()


def test_reduction_is_an_outer_approximation_not_the_same_set(gen):
    G = torch.randn(2, 10, generator=gen, dtype=F64)
    R = reduce_girard(G, 3)
    v = Zonotope(torch.zeros(2, dtype=F64), R).vertices()
    assert (zonotope_gauge(v, G) > 1 + 1e-6).any()


def test_padding_when_fewer_generators_than_the_target(gen):
    G = torch.randn(3, 2, 3, generator=gen, dtype=F64)
    for out in (reduce_girard(G, 7), pad_generators(G, 7)):
        assert out.shape == (3, 2, 7)
        torch.testing.assert_close(out[..., :3], G)
        assert torch.equal(out[..., 3:], torch.zeros(3, 2, 4, dtype=F64))
    assert reduce_girard(G, 3) is G or torch.equal(reduce_girard(G, 3), G)
    assert torch.equal(pad_generators(G, 3), G)


def test_batched_reduction_matches_elementwise(gen):
    G = torch.randn(2, 3, 2, 11, generator=gen, dtype=F64)
    R = reduce_girard(G, 4)
    assert R.shape == (2, 3, 2, 4)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(R[i, j], reduce_girard(G[i, j], 4))
    z = Zonotope(torch.zeros(2, 3, 2, dtype=F64), G)
    pts = z.sample(500, generator=gen)  # [500, 2, 3, 2]
    assert (zonotope_gauge(pts, R) <= 1 + 1e-9).all()


def test_float32(gen):
    G = torch.randn(3, 12, generator=gen)
    R = reduce_girard(G, 5)
    assert R.dtype == torch.float32
    pts = Zonotope(torch.zeros(3), G).sample(1000, generator=gen)
    assert (zonotope_gauge(pts, R) <= 1 + 1e-5).all()


def test_gradcheck(gen):
    G = torch.randn(2, 2, 8, generator=gen, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda g: reduce_girard(g, 4), (G,))
    assert torch.autograd.gradcheck(lambda g: pad_generators(g, 10), (G,))


BAD = [
    (lambda: reduce_girard(torch.randn(3, 5), 2), "`n_generators`"),
    (lambda: pad_generators(torch.randn(3, 5), 4), "`n_generators`"),
    (lambda: reduce_girard(torch.ones(2, 5, dtype=torch.long), 3), "`generators`"),
    (lambda: reduce_girard(torch.full((2, 5), math.nan), 3), "`generators`"),
    (lambda: reduce_girard(torch.ones(5), 3), "`generators`"),
    (lambda: pad_generators(torch.ones(2, 5, dtype=torch.int32), 6), "`generators`"),
]


@pytest.mark.parametrize("call, name", BAD)
def test_bad_input_raises_value_error_naming_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


@settings(max_examples=25, deadline=None, derandomize=True, database=None)
@given(n=st.integers(1, 3), extra=st.integers(0, 11), slack=st.integers(0, 6), seed=st.integers(0, 2**31 - 1))
def test_reduction_contains_the_original(n, extra, slack, seed):
    g = torch.Generator().manual_seed(seed)
    G = torch.randn(n, n + extra, generator=g, dtype=F64)  # full rank, so the closed-form gauge applies
    target = n + slack
    R = reduce_girard(G, target)
    assert R.shape == (n, target)
    pts = Zonotope(torch.zeros(n, dtype=F64), G).sample(200, generator=g)
    assert (zonotope_gauge(pts, R) <= 1 + 1e-9).all()
    torch.testing.assert_close(R.abs().sum(-1), G.abs().sum(-1))


def test_docstring_examples():
    result = doctest.testmod(reduction_module)
    assert result.attempted > 0 and result.failed == 0
