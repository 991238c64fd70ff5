"""Top-down plots, zonotope polygons and RGB rendering."""
import itertools

import numpy as np
import pytest
import torch

import envs
from envs import zonotope_polygon



def _rendering_available() -> bool:
    try:
        envs.make("point_circle", seed=0).render(8, 8)
    except envs.RenderingUnavailable:
        return False
    return True


needs_gl = pytest.mark.skipif(not _rendering_available(), reason="no OpenGL backend (MUJOCO_GL=egl/osmesa)")


def test_zonotope_polygon_matches_the_support_function_and_area():
    rng = np.random.RandomState(0)
    for q in (1, 2, 3, 6):
        center, generators = rng.randn(2), rng.randn(2, q)
        vertices = zonotope_polygon(torch.as_tensor(center), torch.as_tensor(generators))
        assert vertices.shape == (2 * q, 2) if q > 1 else vertices.shape == (2, 2)
        directions = rng.randn(50, 2)
        support = directions @ center + np.abs(directions @ generators).sum(axis=1)
        np.testing.assert_allclose((vertices @ directions.T).max(axis=0), support, rtol=1e-10, atol=1e-10)
        x, y = vertices.T
        area = 0.5 * (x @ np.roll(y, -1) - y @ np.roll(x, -1))
        expected = 4 * sum(abs(np.linalg.det(generators[:, [i, j]])) for i, j in itertools.combinations(range(q), 2))
        np.testing.assert_allclose(area, expected, rtol=1e-10, atol=1e-12)  # positive: counter-clockwise


def test_zonotope_polygon_projects_3d_and_drops_zero_generators():
    generators = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 3.0, 0.0]])
    vertices = zonotope_polygon(np.array([1.0, 1.0, 5.0]), generators)
    np.testing.assert_allclose(sorted(map(tuple, vertices)), [(0, -1), (0, 3), (2, -1), (2, 3)])
    np.testing.assert_allclose(zonotope_polygon(np.ones(2), np.zeros((2, 3))), [[1.0, 1.0]])


@pytest.mark.parametrize("name", envs.TASKS)
def test_plot_topdown_writes_a_figure(name, tmp_path):
    env = envs.make(name, seed=0)
    td = env.rollout(10)  # may end early on a collision (random actions)
    steps = len(td)
    info = envs.safety_info(name)
    sets = (td["next", "state"][:, : info.obstacle_dim], 0.05 * torch.randn(steps, info.obstacle_dim, 4))
    ax = envs.plot_topdown(td, path=tmp_path / "rollout.png", sets=sets, layout=env.layout)
    as_mapping = {"center": sets[0], "generators": sets[1]}
    ax_layout = envs.plot_topdown(env.layout, path=tmp_path / "layout.png", sets=as_mapping)
    for path in (tmp_path / "rollout.png", tmp_path / "layout.png"):
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 5000
    # obstacles (minus floor/ceiling), goals and sets are drawn as patches; the path as a line
    n_obstacles = int(td[0]["obstacles", "mask"].sum()) - (2 if info.obstacle_dim == 3 else 0)
    assert len(ax.patches) >= 2 * n_obstacles + steps + len(env.layout.goals)
    assert len(ax.lines[-1].get_xdata()) == steps + 1  # the states + the final next state
    assert len(ax_layout.patches) >= 2 * n_obstacles + steps


@needs_gl
@pytest.mark.parametrize("name", envs.TASKS)
def test_render_rgb(name):
    env = envs.make(name, seed=0)
    env.reset()
    for camera in ("overview", "follow"):
        frame = env.render(48, 64, camera=camera)
        assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
        assert frame.std() > 5  # not a blank image


@needs_gl
def test_from_pixels():
    size = {"height": 32, "width": 40}
    env = envs.make("diffdrive_nav", seed=0, from_pixels=True, pixels_only=False, render_kwargs=size)
    td = env.rollout(2)
    assert td["next", "pixels"].shape == (2, 32, 40, 3)
    assert td["next", "pixels"].dtype == torch.uint8
    assert td["next", "state"].shape == (2, 6)


def test_render_rejects_unknown_camera():
    with pytest.raises(ValueError):
        envs.make("point_circle", seed=0).render(8, 8, camera="nope")
