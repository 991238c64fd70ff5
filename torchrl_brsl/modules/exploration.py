"""Additive Gaussian exploration whose scale is damped geometrically every frame."""
from __future__ import annotations

import math

import torch
from torchrl.modules import AdditiveGaussianModule


class DampedGaussianModule(AdditiveGaussianModule):
    """:class:`~torchrl.modules.AdditiveGaussianModule` with geometric damping.

    The paper's exploration noise is zero-mean Gaussian, damped at every step. After ``k``
    frames the scale is ``max(sigma_end, sigma_init * decay**k)``; ``decay`` is chosen so that
    ``sigma_end`` is reached after ``annealing_num_steps`` frames. TorchRL's module anneals
    linearly; everything else (the action spec projection, ``std`` per action dim, the state
    dict with ``sigma``) is inherited, so the two are interchangeable in a policy.

    Args:
        spec: the action spec (the noisy action is projected into it).
        sigma_init: initial scale, > 0.
        sigma_end: final scale, in ``(0, sigma_init]``.
        annealing_num_steps: frames until ``sigma_end``, > 0.
        **kwargs: ``mean``, ``std``, ``action_key``, ``device`` as in the parent class.

    Examples:
        >>> noise = DampedGaussianModule(spec, sigma_init=0.7071, sigma_end=0.05, annealing_num_steps=20_000)
        >>> policy = TensorDictSequential(actor, noise)
        >>> noise.step(200)  # after each collected batch of 200 frames
    """

    def __init__(self, spec=None, sigma_init: float = 1.0, sigma_end: float = 0.1, annealing_num_steps: int = 1000,
                 **kwargs):
        if not sigma_init > 0:
            raise ValueError(f"`sigma_init` must be positive, got {sigma_init}")
        if not 0 < sigma_end <= sigma_init:
            raise ValueError(f"`sigma_end` must be in (0, sigma_init={sigma_init}], got {sigma_end}")
        if int(annealing_num_steps) < 1:
            raise ValueError(f"`annealing_num_steps` must be a positive integer, got {annealing_num_steps}")
        super().__init__(spec, sigma_init=float(sigma_init), sigma_end=float(sigma_end),
                         annealing_num_steps=int(annealing_num_steps), **kwargs)
        self.decay = math.exp(math.log(sigma_end / sigma_init) / int(annealing_num_steps))

    def step(self, frames: int = 1) -> None:
        """Damps the scale by ``decay ** frames`` (never below ``sigma_end``)."""
        if frames < 0:
            raise ValueError(f"`frames` must be non-negative, got {frames}")
        damped = self.sigma * self.decay ** int(frames)
        self.sigma.data.copy_(torch.maximum(self.sigma_end.to(self.sigma.dtype), damped))
