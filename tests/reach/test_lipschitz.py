import math

import torch

from torchrl_brsl.reach import covering_radius, residual_lipschitz


def test_covering_radius_of_a_grid_is_its_spacing():
    g = torch.linspace(0, 1, 11, dtype=torch.float64)
    pts = torch.cartesian_prod(g, g)
    assert math.isclose(covering_radius(pts), 0.1, rel_tol=1e-9)


def test_lipschitz_recovers_known_slopes_without_noise():
    gen = torch.Generator().manual_seed(0)
    z = torch.rand(800, 2, generator=gen, dtype=torch.float64)
    r = torch.stack((3.0 * z[:, 0], torch.sin(2.0 * z[:, 1])), dim=-1)
    L = residual_lipschitz(z, r, torch.zeros(2, dtype=torch.float64))
    assert 2.5 < L[0] <= 3.0 + 1e-9
    assert 1.5 < L[1] <= 2.0 + 1e-9


def test_pure_noise_gives_zero_lipschitz():
    gen = torch.Generator().manual_seed(1)
    z = torch.rand(500, 3, generator=gen, dtype=torch.float64)
    half = torch.tensor([0.1, 0.5], dtype=torch.float64)
    noise = (torch.rand(500, 2, generator=gen, dtype=torch.float64) * 2 - 1) * half
    assert torch.all(residual_lipschitz(z, noise, 2 * half) == 0)
    # without removing the noise width, close pairs would suggest a huge constant
    assert torch.all(residual_lipschitz(z, noise, torch.zeros(2, dtype=torch.float64)) > 1)
