"""Small nonlinear black-box systems with bounded noise, for demos, tests and benchmarks.

Each system exposes ``step(x, u, generator=None)`` (batched, noisy), its noise zonotope,
its data region, and :meth:`offline_data` in the layout :meth:`DataDrivenReach.fit` takes.
The reachability code never reads their equations: it only sees sampled transitions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchrl_brsl.reach.body_frame import BodyFrame
from torchrl_brsl.sets import Zonotope


@dataclass
class BlackBoxSystem:
    """Base class: subclasses define ``dynamics`` and the data region.

    Attributes:
        dt: time step [s].
        state_low, state_high: ``[n]`` box of the data region.
        action_low, action_high: ``[m]`` action bounds.
        noise_half_width: ``[n]`` half-widths of the (box) noise zonotope.
        translation_invariant_dims: position dims.
        body_frame: the position and heading dims of a yaw-invariant robot (``None``: not one).
    """

    dt: float
    state_low: Tensor
    state_high: Tensor
    action_low: Tensor
    action_high: Tensor
    noise_half_width: Tensor
    translation_invariant_dims: tuple[int, ...]
    body_frame: BodyFrame | None = None

    @property
    def noise(self) -> Zonotope:
        """The process-noise zonotope ``W``."""
        return Zonotope(torch.zeros_like(self.noise_half_width), torch.diag(self.noise_half_width))

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        raise NotImplementedError

    def step(self, x: Tensor, u: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``f(x, u) + w`` with ``w`` uniform in ``W``: ``[..., n]``."""
        nominal = self.dynamics(x, u)
        w = (torch.rand(nominal.shape, generator=generator, dtype=nominal.dtype) * 2 - 1) * self.noise_half_width
        return nominal + w

    def sample_states(self, num: int, generator: torch.Generator | None = None) -> Tensor:
        """Uniform states in the data region: ``[num, n]``."""
        return _uniform(self.state_low, self.state_high, num, generator)

    def sample_actions(self, *shape: int, generator: torch.Generator | None = None) -> Tensor:
        """Uniform admissible actions: ``[*shape, m]``."""
        flat = _uniform(self.action_low, self.action_high, math.prod(shape), generator)
        return flat.reshape(*shape, self.action_low.shape[-1])

    def offline_data(self, num: int = 500, generator: torch.Generator | None = None):
        """``num`` noisy transitions from random states and actions: ``(x_minus, x_plus, u_minus)``."""
        x = self.sample_states(num, generator)
        u = self.sample_actions(num, generator=generator)
        return x, self.step(x, u, generator), u


class DoubleIntegrator(BlackBoxSystem):
    """Planar double integrator with quadratic drag and speed / acceleration saturation.

    State ``(x, y, vx, vy)``, action ``(ax, ay)`` in ``[-1, 1]^2``, ``dt = 0.1``. The data
    region spans speeds up to ``data_speed`` per axis (default ``max_speed``, where the
    saturation is part of the data).
    """

    def __init__(self, drag: float = 0.3, max_speed: float = 2.0, data_speed: float | None = None):
        d = torch.float64
        v = max_speed if data_speed is None else data_speed
        super().__init__(dt=0.1, state_low=torch.tensor([-2.0, -2.0, -v, -v], dtype=d),
                         state_high=torch.tensor([2.0, 2.0, v, v], dtype=d),
                         action_low=-torch.ones(2, dtype=d), action_high=torch.ones(2, dtype=d),
                         noise_half_width=torch.tensor([0.002, 0.002, 0.01, 0.01], dtype=d),
                         translation_invariant_dims=(0, 1))
        self.drag, self.max_speed = drag, max_speed

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        p, v = x[..., :2], x[..., 2:]
        a = u.clamp(-1.0, 1.0) - self.drag * v * v.abs()
        v_next = (v + self.dt * a).clamp(-self.max_speed, self.max_speed)
        return torch.cat((p + self.dt * v_next, v_next), dim=-1)

    def braking(self, x: Tensor) -> Tensor:
        """Decelerate as hard as allowed: ``clip(-v / dt, -1, 1)``."""
        return (-x[..., 2:] / self.dt).clamp(-1.0, 1.0)


class Unicycle(BlackBoxSystem):
    """Unicycle with speed state: ``(x, y, theta, v)``, action ``(acceleration, yaw rate)``.

    ``x+ = x + dt v cos(theta)``, ``y+ = y + dt v sin(theta)``, ``theta+ = theta + dt omega``,
    ``v+ = clip(v + dt a, 0, v_max)``; ``a in [-1, 1]``, ``omega in [-1, 1]``.
    """

    def __init__(self, max_speed: float = 1.0):
        d = torch.float64
        super().__init__(dt=0.1, state_low=torch.tensor([-2.0, -2.0, -1.0, 0.0], dtype=d),
                         state_high=torch.tensor([2.0, 2.0, 1.0, max_speed], dtype=d),
                         action_low=-torch.ones(2, dtype=d), action_high=torch.ones(2, dtype=d),
                         noise_half_width=torch.tensor([0.002, 0.002, 0.005, 0.01], dtype=d),
                         translation_invariant_dims=(0, 1), body_frame=BodyFrame((0, 1), 2))
        self.max_speed = max_speed

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        theta, v = x[..., 2], x[..., 3]
        a, omega = u[..., 0].clamp(-1.0, 1.0), u[..., 1].clamp(-1.0, 1.0)
        return torch.stack((x[..., 0] + self.dt * v * torch.cos(theta), x[..., 1] + self.dt * v * torch.sin(theta),
                            theta + self.dt * omega, (v + self.dt * a).clamp(0.0, self.max_speed)), dim=-1)

    def braking(self, x: Tensor) -> Tensor:
        """Full deceleration, no turning."""
        return torch.stack(((-x[..., 3] / self.dt).clamp(-1.0, 1.0), torch.zeros_like(x[..., 3])), dim=-1)


class KinematicBicycle(BlackBoxSystem):
    """Kinematic bicycle with quadratic drag, heading over the full circle.

    State ``(x, y, theta, v)``, action ``(acceleration, steering angle)`` in
    ``[-1, 1] x [-0.5, 0.5]``, ``dt = 0.1``, wheelbase ``0.3``:
    ``theta+ = theta + dt v tan(steer) / wheelbase``,
    ``v+ = clip(v + dt (a - drag v |v|), 0, max_speed)``, positions advance with the old
    heading and speed. The data region spans ``theta in [-pi, pi]``.
    """

    def __init__(self, drag: float = 0.5, max_speed: float = 1.5, wheelbase: float = 0.3):
        d = torch.float64
        super().__init__(dt=0.1, state_low=torch.tensor([-2.0, -2.0, -math.pi, 0.0], dtype=d),
                         state_high=torch.tensor([2.0, 2.0, math.pi, max_speed], dtype=d),
                         action_low=torch.tensor([-1.0, -0.5], dtype=d), action_high=torch.tensor([1.0, 0.5], dtype=d),
                         noise_half_width=torch.tensor([0.002, 0.002, 0.004, 0.01], dtype=d),
                         translation_invariant_dims=(0, 1), body_frame=BodyFrame((0, 1), 2))
        self.drag, self.max_speed, self.wheelbase = drag, max_speed, wheelbase

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        theta, v = x[..., 2], x[..., 3]
        a, steer = u[..., 0].clamp(-1.0, 1.0), u[..., 1].clamp(-0.5, 0.5)
        return torch.stack((x[..., 0] + self.dt * v * torch.cos(theta), x[..., 1] + self.dt * v * torch.sin(theta),
                            theta + self.dt * v * torch.tan(steer) / self.wheelbase,
                            (v + self.dt * (a - self.drag * v * v.abs())).clamp(0.0, self.max_speed)), dim=-1)

    def braking(self, x: Tensor) -> Tensor:
        """Full deceleration, wheels straight."""
        return torch.stack(((-x[..., 3] / self.dt).clamp(-1.0, 1.0), torch.zeros_like(x[..., 3])), dim=-1)


class SaturatedThrustPoint(BlackBoxSystem):
    """Planar point with tanh-saturated thrust and quadratic drag.

    State ``(x, y, vx, vy)``, action ``(ux, uy)`` in ``[-1, 1]^2``, ``dt = 0.1``:
    ``v+ = v + dt (a_max tanh(gain u) - drag v |v|)``, ``p+ = p + dt v+``.
    """

    def __init__(self, max_thrust: float = 2.0, gain: float = 2.0, drag: float = 0.5, max_speed: float = 2.0):
        d = torch.float64
        super().__init__(dt=0.1, state_low=torch.tensor([-2.0, -2.0, -max_speed, -max_speed], dtype=d),
                         state_high=torch.tensor([2.0, 2.0, max_speed, max_speed], dtype=d),
                         action_low=-torch.ones(2, dtype=d), action_high=torch.ones(2, dtype=d),
                         noise_half_width=torch.tensor([0.002, 0.002, 0.01, 0.01], dtype=d),
                         translation_invariant_dims=(0, 1))
        self.max_thrust, self.gain, self.drag = max_thrust, gain, drag

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        p, v = x[..., :2], x[..., 2:]
        a = self.max_thrust * torch.tanh(self.gain * u.clamp(-1.0, 1.0)) - self.drag * v * v.abs()
        v_next = v + self.dt * a
        return torch.cat((p + self.dt * v_next, v_next), dim=-1)

    def braking(self, x: Tensor) -> Tensor:
        """Thrust against the velocity, as hard as the saturation allows."""
        return (-x[..., 2:]).clamp(-1.0, 1.0)


class CappedVelocityServo(BlackBoxSystem):
    """Planar point whose velocity servo has a hard acceleration cap (a multirotor's velocity mode).

    State ``(x, y, vx, vy)``, action: the commanded velocity ``(ux, uy)`` in ``[-2, 2]^2``,
    ``dt = 0.1``: ``v+ = v + clip(gain dt (u - v), -a_max dt, a_max dt)``, ``p+ = p + dt v+``.
    The servo is linear only on the ramp ``|u - v| < a_max / gain`` and saturates beyond: its
    kinks lie along ``u - v``, and most random commands are saturated.
    """

    def __init__(self, max_acceleration: float = 4.0, gain: float = 8.0, max_speed: float = 2.0):
        d = torch.float64
        super().__init__(dt=0.1, state_low=torch.tensor([-2.0, -2.0, -max_speed, -max_speed], dtype=d),
                         state_high=torch.tensor([2.0, 2.0, max_speed, max_speed], dtype=d),
                         action_low=-max_speed * torch.ones(2, dtype=d), action_high=max_speed * torch.ones(2, dtype=d),
                         noise_half_width=torch.tensor([0.0, 0.0, 0.01, 0.01], dtype=d),
                         translation_invariant_dims=(0, 1))
        self.max_acceleration, self.gain = max_acceleration, gain

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        p, v = x[..., :2], x[..., 2:]
        cap = self.max_acceleration * self.dt
        v_next = v + (self.gain * self.dt * (u - v)).clamp(-cap, cap)
        return torch.cat((p + self.dt * v_next, v_next), dim=-1)

    def braking(self, x: Tensor) -> Tensor:
        """Command zero velocity."""
        return torch.zeros_like(x[..., 2:])


def _uniform(low: Tensor, high: Tensor, num: int, generator: torch.Generator | None) -> Tensor:
    return low + (high - low) * torch.rand(num, low.shape[-1], generator=generator, dtype=low.dtype)
