"""What a collision check returns: values, clearances and a per-element status."""
from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

from torch import Tensor


class CollisionStatus(IntEnum):
    """Why a collision value could (not) be certified, one code per checked pair.

    Every code other than ``OK`` comes with ``value = 0`` and ``clearance = 0``: the pair is
    treated as colliding.
    """

    OK = 0
    """The value was computed and verified."""
    NONFINITE = 1
    """A centre, generator or constraint entry of either set is NaN or infinite."""
    EMPTY_SET = 2
    """A constrained zonotope is empty: its own constraints need ``||z||_inf > 1``."""
    INFEASIBLE = 3
    """A constrained zonotope's own equality constraints ``A z = b`` have no solution at all."""
    SOLVER_FAILED = 4
    """The solver raised, or returned a point that fails the feasibility check."""


class CollisionResult(NamedTuple):
    """Everything a collision check knows about each (set, obstacle) pair.

    All fields share the broadcast batch shape of the two set batches.

    Attributes:
        value: ``v*`` of the intersection program; the sets intersect iff ``v* <= 1``.
            ``0`` where ``ok`` is ``False``.
        clearance: signed clearance in the units of the state space (negative when
            intersecting, positive when disjoint), or ``None`` if it was not requested.
            ``0`` where ``ok`` is ``False``.
        ok: bool, ``True`` where ``reason == CollisionStatus.OK``.
        reason: ``torch.int8`` codes of :class:`CollisionStatus`.
    """

    value: Tensor
    clearance: Tensor | None
    ok: Tensor
    reason: Tensor

    def reason_names(self) -> list[str]:
        """The :class:`CollisionStatus` names of ``reason``, flattened in row-major order."""
        return [CollisionStatus(int(code)).name for code in self.reason.reshape(-1).tolist()]


__all__ = ["CollisionResult", "CollisionStatus"]
