"""The braking failsafe the safety layer appends to every plan."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


@dataclass
class Failsafe:
    """A braking manoeuvre: bring the robot to a stop, then keep it stopped (paper Assumption 1).

    Args:
        hold_action: ``[m]`` the action ``u_brk`` that keeps a stopped robot stopped (e.g. a
            zero velocity command, zero acceleration).
        n_brk: steps the robot needs to stop from any state of its operating region.
        policy: optional braking policy ``state [..., n] -> action [..., m]`` (e.g. full
            deceleration ``clip(-v / dt)`` for an acceleration-commanded robot). It is
            evaluated on the *nominal* (centre) trajectory to produce open-loop braking
            actions, whose reachable sets the layer then verifies. ``None`` brakes with
            ``hold_action`` (velocity-commanded robots).

    Which one: the constant brake when ``hold_action`` itself stops the robot within ``n_brk``
    steps and keeps it stopped (a zero velocity command on a velocity servo); it is the
    cheapest, every reachable-set centre then being one affine map of state and plan. A
    braking policy for acceleration- or force-commanded robots and for any robot that drifts
    under a constant command (with the constant brake their stop check is rarely met and the
    layer intervenes far more; see "Bring your own robot", ``docs/own_robot.md``). Check either
    on the true system: from the states the robot reaches, ``n_brk`` steps of braking stop it
    and it stays stopped (paper Assumption 1).

    Examples:
        >>> brake = Failsafe(torch.zeros(2), n_brk=6)  # velocity commands: command zero
        >>> brake.actions(torch.zeros(4, 5)).shape
        torch.Size([4, 2])
    """

    hold_action: Tensor
    n_brk: int
    policy: Callable[[Tensor], Tensor] | None = None

    def __post_init__(self):
        if not isinstance(self.hold_action, Tensor) or self.hold_action.ndim != 1:
            raise ValueError("`hold_action` must be a 1-D tensor [m]")
        if int(self.n_brk) < 1:
            raise ValueError(f"`n_brk` must be a positive integer, got {self.n_brk}")
        if self.policy is not None and not callable(self.policy):
            raise ValueError("`policy` must be callable: state [..., n] -> action [..., m]")

    def actions(self, states: Tensor) -> Tensor:
        """Braking actions for ``states`` ``[..., n]``: ``[..., m]``."""
        if self.policy is None:
            return self.hold_action.to(states).expand(*states.shape[:-1], -1)
        return self.policy(states).to(states.dtype)
