"""matplotlib drawing of 2-D sets."""
from __future__ import annotations

from typing import Sequence

import numpy as np


def plot_polygons(polygons: Sequence[np.ndarray], ax=None, **kwargs):
    """Draw each ``[k, 2]`` vertex array as a filled polygon and rescale the axis.

    Args:
        polygons: vertex arrays in drawing order.
        ax: a matplotlib axis; a new figure when ``None``.
        **kwargs: ``matplotlib.patches.Polygon`` options; defaults to a translucent fill.

    Returns:
        The axis.
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    if ax is None:
        _, ax = plt.subplots()
    style = {"alpha": 0.4, "edgecolor": "k", "linewidth": 0.8} | kwargs
    for verts in polygons:
        ax.add_patch(Polygon(np.asarray(verts), closed=True, **style))
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    return ax
