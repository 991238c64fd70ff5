"""Obstacle zonotopes against MuJoCo's own geometry, and the lidar."""
import numpy as np
import pytest

import envs
from envs._obstacles import (
    PARKING_POS,
    Obstacle,
    ObstacleSlots,
    dodecagon_generators,
    obstacle_zonotope,
    octagon_generators,
)
from envs_support import robot_obstacle_distance, zonotope_contains


@pytest.mark.parametrize("name", envs.TASKS)
def test_zonotopes_contain_every_touching_robot_position(name):
    """Sample robot-centre positions around each obstacle; wherever MuJoCo reports the
    robot geom touching the obstacle geom (signed distance <= 0) the position must lie
    in that obstacle's zonotope; and positions clearly away from it must lie outside."""
    env = envs.make(name, seed=0)
    td = env.reset()
    layout = env.layout
    centers = td["obstacles", "center"].double().numpy()
    generators = td["obstacles", "generators"].double().numpy()
    slots = env.task._slots
    rho = env.task.robot_radius
    rng = np.random.RandomState(0)
    touching_total = 0
    for i, obstacle in enumerate(layout.obstacles):
        c, g = centers[i], generators[i]
        np.testing.assert_allclose(c, obstacle_zonotope(obstacle, rho, len(c))[0], atol=1e-5)
        half = np.abs(g).sum(axis=1)
        if len(c) == 3:  # sample near the slab/obstacle, not the whole 20 m floor
            half = np.minimum(half, obstacle.xy_radius + 2 * rho)
        points = c + rng.uniform(-1.2, 1.2, (400, len(c))) * half
        distance = np.array([robot_obstacle_distance(env, p, slots.geom_ids[i]) for p in points])
        inside = zonotope_contains(c, g, points, tol=1e-4)
        touching = distance <= 0
        touching_total += touching.sum()
        assert inside[touching].all(), f"obstacle {i}: touching positions outside its zonotope"
        # largest excess of the polygon/prism over the rounded Minkowski sum:
        # octagon corners 0.08 rho, 12-gon corners 0.035 (R + rho), prism edges 0.47 rho
        slack = (0.5 if len(c) == 3 else 0.09) * rho + 0.04 * (obstacle.xy_radius + rho)
        assert not inside[distance > slack].any(), f"obstacle {i}: zonotope is too loose"
    assert touching_total > 100


@pytest.mark.parametrize("inradius", [0.05, 0.3, 1.7])
def test_regular_polygon_generators_circumscribe_the_disc(inradius):
    from envs import zonotope_polygon

    for generators, n_sides in ((octagon_generators(inradius), 8), (dodecagon_generators(inradius), 12)):
        vertices = zonotope_polygon(np.zeros(2), generators)
        assert len(vertices) == n_sides
        np.testing.assert_allclose(np.linalg.norm(vertices, axis=1), inradius / np.cos(np.pi / n_sides))
        edge_midpoints = (vertices + np.roll(vertices, -1, axis=0)) / 2
        np.testing.assert_allclose(np.linalg.norm(edge_midpoints, axis=1), inradius)


def test_box_zonotope_3d_is_box_plus_octagon_prism():
    box = Obstacle("box", np.array([1.0, 2.0, 3.0]), np.array([0.5, 0.2, 0.4]), yaw=0.0)
    center, generators = obstacle_zonotope(box, robot_radius=0.1, dim=3)
    np.testing.assert_allclose(center, [1.0, 2.0, 3.0])
    assert generators.shape == (3, 7)
    np.testing.assert_allclose(np.abs(generators).sum(axis=1), [0.5 + 0.1, 0.2 + 0.1, 0.4 + 0.1])


def test_diffdrive_lidar_matches_the_walls():
    """Rays cannot see further than the arena walls and most rays end on a wall."""
    env = envs.make("diffdrive_nav", seed=3)
    td = env.reset()
    heading = float(np.arctan2(td["state"][3], td["state"][2]))
    ranges = td["observation"][:18].double().numpy() * 3.5
    angles = heading + np.linspace(-np.pi / 2, np.pi / 2, 18)
    with np.errstate(divide="ignore"):
        to_wall = np.minimum(np.abs(2.5 / np.cos(angles)), np.abs(2.5 / np.sin(angles)))
    expected = np.minimum(to_wall, 3.5)
    assert (ranges <= expected + 1e-5).all()
    assert np.isclose(ranges, expected, atol=1e-5).sum() >= 3


def test_aerial_lidar_sees_floor_and_ceiling():
    env = envs.make("quadrotor_nav", seed=0)
    td = env.reset()
    ranges = td["observation"][:16].double().numpy() * 10.0
    z = float(td["state"][2])
    assert (ranges[:8] <= z / np.sin(np.deg2rad(25)) + 1e-5).all()
    assert (ranges[8:] <= (6.0 - z) / np.sin(np.deg2rad(25)) + 1e-5).all()
    empty = envs.make("quadrotor_nav", seed=0, empty=True).reset()
    assert (empty["observation"][:16] == 1.0).all()


def test_point_boxes_layouts_surround_a_clear_start():
    """4-6 axis-aligned boxes inside the arena, all around the start; the robot
    centre at the start is at least 0.25 m outside every inflated obstacle."""
    from envs.point_boxes import ARENA, N_BOXES

    env = envs.make("point_boxes", seed=0)
    counts, angles = set(), []
    for _ in range(40):
        td = env.reset()
        layout = env.layout
        boxes = layout.obstacles[4:]
        counts.add(len(boxes))
        assert int(td["obstacles", "mask"].sum()) == len(layout.obstacles) == 4 + len(boxes)
        assert not td["obstacles", "mask"][len(layout.obstacles) :].any()
        np.testing.assert_array_equal(layout.start, [0.0, 0.0])
        for box in boxes:
            assert box.kind == "box" and box.yaw == 0.0
            assert (np.abs(box.pos[:2]) + box.half_size[:2] < ARENA).all()
            gap = np.linalg.norm(np.maximum(np.abs(box.pos[:2] - layout.start) - box.half_size[:2], 0.0))
            disc_gap = np.linalg.norm(box.pos[:2] - layout.start) - box.xy_radius
            assert 0.35 - 1e-9 <= disc_gap <= gap and disc_gap <= 0.65 + 1e-9
            angles.append(np.arctan2(box.pos[1], box.pos[0]))
        # the start, grown by 0.2 m, misses every inflated obstacle (the octagons reach
        # at most 0.1 / cos(22.5°) < 0.11 m beyond a box)
        circle = np.linspace(0, 2 * np.pi, 64)
        disc = layout.start + np.concatenate([[[0.0, 0.0]], 0.2 * np.stack([np.cos(circle), np.sin(circle)], 1)])
        for c, g, real in zip(layout.obstacle_center, layout.obstacle_generators, layout.obstacle_mask):
            assert not real or not zonotope_contains(c, g, disc).any()
        # unused slots wait out of reach
        parked = env.task._slots.mocap_ids[len(layout.obstacles) :]
        np.testing.assert_array_equal(env.physics.data.mocap_pos[parked], np.tile(PARKING_POS, (len(parked), 1)))
    assert counts == set(range(N_BOXES[0], N_BOXES[1] + 1))
    # boxes come from every direction
    assert np.histogram(angles, bins=8, range=(-np.pi, np.pi))[0].min() > 0


def test_obstacle_slots_park_unused_slots_and_reject_too_many():
    env = envs.make("point_circle", seed=0)
    env.reset()
    slots = ObstacleSlots(env.physics, ["box"] * 4)
    wall = Obstacle("box", np.array([2.0, 0.0, 0.1]), np.array([0.1, 0.2, 0.2]))
    with env.physics.reset_context():
        slots.apply(env.physics, [wall])
    expected = [wall.pos, PARKING_POS, PARKING_POS, PARKING_POS]
    np.testing.assert_array_equal(env.physics.data.mocap_pos[slots.mocap_ids], expected)
    with pytest.raises(ValueError, match="at most 4"):
        slots.apply(env.physics, [wall] * 5)
