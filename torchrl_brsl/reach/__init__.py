"""Data-driven reachability analysis of black-box systems."""
from torchrl_brsl.reach.data_driven import DataDrivenReach
from torchrl_brsl.reach.examples import BlackBoxSystem, DoubleIntegrator, Unicycle
from torchrl_brsl.reach.lipschitz import covering_radius, residual_lipschitz

__all__ = ["BlackBoxSystem", "DataDrivenReach", "DoubleIntegrator", "Unicycle", "covering_radius", "residual_lipschitz"]
