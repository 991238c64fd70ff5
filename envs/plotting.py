"""Top-down matplotlib view of a layout, a trajectory and reachable sets."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon
from matplotlib.path import Path as MplPath
from tensordict import TensorDictBase

from envs._obstacles import Layout


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64) if hasattr(x, "detach") else np.asarray(x, dtype=np.float64)


def zonotope_polygon(center, generators) -> np.ndarray:
    """Vertices of the x-y projection of a zonotope, counter-clockwise.

    The generators are flipped into the upper half-plane and sorted by angle; the
    boundary walks from the lowest vertex ``c - Σ g_i`` along ``2 g_i`` in that order
    and back along ``-2 g_i``.

    Args:
        center: ``[d]`` (array or tensor), ``d ≥ 2``; only x-y are used.
        generators: ``[d, q]``; all-zero projected generators are ignored.

    Returns:
        ``[2 q', 2]`` vertices (``q'`` non-zero projected generators), or ``[1, 2]``
        for a point.

    Examples:
        >>> zonotope_polygon(np.zeros(2), np.eye(2)).tolist()
        [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]
    """
    c = _numpy(center)[:2]
    g = _numpy(generators)[:2]
    g = g[:, np.linalg.norm(g, axis=0) > 1e-12]
    if g.shape[1] == 0:
        return c[None].copy()
    flip = (g[1] < 0) | ((g[1] == 0) & (g[0] < 0))
    g = np.where(flip, -g, g)
    g = g[:, np.argsort(np.arctan2(g[1], g[0]))]
    steps = np.concatenate([2 * g, -2 * g], axis=1).T
    vertices = c - g.sum(axis=1) + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)[:-1]])
    return vertices


def _obstacle_arrays(source) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(source, Layout):
        return source.obstacle_center, source.obstacle_generators, source.obstacle_mask
    obstacles = source["obstacles"].reshape(-1)[0] if source.batch_dims else source["obstacles"]
    return _numpy(obstacles["center"]), _numpy(obstacles["generators"]), obstacles["mask"].cpu().numpy()


def _map_layers(center: np.ndarray, polygons: list[np.ndarray | None]) -> set[int]:
    """Indices of 3-D obstacles whose footprint holds every other centre (floor, ceiling)."""
    if center.shape[1] != 3:
        return set()
    active = [i for i, p in enumerate(polygons) if p is not None]
    layers = set()
    for i in active:
        others = np.array([center[j, :2] for j in active if j != i])
        if len(others) and MplPath(polygons[i]).contains_points(others).all():
            layers.add(i)
    return layers


def _draw_geometry(ax: Axes, obstacle) -> None:
    x, y = obstacle.pos[:2]
    if obstacle.kind == "cylinder":
        ax.add_patch(Circle((x, y), obstacle.half_size[0], color="0.25", zorder=2))
        return
    hx, hy = obstacle.half_size[:2]
    rotation = np.array([[np.cos(obstacle.yaw), -np.sin(obstacle.yaw)], [np.sin(obstacle.yaw), np.cos(obstacle.yaw)]])
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) @ rotation.T + [x, y]
    ax.add_patch(Polygon(corners, closed=True, color="0.25", zorder=2))


def _trajectory(td: TensorDictBase) -> np.ndarray:
    states = _numpy(td["state"]).reshape(-1, td["state"].shape[-1])
    if ("next", "state") in td.keys(True) and td.batch_dims:
        last = _numpy(td["next", "state"]).reshape(-1, states.shape[-1])[-1:]
        states = np.concatenate([states, last])
    return states[:, :2]


def _sets(sets) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(sets, (Mapping, TensorDictBase)):
        center, generators = sets["center"], sets["generators"]
    else:
        center, generators = sets
    center, generators = _numpy(center), _numpy(generators)
    return center.reshape(-1, center.shape[-1]), generators.reshape(-1, *generators.shape[-2:])


def plot_topdown(
    td_or_layout: TensorDictBase | Layout,
    path: str | Path | None = None,
    sets=None,
    ax: Axes | None = None,
    *,
    layout: Layout | None = None,
) -> Axes:
    """Draws the x-y plane: obstacles, goals, the robot's path and reachable sets.

    Inflated obstacle zonotopes are drawn in light red, true obstacle geometry (when
    a :class:`Layout` is known) in dark grey, goals in green (numbered when there
    are several), the path-following circle dashed, the trajectory in blue and the
    reachable sets as translucent orange polygons. In 3-D the x-y projection is
    drawn; slabs covering the whole map (floor, ceiling) are left out.

    Args:
        td_or_layout: a :class:`Layout` (``env.layout``), or a TensorDict from
            ``reset``/``step``/``rollout`` (batch dims ``[]`` or ``[T]``): its
            ``obstacles`` (first entry) and its ``state`` (and final
            ``("next", "state")``) as the trajectory.
        path: if given, the figure is saved there.
        sets: zonotopes to draw: ``(center [..., d], generators [..., d, q])`` or a
            mapping with ``"center"`` and ``"generators"`` (tensors or arrays);
            only the first two rows (x, y) are used.
        ax: axes to draw on; a new figure is created when ``None``.
        layout: true geometry and goals to add when ``td_or_layout`` is a TensorDict.

    Returns:
        The axes.

    Examples:
        >>> import envs, torch
        >>> env = envs.make("point_circle", seed=0)
        >>> td = env.rollout(20)
        >>> ax = envs.plot_topdown(td, layout=env.layout,
        ...                        sets=(torch.zeros(3, 2), 0.1 * torch.randn(3, 2, 4)))
    """
    if isinstance(td_or_layout, Layout):
        layout, td = td_or_layout, None
    else:
        td = td_or_layout
    if ax is None:
        ax = Figure(figsize=(6, 6)).add_subplot()

    center, generators, mask = _obstacle_arrays(td_or_layout)
    polygons = [zonotope_polygon(center[i], generators[i]) if mask[i] else None for i in range(len(mask))]
    layers = _map_layers(center, polygons)
    for i, polygon in enumerate(polygons):
        if polygon is not None and i not in layers:
            ax.add_patch(Polygon(polygon, closed=True, facecolor=(0.9, 0.4, 0.4, 0.35), edgecolor="tab:red", lw=0.8))

    if layout is not None:
        for i, obstacle in enumerate(layout.obstacles):
            if i not in layers:
                _draw_geometry(ax, obstacle)
        for k, goal in enumerate(layout.goals):
            ax.add_patch(Circle(goal[:2], layout.goal_radius, facecolor=(0.2, 0.7, 0.3, 0.35), edgecolor="tab:green"))
            if len(layout.goals) > 1:
                ax.annotate(str(k), goal[:2], ha="center", va="center", fontsize=8)
        if layout.path_radius is not None:
            ax.add_patch(Circle((0, 0), layout.path_radius, fill=False, ls="--", color="tab:green"))
        ax.plot(*layout.start[:2], marker="s", color="k", ms=5)

    if sets is not None:
        set_centers, set_generators = _sets(sets)
        for c, g in zip(set_centers, set_generators):
            polygon = zonotope_polygon(c, g)
            ax.add_patch(Polygon(polygon, closed=True, facecolor=(1.0, 0.6, 0.1, 0.25), edgecolor="tab:orange", lw=0.6))

    if td is not None:
        xy = _trajectory(td)
        ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=1.2, marker="." if len(xy) < 3 else None)

    if layout is not None:
        ax.set_xlim(layout.extent[:2])
        ax.set_ylim(layout.extent[2:])
    else:
        ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if path is not None:
        ax.figure.savefig(path, dpi=100, bbox_inches="tight")
    return ax
