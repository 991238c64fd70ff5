"""What the safety layer needs to know about a task, independent of its dynamics."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from torch import Tensor


@dataclass(frozen=True, eq=False)
class SafetyInfo:
    """Machine-readable description of a task for the safety layer.

    Nothing here describes the dynamics: the layer learns those from offline data.
    All tensors are ``float32`` on the CPU. Instances compare by identity.

    Attributes:
        name: the task name accepted by :func:`envs.make`.
        state_dim: ``n``, size of the ``"state"`` entry.
        action_dim: ``m``, size of the ``"action"`` entry.
        position_dims: indices of the position inside ``"state"``; these dims are
            also the translation-invariant ones (paper Assumption 1). Always the
            leading dims, of length ``obstacle_dim``.
        velocity_dims: indices of ``"state"`` that are ~0 once the robot is stopped.
        heading_dims: the heading of a yaw-invariant planar robot inside ``"state"``: one
            angle dim or ``(cos θ, sin θ)``; empty for robots without one. Reachability can
            then be fitted in the body frame (``BodyFrame(position_dims, heading_dims)``).
        obstacle_dim: ``d``, dimension of the obstacle zonotopes (2 or 3).
        action_low: lower action bounds, shape ``[m]``.
        action_high: upper action bounds, shape ``[m]``.
        noise_center: centre of the process-noise zonotope W, shape ``[n]``.
        noise_generators: generators of W, shape ``[n, q]``. Every step the task
            adds ``noise_center + noise_generators @ z`` with ``z ~ U[-1, 1]^q``
            to the state, inside the simulation.
        n_brk: number of steps within which :attr:`braking_policy` stops the
            robot from any state of the data region.
        n_plan: plan length the paper uses with this ``n_brk``.
        braking_action: the action that keeps a stopped robot stopped, shape ``[m]``.
        braking_policy: ``state [..., n] -> action [..., m]``; a torch function
            that stops the robot within ``n_brk`` steps.
        stop_tolerance: the robot counts as stopped when
            ``state[..., velocity_dims].abs().max(-1) <= stop_tolerance``.
        dt: control period in seconds.

    Examples:
        >>> import envs, torch
        >>> info = envs.safety_info("point_circle")
        >>> info.state_dim, info.position_dims, info.n_brk
        (4, (0, 1), 23)
        >>> info.braking_policy(torch.tensor([0.0, 0.0, 0.05, -2.0]))
        tensor([-0.5000,  1.0000])
    """

    name: str
    state_dim: int
    action_dim: int
    position_dims: tuple[int, ...]
    velocity_dims: tuple[int, ...]
    obstacle_dim: int
    action_low: Tensor
    action_high: Tensor
    noise_center: Tensor
    noise_generators: Tensor
    n_brk: int
    n_plan: int
    braking_action: Tensor
    braking_policy: Callable[[Tensor], Tensor]
    stop_tolerance: float
    dt: float
    heading_dims: tuple[int, ...] = ()

    def is_stopped(self, state: Tensor) -> Tensor:
        """Whether each state counts as stopped.

        Args:
            state: ``[..., n]``.

        Returns:
            Bool tensor ``[...]``.

        Examples:
            >>> import envs, torch
            >>> info = envs.safety_info("quadrotor_nav")
            >>> info.is_stopped(torch.zeros(2, info.state_dim))
            tensor([True, True])
        """
        velocity = state[..., list(self.velocity_dims)]
        return velocity.abs().amax(-1) <= self.stop_tolerance
