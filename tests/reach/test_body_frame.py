"""Body-frame (yaw-invariant) fits: the rotation's enclosure, soundness on sampled robots, tightness, errors."""
import math

import pytest
import torch

from torchrl_brsl.reach import (BlackBoxSystem, BodyFrame, CappedVelocityServo, DataDrivenReach, DoubleIntegrator,
                                KinematicBicycle, SaturatedThrustPoint, Unicycle, points_outside, sample_reach)
from torchrl_brsl.reach import body_frame, cells, hinges
from torchrl_brsl.sets import Zonotope

from reach_support import sampled, shared_fit

SYSTEMS = {"bicycle": KinematicBicycle, "unicycle": Unicycle}


def _rotation_samples(frame: BodyFrame, seed: int, samples: int = 4000):
    """A random heading set and body vector, the enclosure of ``M(q) h`` and true products."""
    gen = torch.Generator().manual_seed(seed)
    kw = dict(generator=gen, dtype=torch.float64)
    p = 4
    n = 3 if frame.angle else 4
    center = torch.randn(n, **kw)
    generators = torch.randn(n, p, **kw) * 0.3 * torch.rand((), **kw)
    if not frame.angle:  # a heading vector near the unit circle
        center[2:] = center[2:] / center[2:].norm()
    h0, h_gens, h_err = torch.randn(2, **kw), torch.randn(2, p, **kw) * 0.1, torch.rand(2, **kw) * 0.05
    eps = torch.rand(samples, p, **kw) * 2 - 1
    eps[: samples // 4] = eps[: samples // 4].sign()  # the vertices
    h = h0 + eps @ h_gens.T + h_err * (torch.rand(samples, 2, **kw) * 2 - 1)
    if frame.angle:
        theta = center[2] + eps @ generators[2]
        q = torch.stack((theta.cos(), theta.sin()), -1)
    else:
        q = center[2:] + eps @ generators[2:].T
    true = torch.stack((q[:, 0] * h[:, 0] - q[:, 1] * h[:, 1], q[:, 1] * h[:, 0] + q[:, 0] * h[:, 1]), -1)
    return frame.rotate(frame.heading_form(center, generators), h0, h_gens, h_err), true


@pytest.mark.parametrize("frame", [BodyFrame((0, 1), 2), BodyFrame((0, 1), (2, 3))], ids=["angle", "vector"])
def test_the_rotation_enclosure_contains_every_sampled_product(frame):
    outside = 0
    for seed in range(100):
        (center, gens, error, box), true = _rotation_samples(frame, seed)
        outside += int(points_outside(Zonotope(center, torch.cat((gens, error, torch.diag(box)), -1)), true).sum())
    assert outside == 0


def test_the_rotation_enclosure_needs_its_second_order_term():
    """Teeth: without the remainder box, sampled products fall outside."""
    frame, outside = BodyFrame((0, 1), 2), 0
    for seed in range(100):
        (center, gens, error, _), true = _rotation_samples(frame, seed)
        outside += int(points_outside(Zonotope(center, torch.cat((gens, error), -1)), true).sum())
    assert outside > 0


# system, offline steps, data seed, share of the 20 random plans the model must claim (measured:
# bicycle 15-19, unicycle 16 and 20: its speed clip at 0 and 1 m/s has a hinge along v + dt a).
# The bicycle's data seed 1 caught a step that summed the world noise's generators with the
# rotated error's pairwise (5 states outside) instead of adding both sets.
CLAIMED = [("bicycle", 500, 0, 0.5), ("bicycle", 500, 1, 0.5), ("bicycle", 2000, 0, 0.5),
           ("unicycle", 500, 0, 0.6), ("unicycle", 2000, 0, 0.8)]


@pytest.mark.parametrize("name, num, seed, min_claimed", CLAIMED)
def test_sampled_true_states_lie_in_the_body_frame_sets(name, num, seed, min_claimed):
    system = SYSTEMS[name]()
    result = sampled(system, shared_fit(system, num, seed=seed, body_frame=system.body_frame))
    assert result.covered.float().mean() >= min_claimed, f"{int(result.covered.sum())} of 20 plans claimed"
    assert result.violations == 0, f"{result.violations} of {result.checked} sampled states outside their sets"


def test_a_weakened_body_frame_bound_is_caught_by_the_sampling():
    """Teeth: the leaves' error intervals scaled by 0.3 let sampled states out (measured: 83 of
    51,000 on the bicycle with 500 steps; with 2,000 none, the bound has that slack there)."""
    system = KinematicBicycle()
    reach = shared_fit(system, 500, body_frame=system.body_frame)
    reach.cell_errors.mul_(0.3)
    assert sampled(system, reach).violations > 0


def test_the_body_frame_is_tighter_on_the_bicycle():
    """Width over sampled spread, median: measured 4.4 (body frame) against 11 (world frame) with
    500 steps, 4.2 against 7.0 with 2,000 (5.6 with the data of seed 1 and 500 steps)."""
    system = KinematicBicycle()
    for num, limit in ((500, 5.5), (2000, 5.0)):
        body = sampled(system, shared_fit(system, num, body_frame=system.body_frame)).median_ratio
        world = sampled(system, shared_fit(system, num, body_frame=None)).median_ratio
        assert body < limit and body < 0.7 * world, (num, body, world)


def test_the_body_frame_survives_save_and_load(tmp_path):
    system = KinematicBicycle()
    reach = shared_fit(system, 500, body_frame=system.body_frame)
    reach.save(tmp_path / "reach.pt")
    loaded = DataDrivenReach.load(tmp_path / "reach.pt")
    assert loaded.body_frame == system.body_frame
    x0, plan = torch.tensor([[0.0, 0.0, 2.0, 0.8]], dtype=torch.float64), torch.zeros(1, 5, 2, dtype=torch.float64)
    a, b = reach.reach(Zonotope.from_point(x0), plan), loaded.reach(Zonotope.from_point(x0), plan)
    assert torch.equal(a.center, b.center) and torch.equal(a.generators, b.generators)


def test_body_frame_sets_are_differentiable_in_the_plan():
    system = KinematicBicycle()
    reach = shared_fit(system, 500, body_frame=system.body_frame)
    plan = torch.full((1, 5, 2), 0.2, dtype=torch.float64, requires_grad=True)
    sets = reach.reach(Zonotope.from_point(torch.tensor([[0.0, 0.0, 1.0, 0.7]], dtype=torch.float64)), plan)
    (sets.center[..., :2].sum() + sets.generators.abs().sum()).backward()
    assert plan.grad is not None and torch.isfinite(plan.grad).all() and plan.grad.abs().sum() > 0


def _detected(system, num: int, seed: int, vector: bool = False):
    x, xp, u = system.offline_data(num, torch.Generator().manual_seed(seed))
    if vector:  # the heading stored as (cos θ, sin θ): (x, y, cos θ, sin θ, v)
        x, xp = ((s[:, :2], s[:, 2:3].cos(), s[:, 2:3].sin(), s[:, 3:]) for s in (x, xp))
        x, xp = torch.cat(tuple(x), -1), torch.cat(tuple(xp), -1)
    return BodyFrame.detect(x, xp, u, system.translation_invariant_dims)


@pytest.mark.parametrize("num", [200, 500, 2000])
def test_the_heading_is_detected_from_the_data(num):
    for seed in range(3):
        assert _detected(KinematicBicycle(), num, seed) == BodyFrame((0, 1), 2)
        assert _detected(Unicycle(), num, seed) == BodyFrame((0, 1), 2)
        assert _detected(Unicycle(), num, seed, vector=True) == BodyFrame((0, 1), (2, 3))
        for system in (DoubleIntegrator(), SaturatedThrustPoint(), CappedVelocityServo()):
            assert _detected(system, num, seed) is None, type(system).__name__


class _NorthSensingCar(BlackBoxSystem):
    """A unicycle that also reports its northward speed, a world-frame quantity: ``(x, y, θ, v, north)``."""

    def __init__(self):
        d = torch.float64
        high, ones = torch.tensor([1.0, 1.0, math.pi, 1.0, 1.0], dtype=d), torch.ones(2, dtype=d)
        low = torch.cat((-high[:3], torch.tensor([0.0, -1.0], dtype=d)))
        super().__init__(dt=0.1, state_low=low, state_high=high, action_low=-ones, action_high=ones,
                         noise_half_width=torch.full((5,), 0.002, dtype=d), translation_invariant_dims=(0, 1))

    def dynamics(self, x, u):
        theta, v = x[..., 2], (x[..., 3] + 0.1 * u[..., 0]).clamp(0.0, 1.0)
        return torch.stack((x[..., 0] + 0.1 * v * theta.cos(), x[..., 1] + 0.1 * v * theta.sin(),
                            theta + 0.1 * u[..., 1], v, 0.5 * x[..., 4] + 0.5 * v * theta.sin()), -1)


def test_a_robot_with_a_world_frame_state_gets_no_frame(monkeypatch):
    """The body frame rotates the position (and a heading vector) only: a state that turns with the heading needs
    the heading among its inputs. Teeth: without that check the frame is taken."""
    system = _NorthSensingCar()
    cases = [(num, seed) for num in (500, 2000) for seed in range(3)]
    assert all(_detected(system, num, seed) is None for num, seed in cases)
    monkeypatch.setattr(body_frame, "HEADING_FREE_RATIO", float("inf"))
    assert all(_detected(system, num, seed) == BodyFrame((0, 1), 2) for num, seed in cases)


def test_too_few_transitions_show_no_frame():
    system = KinematicBicycle()
    x, xp, u = system.offline_data(200, torch.Generator().manual_seed(0))
    assert BodyFrame.detect(x[:49], xp[:49], u[:49], (0, 1)) is None
    assert BodyFrame.detect(x, xp, u, (0, 1)) == system.body_frame


def test_the_fit_takes_the_frame_the_data_show_by_default():
    system = KinematicBicycle()
    x, xp, u = system.offline_data(200, torch.Generator().manual_seed(0))
    fits = {frame: DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=12,
                                       **({} if frame == "default" else {"body_frame": frame}))
            for frame in ("default", None, system.body_frame)}
    assert fits["default"].body_frame == system.body_frame and fits[None].body_frame is None
    x0, plan = torch.tensor([[0.0, 0.0, 2.0, 0.8]], dtype=torch.float64), torch.full((1, 4, 2), 0.2).double()
    sets = {frame: reach.reach(Zonotope.from_point(x0), plan) for frame, reach in fits.items()}
    assert torch.equal(sets["default"].generators, sets[system.body_frame].generators)
    assert not torch.equal(sets["default"].generators, sets[None].generators)
    globally = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), method="global")
    assert globally.body_frame is None


@pytest.mark.parametrize("kwargs, message", [
    (dict(body_frame="yes"), "'auto' or None"),
    (dict(body_frame=BodyFrame((0, 1), 2), method="global"), "method='local'"),
    (dict(body_frame=BodyFrame((0, 3), 2)), "translation_invariant_dims"),
    (dict(body_frame=BodyFrame((0, 1), 7)), "state indices"),
])
def test_a_bad_body_frame_is_rejected_by_name(kwargs, message):
    system = KinematicBicycle()
    x, xp, u = system.offline_data(200, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=message):
        DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), **kwargs)


@pytest.mark.parametrize("position, heading", [((0, 1), 1), ((0, 0), 2), ((0, 1), (2, 3, 4))])
def test_a_malformed_body_frame_is_rejected(position, heading):
    with pytest.raises(ValueError, match="body_frame"):
        BodyFrame(position, heading)


def _bicycle_states_outside(monkeypatch, floor: bool) -> int:
    """Sampled states outside on the bicycle case where the leaves' curvature is as small as the
    noise (500 steps and plans drawn from one generator, as in bench_reach_tightness.py)."""
    # hinges only, left on their grid of directions and knots: a product feature, or hinges moved to the kinks,
    # take the curvature out of this case
    monkeypatch.setattr(cells, "fit_features", lambda *args, n_actions: hinges.fit_features(*args))
    monkeypatch.setattr(hinges, "refine_hinges", lambda inputs, directions, knots, *args: (directions, knots))
    # every output on all its inputs: the heading step fitted on speed and steering alone does not need the floor here
    monkeypatch.setattr(cells, "select_inputs", lambda inputs, target: torch.ones(inputs.shape[1], dtype=torch.bool))
    # nor the bend term: the grid's hinges cut the heading's bend into pieces, whose stray it covers too
    monkeypatch.setattr(cells, "bend_error", lambda low, high, features, points=None: low.new_zeros(low.shape[0]))
    # and the grid of 8 hinges over 25 knots where this was measured: 50 knots put a hinge near enough to the kinks,
    # and so does a hinge halfway between two fitted ones
    monkeypatch.setattr(hinges, "MAX_HINGES", 8)
    monkeypatch.setattr(hinges, "KNOTS", 25)
    monkeypatch.setattr(hinges, "midpoint_hinges", lambda directions, knots, signs: (directions[:0], knots[:0]))
    # nor a leaf's hidden noise, which reads part of this curvature's scatter as noise and covers it too
    monkeypatch.setattr(cells, "HIDDEN_QUANTILES", ())
    if not floor:
        monkeypatch.setattr(cells, "curvature_floor", lambda low, high, slopes, weights: slopes.new_zeros(len(low)))
    system = KinematicBicycle()
    gen = torch.Generator().manual_seed(0)
    x, xp, u = system.offline_data(500, gen)
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24,
                                body_frame=system.body_frame)
    center, half = (system.state_low + system.state_high) / 2, (system.state_high - system.state_low) / 2
    x0 = center + 0.7 * half * (torch.rand(20, 4, generator=gen, dtype=torch.float64) * 2 - 1)
    x0[:, :2] = 0.0
    plans = system.sample_actions(20, 10, generator=gen)
    return sample_reach(reach, lambda s, a: system.step(s, a, gen), x0, plans, 300).violations


def test_the_curvature_floor_is_what_keeps_the_bicycle_heading_inside(monkeypatch):
    """Teeth of :func:`~torchrl_brsl.reach.cells.curvature_floor`: measured 11 sampled states
    outside without it (the heading, 0.3 mrad beyond its set), none with it."""
    assert _bicycle_states_outside(monkeypatch, floor=True) == 0
    assert _bicycle_states_outside(monkeypatch, floor=False) > 0
