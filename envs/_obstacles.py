"""True obstacle geometry, its footprint-inflated zonotopes, and random placement.

Every obstacle is a vertical prism: a box rotated about z, or an upright cylinder.
In MuJoCo each obstacle lives in its own mocap body (one geom per body), so a layout
is applied by moving mocap bodies and resizing geoms, without recompiling the model.

Inflation by the robot footprint (robot collision geometry = a sphere of radius
``rho`` whose centre is the robot position) is the library's public
:mod:`torchrl_brsl.sets.obstacles` (``inflate_box``, ``inflate_disc``); see there for the
construction. Ground robots use the planar cross-section (obstacles are taller than the
robot sphere), aerial robots the 3-D prisms.

Both containments are exact supersets, so every robot-centre position at which the
robot geometry touches the obstacle geometry lies in the obstacle's zonotope.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from torchrl_brsl.sets.obstacles import inflate_box, inflate_disc, regular_polygon_generators

#: number of generators of one obstacle zonotope, by position dimension
GENERATORS_PER_OBSTACLE = {2: 6, 3: 7}
#: where unused obstacle slots wait, far below every arena
PARKING_POS = np.array([0.0, 0.0, -50.0])


@dataclass(frozen=True)
class Obstacle:
    """One vertical-prism obstacle in world coordinates.

    Attributes:
        kind: ``"box"`` or ``"cylinder"``.
        pos: centre ``[3]`` (m).
        half_size: box ``(hx, hy, hz)``; cylinder ``(r, r, hz)`` (m).
        yaw: rotation about z (rad); irrelevant for cylinders.

    Examples:
        >>> Obstacle("box", np.array([1.0, 0.0, 0.2]), np.array([0.2, 0.1, 0.2]), yaw=0.3).xy_radius
        0.223606797749979
    """

    kind: str
    pos: np.ndarray
    half_size: np.ndarray
    yaw: float = 0.0

    @property
    def xy_radius(self) -> float:
        """Radius of the smallest disc around ``pos[:2]`` containing the footprint."""
        if self.kind == "box":
            return float(np.hypot(self.half_size[0], self.half_size[1]))
        return float(self.half_size[0])

    def mujoco_size(self) -> np.ndarray:
        """The geom ``size`` MuJoCo expects, shape ``[3]``."""
        if self.kind == "box":
            return np.asarray(self.half_size, dtype=np.float64)
        return np.array([self.half_size[0], self.half_size[2], 0.0])


@dataclass(frozen=True)
class Layout:
    """Everything that is fixed for one episode, for plotting and tests.

    Attributes:
        obstacles: the true geometry (boundary walls first, then random obstacles).
        obstacle_center: ``[K, d]`` footprint-inflated zonotope centres.
        obstacle_generators: ``[K, d, p]`` their generators.
        obstacle_mask: ``[K]`` which entries are real.
        goals: ``[G, d]`` goal centre(s): one goal, the checkpoints in order, or none.
        goal_radius: radius of each goal region (m).
        start: ``[d]`` start position.
        extent: ``(xmin, xmax, ymin, ymax)`` of the map for top-down plots.
        path_radius: radius of the circle to follow (path-following point task).
    """

    obstacles: tuple[Obstacle, ...]
    obstacle_center: np.ndarray
    obstacle_generators: np.ndarray
    obstacle_mask: np.ndarray
    goals: np.ndarray
    goal_radius: float
    start: np.ndarray
    extent: tuple[float, float, float, float]
    path_radius: float | None = None


def octagon_generators(inradius: float) -> np.ndarray:
    """Generators ``[2, 4]`` of the regular octagon with the given inradius.

    Examples:
        >>> octagon_generators(1.0).shape
        (2, 4)
    """
    return regular_polygon_generators(4, inradius).numpy()


def dodecagon_generators(inradius: float) -> np.ndarray:
    """Generators ``[2, 6]`` of the regular 12-gon with the given inradius.

    Examples:
        >>> dodecagon_generators(1.0).shape
        (2, 6)
    """
    return regular_polygon_generators(6, inradius).numpy()


def obstacle_zonotope(obstacle: Obstacle, robot_radius: float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Zonotope containing every robot-centre position that touches ``obstacle``.

    Args:
        obstacle: the true obstacle.
        robot_radius: ``rho``, radius of the robot's collision sphere.
        dim: 2 (ground robot, x-y) or 3 (aerial robot, x-y-z).

    Returns:
        ``(center [dim], generators [dim, p])`` with ``p = GENERATORS_PER_OBSTACLE[dim]``.

    Examples:
        >>> box = Obstacle("box", np.zeros(3), np.array([1.0, 0.5, 1.0]))
        >>> c, G = obstacle_zonotope(box, 0.1, 2)
        >>> c.shape, G.shape
        ((2,), (2, 6))
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    center = torch.as_tensor(np.asarray(obstacle.pos, dtype=np.float64)[:dim])
    half = torch.as_tensor(np.asarray(obstacle.half_size, dtype=np.float64))
    if obstacle.kind == "box":
        zonotope = inflate_box(center, half[:dim], robot_radius, yaw=obstacle.yaw)
    elif obstacle.kind == "cylinder":
        zonotope = inflate_disc(center, float(half[0]), robot_radius, half_height=float(half[2]) if dim == 3 else None)
    else:
        raise ValueError(f"unknown obstacle kind {obstacle.kind!r}")
    return zonotope.center.numpy().copy(), zonotope.generators.numpy().copy()


def zonotope_batch(
    obstacles: Sequence[Obstacle], robot_radius: float, dim: int, capacity: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Padded batch of inflated obstacle zonotopes.

    Args:
        obstacles: at most ``capacity`` obstacles.
        robot_radius: radius of the robot's collision sphere.
        dim: position dimension ``d``.
        capacity: ``K``.

    Returns:
        ``center [K, d]``, ``generators [K, d, p]``, ``mask [K]``; padded entries
        are all zero with ``mask=False``.

    Examples:
        >>> c, G, m = zonotope_batch([], 0.1, 2, capacity=3)
        >>> c.shape, G.shape, m.tolist()
        ((3, 2), (3, 2, 6), [False, False, False])
    """
    if len(obstacles) > capacity:
        raise ValueError(f"{len(obstacles)} obstacles exceed the capacity {capacity}")
    p = GENERATORS_PER_OBSTACLE[dim]
    center = np.zeros((capacity, dim))
    generators = np.zeros((capacity, dim, p))
    mask = np.zeros(capacity, dtype=bool)
    for i, obstacle in enumerate(obstacles):
        center[i], generators[i] = obstacle_zonotope(obstacle, robot_radius, dim)
        mask[i] = True
    return center, generators, mask


def obstacle_bodies_xml(kinds: Sequence[str], max_half_size: Sequence[Sequence[float]]) -> str:
    """MJCF for obstacle slots: one mocap body per obstacle, one geom per body.

    Each geom is declared at its largest size, so the compiled bounding volumes
    stay conservative when :class:`ObstacleSlots` shrinks it.

    Args:
        kinds: ``"box"`` / ``"cylinder"`` for each slot.
        max_half_size: ``[len(kinds), 3]`` largest half sizes (box ``hx hy hz``,
            cylinder ``r r hz``).

    Returns:
        XML to put inside ``<worldbody>``; geoms use the default class ``obstacle``.
    """
    parts = []
    parking = " ".join(f"{v:.6g}" for v in PARKING_POS)
    for i, (kind, half) in enumerate(zip(kinds, max_half_size)):
        size = Obstacle(kind, np.zeros(3), np.asarray(half, dtype=np.float64)).mujoco_size()
        size_text = " ".join(f"{v:.6g}" for v in (size if kind == "box" else size[:2]))
        parts.append(
            f'<body name="obstacle_{i}" mocap="true" pos="{parking}">'
            f'<geom name="obstacle_{i}" class="obstacle" type="{kind}" size="{size_text}"/></body>'
        )
    return "\n".join(parts)


class ObstacleSlots:
    """Writes a list of :class:`Obstacle` into the mocap obstacle bodies of a model.

    Args:
        physics: the dm_control physics whose model holds the slots.
        kinds: slot kinds, as given to :func:`obstacle_bodies_xml`.

    Examples:
        >>> from envs.point_circle import build_environment
        >>> env = build_environment(seed=0)
        >>> slots = ObstacleSlots(env.physics, ["box"] * 4)
        >>> wall = Obstacle("box", np.array([2.0, 0.0, 0.1]), np.array([0.1, 0.2, 0.2]))
        >>> with env.physics.reset_context():
        ...     slots.apply(env.physics, [wall] * 4)
        >>> env.physics.data.mocap_pos[0].tolist()
        [2.0, 0.0, 0.1]
    """

    def __init__(self, physics, kinds: Sequence[str]):
        model = physics.model
        self.kinds = tuple(kinds)
        self.geom_ids = np.array([model.name2id(f"obstacle_{i}", "geom") for i in range(len(kinds))], dtype=int)
        body_ids = [model.name2id(f"obstacle_{i}", "body") for i in range(len(kinds))]
        self.mocap_ids = np.array([model.body_mocapid[b] for b in body_ids], dtype=int)
        self._max_size = model.geom_size[self.geom_ids].copy()

    def apply(self, physics, obstacles: Sequence[Obstacle]) -> None:
        """Moves and resizes slot ``i`` to ``obstacles[i]``.

        Slots beyond ``len(obstacles)`` are parked at ``PARKING_POS``, out of reach of
        every robot (layouts with a variable number of obstacles). Call inside
        ``physics.reset_context()`` (mocap poses live in the data).
        """
        if len(obstacles) > len(self.kinds):
            raise ValueError(f"expected at most {len(self.kinds)} obstacles, got {len(obstacles)}")
        parked = [Obstacle(kind, PARKING_POS, np.full(3, 0.01)) for kind in self.kinds[len(obstacles) :]]
        obstacles = [*obstacles, *parked]
        model, data = physics.model, physics.data
        for i, obstacle in enumerate(obstacles):
            if obstacle.kind != self.kinds[i]:
                raise ValueError(f"slot {i} holds a {self.kinds[i]}, not a {obstacle.kind}")
            size = obstacle.mujoco_size()
            if np.any(size > self._max_size[i] + 1e-9):
                raise ValueError(f"obstacle {i} is larger than its slot: {size} > {self._max_size[i]}")
            geom = self.geom_ids[i]
            model.geom_size[geom] = size
            half_extent = size if obstacle.kind == "box" else np.array([size[0], size[0], size[1]])
            model.geom_aabb[geom] = np.concatenate([np.zeros(3), half_extent])
            model.geom_rbound[geom] = np.linalg.norm(half_extent if obstacle.kind == "box" else size[:2])
            data.mocap_pos[self.mocap_ids[i]] = obstacle.pos
            data.mocap_quat[self.mocap_ids[i]] = [np.cos(obstacle.yaw / 2), 0.0, 0.0, np.sin(obstacle.yaw / 2)]


@dataclass(frozen=True)
class KeepOut:
    """A segment ``a``–``b`` in the x-y plane that obstacles keep ``clearance`` away from.

    A point is a segment with ``a == b``.
    """

    a: np.ndarray
    b: np.ndarray | None = None
    clearance: float = 0.0

    def distance(self, point: np.ndarray) -> float:
        """Distance of ``point [2]`` to the segment."""
        a = np.asarray(self.a[:2], dtype=np.float64)
        b = a if self.b is None else np.asarray(self.b[:2], dtype=np.float64)
        ab = b - a
        denom = float(ab @ ab)
        t = 0.0 if denom == 0.0 else float(np.clip((point - a) @ ab / denom, 0.0, 1.0))
        return float(np.linalg.norm(point - (a + t * ab)))


def place_obstacles(
    rng: np.random.RandomState,
    draw: Callable[[np.random.RandomState, str], Obstacle],
    kinds: Sequence[str],
    keep_out: Sequence[KeepOut],
    max_tries: int = 2000,
) -> list[Obstacle]:
    """Rejection-samples one obstacle per kind, clear of every keep-out region.

    Args:
        rng: source of randomness.
        draw: ``draw(rng, kind)`` returns a random obstacle of that kind.
        kinds: kinds to place.
        keep_out: regions whose x-y distance to the obstacle footprint must exceed
            their clearance.
        max_tries: attempts per obstacle before giving up.

    Returns:
        The obstacles, in the order of ``kinds``.

    Examples:
        >>> rng = np.random.RandomState(0)
        >>> draw = lambda r, k: Obstacle(k, np.r_[r.uniform(-2, 2, 2), 0.2], np.full(3, 0.2))
        >>> len(place_obstacles(rng, draw, ["box", "cylinder"], [KeepOut(np.zeros(2), clearance=0.5)]))
        2
    """
    placed = []
    for kind in kinds:
        for _ in range(max_tries):
            obstacle = draw(rng, kind)
            centre = np.asarray(obstacle.pos[:2], dtype=np.float64)
            if all(region.distance(centre) >= obstacle.xy_radius + region.clearance for region in keep_out):
                placed.append(obstacle)
                break
        else:
            raise RuntimeError(f"could not place a {kind} clear of the keep-out regions in {max_tries} tries")
    return placed


def boundary_walls(half_extent: float, thickness: float, height: float, z_center: float) -> list[Obstacle]:
    """Four boxes whose inner faces are the lines ``|x| = half_extent``, ``|y| = half_extent``.

    Args:
        half_extent: distance from the origin to each wall's inner face.
        thickness: full wall thickness.
        height: full wall height.
        z_center: z of the wall centres.

    Returns:
        Walls at ``+x, -x, +y, -y``.
    """
    offset = half_extent + thickness / 2
    long = half_extent + thickness
    walls = []
    for axis, sign in ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)):
        pos = np.array([0.0, 0.0, z_center])
        pos[axis] = sign * offset
        half = np.array([long, long, height / 2])
        half[axis] = thickness / 2
        walls.append(Obstacle("box", pos, half))
    return walls
