"""Obstacle zonotopes inflated by the robot footprint: they contain every touching robot position."""
import math

import pytest
import torch

from torchrl_brsl.sets import (Obstacles, Zonotope, inflate_box, inflate_disc, inflate_polygon, obstacle_batch,
                               regular_polygon_generators)

GEN = torch.Generator().manual_seed(0)


def _rand(*shape):
    return torch.rand(*shape, generator=GEN, dtype=torch.float64)


def _box_distance(points, center, half, yaw):
    """Euclidean distance of planar ``points`` [N, 2] to a rotated box."""
    cos, sin = math.cos(yaw), math.sin(yaw)
    rotation = torch.tensor([[cos, -sin], [sin, cos]], dtype=torch.float64)
    local = (points - center) @ rotation  # coordinates along the box axes
    outside = (local.abs() - half).clamp_min(0)
    return outside.norm(dim=-1)


def _polygon_distance(points, vertices):
    """Distance of ``points`` [N, 2] to a convex polygon (counter-clockwise ``vertices``)."""
    a, b = vertices, vertices.roll(-1, 0)
    ab = b - a
    ap = points.unsqueeze(1) - a
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
    edge = (ap - t.unsqueeze(-1) * ab).norm(dim=-1).amin(-1)
    inside = ((ab[:, 0] * ap[..., 1] - ab[:, 1] * ap[..., 0]) >= 0).all(-1)
    return torch.where(inside, torch.zeros_like(edge), edge)


@pytest.mark.parametrize("yaw", [0.0, 0.4, -1.2, math.pi / 2])
def test_rotated_box_contains_every_position_within_the_footprint(yaw):
    center, half, rho = torch.tensor([1.0, -0.5], dtype=torch.float64), torch.tensor([0.6, 0.2]), 0.25
    zonotope = inflate_box(center, half, rho, yaw=yaw)
    points = center + (_rand(20_000, 2) * 2 - 1) * 1.2
    distance = _box_distance(points, center, half.double(), yaw)
    touching = distance <= rho
    assert int(touching.sum()) > 1000
    assert zonotope.contains(points[touching]).all()
    # and not much more: a point well beyond the octagon's corners is outside
    far = distance > rho / math.cos(math.pi / 8) + 1e-9
    assert not zonotope.contains(points[far]).any()


def test_box_in_3d_has_a_z_generator_of_height_plus_radius():
    zonotope = inflate_box(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.5, 0.3, 0.4]), 0.1, yaw=0.7)
    assert zonotope.generators.shape == (3, 7)
    low, high = zonotope.interval()
    assert torch.allclose(high[2] - low[2], torch.tensor(2 * (0.4 + 0.1), dtype=torch.float64))
    assert zonotope.contains(torch.tensor([0.0, 0.0, 1.49], dtype=torch.float64))
    assert not zonotope.contains(torch.tensor([0.0, 0.0, 1.51], dtype=torch.float64))


def test_disc_and_cylinder_contain_the_inflated_disc():
    center, radius, rho = torch.tensor([0.3, 0.2]), 0.4, 0.15
    zonotope = inflate_disc(center, radius, rho)
    assert zonotope.generators.shape == (2, 6)
    angles = _rand(2000) * 2 * math.pi
    rim = center.double() + (radius + rho) * torch.stack((angles.cos(), angles.sin()), -1)
    assert zonotope.contains(rim).all()
    assert not zonotope.contains(center.double() + (radius + rho) / math.cos(math.pi / 12) * 1.001
                                 * torch.stack((angles.cos(), angles.sin()), -1)).any()
    cylinder = inflate_disc(torch.tensor([0.0, 0.0, 0.5]), radius, rho, half_height=0.5)
    assert cylinder.generators.shape == (3, 7)
    assert cylinder.contains(torch.tensor([0.0, radius + rho - 1e-6, 1.15 - 1e-6], dtype=torch.float64))


def test_polygon_contains_every_position_within_the_footprint():
    vertices = torch.tensor([[0.0, 0.0], [1.0, -0.2], [1.4, 0.6], [0.5, 1.1], [-0.2, 0.7]], dtype=torch.float64)
    rho = 0.2
    zonotope = inflate_polygon(vertices[torch.randperm(5, generator=GEN)], rho)  # any vertex order
    points = (_rand(20_000, 2) * 2.4 - 0.6)
    touching = _polygon_distance(points, vertices) <= rho
    assert int(touching.sum()) > 1000
    assert zonotope.contains(points[touching]).all()


def test_polygon_of_a_rotated_rectangle_is_exact():
    box = inflate_box(torch.tensor([0.5, 0.5]), torch.tensor([0.4, 0.1]), 0.0, yaw=0.3)
    signs = torch.tensor([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=torch.float64)
    corners = box.center + signs @ box.generators[:, :2].T
    polygon = inflate_polygon(corners, 0.0)
    assert torch.allclose(polygon.center, box.center)
    assert polygon.contains(box.center + 0.999 * (corners - box.center)).all()
    side_mids = box.center + 1.001 * torch.stack((box.generators[:, 0], -box.generators[:, 0], box.generators[:, 1]))
    assert not polygon.contains(side_mids).any()  # just beyond the middle of three sides
    assert not polygon.contains(box.center + 1.001 * (corners - box.center)).any()


def test_regular_polygon_contains_its_inscribed_disc():
    generators = regular_polygon_generators(4, 1.0)
    octagon = Zonotope(torch.zeros(2, dtype=torch.float64), generators)
    angles = torch.linspace(0, 2 * math.pi, 100, dtype=torch.float64)
    assert octagon.contains(torch.stack((angles.cos(), angles.sin()), -1)).all()
    with pytest.raises(ValueError, match="n"):
        regular_polygon_generators(1, 1.0)


def test_obstacle_batch_pads_slots_and_generators():
    obstacles = obstacle_batch([inflate_box([0.0, 0.0], [0.2, 0.2], 0.1),
                                Zonotope(torch.ones(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))],
                               capacity=4)
    assert obstacles["center"].shape == (4, 2) and obstacles["generators"].shape == (4, 2, 6)
    assert obstacles["mask"].tolist() == [True, True, False, False]
    assert torch.equal(obstacles["generators"][1, :, :2], torch.eye(2, dtype=torch.float64))
    assert not obstacles["generators"][1, :, 2:].any() and not obstacles["center"][2:].any()
    empty = obstacle_batch([], capacity=0)
    assert empty["center"].shape == (0, 2) and empty["mask"].shape == (0,)


def test_a_repeated_batch_is_the_batch_copy_after_copy():
    center, generators = torch.randn(3, 4, 2, generator=GEN), torch.randn(3, 4, 2, 5, generator=GEN)
    mask = torch.rand(3, 4, generator=GEN) > 0.5
    matrix, offset = torch.randn(3, 4, 1, 5, generator=GEN), torch.randn(3, 4, 1, generator=GEN)
    for extra in ((), (matrix, offset)):
        obstacles = Obstacles(center, generators, mask, *extra)
        repeated, expected = obstacles.repeat(2), obstacles.expand(2, 3).reshape(6)
        assert repeated.batch_size == (6,)
        for got, want in zip(vars(repeated).values(), vars(expected).values()):
            assert (got is None and want is None) or torch.equal(got, want)


def test_bad_arguments_are_clear_errors():
    with pytest.raises(ValueError, match="half_size"):
        inflate_box([0.0, 0.0], [0.1, 0.1, 0.1], 0.1)
    with pytest.raises(ValueError, match="robot_radius"):
        inflate_box([0.0, 0.0], [0.1, 0.1], -0.1)
    with pytest.raises(ValueError, match="half_height"):
        inflate_disc([0.0, 0.0, 0.0], 0.1, 0.1)
    with pytest.raises(ValueError, match="vertices"):
        inflate_polygon(torch.zeros(3, 3), 0.1)
    with pytest.raises(ValueError, match="capacity"):
        obstacle_batch([inflate_disc([0.0, 0.0], 0.1, 0.1)] * 3, capacity=2)
    with pytest.raises(ValueError, match="dimension"):
        obstacle_batch([inflate_disc([0.0, 0.0], 0.1, 0.1), inflate_box([0.0, 0.0, 0.0], [0.1] * 3, 0.1)])
