"""Rotor-driven multirotors: ``robot="rotor"`` of ``quadrotor_nav`` and ``hexarotor_wind``.

The kinematic multirotor of :mod:`envs._aerial` is a level body pushed by per-axis velocity servos. The
rotor robot is a MuJoCo free body lifted and steered only by its rotors, flown by an onboard cascaded
velocity controller in Python, as PX4's or AirSim's velocity mode:

* Airframe (:data:`QUADROTOR`, :data:`HEXAROTOR`): ``n`` rotors at the ends of arms of length
  ``0.8 * robot_radius`` (rotor ``i`` at the angle ``(i + 0.5) 2π / n``, 0.03 m above the centre of mass),
  spinning in alternating directions. Each is a ``site`` actuator with ``gear="0 0 1 0 0 ±c"``: thrust
  ``f_i ∈ [0, f_max]`` along the body z axis and the drag torque ``±c f_i`` about it (``c`` = 0.016 m,
  the rotor's torque-to-thrust ratio), ``f_max = THRUST_TO_WEIGHT * m g / n`` (twice the hover share).
  Thrust follows the command at once (no motor lag). Quadrotor: 1 kg, arms 0.24 m, inertia
  ``diag(0.010, 0.010, 0.020)`` kg m^2 (four 75 g motors with propellers at the arm ends and a 0.7 kg hub);
  hexarotor: 2 kg, arms 0.32 m, ``diag(0.042, 0.042, 0.082)`` kg m^2 (six 120 g motors, a 1.28 kg hub).
  Contacts and the footprint stay the collision sphere of :mod:`envs._aerial` centred on the body origin,
  which is the centre of mass.
* Physics at :data:`TIMESTEP` = 5 ms (20 steps per 0.1 s control step); :class:`CascadeController` runs
  before every physics step (200 Hz), as does the hexarotor's wind drag (``xfrc_applied``, on the
  air-relative velocity). The lidar stays world-aligned (as on a gimbal); the heading is held at 0.
* Controller, for the held command ``u`` (the action, ``[-5, 5]^3`` m/s), velocity ``v`` and attitude ``R``:

  1. velocity loop: ``a = VELOCITY_GAIN (u + o - v) + (D / m) v`` per world axis (gains (8, 8, 16) /s),
     clipped to ``±MAX_ACCELERATION`` (8 m/s^2, the kinematic servo's limit). The drag feedforward ``D`` and the
     integral offset ``o`` are the hexarotor's (see :class:`envs.hexarotor_wind.RotorHexarotorWind`); ``o``
     integrates ``INTEGRAL_GAIN (u - v)`` only while hovering: command within :data:`HOLD_COMMAND` of zero and
     velocity error within :data:`INTEGRAL_BAND` on every axis.
  2. thrust and tilt: for an upward or zero demand (``a_z >= 0``) the thrust vector ``m (a + g e_z)`` is exact,
     scaled down along ``a`` to at most :data:`COLLECTIVE_SHARE` (90 %) of the full thrust (the rest is left to
     the attitude); for a downward one (``a_z < 0``) the body z axis is taken along ``(a_x, a_y, g)`` as PX4
     does (:data:`TILT_REFERENCE`), so a small thrust does not swing the body to large tilts (the horizontal
     acceleration is then ``a_xy (g + a_z) / g``). The tilt is at most :data:`MAX_TILT` (60°), and the
     horizontal demand is cut to what the thrust limit leaves once the vertical one is met. Collective thrust
     ``m (g + a_z) / cos(tilt)`` with the current tilt (at most 60° in it), so the vertical demand is met while
     the body turns.
  3. attitude: desired body z as above at heading 0 (yaw hold); rate setpoint ``-ATTITUDE_GAIN e_R``
     ((20, 20, 4) /s; ``e_R = vee(R_dᵀR - RᵀR_d) / 2``, the geometric attitude error), clipped to
     :data:`MAX_RATE` (7, 7, 1.5) rad/s; rate loop: body torque ``J RATE_GAIN (ω_d - ω) + ω × Jω``
     ((60, 60, 20) /s).
  4. mixer: the pseudo-inverse of the rotor allocation; roll and pitch first (scaled into the thrust range),
     then the collective in what is left, then as much yaw as fits; every rotor clipped to ``[0, f_max]``.

* Braking: the zero command stops either robot within 15 control steps from all of 400 sampled reachable
  states (median 8; the kinematic robots: at most 7 and 9 under the same protocol), so the rotor tasks set
  ``n_brk = 16``, ``n_plan = 17``. The slowest are full-speed diagonals: the body must first swing its thrust
  around (up to ~80°), its thrust is limited, and braking a climb leaves little thrust to tilt with.

What the safety layer's model sees is the task's state, unchanged: ``(x, y, z, vx, vy, vz)``, and for
``hexarotor_wind`` also the offset ``o`` (the controller's only memory). The attitude and body rates are hidden
from it, and they matter: to accelerate another way the body must first turn its thrust (up to ~80° at
7 rad/s at most, longer than a 0.1 s control step), so the velocity alone is not a Markov state. Measured
(``python benchmarks/bench_rotor.py``): for the same (state, action), the attitude and rates of 8 other
reachable states with a velocity within 0.25 m/s move the next velocity by 0.79 m/s (quadrotor) and 0.82 m/s
(hexarotor) in the median over 300 pairs, by 1.27 m/s at most for either, against a process-noise width of
0.04 m/s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar

import mujoco
import numpy as np
from dm_control import mujoco as dm_mujoco

from envs._aerial import MAX_ACCELERATION, airframe_visuals, arena_xml
from envs._mjcf import with_actuators
from envs._task import task_environment

TIMESTEP = 0.005
GRAVITY = 9.81
THRUST_TO_WEIGHT = 2.0
COLLECTIVE_SHARE = 0.9
VELOCITY_GAIN = (8.0, 8.0, 16.0)
INTEGRAL_GAIN = 5.0
INTEGRAL_BAND = 0.15
HOLD_COMMAND = 0.05
MAX_TILT = math.radians(60.0)
TILT_REFERENCE = GRAVITY
ATTITUDE_GAIN = (20.0, 20.0, 4.0)
RATE_GAIN = (60.0, 60.0, 20.0)
MAX_RATE = (7.0, 7.0, 1.5)
_ROTOR_HEIGHT = 0.03


@dataclass(frozen=True)
class Airframe:
    """Physical parameters of a rotor-driven multirotor.

    Attributes:
        mass: total mass (kg).
        n_rotors: number of rotors.
        radius: collision sphere radius (m); the arms are ``0.8 * radius`` long.
        inertia: principal moments of inertia about the body axes (kg m^2).
        drag_ratio: rotor drag torque per unit thrust (m).

    Examples:
        >>> QUADROTOR.max_thrust, QUADROTOR.rotor_positions.shape
        (4.905, (4, 2))
    """

    mass: float
    n_rotors: int
    radius: float
    inertia: tuple[float, float, float]
    drag_ratio: float = 0.016

    @property
    def arm(self) -> float:
        """Arm length (m)."""
        return 0.8 * self.radius

    @property
    def rotor_positions(self) -> np.ndarray:
        """Rotor hub positions in the body xy plane ``[n_rotors, 2]`` (m)."""
        angles = (np.arange(self.n_rotors) + 0.5) * 2 * np.pi / self.n_rotors
        return self.arm * np.stack([np.cos(angles), np.sin(angles)], axis=1)

    @property
    def spins(self) -> np.ndarray:
        """Sign ``[n_rotors]`` of each rotor's drag torque about the body z axis (alternating)."""
        return np.where(np.arange(self.n_rotors) % 2 == 0, 1.0, -1.0)

    @property
    def max_thrust(self) -> float:
        """Thrust limit of one rotor (N)."""
        return THRUST_TO_WEIGHT * self.mass * GRAVITY / self.n_rotors

    def allocation(self) -> np.ndarray:
        """``[4, n_rotors]``: rotor thrusts to (collective thrust, body torques x, y, z)."""
        x, y = self.rotor_positions.T
        return np.stack([np.ones(self.n_rotors), y, -x, self.drag_ratio * self.spins])


QUADROTOR = Airframe(mass=1.0, n_rotors=4, radius=0.3, inertia=(0.010, 0.010, 0.020))
HEXAROTOR = Airframe(mass=2.0, n_rotors=6, radius=0.4, inertia=(0.042, 0.042, 0.082))


def rotor_model(name: str, empty: bool, n_pillars: int, n_boxes: int, airframe: Airframe) -> str:
    """MJCF of a rotor-driven multirotor in the arena of :mod:`envs._aerial` (see the module docstring).

    Args:
        name: model name.
        empty: leave out every obstacle body.
        n_pillars: number of random cylinder slots.
        n_boxes: number of random box slots.
        airframe: the robot.

    Returns:
        The XML string, one ``motor`` actuator per rotor (control = thrust in N).
    """
    inertia = " ".join(f"{value:.6g}" for value in airframe.inertia)
    sites = "\n      ".join(f'<site name="rotor{i}" pos="{x:.6g} {y:.6g} {_ROTOR_HEIGHT}" size="0.01"/>'
                            for i, (x, y) in enumerate(airframe.rotor_positions))
    robot = f"""
    <body name="robot" pos="0 0 2">
      <freejoint name="root"/>
      <inertial pos="0 0 0" mass="{airframe.mass}" diaginertia="{inertia}"/>
      <geom name="robot" class="robot" type="sphere" size="{airframe.radius}"/>
      {airframe_visuals(airframe.radius, airframe.n_rotors)}
      {sites}
    </body>"""
    xml = arena_xml(name, TIMESTEP, robot, empty, n_pillars, n_boxes)
    actuators = "\n".join(
        f'    <motor name="rotor{i}" site="rotor{i}" gear="0 0 1 0 0 {airframe.drag_ratio * spin:.6g}"'
        f' ctrllimited="true" ctrlrange="0 {airframe.max_thrust:.6g}"/>'
        for i, spin in enumerate(airframe.spins)
    )
    return with_actuators(xml, actuators)


class OnboardPhysics(dm_mujoco.Physics):
    """A dm_control ``Physics`` whose :meth:`step` calls ``onboard()`` before every physics step.

    ``onboard`` (``None``: a plain ``Physics``) is the robot's onboard computer: it reads the state and
    writes ``ctrl`` and ``xfrc_applied``. The physics steps as dm_control's (``mj_step2`` then ``mj_step1``,
    so the data is in sync with the state after the step).
    """

    onboard: Callable[[], None] | None = None

    def step(self, nstep: int = 1) -> None:
        if self.onboard is None:
            return super().step(nstep)
        model, data = self.model.ptr, self.data.ptr
        with self.check_invalid_state():
            for _ in range(nstep):
                self.onboard()
                mujoco.mj_step2(model, data)
                mujoco.mj_step1(model, data)


class CascadeController:
    """The onboard velocity controller of a rotor-driven multirotor (see the module docstring).

    Scalar Python arithmetic (a few hundred flops per update): numpy's per-call overhead would dominate.

    Args:
        airframe: the robot.
        data: its ``mujoco.MjData`` (free joint first: ``qpos[:7]``, ``qvel[:6]``; one actuator per rotor).
        integral_gain: gain of the integral offset (1/s); 0 leaves the offset at 0.
        drag: the airframe's drag coefficient (kg/s), fed forward on the ground velocity; 0: none.
        dt: time between updates (s).

    Attributes:
        data: the ``mujoco.MjData`` it reads and writes.
        command: the held velocity command ``[3]`` (m/s), a list.
        offset: the integral offset ``[3]`` (m/s), a list.
        saturated: per axis, whether the last update clipped the acceleration demand.
    """

    def __init__(self, airframe: Airframe, data, integral_gain: float = 0.0, drag: float = 0.0,
                 dt: float = TIMESTEP):
        self.data = data
        self._drag = drag / airframe.mass
        self._mass = airframe.mass
        self._inertia = tuple(float(value) for value in airframe.inertia)
        self._max_thrust = airframe.max_thrust
        self._max_collective = COLLECTIVE_SHARE * airframe.n_rotors * airframe.max_thrust / airframe.mass
        self._tan_tilt = math.tan(MAX_TILT)
        self._cos_tilt = math.cos(MAX_TILT)
        self._tilt_reference = TILT_REFERENCE
        self._integral_step = integral_gain * dt
        mixer = np.linalg.pinv(airframe.allocation())  # [n, 4]
        self._mix = [tuple(float(value) for value in column) for column in mixer.T]
        self.reset()

    def reset(self) -> None:
        """Zero command, offset and saturation flags."""
        self.command = [0.0, 0.0, 0.0]
        self.offset = [0.0, 0.0, 0.0]
        self.saturated = [False, False, False]

    def update(self) -> None:
        """Reads the state from ``data`` and writes the rotor thrusts to ``data.ctrl``."""
        data = self.data
        _, _, _, qw, qx, qy, qz = data.qpos.tolist()
        vx, vy, vz, wx, wy, wz = data.qvel.tolist()
        # body-to-world rotation matrix R (columns: body axes in world coordinates)
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)

        # 1. velocity loop with the integral offset and the per-axis acceleration limit
        (kx, ky, kz), limit, offset, command = VELOCITY_GAIN, MAX_ACCELERATION, self.offset, self.command
        drag = self._drag
        demand = [kx * (command[0] + offset[0] - vx) + drag * vx, ky * (command[1] + offset[1] - vy) + drag * vy,
                  kz * (command[2] + offset[2] - vz) + drag * vz]
        saturated = [abs(a) > limit for a in demand]
        ax, ay, az = (max(-limit, min(limit, a)) for a in demand)
        # 2. thrust and tilt limits. For a_z >= 0 the thrust vector m (a + g e_z) is exact, scaled down along a
        # to fit the collective limit; for a_z < 0 the tilt is taken against g (as PX4), so a small
        # vertical thrust does not swing the body to large tilts, and the horizontal gets what the collective
        # limit leaves once the vertical demand is met
        top = self._max_collective
        if az >= 0.0:
            square = ax * ax + ay * ay + az * az
            gz = GRAVITY * az
            scale = (math.sqrt(gz * gz - square * (GRAVITY * GRAVITY - top * top)) - gz) / square if square else 1.0
            if scale < 1.0:
                ax, ay, az = scale * ax, scale * ay, scale * az
                saturated = [True, True, True]
            vertical = reference = GRAVITY + az
            allowed = reference * self._tan_tilt
        else:
            vertical = GRAVITY + az
            reference = max(vertical, self._tilt_reference)
            allowed = reference * min(self._tan_tilt, math.sqrt((top / vertical) ** 2 - 1.0))
        horizontal = math.hypot(ax, ay)
        if horizontal > allowed:
            ax, ay = ax * allowed / horizontal, ay * allowed / horizontal
            saturated = [True, True, saturated[2]]
        self.saturated = saturated
        if self._integral_step and max(abs(command[0]), abs(command[1]), abs(command[2])) <= HOLD_COMMAND:
            errors = (command[0] - vx, command[1] - vy, command[2] - vz)
            if max(abs(errors[0]), abs(errors[1]), abs(errors[2])) <= INTEGRAL_BAND:
                step = self._integral_step
                self.offset = [o if s else o + step * e for o, s, e in zip(offset, saturated, errors)]
        # collective: the vertical demand over the current tilt's cosine (at most that of the tilt limit)
        thrust = self._mass * min(self._max_collective, vertical / max(r22, self._cos_tilt))
        # desired attitude: body z along (a_x, a_y, reference), heading 0 (b1 in the plane of b3 and e_x)
        norm = math.sqrt(ax * ax + ay * ay + reference * reference)
        z0, z1, z2 = ax / norm, ay / norm, reference / norm
        side = math.hypot(z1, z2)
        y1, y2 = z2 / side, -z1 / side  # b2 = normalize(b3 × e_x), its x component is 0
        x0, x1, x2 = y1 * z2 - y2 * z1, y2 * z0, -y1 * z0  # b1 = b2 × b3
        # 3. geometric attitude error e_R = vee(R_dᵀR - RᵀR_d) / 2, rate setpoint, rate loop
        m01 = x0 * r01 + x1 * r11 + x2 * r21
        m02 = x0 * r02 + x1 * r12 + x2 * r22
        m10 = y1 * r10 + y2 * r20
        m12 = y1 * r12 + y2 * r22
        m20 = z0 * r00 + z1 * r10 + z2 * r20
        m21 = z0 * r01 + z1 * r11 + z2 * r21
        error = (0.5 * (m21 - m12), 0.5 * (m02 - m20), 0.5 * (m10 - m01))
        jx, jy, jz = self._inertia
        rates = [max(-r, min(r, -k * e)) for r, k, e in zip(MAX_RATE, ATTITUDE_GAIN, error)]
        kx, ky, kz = RATE_GAIN
        tx = jx * kx * (rates[0] - wx) + (jz - jy) * wy * wz
        ty = jy * ky * (rates[1] - wy) + (jx - jz) * wz * wx
        tz = jz * kz * (rates[2] - wz) + (jy - jx) * wx * wy
        # 4. mixer: roll and pitch first, then the collective in what is left, then as much yaw as fits
        total, mx, my, mz = self._mix
        top = self._max_thrust
        tilt = [a * tx + b * ty for a, b in zip(mx, my)]
        spread = max(tilt) - min(tilt)
        if spread > top:
            tilt = [t * top / spread for t in tilt]
        collective = min(top - max(tilt), max(-min(tilt), thrust * total[0]))
        base = [collective + t for t in tilt]
        share = 1.0
        for b, c in zip(base, mz):
            yaw = c * tz
            if yaw > 0.0:
                share = min(share, (top - b) / yaw)
            elif yaw < 0.0:
                share = min(share, -b / yaw)
        share = max(0.0, share) * tz
        data.ctrl[:] = [min(top, max(0.0, b + share * c)) for b, c in zip(base, mz)]


class RotorTask:
    """Mixin turning an :class:`envs._aerial.AerialTask` into its rotor-driven robot (``robot="rotor"``).

    Put it before the task class: ``class RotorQuadrotorNav(RotorTask, QuadrotorNav)``. The action becomes the
    :class:`CascadeController`'s command, held for the control step; spaces, state, noise and layouts stay the
    task's.
    """

    airframe: ClassVar[Airframe]
    integral_gain: ClassVar[float] = 0.0
    drag_feedforward: ClassVar[float] = 0.0
    physics_class = OnboardPhysics

    @classmethod
    def model(cls, empty: bool) -> str:
        """The MJCF model of the rotor robot in the task's arena (see :func:`rotor_model`)."""
        return rotor_model(cls.name, empty, cls.n_pillars, cls.n_boxes, cls.airframe)

    def _bind(self, physics) -> None:
        super()._bind(physics)
        self._controller = CascadeController(self.airframe, physics.data.ptr, self.integral_gain,
                                             self.drag_feedforward)
        physics.onboard = self._onboard

    def rebind(self, physics) -> None:
        """The onboard controller flies ``physics`` (a copy's), its memory (command, offset) kept."""
        self._controller.data = physics.data.ptr
        physics.onboard = self._onboard

    def _onboard(self) -> None:
        self._controller.update()

    def _reset_robot(self, physics, rng) -> None:
        self._controller.reset()
        super()._reset_robot(physics, rng)

    def _apply_action(self, action, physics) -> None:
        self._controller.command = action.tolist()


def aerial_environment(tasks: dict, robot: str, max_acceleration: float | None, **options):
    """The environment of an aerial task's ``robot``, one of ``tasks`` (``{"kinematic": cls, "rotor": cls}``).

    ``max_acceleration`` caps the kinematic robot's servos; the rotor robot's velocity loop has its own
    limit (:data:`~envs._aerial.MAX_ACCELERATION`), so any other value is an error for it.
    """
    if robot not in tasks:
        raise ValueError(f"unknown robot {robot!r} for {tasks['kinematic'].name}; choose one of {tuple(tasks)}")
    task = tasks[robot]
    if robot == "kinematic":
        return task_environment(task, task.model, max_acceleration=max_acceleration, **options)
    if max_acceleration != MAX_ACCELERATION:
        raise ValueError("max_acceleration applies to robot='kinematic' only; the rotor robot's velocity loop "
                         f"asks for {MAX_ACCELERATION} m/s^2 per axis at most")
    return task_environment(task, task.model, **options)
