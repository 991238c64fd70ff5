"""Data-driven reachability analysis of black-box systems."""
from torchrl_brsl.reach.data_driven import DataDrivenReach
from torchrl_brsl.reach.examples import BlackBoxSystem, DoubleIntegrator, Unicycle
from torchrl_brsl.reach.lipschitz import covering_radius, residual_lipschitz
from torchrl_brsl.reach.offline import collect_offline_data, load_offline_data, save_offline_data

__all__ = ["BlackBoxSystem", "DataDrivenReach", "DoubleIntegrator", "Unicycle", "collect_offline_data", "covering_radius", "load_offline_data",
           "residual_lipschitz", "save_offline_data"]
