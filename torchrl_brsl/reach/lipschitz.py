"""Per-dimension Lipschitz constants and data covering radius from nearest neighbours."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor


def covering_radius(inputs: Tensor) -> float:
    """Largest nearest-neighbour distance among the data points (paper Sec. III-A).

    Every data point has another within this distance; a query that lies among the data at
    this density is within it of some data point.

    Args:
        inputs: ``[N, d]`` (already scaled to a common unit).
    """
    pts = inputs.detach().double().cpu().numpy()
    if len(pts) < 2:
        raise ValueError("`inputs` needs at least two data points for a covering radius")
    dist, _ = cKDTree(pts).query(pts, k=2)
    return float(dist[:, 1].max())


def residual_lipschitz(inputs: Tensor, residuals: Tensor, noise_width: Tensor, n_neighbors: int = 10) -> Tensor:
    """Per-output Lipschitz constants of the linearisation residual, noise removed.

    The residual ``r_i = g(z_i) + (w_i - c_w)`` mixes the model error ``g`` with noise, and
    two noise samples differ by at most ``noise_width`` per dimension. Over the
    ``n_neighbors`` nearest pairs (KD-tree, ``O(N log N)``)::

        L_k = max_{(i, j)} max(0, |r_ik - r_jk| - noise_width_k) / ||z_i - z_j||

    so pure noise never inflates ``L_k``; each pair's ratio is a lower bound of the true
    constant of ``g_k``.

    Args:
        inputs: ``[N, d]`` scaled regressor inputs ``z``.
        residuals: ``[N, n]``.
        noise_width: ``[n]`` full width of ``W - W`` per dimension.
        n_neighbors: neighbours per point.

    Returns:
        ``[n]`` constants, in residual units per scaled input unit.
    """
    pts = inputs.detach().double().cpu().numpy()
    res = residuals.detach().double().cpu().numpy()
    k = min(n_neighbors + 1, len(pts))
    dist, idx = cKDTree(pts).query(pts, k=k)
    dist, idx = dist[:, 1:], idx[:, 1:]
    diff = np.abs(res[:, None, :] - res[idx])  # [N, k, n]
    excess = np.clip(diff - noise_width.detach().double().cpu().numpy(), 0.0, None)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(dist[..., None] > 0, excess / dist[..., None], 0.0)
    return torch.as_tensor(ratio.reshape(-1, res.shape[1]).max(0), dtype=residuals.dtype, device=residuals.device)
