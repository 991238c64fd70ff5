"""Small systems for the baselines' tests: a 2-D double integrator and a velocity-commanded point."""
import torch

from torchrl_brsl.baselines import AffineModel

DT = 0.1


def double_integrator(residual: float = 0.0) -> AffineModel:
    """``p' = p + dt v + dt^2/2 a``, ``v' = v + dt a`` on the state ``(x, y, vx, vy)``."""
    A = torch.eye(4, dtype=torch.float64)
    A[0, 2] = A[1, 3] = DT
    B = torch.zeros(4, 2, dtype=torch.float64)
    B[0, 0] = B[1, 1] = DT ** 2 / 2
    B[2, 0] = B[3, 1] = DT
    return AffineModel(A, B, torch.zeros(4, dtype=torch.float64), torch.full((4,), residual, dtype=torch.float64))


def velocity_point(residual: float = 0.0) -> AffineModel:
    """``p' = p + dt u``, ``v' = u`` (a velocity-commanded point)."""
    A = torch.zeros(4, 4, dtype=torch.float64)
    A[0, 0] = A[1, 1] = 1.0
    B = torch.zeros(4, 2, dtype=torch.float64)
    B[0, 0] = B[1, 1] = DT
    B[2, 0] = B[3, 1] = 1.0
    return AffineModel(A, B, torch.zeros(4, dtype=torch.float64), torch.full((4,), residual, dtype=torch.float64))


def braking(state: torch.Tensor) -> torch.Tensor:
    """The double integrator's braking policy ``clip(-v / dt, -1, 1)``."""
    return (-state[..., 2:4] / DT).clamp(-1.0, 1.0)


def boxes(batch: int, k: int, generator: torch.Generator, spread: float = 1.5):
    """Random axis-aligned boxes ``(centers [B, K, 2], generators [B, K, 2, 2], mask [B, K])``, float64."""
    centers = spread * (2 * torch.rand(batch, k, 2, generator=generator, dtype=torch.float64) - 1)
    half = 0.1 + 0.3 * torch.rand(batch, k, 2, generator=generator, dtype=torch.float64)
    generators = torch.diag_embed(half)
    mask = torch.rand(batch, k, generator=generator) < 0.8
    return centers, generators, mask
