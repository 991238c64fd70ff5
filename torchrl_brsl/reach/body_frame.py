"""Yaw invariance: fit a planar robot's step in its body frame and rotate it by the heading set.

A ground robot (or a multirotor at a fixed yaw servo) moves the same way whatever direction
it faces: with ``R(θ)`` the rotation by its heading, its position step is
``p+ - p = R(θ) h(z)`` with ``h`` the body-frame displacement, a function of the body-frame
state (speeds, turn rate) and the action only. A model fitted in the world frame sees
``v cos θ`` and ``v sin θ`` and must cover the whole circle of headings with its leaves;
fitted in the body frame, the same data describe a function of fewer inputs that is nearly
affine (``h ≈ (v dt, 0)`` for a car), so the leaves' errors fall to the noise.

The heading is either an angle (one state dim, whose step ``θ+ - θ`` is then also yaw
invariant and modelled with identity slope) or a unit vector ``q = (cos θ, sin θ)`` (two
dims, with ``q+ = R(θ) h_q(z)``, ``h_q = (cos Δθ, sin Δθ)``). Writing ``M(q) = [[c, -s],
[s, c]]`` (``= R(θ)`` for the unit vector), a step rotates each body output ``h`` by
``M(q)`` with ``q`` and ``h`` both uncertain. Over a zonotope set, with
``q = q0 + δq`` and ``h = h0 + δh`` affine in the set's noise symbols (plus intervals), the
bilinear product is enclosed exactly to first order and soundly to second:

    M(q) h = M(q0) h0 + M(q0) δh + M(h0) δq + M(δq) δh

(``M(q) h = M(h) q``: both are the complex product ``q h``), the last term bounded by the
intervals ``|δq| |δh|`` (as in affine arithmetic; de Figueiredo & Stolfi, "Affine
arithmetic", Numer. Algorithms 2004). For an angle heading,
``q = (cos θ, sin θ)`` is itself enclosed by its first-order form around the set's centre
with the Taylor remainder ``|τ|² / 2`` (``|τ| <=`` the heading's interval radius). The
transformations at fit time are exact identities on the data: the body target is
``M(q_i)^{-1} (p+_i - p_i - c_w)``, so ``p+ = p + M(q) h + c_w + (w - c_w)`` holds for the
true ``h``, and the world-frame noise, rotated into the body frame, has radius at most
``max_v ||v||_2 / |q|`` per body dim, over the vertices ``v`` of the pair's noise zonotope.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

from torchrl_brsl._compiling import small_matmul


@dataclass(frozen=True)
class BodyFrame:
    """Which state dims are the planar position and the heading of a yaw-invariant robot.

    The state's other dims must not depend on the heading (body-frame speeds and turn rates):
    world-frame velocity vectors would have to rotate too, which this frame does not do.

    Args:
        position: the two state dims ``(x, y)`` of the planar position (translation invariant).
        heading: one dim holding the heading angle [rad], or two dims holding
            ``(cos θ, sin θ)``.

    Examples:
        >>> frame = BodyFrame(position=(0, 1), heading=2)          # state (x, y, θ, v)
        >>> frame = BodyFrame(position=(0, 1), heading=(2, 3))     # state (x, y, cos θ, sin θ, v, ω)
        >>> reach = DataDrivenReach.fit(x, xp, u, W, translation_invariant_dims=(0, 1), body_frame=frame)
    """

    position: tuple[int, int]
    heading: int | tuple[int, int]

    def __post_init__(self):
        position = tuple(int(d) for d in self.position)
        heading = (int(self.heading),) if isinstance(self.heading, int) else tuple(int(d) for d in self.heading)
        distinct = len({*position, *heading}) == len(position) + len(heading)
        if len(position) != 2 or len(heading) not in (1, 2) or not distinct:
            raise ValueError(f"`body_frame` needs two distinct position dims and one heading angle dim or two "
                             f"(cos, sin) dims, got position={self.position}, heading={self.heading}")
        object.__setattr__(self, "position", position)
        object.__setattr__(self, "heading", heading[0] if len(heading) == 1 else heading)

    @classmethod
    def detect(cls, x_minus: Tensor, x_plus: Tensor, u_minus: Tensor, translation_invariant_dims: tuple[int, ...],
               max_points: int = 2000) -> BodyFrame | None:
        """The body frame the transitions ``[N, n]``, ``[N, n]``, ``[N, m]`` show, or ``None``.

        A candidate is a pair of the translation-invariant dims and a heading: a dim whose data turn through at
        least :data:`MIN_TURN` rad (an angle), or a pair of dims on the unit circle (``(cos θ, sin θ)``). It is
        taken where the position step rotated into its body frame is predicted from the other inputs (the heading
        left out) at most :data:`BODY_ERROR_SHARE` times as badly as the world-frame step from all of them, and
        the other state dims' steps do not need the heading (at most :data:`HEADING_FREE_RATIO` times worse
        without it): a yaw-invariant robot whose other states are body-frame quantities. Both predictions are
        the mean of the :data:`NEIGHBOURS` nearest transitions (inputs scaled to unit spread; at most
        ``max_points`` transitions, evenly spaced). The best candidate wins. Both tests matter for soundness, not
        only tightness: the body-frame model leaves the heading out of every output's inputs, and an output that
        depends on it would then depend on an input the data-driven bound does not see (as a hidden state does).
        Fewer than :data:`MIN_TRANSITIONS` transitions say nothing: ``None``.

        Examples:
            >>> bicycle = KinematicBicycle()
            >>> BodyFrame.detect(*bicycle.offline_data(500), translation_invariant_dims=(0, 1))
            BodyFrame(position=(0, 1), heading=2)
        """
        fixed = sorted(int(d) for d in translation_invariant_dims)
        if len(fixed) < 2 or x_minus.shape[0] < MIN_TRANSITIONS:
            return None
        rows = torch.linspace(0, x_minus.shape[0] - 1, min(max_points, x_minus.shape[0])).long()
        x, u, step = x_minus[rows], u_minus[rows], (x_plus - x_minus)[rows]
        free = [d for d in range(x.shape[1]) if d not in fixed]
        angles = [(d,) for d in free if float(x[:, d].max() - x[:, d].min()) >= MIN_TURN]
        vectors = [pair for pair in itertools.permutations(free, 2)
                   if float((x[:, list(pair)].square().sum(-1) - 1).abs().max()) <= UNIT_TOLERANCE]
        world = _neighbour_error(torch.cat((x[:, free], u), -1), step)  # [n]: each step from every input
        positions = list(itertools.combinations(fixed, 2))
        best, best_share = None, BODY_ERROR_SHARE
        for heading in angles + vectors:
            rest = [d for d in free if d not in heading]
            q = cls(positions[0], heading[0] if len(heading) == 1 else heading).heading_vectors(x)
            bodies = [_solve(q, step[:, list(position)]) for position in positions]
            errors = _neighbour_error(torch.cat((x[:, rest], u), -1), torch.cat((step[:, rest], *bodies), -1))
            if bool((errors[:len(rest)] > HEADING_FREE_RATIO * world[rest]).any()):
                continue
            for k, position in enumerate(positions):
                body = errors[len(rest) + 2 * k:len(rest) + 2 * k + 2]
                share = float(body.mean() / world[list(position)].mean().clamp_min(1e-300))
                if share <= best_share:
                    best, best_share = cls(position, heading[0] if len(heading) == 1 else heading), share
        return best

    @property
    def heading_dims(self) -> tuple[int, ...]:
        """The heading's state dims (one angle or ``(cos, sin)``)."""
        return (self.heading,) if isinstance(self.heading, int) else tuple(self.heading)

    @property
    def angle(self) -> bool:
        """Whether the heading is an angle (else a ``(cos, sin)`` vector)."""
        return isinstance(self.heading, int)

    @property
    def rotated_pairs(self) -> tuple[tuple[int, int], ...]:
        """The output pairs fitted in the body frame: the position, and the heading vector if any."""
        return (self.position,) if self.angle else (self.position, tuple(self.heading))

    def check(self, state_dim: int, translation_invariant_dims: tuple[int, ...]) -> None:
        """Raise a ``ValueError`` naming the dims when the frame does not fit the state."""
        dims = (*self.position, *self.heading_dims)
        if any(not 0 <= d < state_dim for d in dims):
            raise ValueError(f"`body_frame` dims {dims} must be state indices < {state_dim}")
        if set(self.position) - set(translation_invariant_dims):
            raise ValueError(f"`body_frame.position`={self.position} must be among `translation_invariant_dims`="
                             f"{tuple(translation_invariant_dims)}")
        if set(self.heading_dims) & set(translation_invariant_dims):
            raise ValueError(f"`body_frame.heading`={self.heading} must not be among `translation_invariant_dims`")

    def heading_vectors(self, states: Tensor) -> Tensor:
        """``q`` ``[N, 2]`` of data states ``[N, n]`` (``(cos θ, sin θ)`` or the state's own vector)."""
        if self.angle:
            theta = states[:, self.heading]
            return torch.stack((theta.cos(), theta.sin()), dim=-1)
        return states[:, list(self.heading)]

    def body_targets(self, x_minus: Tensor, x_plus: Tensor, noise_center: Tensor, target: Tensor) -> Tensor:
        """The fit's targets ``[N, n]`` with the rotated pairs in the body frame and an angle's step wrapped.

        ``target`` holds ``x+ - c_w - P x`` (``P`` the identity on the identity-slope dims); a
        position pair becomes ``M(q)^{-1} (p+ - p - c_w)``, a heading vector
        ``M(q)^{-1} (q+ - c_w)``, and an angle's step is wrapped into ``(-π, π]``.
        """
        q = self.heading_vectors(x_minus)
        out = target.clone()
        for pair in self.rotated_pairs:
            out[:, list(pair)] = _solve(q, target[:, list(pair)])
        if self.angle:
            step = target[:, self.heading]
            out[:, self.heading] = torch.atan2(step.sin(), step.cos())
        return out

    def body_noise_radius(self, x_minus: Tensor, noise_generators: Tensor, radius: Tensor) -> Tensor:
        """``radius`` ``[n]`` with each rotated pair's entries replaced by the bound of the rotated noise."""
        norm = self.heading_vectors(x_minus).norm(dim=-1).amin().clamp_min(1e-12)
        out = radius.clone()
        for pair in self.rotated_pairs:
            out[list(pair)] = _largest_norm(noise_generators[list(pair)]) / norm
        return out

    def heading_form(self, center: Tensor, generators: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The heading vector over a set ``Z(center [..., n], generators [..., n, p])``.

        Returns:
            ``(q0 [..., 2], G_q [..., 2, p], e_q [..., 2])``: ``q ∈ q0 + G_q ε + [-e_q, e_q]``.
        """
        if not self.angle:
            dims = list(self.heading)
            return center[..., dims], generators[..., dims, :], center.new_zeros(*center.shape[:-1], 2)
        theta, row = center[..., self.heading], generators[..., self.heading, :]
        q0 = torch.stack((theta.cos(), theta.sin()), dim=-1)
        tangent = torch.stack((-theta.sin(), theta.cos()), dim=-1)
        remainder = row.abs().sum(-1).square() / 2
        return q0, tangent.unsqueeze(-1) * row.unsqueeze(-2), torch.stack((remainder, remainder), dim=-1)

    def rotate(self, heading: tuple[Tensor, Tensor, Tensor], h0: Tensor, h_gens: Tensor,
               h_error: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Enclose ``M(q) h`` for ``q`` in ``heading`` (:meth:`heading_form`) and ``h ∈ h0 + G_h ε + [-e_h, e_h]``.

        Args:
            h0: ``[..., 2]``; h_gens: ``[..., 2, p]`` over the same symbols as ``G_q``;
            h_error: ``[..., 2]`` an independent interval.

        Returns:
            ``(center [..., 2], generators [..., 2, p], error [..., 2, 2], box [..., 2])``: the
            result lies in ``center + generators ε + error ε' + [-box, box]`` (``error`` the
            rotated interval of ``h``; ``box`` the heading's remainder and the second-order term).
        """
        q0, q_gens, q_error = heading
        rotation = _matrix(q0)  # M(q0) [..., 2, 2]
        along_q = _matrix(h0)  # M(q) h0 = M(h0) q
        center = small_matmul(rotation, h0.unsqueeze(-1)).squeeze(-1)
        generators = small_matmul(rotation, h_gens) + small_matmul(along_q, q_gens)
        error = rotation * h_error.unsqueeze(-2)
        q_radius = q_gens.abs().sum(-1) + q_error
        h_radius = h_gens.abs().sum(-1) + h_error
        second = torch.stack((q_radius[..., 0] * h_radius[..., 0] + q_radius[..., 1] * h_radius[..., 1],
                              q_radius[..., 1] * h_radius[..., 0] + q_radius[..., 0] * h_radius[..., 1]), dim=-1)
        box = small_matmul(along_q.abs(), q_error.unsqueeze(-1)).squeeze(-1) + second
        return center, generators, error, box


MIN_TURN = 1.0
"""Radians a state dim's data must span to be tried as a heading angle by :meth:`BodyFrame.detect`."""

UNIT_TOLERANCE = 1e-3
"""How far from 1 the squared norm of a pair of dims may be, in every transition, to be tried as ``(cos θ, sin θ)``."""

BODY_ERROR_SHARE = 0.7
""":meth:`BodyFrame.detect` takes a frame whose body-frame position step is predicted at most this share as badly as
the world-frame one. On the example robots (500 and 2,000 random steps) a true heading gives 0.18 (bicycle), 0.43-0.49
(unicycle), 0.37-0.42 (``diffdrive_nav``'s heading vector, kinematic and wheeled); every other dim tried 1.35 or more
(a velocity, a wind offset, a heading vector's component read as an angle)."""

HEADING_FREE_RATIO = 1.5
"""The most the other state dims' step prediction may worsen without the heading for :meth:`BodyFrame.detect` (0.6-0.8
on the example robots with a heading: their other states are speeds in the body frame)."""

NEIGHBOURS = 5
"""Nearest transitions averaged by :meth:`BodyFrame.detect`'s predictions."""

MIN_TRANSITIONS = 50
"""The fewest transitions :meth:`BodyFrame.detect` reads a frame from (it is reliable from 200 on the example
robots; ``tests/reach/test_body_frame.py``)."""


def _neighbour_error(inputs: Tensor, targets: Tensor) -> Tensor:
    """Mean absolute error per target ``[k]`` of predicting each of ``targets`` ``[N, k]`` by the mean over its
    :data:`NEIGHBOURS` nearest other rows of ``inputs`` ``[N, d]`` (each input scaled to unit spread)."""
    scaled = (inputs - inputs.mean(0)) / inputs.std(0).clamp_min(1e-12)
    distances = torch.cdist(scaled, scaled)
    distances.fill_diagonal_(float("inf"))
    nearest = distances.topk(min(NEIGHBOURS, inputs.shape[0] - 1), largest=False).indices
    return (targets[nearest].mean(1) - targets).abs().mean(0)


def _matrix(q: Tensor) -> Tensor:
    """``M(q) = [[c, -s], [s, c]]`` ``[..., 2, 2]`` of ``q = (c, s)`` ``[..., 2]``."""
    c, s = q.unbind(-1)
    return torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), -2)


def _solve(q: Tensor, v: Tensor) -> Tensor:
    """``M(q)^{-1} v = M(q)ᵀ v / |q|²`` row-wise: ``[N, 2]``."""
    return (_matrix(q).transpose(-1, -2) @ v.unsqueeze(-1)).squeeze(-1) / q.square().sum(-1, keepdim=True)


def _largest_norm(generators: Tensor, max_enumerated: int = 12) -> Tensor:
    """``max ||v||_2`` over the vertices ``v`` of ``Z(0, generators [2, p])``: the largest support
    of the zonotope along a unit direction, so its radius per dim under every rotation (by
    enumeration; ``Σ_j ||g_j||``, an upper bound, above ``max_enumerated`` non-zero generators)."""
    generators = generators[:, generators.norm(dim=0) > 0]
    p = generators.shape[1]
    if p == 0 or p > max_enumerated:
        return generators.norm(dim=0).sum()
    signs = torch.cartesian_prod(*[generators.new_tensor([-1.0, 1.0])] * p).reshape(-1, p)
    return (signs @ generators.T).norm(dim=-1).amax()
