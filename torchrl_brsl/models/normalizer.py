"""``Normalizer``: per-dimension mean / standard deviation kept as module buffers."""
from __future__ import annotations

import torch
from torch import Tensor, nn


class Normalizer(nn.Module):
    """Per-dimension affine normalisation ``z = (x - mean) / std`` fitted from data.

    The statistics are buffers, so they travel with ``state_dict``, ``.to(device)`` and
    ``deepcopy``. Before any data is seen the normaliser is the identity (``mean = 0``,
    ``std = 1``). Dimensions whose standard deviation is below ``min_std`` (constant
    features) get ``std = 1`` so they are centred but never divided by ~0.

    Two ways to set the statistics:

    - :meth:`fit` replaces them by the statistics of a data set (e.g. the whole replay buffer,
      as PETS does before each round of model training);
    - :meth:`update` merges a new batch into running statistics (Chan et al.'s parallel
      mean / variance update), so streaming the data batch by batch gives the same result as
      one :meth:`fit` on all of it.

    Args:
        dim: feature dimension ``d``.
        min_std: standard deviations below this are replaced by 1.
        device, dtype: of the buffers.

    Examples:
        >>> norm = Normalizer(3)
        >>> x = torch.randn(1000, 3) * torch.tensor([1.0, 10.0, 0.1]) + 5
        >>> _ = norm.fit(x)
        >>> z = norm.normalize(x)
        >>> bool(z.mean(0).abs().max() < 1e-4), bool((z.std(0, unbiased=False) - 1).abs().max() < 1e-4)
        (True, True)
        >>> torch.allclose(norm.denormalize(z), x, atol=1e-4)
        True
    """

    mean: Tensor
    std: Tensor
    count: Tensor

    def __init__(self, dim: int, *, min_std: float = 1e-6, device=None, dtype=None):
        super().__init__()
        self.dim = int(dim)
        self.min_std = float(min_std)
        factory = {"device": device, "dtype": dtype}
        self.register_buffer("mean", torch.zeros(self.dim, **factory))
        self.register_buffer("std", torch.ones(self.dim, **factory))
        # population variance before the ``min_std`` replacement, for running updates
        self.register_buffer("var", torch.ones(self.dim, **factory))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64, device=device))

    def _flat(self, data: Tensor) -> Tensor:
        if data.shape[-1] != self.dim:
            raise ValueError(f"expected data [..., {self.dim}], got {tuple(data.shape)}")
        return data.detach().reshape(-1, self.dim).to(torch.float64)

    def _store(self, mean: Tensor, var: Tensor, count: float) -> None:
        std = var.clamp_min(0).sqrt()
        std = torch.where(std < self.min_std, torch.ones_like(std), std)
        self.mean.copy_(mean.to(self.mean))
        self.var.copy_(var.to(self.var))
        self.std.copy_(std.to(self.std))
        self.count.fill_(count)

    @torch.no_grad()
    def fit(self, data: Tensor) -> Normalizer:
        """Sets the statistics to those of ``data [..., d]`` (all leading dims are samples)."""
        x = self._flat(data)
        if x.shape[0] == 0:
            raise ValueError("cannot fit a Normalizer on an empty data set")
        self._store(x.mean(0), x.var(0, unbiased=False), float(x.shape[0]))
        return self

    @torch.no_grad()
    def update(self, data: Tensor) -> Normalizer:
        """Merges ``data [..., d]`` into the running statistics."""
        x = self._flat(data)
        n_new = x.shape[0]
        if n_new == 0:
            return self
        n_old = float(self.count)
        if n_old == 0:
            return self.fit(x)
        mean_new, var_new = x.mean(0), x.var(0, unbiased=False)
        mean_old, var_old = self.mean.to(torch.float64), self.var.to(torch.float64)
        n = n_old + n_new
        delta = mean_new - mean_old
        mean = mean_old + delta * (n_new / n)
        var = (var_old * n_old + var_new * n_new + delta.square() * (n_old * n_new / n)) / n
        self._store(mean, var, n)
        return self

    def normalize(self, x: Tensor) -> Tensor:
        """``(x - mean) / std`` for ``x [..., d]`` (differentiable in ``x``)."""
        return (x - self.mean) / self.std

    def denormalize(self, z: Tensor) -> Tensor:
        """``z * std + mean`` for ``z [..., d]``."""
        return z * self.std + self.mean

    def extra_repr(self) -> str:
        return f"dim={self.dim}, count={int(self.count)}"
