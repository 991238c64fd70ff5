"""Local affine models on leaves that tile the data, each with a set-membership error bound.

A global affine fit of a nonlinear robot leaves a residual as wide as the nonlinearity over
the whole data region (saturation, drag, heading), which then enters every reachable set.
Here the regressor space ``z = (x_F, u)`` (the non-translation-invariant states and the
actions, scaled to unit range) is split by a regression tree per output, along the inputs
and along the differences and sums of a state and an action; each split is the median of
the candidate direction that leaves the smallest squared residual of the two halves' affine
fits (as M5 model trees do). The leaves tile the data's bounding region (extended beyond its
edges); each has its own least-squares fit, on its points and those just beyond its faces,
and an error interval valid for every ``z`` in it. A saturating servo's kinks (``u - v =
const``) are taken out first, where they help: hinge features fitted once over all data
(:mod:`~torchrl_brsl.reach.hinges`), so that the leaves fit what the hinges leave. A
reachable-set step (:func:`leaf_bounds`) uses the model of the leaf holding the set's centre
and the worst error over every leaf the set meets (Nguyen-Tuong et al., "Local Gaussian
process regression for real time online model learning", NeurIPS 2008, for local models;
Milanese & Novara, "Set membership identification of nonlinear systems", Automatica 2004, for
the bound).

**Bound of one leaf.** Data ``y_i = h(z_i) + (w_i - c_w)`` with ``|w_i - c_w| <= w̄``
per dimension; ``ℓ`` the leaf's affine fit, ``r_i = y_i - ℓ(z_i)`` and ``g = h - ℓ``. If
``g_k`` is ``L_k``-Lipschitz on the leaf (Euclidean distance of the scaled inputs, each
weighted per output by :func:`input_relevance`), every data point constrains it:

    g_k(z) <= min_i (r_ik + w̄_k + L_k ||z - z_i||) =: U_k(z),

and ``U_k`` is ``L_k``-Lipschitz itself, so at a distance ``D(z)`` from the leaf's nearest
data point, ``g_k(z) <= max_j U_k(z_j) + L_k max(δ, D(z))``, with ``δ`` the data's covering
radius (the largest distance of a point to its nearest neighbour): ``L_k D`` alone would
suffice for an exact ``L_k``, the ``δ`` floor is slack against the sampled ``L_k`` being too
small (without it one of 440 sampled states of a capped multirotor fell outside); the lower
bound likewise. Unlike the residual box plus noise, the intersection over data points removes
most of the data's own noise: with many neighbours ``max_j U_k(z_j)`` approaches ``g + (noise
seen)`` from above instead of ``g + 2 w̄``. For a whole set, ``D`` is bounded by its centre's distance to the
leaf's data (or to any one of its points) plus its radius (:func:`leaf_distance`): no assumption that the
data cover the set is needed.

``L_k`` is the smallest constant consistent with the leaf's data, ``max_{i,j} (|r_ik - r_jk|
- 2 w̄_k)_+ / ||z_i - z_j||`` over all pairs, times ``lipschitz_margin``, and never below
``max(2 w̄_k, range of r_k) / diam``: a floor that lets ``g`` drift across the cell by as much
as the residuals themselves vary, which the data cannot rule out (the fit's slope error is
of that order) and which keeps the intersection from claiming an exact value where the
data are merely consistent with one (a noise-free output, such as a position, would
otherwise get ``L = 0`` from data that never show its variation); nor below half the change
of the fitted slope to a touching leaf (:func:`curvature_floor`), the curvature that noise of
the same size hides from the pairs; nor below the slope that a quadratic fitted to the leaf's
residual reaches over its box (:func:`corner_slopes`, :func:`slope_reach`): the box extends beyond
the data, between whose pairs the estimate looks. Where hinges of one sign cut a smooth bend into
pieces, the bend's stray from them between their knots is added to the leaf's error
(:func:`bend_error`): it too can hide below the noise. Where nearby points scatter beyond ``w̄``
(a step that depends on something the state does not hold), a leaf may read part of the scatter
as a hidden noise ``h`` instead of slope, if that is tighter: ``w̄ + h`` in the pairs and the
envelope, and ``h`` added to the half-width as a disturbance of every step (:func:`_bound_cell`).
"""
from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from tqdm.auto import tqdm

from torchrl_brsl._compiling import small_matmul
from torchrl_brsl.reach.hinges import Features, feature_values, fit_features, parallel_knots, product_relaxation


class Cells(NamedTuple):
    """Stacked local models: for each of the ``n`` outputs, ``M`` leaves (cells) over scaled regressors ``z``.

    A cell is a box in the split directions ``φ = directions @ z``; an output's cells tile the
    data's region. Outputs with fewer cells are padded with empty boxes (``low = inf``) that
    contain nothing.

    Attributes:
        directions: ``[f, d]`` the split directions (scaled units).
        weights: ``[n, d]`` each output's input weights in the bound's distance.
        low, high: ``[n, M, f]`` the cell boxes in those directions.
        slopes: ``[n, M, d + H + Q]`` least-squares slopes of the output on ``z`` (scaled units),
            then on the output's hinge features ``relu(hinge_directions @ z - hinge_knots)``
            and product features (:func:`~torchrl_brsl.reach.hinges.product_features`).
        intercepts: ``[n, M]`` intercept at ``z = 0`` plus the centre of the error interval.
        errors: ``[n, M]`` half-widths of the error interval within ``delta`` of the cell's data
            (model error with :func:`bend_error`, noise not included); a query at distance ``D > delta``
            adds ``L (D - delta)``.
        lipschitz: ``[n, M]`` the residual's Lipschitz constants used in the bound.
        delta: ``[n, M]`` the covering radius of each cell's data in its output's weighted metric
            (the largest distance of a data point to its nearest neighbour).
        score: ``[n, M]`` the error in noise units, lower is tighter (selects among cells).
        hinge_directions: ``[n, H, d]`` each output's hinges (padding: zero rows).
        hinge_knots: ``[n, H]`` their knots (padding: 1, a feature that is always 0).
        product_directions: ``[n, Q, 2, d]`` each output's products' factors (padding: zeros).
        product_knots: ``[n, Q, 2]`` the factors' centres (padding: 0).
        members: ``[n, N]`` the cell holding each data point, per output.
    """

    directions: Tensor
    weights: Tensor
    low: Tensor
    high: Tensor
    slopes: Tensor
    intercepts: Tensor
    errors: Tensor
    lipschitz: Tensor
    delta: Tensor
    score: Tensor
    hinge_directions: Tensor
    hinge_knots: Tensor
    product_directions: Tensor
    product_knots: Tensor
    members: Tensor


METRIC_FLOORS = (0.05, 0.3, 1.0)
"""Floors of the input weights tried per output (1.0: the plain metric); the tightest is kept."""


HINGE_RATIOS = (1.0, 0.3, 0.1)
"""Ratios ``r`` of the hinges' candidate directions ``x_i ± r u_j`` (original units): a velocity
servo saturates along ``u - v`` (``r = 1``), an acceleration-commanded speed clips along
``v + dt a`` (``r = dt``, 0.1 s in the tasks; without it the unicycle's clip at 0 and 1 m/s had no
hinge, and 3 of 20 random plans were claimed with 500 steps, 18 with it). :func:`fit_cells` offers
each output the hinges of the first ratio alone and of all, and keeps what its probe error
prefers: the extra candidates let the greedy selection pick worse hinges for a tanh thrust (5.4x
the sampled spread instead of 4.8x)."""


def split_directions(n_states: int, n_actions: int, scale: Tensor | None = None, dtype=torch.float64,
                     ratios: tuple[float, ...] = (1.0,)) -> Tensor:
    """The inputs, then ``x_i ± r u_j`` for every state-action pair and ratio: ``[f, n_states + n_actions]``.

    The rows act on scaled inputs ``z = (x, u) / scale``; a pair's row is the difference or sum
    in the original units (``scale_i z_i ± r scale_j z_j``, divided by its larger entry), so that
    a servo's kink ``u - v = const`` is a hyperplane of the direction also when ``v`` and ``u``
    span different ranges. ``scale=None``: equal scales.
    """
    d = n_states + n_actions
    scale = torch.ones(d, dtype=dtype) if scale is None else scale.to(dtype)
    rows = [torch.eye(d, dtype=dtype)]
    for ratio in ratios:
        for i in range(n_states):
            for j in range(n_states, d):
                for sign in (-1.0, 1.0):
                    row = torch.zeros(d, dtype=dtype)
                    row[i], row[j] = scale[i], sign * ratio * scale[j]
                    rows.append((row / row.abs().max()).unsqueeze(0))
    return torch.cat(rows)


def tree_nodes(features: Tensor, inputs: Tensor, target: Tensor, leaf_size: int,
               allowed: Tensor) -> list[tuple[Tensor, Tensor]]:
    """The nodes of a regression tree, root first: ``(index, region)`` with ``region`` ``[2, f]``.

    The root's region is the data's bounding box in the ``allowed`` directions of ``features``
    ``[N, f]`` (unbounded in the others). A node holding at least ``2 leaf_size`` points is
    split at the median of the allowed feature whose halves leave the smallest summed squared
    residual of affine fits of ``target`` ``[N]`` on ``inputs`` ``[N, d]``; the children's
    regions are the parent's cut at the split, so that they tile it without gaps.
    """
    root = torch.stack((torch.where(allowed, features.amin(0), -torch.inf),
                        torch.where(allowed, features.amax(0), torch.inf)))
    nodes, stack = [], [(torch.arange(inputs.shape[0]), root)]
    while stack:
        index, region = stack.pop()
        nodes.append((index, region))
        if len(index) < 2 * leaf_size:
            continue
        best, best_error = None, torch.inf
        for column in allowed.nonzero().flatten().tolist():
            values = features[index, column]
            order = values.argsort()
            halves = (index[order[:len(index) // 2]], index[order[len(index) // 2:]])
            error = sum(float(_affine_fit(inputs[h], target[h].unsqueeze(-1))[1].square().sum()) for h in halves)
            if error < best_error:
                cut = float(values[order[len(index) // 2 - 1]] + values[order[len(index) // 2]]) / 2
                best, best_error = (halves, column, cut), error
        (left, right), column, cut = best
        left_region, right_region = region.clone(), region.clone()
        left_region[1, column], right_region[0, column] = cut, cut
        stack.extend(((left, left_region), (right, right_region)))
    return nodes


def fit_cells(inputs: Tensor, targets: Tensor, noise_radius: Tensor, n_actions: int, *, scale: Tensor | None = None,
              leaf_size: int | None = None, overlap: float = 0.15, extend: float = 0.25,
              lipschitz_margin: float = 1.0, use_features: bool = True, progress: bool = False) -> Cells:
    """Fit local affine models and their error intervals, one tree of cells per output.

    Per output, the target is offered without features and with two sets of fitted features
    (hinges along the pairs of ratio 1, or of every :data:`HINGE_RATIOS`, and state-action
    products); for each, two trees are grown (splits along the inputs only, and also along the
    state-action pairs); the cells' local slopes give the inputs' weights in the bound's
    distance (:func:`input_relevance`) and several floors of the weights are tried. All of this
    on every input, and again on the inputs :func:`select_inputs` finds the output depending on
    (the others weigh 0). The cells with the smallest mean error over probe sets (boxes around
    the data points) are kept; the bound is sound for every choice.

    Args:
        inputs: ``[N, d]`` scaled regressors ``z`` (states first, the ``n_actions`` actions last).
        targets: ``[N, n]`` ``y = x+ - c_w - P x``.
        noise_radius: ``[n]`` ``w̄``, the noise's interval radius per state dimension.
        n_actions: the number of action columns of ``inputs``.
        scale: ``[d]`` the units of ``inputs`` (``z = (x, u) / scale``), for the hinges' state-action
            pair directions (:func:`split_directions`); ``None``: equal units.
        leaf_size: points per leaf (about; a node of ``2 leaf_size`` or more is split). Default
            ``10 (d + 1)``: fewer points per leaf under-estimate the Lipschitz constants in
            higher dimensions (with 32, one sampled state of a 6-D diffdrive model fell 1 mm
            outside its set).
        overlap: each cell box is widened by this share of its width on every side, so that a
            small set near a split still fits into one cell.
        extend: cells reaching the edge of the data's bounding box extend beyond it by this
            share of each direction's range (the braking action at its bound, a robot at rest
            on the edge of its speeds); a query there is farther from the data, which the
            per-query distance term of the error accounts for.
        lipschitz_margin: factor (>= 1) on the data's Lipschitz constants.
        use_features: offer each output its hinge and product features
            (:func:`~torchrl_brsl.reach.hinges.fit_features`, kept where the probe error says they
            help); ``False``: leaves affine in ``z`` only.
        progress: show a progress bar over the outputs (a fit takes seconds to minutes).

    Returns:
        The stacked :class:`Cells`, root first for every output.
    """
    leaf_size = 10 * (inputs.shape[1] + 1) if leaf_size is None else int(leaf_size)
    n_states = inputs.shape[1] - n_actions
    directions = split_directions(n_states, n_actions, dtype=inputs.dtype)
    features = inputs @ directions.T
    kink_sets = [split_directions(n_states, n_actions, scale, inputs.dtype, ratios)  # the hinges' candidates
                 for ratios in (HINGE_RATIOS[:1], HINGE_RATIOS)]
    axes = torch.zeros(directions.shape[0], dtype=torch.bool)
    axes[:inputs.shape[1]] = True
    d = inputs.shape[1]
    grid = (directions, features, kink_sets, axes)
    sizes = (leaf_size, overlap, extend, lipschitz_margin)
    per_output, chosen, fitted = [], [], []
    for k in tqdm(range(targets.shape[1]), desc="local model", unit="output", disable=not progress):
        support = select_inputs(inputs, targets[:, k])
        supports = [torch.ones_like(support)] + ([support] if 0 < int(support.sum()) < d else [])
        candidates = [candidate for inputs_of in supports for candidate in _output_candidates(
            inputs, targets[:, k], noise_radius[k], n_actions, inputs_of, grid, sizes, use_features)]
        best = min(candidates, key=lambda c: _probe_error(*c, inputs, directions, n_states))
        per_output.append(best[0])
        chosen.append(best[1])
        fitted.append(best[2])
    n_hinges = max(len(f.hinge_knots) for f in fitted)
    n_products = max(len(f.product_knots) for f in fitted)
    width = max(parts[0].shape[0] for parts in per_output)
    fill = (torch.inf, -torch.inf, 0.0, 0.0, 0.0, 0.0, 0.0, torch.inf)
    for parts, f in zip(per_output, fitted):  # slopes of every output over d + n_hinges + n_products columns
        linear, hinge, product = parts[2].split((d, len(f.hinge_knots), len(f.product_knots)), dim=-1)
        parts[2] = torch.cat((linear, torch.nn.functional.pad(hinge, (0, n_hinges - hinge.shape[-1])),
                              torch.nn.functional.pad(product, (0, n_products - product.shape[-1]))), dim=-1)
    stacked = [torch.stack([_pad_rows(parts[i], width, fill[i]) for parts in per_output]) for i in range(len(fill))]
    members = torch.stack([parts[-1] for parts in per_output])
    return Cells(directions, torch.stack(chosen), *stacked,
                 torch.stack([_pad_rows(f.hinge_directions, n_hinges, 0.0) for f in fitted]),
                 torch.stack([_pad_rows(f.hinge_knots, n_hinges, 1.0) for f in fitted]),
                 torch.stack([_pad_rows(f.product_directions, n_products, 0.0) for f in fitted]),
                 torch.stack([_pad_rows(f.product_knots, n_products, 0.0) for f in fitted]), members)


def _output_candidates(inputs: Tensor, target: Tensor, noise_radius: Tensor, n_actions: int, support: Tensor,
                       grid: tuple, sizes: tuple, use_features: bool) -> list[tuple]:
    """Candidate cells of one output on the inputs ``support`` ``[d]``: ``(parts, weights, features)`` for each
    feature set, split family and metric floor (:func:`fit_cells`).

    Inputs outside the support are zeroed for the fits and the hinges, never split along, and weigh 0 in the
    bound's metric; the leaves still end at the data's range along them (extended by ``extend``), so a set beyond
    it is not covered. ``grid``: ``(directions, features, kink_sets, axes)``; ``sizes``: ``(leaf_size, overlap,
    extend, lipschitz_margin)``.
    """
    directions, features, kink_sets, axes = grid
    leaf_size, overlap, extend, margin = sizes
    d = inputs.shape[1]
    masked = inputs * support
    inside = (directions[:, ~support] == 0).all(-1)  # the split directions within the support
    options = [Features(inputs.new_zeros(0, d), inputs.new_zeros(0), inputs.new_zeros(0, 2, d),
                        inputs.new_zeros(0, 2), inputs.new_zeros(0))]
    if use_features:
        for kinks in kink_sets:
            kinks = kinks[(kinks[:, ~support] == 0).all(-1)]
            options.append(fit_features(masked @ kinks.T, kinks, masked, target, noise_radius, n_actions=n_actions))
    candidates, extremes = [], observed_extremes(target, noise_radius, d)
    plateau = bool(torch.isfinite(extremes[0]) or torch.isfinite(extremes[1]))  # else no range error to check
    resolution = RESOLUTION * (target.amax() - target.amin())
    resolved = noise_radius.clamp_min(resolution)  # the bound's w̄
    for option in options:
        residual = target - feature_values(inputs, option) @ option.coefficients  # what the features leave
        for allowed in (axes & inside, inside):  # splits along the inputs only, or also the pairs
            nodes = tree_nodes(features, masked, residual, leaf_size, allowed)
            leaves = [node for node in nodes if len(node[0]) < 2 * leaf_size] or nodes[:1]
            boxes = _cell_boxes(features, nodes[0][1], leaves, overlap, extend, allowed, axes)
            fits = [_affine_fit(masked[fit], residual[fit, None]) for _, _, fit, _ in boxes]
            for theta, _ in fits:  # a zeroed input's slope, exactly (the curvature floor of any other is infinite)
                theta[1:][~support] = 0.0
            relevance = input_relevance(torch.stack([theta[1:] for theta, _ in fits]), floor=0.0)[0]
            spans = [prediction_range(inputs, lo, hi, theta[:, 0], option, support, directions) if plateau else None
                     for (lo, hi, *_), (theta, _) in zip(boxes, fits)]
            slopes = [corner_slopes(inputs[fit], residual[:, 0], support, lo[:d], hi[:d], resolved)
                      for (lo, hi, fit, _), (_, residual) in zip(boxes, fits)]
            for weights in (relevance.clamp_min(floor) * support for floor in METRIC_FLOORS):
                parts = _output_cells(inputs, boxes, fits, resolved, weights, option, margin, spans, slopes, extremes,
                                      noise_free=bool(noise_radius <= resolution))
                parts[2] = torch.cat((parts[2], option.coefficients.expand(parts[2].shape[0], -1)), dim=-1)
                candidates.append((parts, weights, option))
    return candidates


RESOLUTION = 1e-5
"""The least noise radius of an output's bound, as a share of the range of its values in the data. A noise-free
output (a position advanced by the velocity) is fitted as exactly as the hinges' kinks are found, and an optimiser
finds those to about a millionth of the range: the capped servo's position kinks at ``u - v = 0.500002`` for
``0.5``. Between the fitted and the true kink there is then no data point to show the model's miss, about 1e-7 m;
with no noise the bound had no slack for it, and 23 of 100,000 worst-noise queries of the servo's 2,000-step model
(one of its fits, :func:`~torchrl_brsl.reach.evaluation.worst_noise_outside`) fell 1e-8 m beyond position bounds of
1.3e-8 m. Outputs with noise are not touched (their ``w̄`` is a thousandth of their range or more)."""


SELECTION_NEIGHBOURS = 8
"""Neighbours whose mean predicts a data point's target in :func:`select_inputs`."""

SELECTION_GAIN = 0.1
"""The least share of the prediction error an input must remove to join an output's support (:func:`select_inputs`)."""


def select_inputs(inputs: Tensor, target: Tensor, neighbours: int = SELECTION_NEIGHBOURS,
                  gain: float = SELECTION_GAIN) -> Tensor:
    """The inputs an output depends on, by greedy forward selection: ``[d]`` bool.

    Each round adds the input that most lowers the leave-one-out error of predicting ``target`` ``[N]`` by the mean
    of the ``neighbours`` nearest data points in the inputs chosen so far (``inputs`` ``[N, d]``, scaled), while it
    lowers it by at least ``gain`` of the last error. A capped servo's velocity depends on its own axis' velocity
    and command, two of six inputs, along which 500 points lie about as densely as 2,000 per axis: :func:`fit_cells`
    offers each output cells on these inputs alone beside cells on all, and the probe error chooses (the bound of
    either holds if its Lipschitz constants do; an input the selection misses shows up in the constants, as pairs
    of nearby points whose outputs differ).

    Examples:
        >>> z = torch.rand(400, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        >>> select_inputs(z, torch.sin(3 * z[:, 1])).tolist()
        [False, True, False]
    """
    points, values = inputs.detach().cpu().numpy(), target.detach().cpu().numpy()
    chosen, error = [], float(np.var(values))
    while len(chosen) < inputs.shape[1]:
        trials = {j: _neighbour_error(points[:, chosen + [j]], values, neighbours)
                  for j in range(inputs.shape[1]) if j not in chosen}
        best = min(trials, key=trials.get)
        if trials[best] > (1 - gain) * error:
            break
        chosen.append(best)
        error = trials[best]
    support = torch.zeros(inputs.shape[1], dtype=torch.bool, device=inputs.device)
    support[chosen] = True
    return support


def _neighbour_error(points: np.ndarray, values: np.ndarray, neighbours: int) -> float:
    """Mean squared error of predicting each value by the mean of its ``neighbours`` nearest other points'."""
    _, index = cKDTree(points).query(points, k=neighbours + 1)
    return float(np.mean((values - values[index[:, 1:]].mean(1)) ** 2))


PROBE_RADII = (0.01, 0.03, 0.1)
"""Radii (scaled units, on the state inputs) of the probe sets that rank candidate cells."""


def _probe_error(parts: list[Tensor], weights: Tensor, features: Features, inputs: Tensor,
                 directions: Tensor, n_states: int) -> float:
    """Mean error bound over boxes of :data:`PROBE_RADII` around every data point (on the state
    inputs; uncovered probes count as twice the largest leaf error; a NaN bound anywhere: ``inf``)."""
    cells = Cells(directions, weights.unsqueeze(0), *(part.unsqueeze(0) for part in parts[:-1]),
                  *(part.unsqueeze(0) for part in features[:4]), parts[-1].unsqueeze(0))
    layout = leaf_layout(cells, (inputs * weights).unsqueeze(0))
    centre_distance = leaf_distance(cells, None, inputs, layout=layout)  # [N, 1, M]
    total = 0.0
    for radius in PROBE_RADII:
        z_radius = torch.zeros_like(inputs)
        z_radius[:, :n_states] = radius
        h_center = (inputs @ features.hinge_directions.T - features.hinge_knots).unsqueeze(-2)  # [N, 1, H]
        h_radius = (z_radius @ features.hinge_directions.abs().T).unsqueeze(-2)
        p_center = torch.einsum("nd,qkd->nqk", inputs, features.product_directions) - features.product_knots
        p_radius = torch.einsum("nd,qkd->nqk", z_radius, features.product_directions.abs())
        *_, p_low, p_high = product_relaxation(p_center, p_radius)
        low = torch.cat(((h_center - h_radius).clamp_min(0), p_low.unsqueeze(-2)), -1)
        high = torch.cat(((h_center + h_radius).clamp_min(0), p_high.unsqueeze(-2)), -1)
        distance = centre_distance + (weights * z_radius).norm(dim=-1)[:, None, None]
        _, errors, covered = leaf_bounds(cells, inputs, z_radius, directions[:, :n_states].abs().sum(-1) * radius,
                                         low, high, distance)
        total += float(torch.where(covered, errors[:, 0], 2 * parts[4].max()).mean())
    return math.inf if math.isnan(total) else total  # a NaN error bound never ranks first (``min`` would keep it)


def _cell_boxes(features: Tensor, root: Tensor, leaves: list[tuple], overlap: float, extend: float,
                allowed: Tensor, axes: Tensor) -> list[tuple]:
    """``(low, high, fit, index)`` per leaf: its region (extended by ``extend`` where it reaches
    the root's edge), the data of the region widened by ``overlap`` (the fit's points, a mask)
    and the data of the region itself (indices). Along the input ``axes`` the tree does not split,
    every leaf spans the data's range, extended likewise."""
    lo_all, hi_all = root
    span = torch.where(allowed, extend * (hi_all - lo_all), 0.0)
    unsplit = axes & ~allowed
    low_data, high_data = features.amin(0), features.amax(0)
    margin = extend * (high_data - low_data)
    boxes = []
    for index, (lo, hi) in leaves:
        pad = torch.where(allowed, overlap * (hi - lo), 0.0)
        fit = ((features >= lo - pad) & (features <= hi + pad)).all(-1)
        fit[index] = True
        low_edge, high_edge = (lo <= lo_all) & allowed, (hi >= hi_all) & allowed
        low, high = lo - span * low_edge, hi + span * high_edge
        boxes.append((torch.where(unsplit, low_data - margin, low), torch.where(unsplit, high_data + margin, high),
                      fit, index))
    return boxes


def _output_cells(inputs: Tensor, boxes: list[tuple], fits: list[tuple], noise_radius: Tensor, weights: Tensor,
                  option: Features, margin: float, spans: list[Tensor | None], slopes: list[Tensor],
                  extremes: tuple[Tensor, Tensor], noise_free: bool = False) -> list[Tensor]:
    """The stacked cells of one output in the metric ``weights``, on the features ``option``: the fields of
    :class:`Cells` from ``low`` to ``score``, then ``members`` ``[N]``. ``spans``: each leaf's
    :func:`prediction_range` (``None``: not needed), ``slopes``: its :func:`corner_slopes`, ``extremes``:
    :func:`observed_extremes`. ``noise_free``: the output has no noise (below the resolution), so its data bound
    a bend's stray where they are dense (:func:`bend_error`); with noise they do not: the saturated point's velocity
    (2,000 steps) let 2 of 20,000 worst-noise one-step queries out of its sets where they did."""
    cells, members = [], torch.empty(inputs.shape[0], dtype=torch.long)
    low, high = torch.stack([lo for lo, *_ in boxes]), torch.stack([hi for _, hi, *_ in boxes])
    floors = curvature_floor(low, high, torch.stack([theta[1:, 0] for theta, _ in fits]), weights)
    bends = bend_error(low[:, :inputs.shape[1]], high[:, :inputs.shape[1]], option,
                       [inputs[fit] for _, _, fit, _ in boxes] if noise_free else None)
    for leaf, ((lo, hi, fit, index), (theta, residual)) in enumerate(zip(boxes, fits)):
        floor = torch.maximum(floors[leaf], slope_reach(slopes[leaf], weights))
        errors, centre, lipschitz, delta, _ = _bound_cell(inputs[fit], residual[:, 0], noise_radius, weights, margin,
                                                          floor)
        errors = torch.maximum(errors + bends[leaf], range_error(spans[leaf], centre, noise_radius, *extremes))
        cells.append((lo, hi, theta[1:, 0], theta[0, 0] + centre, errors, lipschitz, delta,
                      errors / noise_radius.clamp_min(1e-12)))
        members[index] = leaf
    return [torch.stack(parts) for parts in zip(*cells)] + [members]


def observed_extremes(target: Tensor, noise_radius: Tensor, d: int) -> tuple[Tensor, Tensor]:
    """The output's least and largest value where the data show it as a plateau (more than ``d + 1`` points within
    the noise's width ``2 w̄`` of it, as a saturation piles them up), ``-inf`` and ``inf`` where they do not."""
    lowest, highest = target.amin(), target.amax()
    at_low = int((target <= lowest + 2 * noise_radius).sum()) >= d + 2
    at_high = int((target >= highest - 2 * noise_radius).sum()) >= d + 2
    none = lowest.new_tensor(torch.inf)
    return (lowest if at_low else -none), (highest if at_high else none)


RANGE_CORNERS = 4096
"""Most points of a leaf's box (its corners and the midpoints between them along each input) at which
:func:`prediction_range` evaluates its model (random ones beyond)."""

RANGE_VERTEX_SYSTEMS = 50000
"""Most linear systems :func:`leaf_vertices` solves for one leaf (choices of as many of its planes as the output
has inputs); a leaf with more gets the grid of :data:`RANGE_CORNERS` only. The wheeled Turtlebot's wheel-speed
outputs (4 inputs, up to 28 planes: 20,475 systems) are within it."""


def range_error(span: Tensor | None, centre: Tensor, noise_radius: Tensor, lowest: Tensor, highest: Tensor) -> Tensor:
    """The least error half-width at which one leaf's interval reaches the output's observed range wherever its model
    is checked (:func:`prediction_range`): a scalar.

    Where an output saturates at the edge of the data region (a speed that clips at 0 under hard braking), a
    leaf fitted on data that never reach the clip extrapolates past it: its model predicts speeds below any the
    data show, where the true speed is that least value. The output's least value ``m`` over the data region is at
    most ``min_i y_i + w̄``, so an interval whose upper end lies below that at some input cannot hold a true value
    that reaches ``m`` there; the half-width is raised until it does (and likewise at the top), where the data
    show the value as a plateau (:func:`observed_extremes`). Where the plateau is the least value over the
    region, a correct interval is widened by at most ``2 w̄``, at those points only.

    Args:
        span: ``[2]`` the least and largest value of the leaf's model without its interval's centre ``centre``
            (``None``: the output shows no plateau, or the leaf's box misses the data's).
        lowest, highest: the output's least and largest value in the data where they are plateaus (else ``∓inf``).
    """
    if span is None:
        return centre.new_zeros(())
    short = torch.maximum(lowest + noise_radius - (span[0] + centre), span[1] + centre - highest + noise_radius)
    return short.clamp_min(0)


def prediction_range(inputs: Tensor, low: Tensor, high: Tensor, theta: Tensor, features: Features, support: Tensor,
                     directions: Tensor) -> Tensor | None:
    """The least and largest value ``[2]`` of one leaf's model (without its interval's centre) at every vertex of the
    leaf's region within the data's bounding box, cut by its hinges' kinks (:func:`leaf_vertices`), and at the
    corners and mid-edge points of that box; ``None`` where the leaf's box misses the data's.

    A model affine between its hinges' kinks takes its extremes over the region at those vertices, so the range is
    exact for it; product features can bend it between them.

    Args:
        inputs: ``[N, d]`` the scaled data; low, high: ``[f]`` the leaf's box in the split directions (the
            first ``d`` along the inputs).
        theta: ``[1 + d]`` the leaf's affine fit of what ``features`` leave.
        support: ``[d]`` the output's inputs; directions: ``[f, d]`` the split directions of ``low`` and ``high``.
    """
    d = inputs.shape[1]
    lo, hi = torch.maximum(low[:d], inputs.amin(0)), torch.minimum(high[:d], inputs.amax(0))
    if bool((lo > hi).any()):
        return None
    free = support.nonzero()[:, 0]
    levels = torch.tensor([0.0, 0.5, 1.0], dtype=lo.dtype)
    if 3 ** len(free) <= RANGE_CORNERS:
        corners = torch.cartesian_prod(*([levels] * len(free))).reshape(-1, len(free))
    else:
        corners = levels[torch.randint(3, (RANGE_CORNERS, len(free)), generator=torch.Generator().manual_seed(0))]
    z = ((lo + hi) / 2).expand(len(corners), d).clone()
    z[:, free] = lo[free] + corners * (hi - lo)[free]
    phi = z @ directions.T
    z = torch.cat((z[((phi >= low - 1e-9) & (phi <= high + 1e-9)).all(-1)],
                   leaf_vertices(lo, hi, low, high, directions, support, features.hinge_directions,
                                 features.hinge_knots)))
    if len(z) == 0:
        return None
    prediction = theta[0] + z @ theta[1:] + feature_values(z, features) @ features.coefficients
    return torch.stack((prediction.amin(), prediction.amax()))


def leaf_vertices(lo: Tensor, hi: Tensor, low: Tensor, high: Tensor, directions: Tensor, support: Tensor,
                  hinge_directions: Tensor, hinge_knots: Tensor) -> Tensor:
    """The vertices of a leaf's region ``{lo <= z <= hi, low <= directions @ z <= high}`` cut by the hinges'
    kinks ``hinge_directions @ z = hinge_knots``, in the ``support`` inputs (the others at the middle of
    ``[lo, hi]``): ``[V, d]``, none where that takes more than :data:`RANGE_VERTEX_SYSTEMS` systems.

    Each choice of ``s`` of these planes (``s`` inputs in the support) that meets in one point inside the
    region is a vertex, by enumeration: an output's support and a leaf's finite faces are few, and only the kinks
    that cross the box along the inputs count.

    Args:
        lo, hi: ``[d]`` the box along the inputs; low, high: ``[f]`` the leaf's box along ``directions``
            ``[f, d]`` (the rows that use only the support and have a finite side give faces).
        support: ``[d]`` bool; hinge_directions: ``[H, d]``, hinge_knots: ``[H]`` (zero rows: none).
    """
    free = support.nonzero()[:, 0]
    rows = directions[:, free]
    within = (directions[:, ~support] == 0).all(-1)
    within[:len(lo)] = False  # the axes: lo and hi
    faces = [(rows[within & torch.isfinite(high)], high[within & torch.isfinite(high)]),
             (-rows[within & torch.isfinite(low)], -low[within & torch.isfinite(low)])]
    eye = torch.eye(len(free), dtype=lo.dtype)
    faces += [(eye, hi[free]), (-eye, -lo[free])]
    face_rows, face_bounds = torch.cat([f[0] for f in faces]), torch.cat([f[1] for f in faces])
    centre, radius = (lo + hi)[free] / 2, (hi - lo)[free] / 2
    along = hinge_directions[:, free] @ centre
    spread = hinge_directions[:, free].abs() @ radius
    kinks = (spread > 0) & ((along - hinge_knots).abs() <= spread)  # the kinks that cross the box
    planes = torch.cat((face_rows, hinge_directions[kinks][:, free]))
    values = torch.cat((face_bounds, hinge_knots[kinks]))
    if len(free) == 0 or math.comb(len(planes), len(free)) > RANGE_VERTEX_SYSTEMS:
        return lo.new_zeros(0, len(lo))
    # (torch.combinations builds the whole grid of len(planes) ** len(free) index tuples first)
    choice = torch.tensor(list(itertools.combinations(range(len(planes)), len(free))), dtype=torch.long)
    solution, info = torch.linalg.solve_ex(planes[choice], values[choice])
    points = solution[(info == 0) & torch.isfinite(solution).all(-1)]
    inside = (points @ face_rows.T <= face_bounds + 1e-9 * (1 + face_bounds.abs())).all(-1)
    z = ((lo + hi) / 2).expand(int(inside.sum()), -1).clone()
    z[:, free] = points[inside]
    return z


def curvature_floor(low: Tensor, high: Tensor, slopes: Tensor, weights: Tensor) -> Tensor:
    """A lower bound on each leaf's residual Lipschitz constant from its neighbours' slopes: ``[M]``.

    Within a leaf whose own data show no curvature above the noise, the pairwise estimate of
    :func:`_bound_cell` sees nothing; but where the true slope changes from one leaf's fitted
    slope ``s_l`` to its neighbour's ``s_b``, it passes the middle at their common face, so the
    residual ``g = h - ℓ_l`` has a gradient of about ``(s_b - s_l) / 2`` there. Its Lipschitz
    constant in the weighted metric is at least the dual norm ``||(s_b - s_l) / (2 w)||``
    over the touching neighbours ``b``. (A bicycle's heading step ``v tan(steer)``, bilinear,
    fitted in 3-D leaves of 60 points with noise of the same size as the curvature, let
    sampled headings out without this floor.)

    Args:
        low, high: ``[M, f]`` the leaves' boxes (touching boxes are neighbours).
        slopes: ``[M, d]`` their fitted slopes on the scaled inputs.
        weights: ``[d]`` the output's metric weights.
    """
    touching = ((low.unsqueeze(1) <= high.unsqueeze(0)) & (low.unsqueeze(0) <= high.unsqueeze(1))).all(-1)  # [M, M]
    change = slopes.unsqueeze(1) - slopes.unsqueeze(0)  # an input of weight 0 has no slope (else: no bound)
    ratio = torch.where(weights > 0, change / (2 * weights).clamp_min(1e-300), torch.where(change != 0, torch.inf, 0.0))
    return torch.where(touching, ratio.norm(dim=-1), 0.0).amax(-1)


QUADRATIC_POINTS = 3
"""A leaf fits :func:`corner_slopes`' quadratic surrogate when it holds at least this many points per coefficient."""

QUADRATIC_INPUTS = 8
""":func:`corner_slopes` looks at leaves of at most this many inputs of positive weight (``2^k`` corners)."""

QUADRATIC_CONDITION = 1e-3
""":func:`corner_slopes` needs its design's singular values within this ratio of the largest."""

SLOPE_SIGNIFICANCE = 2.0
"""Standard errors that :func:`corner_slopes` takes off each entry of a corner's gradient, at least."""


def corner_slopes(z: Tensor, residual: Tensor, active: Tensor, lo: Tensor, hi: Tensor, noise_radius: Tensor) -> Tensor:
    """The slopes of one leaf's quadratic surrogate at the corners of its box, beyond the noise: ``[C, d]``.

    The pairwise estimate of :func:`_bound_cell` sees the residual's slope between the leaf's data
    points only; the leaf's box reaches beyond them (to the extended edge of the data), where a
    smooth curvature keeps steepening the residual. Fitted by least squares on the leaf's points
    (the ``active`` inputs and all their products), a quadratic ``q`` has an affine gradient, so its
    largest dual norm over the box is attained at a corner (:func:`slope_reach`): the slope that the
    curvature the data show in the mean, not pair by pair, reaches across the box.

    A leaf of a linear system fits curvature to its noise. Each entry of a corner's gradient
    therefore counts only beyond ``t`` of its standard error (noise of the variance a uniform
    ``±w̄`` has): ``t = sqrt(2 ln m)`` for the ``m`` entries over the corners, about the largest of
    ``m`` standard normal noises, and at least :data:`SLOPE_SIGNIFICANCE`. (A bicycle's heading step
    ``v tan(steer)`` at full steer and speed, 500 steps: the leaf's pairs gave 0.017, and one-step
    queries there fell up to 8 % of the noise outside their sets at a vertex of the noise; with the
    surrogate's slope, none. At ``t = 3`` the surrogate missed that curvature; at ``t = 2`` a double
    integrator's sets were 14 % wider.) No corners (``C = 0``) when the leaf holds fewer than
    :data:`QUADRATIC_POINTS` points per coefficient or more than :data:`QUADRATIC_INPUTS` inputs, and
    where the design is degenerate (:data:`QUADRATIC_CONDITION`): data on a curve, such as a heading's
    ``cos θ`` and ``sin θ`` (``cos² + sin² = 1``), leave the quadratic unidentified, and its slope at the
    box's corners, far off the curve, is noise (15 times the pairs' on a world-frame Turtlebot, whose
    layer it froze).

    Args:
        z: ``[s, d]`` the leaf's scaled inputs; ``residual``: ``[s]`` its affine fit's residual.
        active: ``[d]`` the inputs the output is fitted on (positive weight); the others' slopes are 0.
        lo, hi: ``[d]`` the leaf's box. noise_radius: ``w̄`` of the output, a scalar.
    """
    index = active.nonzero().flatten()
    k = len(index)
    pairs = torch.triu_indices(k, k)
    none = z.new_zeros(0, z.shape[1])
    if not 0 < k <= QUADRATIC_INPUTS or len(z) < QUADRATIC_POINTS * (1 + k + pairs.shape[1]):
        return none
    centre, half = (lo[index] + hi[index]) / 2, ((hi[index] - lo[index]) / 2).clamp_min(1e-12)
    u = (z[:, index] - centre) / half  # the box as [-1, 1]^k, for conditioning
    regressors = torch.cat((torch.ones_like(u[:, :1]), u, u[:, pairs[0]] * u[:, pairs[1]]), dim=1)
    left, singular, right = torch.linalg.svd(regressors, full_matrices=False)
    if singular[-1] < QUADRATIC_CONDITION * singular[0]:  # data on a curve (a heading's cos, sin): no quadratic
        return none
    theta = right.T @ ((left.T @ residual) / singular)  # least squares
    corners = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=k)), dtype=u.dtype)  # [2^k, k]
    # the gradient at each corner is linear in theta: d q / d u_i = theta_i + sum over pairs holding i
    gradient_map = u.new_zeros(len(corners), k, len(theta))
    gradient_map[:, torch.arange(k), 1 + torch.arange(k)] = 1.0
    for column, (i, j) in enumerate(pairs.T.tolist()):
        gradient_map[:, i, 1 + k + column] += corners[:, j]
        gradient_map[:, j, 1 + k + column] += corners[:, i]
    covariance = (right.T / singular.square()) @ right * noise_radius ** 2 / 3  # (XᵀX)⁻¹ w̄² / 3
    error = torch.einsum("cip,pq,ciq->ci", gradient_map, covariance, gradient_map).clamp_min(0).sqrt()
    significance = max(math.sqrt(2 * math.log(error.numel())), SLOPE_SIGNIFICANCE)
    slopes = z.new_zeros(len(corners), z.shape[1])
    slopes[:, index] = ((gradient_map @ theta).abs() - significance * error).clamp_min(0) / half  # per unit of z
    return slopes


def slope_reach(slopes: Tensor, weights: Tensor) -> Tensor:
    """A lower bound on one leaf's residual Lipschitz constant in the metric ``weights`` ``[d]``: the largest dual
    norm ``||s / w||`` of its :func:`corner_slopes` ``[C, d]`` (0 without corners); a scalar.

    Examples:
        >>> z = torch.rand(60, 2, dtype=torch.float64)
        >>> one, none = torch.ones(2, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
        >>> slopes = corner_slopes(z, z[:, 0] ** 2, one > 0, 0 * one, one, none)  # d/dz0 of z0² at z0 = 1
        >>> round(float(slope_reach(slopes, one)), 6), round(float(slope_reach(slopes, 0.5 * one)), 6)
        (2.0, 4.0)
    """
    if slopes.shape[0] == 0:
        return slopes.new_zeros(())
    return (slopes / torch.where(weights > 0, weights, 1.0)).norm(dim=-1).amax()


def bend_error(z_low: Tensor, z_high: Tensor, features: Features, points: list[Tensor] | None = None) -> Tensor:
    """How far a smooth bend may stray from the hinges that cut it, in each leaf: ``[M]``.

    A hinge ``c relu(a · z - k)`` changes the model's slope along the unit ``â = a / |a|`` by
    ``J = |c| |a|`` at ``t = k / |a|``, of the sign of ``c`` whichever way ``a`` points. Two parallel
    hinges whose slope changes have one sign cut a bend (a tanh thrust, a quadratic drag) into pieces;
    between their knots, ``s`` apart along ``â``, the true output bends smoothly and strays from a chord
    by up to ``κ s² / 8`` (a parabola of curvature ``κ``), less than the noise where the data cannot see
    it. Each knot's ``κ`` is its ``J`` over its share of the line, the mean of its spacings to the parallel
    knots on either side (the one there is, at an end), and the pair takes the larger: a wide gap beside
    narrow ones gets the curvature the narrow ones show. The leaf error grows by this over the slabs
    between such knots that its box meets. A lone kink, or two of opposite signs (a servo saturating on
    either side of its ramp), is the hard kink it fits. (Without this term, the saturated-thrust point's
    velocity, fitted with 8 hinges on 500 steps, left 90 of 20,000 random one-step queries' true successors
    outside their sets at a vertex of the noise, up to 16 % of the noise beyond;
    :func:`~torchrl_brsl.reach.evaluation.worst_noise_outside`.)

    On an output without noise, whose data show it exactly, dense data bound the stray instead: the leaf's error
    holds at its data points, and between two consecutive points ``g`` apart along ``â`` a bend of curvature
    ``κ`` strays from them by at most ``κ g² / 8``, and a knot between them (where the model kinks by ``J``
    and a smooth output does not) by at most ``J g / 4`` more. The leaf takes the smaller of the two
    bounds, ``g`` the widest gap between its points (the slab's ends included) that the slab's part in the
    leaf meets. The capped quadrotor's position step (noise-free, exactly piecewise linear: ten kinks over the
    servo's substeps) is fitted to 3e-5 m by ten hinges from 500 steps, where ``κ s² / 8`` puts 3.5e-4 m on every
    leaf; random data are seldom dense enough for the gaps to take much off it (2,000 steps: the quadrotor's sets
    5.57 -> 5.53 times their sampled spread, ``point_boxes`` 3.80 -> 3.72).

    Args:
        z_low, z_high: ``[M, d]`` the leaves' boxes along the inputs.
        features: the output's hinges and their coefficients.
        points: each leaf's data ``[S_l, d]`` (those its fit used), or ``None``: the knots' spacing alone (an output
            with noise: a bend below the noise can exceed the curvature its knots show, :func:`_output_cells`).
    """
    directions, knots = features.hinge_directions, features.hinge_knots  # [H, d], [H]
    if directions.shape[0] < 2:
        return z_low.new_zeros(z_low.shape[0])
    coefficients = features.coefficients[:len(knots)]
    unit, length, own, other, gap = parallel_knots(directions, knots)
    left = torch.where(gap < 0, -gap, torch.inf).amin(-1, keepdim=True)  # [H, 1]: the nearest parallel knot below
    right = torch.where(gap > 0, gap, torch.inf).amin(-1, keepdim=True)
    same = coefficients.sign().unsqueeze(0) == coefficients.sign().unsqueeze(1)
    pair = same & ((gap == -left) | (gap == right))  # adjacent: no parallel knot between them
    spacing = torch.where(torch.isinf(left), right, torch.where(torch.isinf(right), left, (left + right) / 2))[:, 0]
    jump = coefficients.abs() * length  # [H]: each knot's slope change along its unit
    curvature = jump / spacing  # [H]: over its share of the line
    kappa = curvature.unsqueeze(1).maximum(curvature.unsqueeze(0))  # [H, H]
    stray = torch.where(pair, kappa * (own - other).square() / 8, 0.0)  # [H, H]
    centre, radius = (z_low + z_high) / 2, (z_high - z_low) / 2
    t, reach = centre @ unit.T, radius @ unit.abs().T  # [M, H]
    slab_low, slab_high = torch.minimum(own, other), torch.maximum(own, other)  # [H, H]
    meets = (t[..., None] + reach[..., None] >= slab_low) & (t[..., None] - reach[..., None] <= slab_high)
    if points is not None:
        gaps = torch.stack([_widest_gap(leaf @ unit.T, torch.maximum(slab_low, (t_l - r_l)[:, None]),
                                        torch.minimum(slab_high, (t_l + r_l)[:, None]))
                            for leaf, t_l, r_l in zip(points, t, reach)])  # [M, H, H]
        by_data = kappa * gaps.square() / 8 + jump.unsqueeze(1).maximum(jump.unsqueeze(0)) * gaps / 4
        stray = torch.where(pair & torch.isfinite(gaps), torch.minimum(stray, by_data), stray)  # [M, H, H]
    return torch.where(meets, stray, 0.0).amax((-1, -2))


def _widest_gap(projections: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """The widest gap between consecutive ``projections`` ``[S, H]`` (column ``i`` along hinge ``i``'s unit; beyond the
    last one on either side: ``inf``) that meets ``[low, high]`` ``[H, H]`` (row ``i`` along unit ``i``): ``[H, H]``."""
    infinite = projections.new_full((1, projections.shape[1]), torch.inf)
    ends = torch.cat((-infinite, projections.sort(0).values, infinite)).T  # [H, S + 2]
    below, above = ends[:, :-1].unsqueeze(1), ends[:, 1:].unsqueeze(1)  # [H, 1, S + 1]
    meets = (above >= low.unsqueeze(-1)) & (below <= high.unsqueeze(-1))  # [H, H, S + 1]
    return torch.where(meets, above - below, 0.0).amax(-1)


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
    its Lipschitz constants are estimated in the same weighted metric; a dependence the slopes
    miss (friction coupling the axes) shows up as a large constant, which is why
    :func:`fit_cells` tries several floors and keeps the tightest.

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


def _bound_cell(z: Tensor, residual: Tensor, noise_radius: Tensor, weights: Tensor, margin: float,
                floor: Tensor, chunk: int = 256) -> tuple[Tensor, Tensor, Tensor, Tensor, float]:
    """Error interval of one output on one cell, in the weighted metric (module docstring), with the hidden noise
    that makes it tightest.

    Nearby points whose residuals differ by more than twice the declared noise ``w̄`` make the pairwise Lipschitz
    estimate steep: every difference is read as slope. Where a robot's step depends on something its state does not
    hold (a wheel's slip, a contact's state), that scatter is noise the declaration misses. Every ``w̄ + h`` with its
    own ``L(h)`` is as consistent with the leaf's pairs; taken as a disturbance of its own at every step (added to the
    half-width), ``h`` gives the bound ``e(h) = envelope(w̄ + h) + h + L(h) δ``. The candidates are quantiles
    (:data:`HIDDEN_QUANTILES`) of the nearest-neighbour pairs' excess ``(|r_i - r_j| / 2 - w̄)_+``, and ``h = 0``; one
    is kept where it lowers ``e`` and does not raise ``L``, so that its bound is no wider at any distance beyond
    ``δ`` (the wheeled Turtlebot's heading step, 2,000 offline steps: the leaves' median ``L`` 0.10 -> 0.06, their
    error 0.012 -> 0.009). Points the metric cannot tell apart whose residuals differ beyond ``w̄`` still get no
    bound: the metric leaves out an input the output depends on, which is not noise.

    Returns:
        ``(half-width, centre, lipschitz, δ, h)``: ``g(z) ∈ centre ± (half-width + lipschitz (D - δ)_+)`` at distance
        ``D`` from the data, the half-width holding the hidden noise ``h`` (a float, 0 where none is kept).
    """
    weighted = z * weights  # [s, d]
    nearest, neighbour = _nearest(weighted)
    delta = nearest.max()
    best, kept = _bound_at_noise(weighted, residual, noise_radius, margin, floor, delta, chunk), 0.0
    if len(weighted) < 2 or not bool(torch.isfinite(best[2])):  # no pair; or the metric drops an input it needs
        return (*best, delta, kept)
    excess = ((residual - residual[neighbour]).abs() / 2 - noise_radius).clamp_min(0)
    for hidden in torch.quantile(excess, excess.new_tensor(HIDDEN_QUANTILES)).unique().tolist():
        if hidden > 0:
            half, centre, lipschitz = _bound_at_noise(weighted, residual, noise_radius + hidden, margin, floor, delta,
                                                      chunk)
            if bool(half + hidden < best[0]) and bool(lipschitz <= best[2]):
                best, kept = (half + hidden, centre, lipschitz), hidden
    return (*best, delta, kept)


HIDDEN_QUANTILES = (0.5, 0.75, 0.9)
"""The quantiles of the nearest-neighbour pairs' excess over the declared noise that :func:`_bound_cell` tries as a
leaf's hidden noise. Not the largest excess: a pair that straddles a kink differs by slope, not by noise (with 1
tried too, the capped quadrotor's model from 500 offline steps, torch seed 2, let 4 of 4,389 sampled states out of
its sets; without it none, nor in seeds 0 and 1)."""


def _bound_at_noise(weighted: Tensor, residual: Tensor, noise_radius: Tensor, margin: float, floor: Tensor,
                    delta: Tensor, chunk: int) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_bound_cell`'s ``(half-width, centre, lipschitz)`` for the noise radius ``noise_radius``, on the weighted
    inputs ``[s, d]``."""
    diameter = (weighted.amax(0) - weighted.amin(0)).norm().clamp_min(1e-12)
    blocks = torch.split(torch.arange(len(weighted)), chunk)
    slope = residual.new_zeros(())
    for rows in blocks:  # pairwise, in row blocks of [c, s]
        distance = torch.cdist(weighted[rows], weighted)
        gap = ((residual[rows].unsqueeze(-1) - residual).abs() - 2 * noise_radius).clamp_min(0)
        steep = torch.where(distance > 0, gap / distance.clamp_min(1e-300), torch.where(gap > 0, torch.inf, 0.0))
        slope = torch.maximum(slope, steep.amax())
    spread = torch.maximum(2 * noise_radius, residual.amax() - residual.amin())
    lipschitz = torch.maximum(torch.maximum(slope * margin, spread / diameter), floor)
    if not bool(torch.isfinite(lipschitz)):  # points the metric cannot tell apart differ beyond the noise
        return residual.new_tensor(torch.inf), residual.new_zeros(()), lipschitz
    upper, lower = residual.new_tensor(-torch.inf), residual.new_tensor(torch.inf)
    for rows in blocks:  # max_j min_i (r_i + L d_ij), min_j max_i (r_i - L d_ij)
        reach = lipschitz * torch.cdist(weighted[rows], weighted)
        upper = torch.maximum(upper, (residual + reach).amin(-1).amax())
        lower = torch.minimum(lower, (residual - reach).amax(-1).amin())
    upper = upper + noise_radius + lipschitz * delta
    lower = lower - noise_radius - lipschitz * delta
    return (upper - lower) / 2, (upper + lower) / 2, lipschitz


def _nearest(points: Tensor) -> tuple[Tensor, Tensor]:
    """Every point's distance to its nearest other point and that point's index: ``([s], [s])``."""
    array = points.detach().cpu().numpy()
    dist, index = cKDTree(array).query(array, k=2)  # a lone point: inf, and index s
    return (torch.as_tensor(np.asarray(dist)[:, 1], dtype=points.dtype),
            torch.as_tensor(np.minimum(np.asarray(index)[:, 1], len(array) - 1), dtype=torch.long))


def leaf_gaps(low: Tensor, high: Tensor, phi: Tensor, phi_radius: Tensor) -> tuple[Tensor, Tensor]:
    """How far a query box misses each leaf, and its centre: ``(box [..., n, M], centre [..., n, M])``,
    ``<= 0`` where it meets (holds) the leaf.

    Args:
        low, high: ``[n, f, M]`` the leaves' boxes, direction by direction (``cells.low.mT``; contiguous, a
            compiled step's reduction over the directions runs 4-5x faster than over the boxes' last dim).
        phi, phi_radius: ``[..., f]`` the box's centre and exact radius along the split directions.
    """
    phi, radius = phi[..., None, :, None], phi_radius[..., None, :, None]  # [..., 1, f, 1]
    # float comparisons: much faster than bool ones here
    box = torch.maximum(low - phi - radius, phi - radius - high).amax(-2)
    centre = torch.maximum(low - phi, phi - high).amax(-2)
    return box, centre


def leaf_bounds(cells: Cells, z_center: Tensor, z_radius: Tensor, phi_radius: Tensor, feature_low: Tensor,
                feature_high: Tensor, distance: Tensor, phi: Tensor | None = None,
                gaps: tuple[Tensor, Tensor] | None = None,
                slopes_by_input: Tensor | None = None, terms: dict | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Per output, one leaf's affine model and an error bound valid over a whole query set.

    The leaves tile the data's region, so every ``z`` of the query set lies in one of the
    leaves its interval hull meets; there ``h(z) ∈ ℓ_l(z) ± (e_l + L_l (D_l - δ_l)_+)``, with
    ``D_l`` the farthest the query's points lie from leaf ``l``'s data. The model ``ℓ_a`` of the
    leaf containing the query's centre is used, with the error ``max_l (e_l + L_l (D_l - δ_l)_+
    + max_z |ℓ_l(z) - ℓ_a(z)|)`` over the met leaves ``l`` (the last term over the query's
    ``z``-box; 0 for ``l = a``).

    Args:
        cells: leaves of ``n`` outputs, boxes in the split directions.
        z_center, z_radius: ``[..., d]`` the query's ``z``-box (scaled units).
        phi_radius: ``[..., f]`` its exact radius along each split direction (around
            ``directions @ z_center``).
        feature_low, feature_high: ``[..., n, H + Q]`` the range of each output's hinge and
            product features over the query set.
        distance: ``[..., n, M]`` ``D_l`` in each output's weighted metric (:func:`leaf_distance`).
        phi: ``[..., f]`` ``directions @ z_center`` when already at hand.
        gaps: :func:`leaf_gaps` when already at hand.
        slopes_by_input: ``[n, d + H + Q, M]`` ``cells.slopes.mT``, contiguous (a compiled step's sums over the
            inputs then run across the leaves, without a horizontal sum per leaf: the Turtlebot's body-frame plan
            loop ran 1.1-1.3x faster at batches 1-4).
        terms: a dict that receives, per output, the three parts of the error ``[..., n]`` of the leaf that sets it:
            ``"leaf"`` (``e_l``), ``"far"`` (``L_l (D_l - δ_l)_+``) and ``"between"`` (the gap to the used
            model).

    Returns:
        ``(index [..., n], errors [..., n], covered [...])``: the leaf whose model is used, the
        error half-width, and whether the query lies inside the data's region.
    """
    n, n_leaves, width = cells.slopes.shape
    phi = z_center @ cells.directions.T if phi is None else phi
    gap_out, centre_out = leaf_gaps(cells.low.mT, cells.high.mT, phi, phi_radius) if gaps is None else gaps
    index = torch.where(centre_out <= 0, cells.score, torch.inf).argmin(-1)  # [..., n]
    flat = index + torch.arange(n, device=index.device) * n_leaves
    # every leaf's model at the query's centre, the features at the middle of their range
    batch = feature_low.shape[:-1]
    center = torch.cat((z_center.unsqueeze(-2).expand(*batch, -1), (feature_low + feature_high) / 2), -1)
    half = torch.cat((z_radius.unsqueeze(-2).expand(*batch, -1), (feature_high - feature_low) / 2), -1)
    by_input = cells.slopes.mT if slopes_by_input is None else slopes_by_input  # [n, d + H + Q, M]
    prediction = small_matmul(center.unsqueeze(-2), by_input).squeeze(-2) + cells.intercepts  # [..., n, M]
    chosen = prediction.gather(-1, index.unsqueeze(-1))
    slope_gap = by_input - cells.slopes.reshape(n * n_leaves, width)[flat].unsqueeze(-1)  # [..., n, d + H + Q, M]
    model_gap = (prediction - chosen).abs() + (slope_gap.abs() * half.unsqueeze(-1)).sum(-2)  # fused when compiled
    far = cells.lipschitz * (distance - cells.delta).clamp_min(0)
    bound = cells.errors + far + model_gap
    errors = torch.where(gap_out <= 0, bound, -torch.inf).amax(-1)
    missed = ~torch.isfinite(errors)  # outside every leaf (not covered): all of them, finite
    errors = torch.where(missed, bound.amax(-1), errors)
    if terms is not None:
        setting = torch.where(missed.unsqueeze(-1) | (gap_out <= 0), bound, -torch.inf).argmax(-1, keepdim=True)
        parts = {"leaf": cells.errors.expand_as(bound), "far": far, "between": model_gap}
        terms.update({name: part.gather(-1, setting).squeeze(-1) for name, part in parts.items()})
    covered = ~missed.any(-1) & (centre_out.amin(-1) <= 0).all(-1) & (_root_excess(cells, phi, phi_radius) <= 0)
    return index, errors, covered


def point_bounds(cells: Cells, points: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Each output's prediction and error half-width at single inputs (noise not included).

    Args:
        cells: fitted on ``points`` ``[N, d]`` (scaled).
        z: ``[B, d]`` scaled query inputs.

    Returns:
        ``(prediction [B, n], errors [B, n], covered [B])``.
    """
    n = cells.errors.shape[0]
    features = torch.stack([feature_values(z, Features(cells.hinge_directions[k], cells.hinge_knots[k],
                                                       cells.product_directions[k], cells.product_knots[k], None))
                            for k in range(n)], dim=1)  # [B, n, H + Q]
    distance = leaf_distance(cells, points, z)
    index, errors, covered = leaf_bounds(cells, z, torch.zeros_like(z), z.new_zeros(z.shape[0], len(cells.directions)),
                                         features, features, distance)
    outputs = torch.arange(n, device=z.device)
    row = torch.cat((z.unsqueeze(1).expand(-1, n, -1), features), dim=-1)
    prediction = (row * cells.slopes[outputs, index]).sum(-1) + cells.intercepts[outputs, index]
    return prediction, errors, covered


def held_out_factors(cells: Cells, inputs: Tensor, targets: Tensor, noise_radius: Tensor, n_actions: int, folds: int,
                     generator: torch.Generator | None = None, **kwargs) -> tuple[Tensor, int]:
    """How much each leaf's error bound must grow to hold the held-out transitions: ``([n, M] >= 1, outside)``.

    The data are split into ``folds`` parts; cells fitted (:func:`fit_cells`, ``kwargs``) on all
    but one part bound the held-out part's targets at its inputs. Where a held-out target falls
    outside ``prediction ± (error + w̄)``, the data near it were too sparse for the Lipschitz
    constants they gave, and the leaf of ``cells`` (fitted on all the data) that holds its input
    gets the ratio of its distance beyond the noise to that error bound. ``outside`` counts the
    held-out transitions outside their bounds. A cross-validation of the bound's constants
    (Milanese & Novara 2004 validate a set-membership model's constants on data; here on data the
    fit did not see).
    """
    order = torch.randperm(inputs.shape[0], generator=generator)
    factors = torch.ones_like(cells.errors)
    outside = 0
    for fold in range(folds):
        test = order[fold::folds]
        train = torch.ones(inputs.shape[0], dtype=torch.bool)
        train[test] = False
        held = fit_cells(inputs[train], targets[train], noise_radius, n_actions, **kwargs)
        prediction, errors, covered = point_bounds(held, inputs[train], inputs[test])
        beyond = ((targets[test] - prediction).abs() - noise_radius) * covered.unsqueeze(-1)  # [B, n]
        outside += int((beyond > errors).any(-1).sum())
        ratio = (beyond / errors.clamp_min(1e-300)).clamp_min(1.0)  # [B, n]
        phi = inputs[test] @ cells.directions.T
        inside = ((phi[:, None, None] >= cells.low) & (phi[:, None, None] <= cells.high)).all(-1)  # [B, n, M]
        factors = torch.maximum(factors, torch.where(inside, ratio.unsqueeze(-1), 1.0).amax(0))
    return factors, outside


class LeafLayout(NamedTuple):
    """Each output's weighted data grouped by leaf, ``S`` slots per leaf (:func:`leaf_layout`).

    Attributes:
        points: ``[n, d, M S]`` the points, leaf after leaf (padding: zeros), transposed for a product.
        norms: ``[n, 1, M S]`` their squared norms (padding: ``inf``, never a nearest point).
        leaves: ``[n, M, d, S]`` the points again, one block per leaf (padding: ``inf``).
        representatives: ``[n, d, M]`` one point of each leaf, the nearest to its mean (empty leaf: ``inf``), dims
            first (a compiled step's distances to them then sum across the leaves).
    """

    points: Tensor
    norms: Tensor
    leaves: Tensor
    representatives: Tensor


NEAR_LEAVES = 8
"""Leaves per output whose distance a compiled step of the local model searches (those its set meets
most deeply, :func:`leaf_distance`'s ``near``); the others get the distance to their representative
point, an upper bound. A random ``diffdrive_nav`` plan's sets meet 1.6 of 32 leaves on average, 99 % of
them at most 5, and with 8 the sets of 64 such plans equal those of the search over every leaf; the wheeled
Turtlebot's braking plans meet up to 24 (``docs/local_model.md``), and their sets are up to 2.5 % wider."""


def leaf_layout(cells: Cells, weighted_points: Tensor) -> LeafLayout:
    """The :class:`LeafLayout` of ``weighted_points`` ``[n, N, d]`` (``points * weights`` per output).

    Built once per model, it turns :func:`leaf_distance` into one batched product and a min over
    each leaf's slots, or a search of a few leaves' blocks, instead of a distance to every point and
    a scatter by leaf (5-7x faster on 2,000 points; the leaves of a tree hold similar counts, so
    ``M S`` stays close to ``N``).
    """
    n, n_leaves = cells.errors.shape
    n_points, d = weighted_points.shape[-2:]
    members = cells.members
    counts = torch.zeros(n, n_leaves, dtype=torch.long, device=members.device).scatter_add_(
        1, members, torch.ones_like(members))
    slots = max(int(counts.max()), 1)
    order = torch.argsort(members * n_points + torch.arange(n_points, device=members.device), dim=1)
    leaf = members.gather(1, order)  # each output's points, leaf by leaf
    rank = torch.arange(n_points, device=members.device) - (counts.cumsum(1) - counts).gather(1, leaf)
    slot = (leaf * slots + rank).unsqueeze(-1)  # [n, N, 1]
    sorted_points = weighted_points.gather(1, order.unsqueeze(-1).expand(-1, -1, d))
    leaves = weighted_points.new_full((n, n_leaves * slots, d), torch.inf).scatter_(
        1, slot.expand(-1, -1, d), sorted_points)
    filled = torch.isfinite(leaves[..., :1])  # [n, M S, 1]
    norms = torch.where(filled, leaves.square().sum(-1, keepdim=True), torch.inf)
    leaves = leaves.view(n, n_leaves, slots, d)
    mean = torch.where(filled.view(n, n_leaves, slots, 1), leaves, 0.0).sum(-2) / counts.clamp_min(1).unsqueeze(-1)
    nearest = (leaves - mean.unsqueeze(-2)).square().sum(-1).argmin(-1)  # [n, M] (empty leaf: slot 0, inf)
    representatives = leaves.gather(2, nearest[..., None, None].expand(-1, -1, 1, d)).squeeze(2)
    points = torch.where(filled, leaves.view(n, -1, d), 0.0)
    return LeafLayout(points.transpose(1, 2).contiguous(), norms.transpose(1, 2).contiguous(),
                      leaves.transpose(-1, -2).contiguous(), representatives.mT.contiguous())


def leaf_distance(cells: Cells, points: Tensor | None, z_center: Tensor, z_radius: Tensor | None = None,
                  weighted_points: Tensor | None = None, layout: LeafLayout | None = None,
                  near: Tensor | None = None) -> Tensor:
    """``D_l``: how far a query box lies at most from each leaf's data, ``[..., n, M]``.

    The distance of the centre ``z_center`` ``[..., d]`` to the leaf's nearest data point plus
    the box's radius ``z_radius`` ``[..., d]`` (both in each output's weighted metric): by the
    triangle inequality every ``z`` of the box is at most that far from the leaf's data. A leaf
    without data (padding) gets 0.

    Args:
        points: ``[N, d]`` the scaled data that ``cells.members`` refers to (unused with ``layout``).
        weighted_points: ``[n, N, d]`` ``points * weights`` per output, when already at hand.
        layout: the data grouped by leaf (:func:`leaf_layout`), for repeated queries.
        near: ``[..., n, K]`` with ``layout``: the leaves whose nearest point is searched; every other
            leaf gets the distance to its representative point, an upper bound. ``None``: every leaf's,
            through one batched product (faster in eager mode, where the search's blocks are copied;
            compiled, the search reads them in place and is faster for large batches).
    """
    n, n_leaves = cells.errors.shape
    query = (z_center[..., None, :] * cells.weights).reshape(-1, n, z_center.shape[-1]).transpose(0, 1)  # [n, B, d]
    if layout is None:
        weighted = points * cells.weights[:, None, :] if weighted_points is None else weighted_points
        dist = torch.cdist(query, weighted)  # [n, B, N]
        leaf = cells.members.unsqueeze(1).expand_as(dist)
        nearest = dist.new_zeros(n, dist.shape[1], n_leaves).scatter_reduce_(-1, leaf, dist, "amin", include_self=False)
    else:
        nearest = _grouped_distance(layout, query, near).sqrt()
        nearest = torch.where(torch.isinf(nearest), 0.0, nearest)
    nearest = nearest.transpose(0, 1).reshape(*z_center.shape[:-1], n, n_leaves)
    if z_radius is None:
        return nearest
    return nearest + (z_radius[..., None, :] * cells.weights).norm(dim=-1).unsqueeze(-1)


def _grouped_distance(layout: LeafLayout, query: Tensor, near: Tensor | None) -> Tensor:
    """Squared distances ``[n, B, M]`` of ``query`` ``[n, B, d]`` to each leaf's nearest point (or an upper bound)."""
    n, _, n_leaves = layout.representatives.shape
    if near is None:  # |q - p|² = |p|² - 2 q.p + |q|², the nearest of each leaf's slots
        squared = torch.baddbmm(layout.norms, query, layout.points, alpha=-2).add_(query.square().sum(-1, keepdim=True))
        return squared.view(n, query.shape[1], n_leaves, layout.norms.shape[-1] // n_leaves).amin(-1).clamp_min_(0)
    bound = (query.unsqueeze(-1) - layout.representatives.unsqueeze(1)).square().sum(-2)  # [n, B, M]
    near = near.reshape(-1, n, near.shape[-1]).transpose(0, 1)  # [n, B, K]
    blocks = layout.leaves[torch.arange(n, device=near.device)[:, None, None], near]  # [n, B, K, d, S]
    return bound.scatter(-1, near, (blocks - query[:, :, None, :, None]).square().sum(-2).amin(-1))


def _root_excess(cells: Cells, phi: Tensor, radius: Tensor) -> Tensor:
    """How far the query box reaches beyond the leaves' hull (the data's region): ``[...]``."""
    low, high = cells.low.amin(-2), cells.high.amax(-2)  # [n, f]
    return torch.maximum(low - (phi - radius).unsqueeze(-2), (phi + radius).unsqueeze(-2) - high).amax((-1, -2))
