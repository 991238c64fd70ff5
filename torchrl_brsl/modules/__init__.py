"""Policy modules: exploration noise damped every step (paper Algorithm 1)."""
from torchrl_brsl.modules.exploration import DampedGaussianModule

__all__ = ["DampedGaussianModule"]
