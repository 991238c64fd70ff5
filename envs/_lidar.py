"""Lidar by MuJoCo ray casting (``mujoco.mj_multiRay``) against obstacle geoms only."""
from __future__ import annotations

import mujoco
import numpy as np

#: MuJoCo geom group that holds obstacle geoms; only these are seen by the lidar.
OBSTACLE_GROUP = 1


def planar_fan(n_rays: int, arc: float) -> np.ndarray:
    """Unit directions ``[n_rays, 3]`` evenly spaced over ``arc`` (rad) centred on +x.

    Examples:
        >>> planar_fan(3, np.pi).round(3).tolist()
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    """
    angles = np.linspace(-arc / 2, arc / 2, n_rays)
    return np.stack([np.cos(angles), np.sin(angles), np.zeros(n_rays)], axis=1)


def rings(n_azimuth: int, elevations: np.ndarray) -> np.ndarray:
    """Unit directions ``[len(elevations) * n_azimuth, 3]``: full-circle rings.

    Examples:
        >>> rings(8, np.deg2rad([-25.0, 25.0])).shape
        (16, 3)
    """
    azimuth = np.arange(n_azimuth) * 2 * np.pi / n_azimuth
    elevation = np.asarray(elevations, dtype=np.float64)[:, None]
    x = np.cos(elevation) * np.cos(azimuth)
    y = np.cos(elevation) * np.sin(azimuth)
    z = np.sin(elevation) * np.ones_like(azimuth)
    return np.stack([x, y, z], axis=-1).reshape(-1, 3)


class Lidar:
    """Range sensor: rays from a point, returning the distance to the nearest obstacle.

    Args:
        directions: ``[n, 3]`` unit ray directions in the sensor frame.
        max_range: ranges beyond this read ``max_range`` (m).
        exclude_body: body id whose geoms the rays ignore (the robot).

    Examples:
        >>> from envs.diffdrive_nav import build_environment
        >>> env = build_environment(seed=0)
        >>> _ = env.reset()
        >>> robot = env.physics.model.name2id("robot", "body")
        >>> lidar = Lidar(planar_fan(18, np.pi), max_range=3.5, exclude_body=robot)
        >>> ranges = lidar.scan(env.physics, origin=np.array([0.0, 0.0, 0.15]), yaw=0.0)
        >>> ranges.shape, bool((ranges <= 3.5).all())
        ((18,), True)
    """

    def __init__(self, directions: np.ndarray, max_range: float, exclude_body: int):
        self.directions = np.ascontiguousarray(directions, dtype=np.float64)
        self.max_range = float(max_range)
        self.exclude_body = int(exclude_body)
        self._n = len(self.directions)
        self._world = np.empty_like(self.directions)
        self._flat_directions = self.directions.reshape(-1)
        self._geomid = np.empty(self._n, dtype=np.int32)
        self._dist = np.empty(self._n, dtype=np.float64)
        self._group = np.zeros(6, dtype=np.uint8)
        self._group[OBSTACLE_GROUP] = 1

    def scan(self, physics, origin: np.ndarray, yaw: float = 0.0) -> np.ndarray:
        """Casts the rays with the sensor frame rotated by ``yaw`` about z.

        Args:
            physics: dm_control physics with up-to-date geom poses.
            origin: ``[3]`` ray origin in world coordinates.
            yaw: sensor heading (rad).

        Returns:
            Ranges ``[n]`` in ``[0, max_range]``.
        """
        if yaw == 0.0:  # world-aligned sensor
            world = self._flat_directions
        else:
            cos, sin = np.cos(yaw), np.sin(yaw)
            d = self.directions
            self._world[:, 0] = cos * d[:, 0] - sin * d[:, 1]
            self._world[:, 1] = sin * d[:, 0] + cos * d[:, 1]
            self._world[:, 2] = d[:, 2]
            world = self._world.reshape(-1)
        mujoco.mj_multiRay(
            physics.model.ptr,
            physics.data.ptr,
            np.asarray(origin, dtype=np.float64),
            world,
            self._group,
            1,
            self.exclude_body,
            self._geomid,
            self._dist,
            None,
            self._n,
            self.max_range,
        )
        return np.where(self._geomid >= 0, np.minimum(self._dist, self.max_range), self.max_range)
