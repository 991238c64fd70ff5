"""Clearance signals and the affine nominal model shared by the baselines."""
import pytest
import torch

from torchrl_brsl.baselines import AffineModel, point_clearance
from torchrl_brsl.collision import check_collision
from torchrl_brsl.sets import Zonotope

from baselines_support import boxes


def test_point_clearance_is_negative_exactly_inside_and_agrees_with_the_collision_check():
    gen = torch.Generator().manual_seed(0)
    centers, generators, mask = boxes(64, 3, gen)
    points = 2 * (2 * torch.rand(64, 2, generator=gen, dtype=torch.float64) - 1)
    clear = point_clearance(points, centers, generators)
    inside = Zonotope(centers, generators).contains(points.unsqueeze(1))
    assert inside.any() and (~inside).any()
    assert torch.equal(clear <= 0, inside)
    # the project's collision check: a point against each box gives the same signed clearance
    point_sets = Zonotope(points.unsqueeze(1).expand(-1, 3, -1), torch.zeros(64, 3, 2, 1, dtype=torch.float64))
    reference = check_collision(point_sets, Zonotope(centers, generators), backend="closed_form").clearance
    assert torch.allclose(clear, reference, atol=1e-12)
    masked = point_clearance(points, centers, generators, mask)
    assert torch.isinf(masked[~mask]).all() and torch.equal(masked[mask], clear[mask])


def test_point_clearance_rejects_mismatched_dimensions():
    with pytest.raises(ValueError, match="share d"):
        point_clearance(torch.zeros(3), torch.zeros(2, 2), torch.zeros(2, 2, 2))


def test_affine_model_recovers_a_linear_system_and_bounds_its_residual():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(200, 3, generator=gen, dtype=torch.float64)
    u = torch.randn(200, 2, generator=gen, dtype=torch.float64)
    A, B = torch.randn(3, 3, generator=gen, dtype=torch.float64), torch.randn(3, 2, generator=gen, dtype=torch.float64)
    noise = 0.01 * (2 * torch.rand(200, 3, generator=gen, dtype=torch.float64) - 1)
    model = AffineModel.fit(x, u, x @ A.T + u @ B.T + 0.5 + noise)
    assert torch.allclose(model.A, A, atol=5e-3) and torch.allclose(model.B, B, atol=5e-3)
    assert torch.allclose(model.c, torch.full((3,), 0.5, dtype=torch.float64), atol=5e-3)
    residual = (x @ model.A.T + u @ model.B.T + model.c - (x @ A.T + u @ B.T + 0.5 + noise)).abs()
    assert torch.allclose(residual.amax(0), model.residual) and (model.residual < 0.02).all()


def test_affine_model_rejects_too_little_or_misshapen_data():
    with pytest.raises(ValueError, match="at least"):
        AffineModel.fit(torch.zeros(3, 2), torch.zeros(3, 1), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="transitions"):
        AffineModel.fit(torch.zeros(10, 2), torch.zeros(9, 1), torch.zeros(10, 2))
    with pytest.raises(ValueError, match="`A`"):
        AffineModel(torch.eye(2), torch.zeros(3, 1), torch.zeros(2))
