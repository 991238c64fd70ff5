"""Drawing sets with the Agg backend."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from torchrl_brsl.sets import ConstrainedZonotope, Zonotope, plot_polygons  # noqa: E402


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def _polygons(ax):
    return [p for p in ax.patches if isinstance(p, Polygon)]


def test_zonotope_plot_writes_a_figure(tmp_path, gen, oracle):
    z = oracle.random_zonotope(gen, 3, 4, batch=(2, 3))
    ax = z.plot(dims=(2, 0), facecolor="tab:blue")
    patches = _polygons(ax)
    assert len(patches) == 6
    expected = z.project([2, 0]).vertices().reshape(6, 8, 2).numpy()
    for patch, verts in zip(patches, expected):
        np.testing.assert_allclose(patch.get_xy()[:8], verts, atol=1e-6)
        assert patch.get_facecolor()[:3] == pytest.approx(matplotlib.colors.to_rgb("tab:blue"))
    x0, x1 = ax.get_xlim()
    assert x0 <= expected[..., 0].min() and x1 >= expected[..., 0].max()
    out = tmp_path / "zonotopes.png"
    ax.figure.savefig(out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 1000


def test_constrained_zonotope_plot_on_a_given_axis(tmp_path):
    box = Zonotope.from_interval(-torch.ones(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    tri = box.to_constrained().intersect_halfspace(torch.tensor([1.0, 1.0], dtype=torch.float64),
                                                   torch.tensor(0.0, dtype=torch.float64))
    fig, ax = plt.subplots()
    returned = tri.plot(ax=ax, n_directions=16, alpha=0.7)
    assert returned is ax
    (patch,) = _polygons(ax)
    xy = patch.get_xy()
    assert patch.get_alpha() == pytest.approx(0.7)
    assert (xy.sum(-1) <= 1e-7).all() and (np.abs(xy) <= 1 + 1e-7).all()  # inside the triangle
    corners = {(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0)}
    assert corners <= {tuple(np.round(v, 6)) for v in xy}
    fig.savefig(tmp_path / "tri.png")
    assert (tmp_path / "tri.png").stat().st_size > 1000


def test_plot_polygons_draws_each_array():
    fig, ax = plt.subplots()
    squares = [np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) + k for k in range(3)]
    assert plot_polygons(squares, ax=ax, edgecolor="r") is ax
    patches = _polygons(ax)
    assert len(patches) == 3
    np.testing.assert_allclose(patches[2].get_xy()[:4], squares[2])
    assert patches[0].get_edgecolor()[:3] == pytest.approx((1.0, 0.0, 0.0))
    new_ax = plot_polygons(squares[:1])
    assert new_ax is not ax and len(_polygons(new_ax)) == 1


def test_plot_rejects_bad_dims():
    z = Zonotope(torch.zeros(3), torch.eye(3))
    with pytest.raises(ValueError, match="`dims`"):
        z.plot(dims=(0, 3))
    with pytest.raises(ValueError, match="`dims`"):
        ConstrainedZonotope.from_zonotope(z).plot(dims=(0, 1, 2))
