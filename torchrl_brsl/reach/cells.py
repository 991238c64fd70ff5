"""Local affine models on overlapping cells of the data, each with a set-membership error bound.

A global affine fit of a nonlinear robot leaves a residual as wide as the nonlinearity over
the whole data region (saturation, drag, heading), which then enters every reachable set.
Here the regressor space ``z = (x_F, u)`` (the non-translation-invariant states and the
actions, scaled to unit range) is split by a k-d tree; every node of the tree (the root
included) is a *cell*: the bounding box of its points, widened by an ``overlap`` share on
each side, with its own least-squares fit on all data inside and an error interval valid
for every ``z`` in the box. A reachable-set step uses the tightest cell containing the
step's whole regressor box (Nguyen-Tuong et al., "Local Gaussian process regression for
real time online model learning", NeurIPS 2008, for local models; Milanese & Novara, "Set
membership identification of nonlinear systems", Automatica 2004, for the bound).

**Bound of one cell.** Data ``y_i = h(z_i) + (w_i - c_w)`` with ``|w_i - c_w| <= w̄``
per dimension; ``ℓ`` the cell's affine fit, ``r_i = y_i - ℓ(z_i)`` and ``g = h - ℓ``. If
``g_k`` is ``L_k``-Lipschitz on the cell (max-norm of scaled inputs' Euclidean distance),
every data point constrains it:

    g_k(z) <= min_i (r_ik + w̄_k + L_k ||z - z_i||) =: U_k(z),

and ``U_k`` is ``L_k``-Lipschitz itself, so with ``δ`` the covering radius (every ``z`` of
the cell lies within ``δ`` of a data point ``z_j``), ``g_k(z) <= max_j U_k(z_j) + L_k δ``;
the lower bound likewise. Unlike the residual box plus noise, the intersection over data
points removes most of the data's own noise: with many neighbours ``max_j U_k(z_j)``
approaches ``g + (noise seen) `` from above instead of ``g + 2 w̄``.

``L_k`` is the smallest constant consistent with the cell's data, ``max_{i,j} (|r_ik - r_jk|
- 2 w̄_k)_+ / ||z_i - z_j||`` over all pairs, times ``lipschitz_margin``, and never below
``2 w̄_k / diam``: a floor that lets ``g`` drift by ``w̄`` across the cell, which the data
cannot rule out (the fit's slope error is of that order) and which keeps the intersection
from claiming an exact value where the data are merely consistent with one.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor


class Cells(NamedTuple):
    """Stacked local models: for each of the ``n`` outputs, ``M`` cells over scaled regressors ``z`` ``[d]``.

    Outputs with fewer cells are padded with empty boxes (``low = inf``) that contain nothing.

    Attributes:
        low, high: ``[n, M, d]`` the cell boxes (scaled units).
        slopes: ``[n, M, d]`` least-squares slopes of the output on ``z`` (scaled units).
        intercepts: ``[n, M]`` intercept at ``z = 0`` plus the centre of the error interval.
        errors: ``[n, M]`` half-widths of the error interval (model error, noise not included).
        lipschitz: ``[n, M]`` the residual's Lipschitz constants used in the bound.
        score: ``[n, M]`` the error in noise units, lower is tighter (selects among cells).
    """

    low: Tensor
    high: Tensor
    slopes: Tensor
    intercepts: Tensor
    errors: Tensor
    lipschitz: Tensor
    score: Tensor


def tree_boxes(inputs: Tensor, leaf_size: int) -> list[Tensor]:
    """Index sets of the nodes of a median-split k-d tree over ``inputs`` ``[N, d]`` (root first).

    A node is split along its widest dimension while it holds at least ``2 leaf_size`` points.
    """
    nodes, stack = [], [torch.arange(inputs.shape[0])]
    while stack:
        index = stack.pop()
        nodes.append(index)
        if len(index) < 2 * leaf_size:
            continue
        points = inputs[index]
        dim = int((points.amax(0) - points.amin(0)).argmax())
        order = points[:, dim].argsort()
        half = len(index) // 2
        stack.extend((index[order[:half]], index[order[half:]]))
    return nodes


def fit_cells(inputs: Tensor, targets: Tensor, noise_radius: Tensor, *, leaf_size: int = 32, overlap: float = 0.15,
              extend: float = 0.05, lipschitz_margin: float = 1.0) -> Cells:
    """Fit local affine models and their error intervals, one tree of cells per output.

    A first tree over ``z`` gives local slopes, hence each output's input weights
    (:func:`input_relevance`); each output then gets its own tree in its weighted metric, so
    its cells are small along the inputs it depends on and span the others.

    Args:
        inputs: ``[N, d]`` scaled regressors ``z``.
        targets: ``[N, n]`` ``y = x+ - c_w - P x``.
        noise_radius: ``[n]`` ``w̄``, the noise's interval radius per state dimension.
        leaf_size: points in the smallest cells (before widening).
        overlap: each cell box is widened by this share of its width on every side, so that a
            small set near a split still fits into one cell.
        extend: cells reaching the edge of the data's bounding box extend beyond it by this
            share of each input's range (the braking action at its bound, a robot at rest on
            the edge of its speeds); their error grows by ``L`` times the weighted extension.
        lipschitz_margin: factor (>= 1) on the data's Lipschitz constants.

    Returns:
        The stacked :class:`Cells`, root first for every output.
    """
    lo_all, hi_all = inputs.amin(0), inputs.amax(0)
    boxes = _cell_boxes(inputs, torch.ones(inputs.shape[1], dtype=inputs.dtype), leaf_size, overlap)
    slopes = torch.stack([_affine_fit(inputs[member], targets[member])[0][1:] for _, _, member in boxes])
    metric = input_relevance(slopes)  # [n, d]
    per_output = []
    for k in range(targets.shape[1]):
        cells = []
        for lo, hi, member in _cell_boxes(inputs, metric[k], leaf_size, overlap):
            theta, residual = _affine_fit(inputs[member], targets[member, k:k + 1])
            bound = _bound_cell(inputs[member], residual[:, 0], noise_radius[k], metric[k], lo, hi, lipschitz_margin)
            low_edge, high_edge = lo <= lo_all, hi >= hi_all
            outward = extend * (hi_all - lo_all) * (low_edge | high_edge)
            errors = bound[0] + bound[2] * (outward * metric[k]).norm()
            lo, hi = lo - extend * (hi_all - lo_all) * low_edge, hi + extend * (hi_all - lo_all) * high_edge
            cells.append((lo, hi, theta[1:, 0], theta[0, 0] + bound[1], errors, bound[2],
                          errors / noise_radius[k].clamp_min(1e-12)))
        per_output.append([torch.stack(parts) for parts in zip(*cells)])
    width = max(parts[0].shape[0] for parts in per_output)
    fill = (torch.inf, -torch.inf, 0.0, 0.0, 0.0, 0.0, torch.inf)
    stacked = [torch.stack([_pad_rows(parts[i], width, fill[i]) for parts in per_output]) for i in range(7)]
    return Cells(*stacked)


def _cell_boxes(inputs: Tensor, weights: Tensor, leaf_size: int, overlap: float) -> list[tuple]:
    """``(low, high, member)`` of the widened nodes of a k-d tree in the metric ``weights``."""
    lo_all, hi_all = inputs.amin(0), inputs.amax(0)
    boxes = []
    for index in tree_boxes(inputs * weights, leaf_size):
        core = inputs[index]
        lo, hi = core.amin(0), core.amax(0)
        pad = overlap * (hi - lo)
        lo, hi = torch.maximum(lo - pad, lo_all), torch.minimum(hi + pad, hi_all)
        member = ((inputs >= lo) & (inputs <= hi)).all(-1)
        if int(member.sum()) >= 2 * (inputs.shape[1] + 1):
            boxes.append((lo, hi, member))
    return boxes


def _pad_rows(values: Tensor, rows: int, fill: float) -> Tensor:
    pad = values.new_full((rows - values.shape[0], *values.shape[1:]), fill)
    return torch.cat((values, pad))


def input_relevance(slopes: Tensor, floor: float = 0.05) -> Tensor:
    """Per-output weights of the inputs in the distance of the Lipschitz bound: ``[n, d]``.

    What a local affine model leaves is its output's curvature, so the residual of output
    ``k`` varies along input ``d`` as much as the local slope ``∂y_k/∂z_d`` changes from cell
    to cell; an input the output depends on linearly (or not at all) should not make the data
    look far apart, or the covering radius of all ``d`` dimensions enters the bound where the
    few curved ones would do. The weight is the range of the slope over the cells, relative to
    the output's largest, floored at ``floor``. The bound stays sound for any weights, because
    its Lipschitz constants are estimated in the same weighted metric.

    Args:
        slopes: ``[M, d, n]`` the cells' fitted slopes.
    """
    relevance = (slopes.amax(0) - slopes.amin(0)).T  # [n, d]
    return (relevance / relevance.amax(-1, keepdim=True).clamp_min(1e-300)).clamp_min(floor)


def _affine_fit(z: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """Least squares ``y ≈ θᵀ [1; z]``: ``(θ [1 + d, n], residuals [s, n])``."""
    regressors = torch.cat((torch.ones(len(z), 1, dtype=z.dtype), z), dim=1)
    theta = torch.linalg.lstsq(regressors, y, driver="gelsd").solution
    return theta, y - regressors @ theta


def _bound_cell(z: Tensor, residual: Tensor, noise_radius: Tensor, weights: Tensor, lo: Tensor, hi: Tensor,
                margin: float, chunk: int = 256) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Error interval of one output on one cell, in the weighted metric (module docstring).

    Returns:
        ``(half-width, centre, lipschitz, score)``, scalars.
    """
    weighted = z * weights  # [s, d]
    diameter = ((hi - lo) * weights).norm().clamp_min(1e-12)
    blocks = torch.split(torch.arange(len(z)), chunk)
    slope = residual.new_zeros(())
    for rows in blocks:  # pairwise, in row blocks of [c, s]
        distance = torch.cdist(weighted[rows], weighted)
        gap = ((residual[rows].unsqueeze(-1) - residual).abs() - 2 * noise_radius).clamp_min(0)
        slope = torch.maximum(slope, torch.where(distance > 0, gap / distance.clamp_min(1e-300), 0.0).amax())
    lipschitz = torch.maximum(slope * margin, 2 * noise_radius / diameter)
    upper, lower = residual.new_tensor(-torch.inf), residual.new_tensor(torch.inf)
    for rows in blocks:  # max_j min_i (r_i + L d_ij), min_j max_i (r_i - L d_ij)
        reach = lipschitz * torch.cdist(weighted[rows], weighted)
        upper = torch.maximum(upper, (residual + reach).amin(-1).amax())
        lower = torch.minimum(lower, (residual - reach).amax(-1).amin())
    delta = _nearest_distance(weighted).max()
    upper = upper + noise_radius + lipschitz * delta
    lower = lower - noise_radius - lipschitz * delta
    errors = (upper - lower) / 2
    return errors, (upper + lower) / 2, lipschitz, errors / noise_radius.clamp_min(1e-12)


def _nearest_distance(points: Tensor) -> Tensor:
    """Distance of every point to its nearest other point: ``[s]``."""
    dist, _ = cKDTree(points.detach().cpu().numpy()).query(points.detach().cpu().numpy(), k=2)
    return torch.as_tensor(np.asarray(dist)[:, 1], dtype=points.dtype)


def select_cells(cells: Cells, low: Tensor, high: Tensor) -> tuple[Tensor, Tensor]:
    """Per output, the tightest cell containing each query box ``[low, high]`` ``[..., d]``.

    Returns:
        ``(index [..., n], covered [...])``: the chosen cells (the root where none contains the
        box) and whether every output found one.
    """
    contains = ((low[..., None, None, :] >= cells.low) & (high[..., None, None, :] <= cells.high)).all(-1)  # [..., n, M]
    score = torch.where(contains, cells.score, torch.inf)
    return score.argmin(-1), contains.any(-1).all(-1)
