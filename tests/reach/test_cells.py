"""The local (cell) model, the default of DataDrivenReach: sound on sampled true systems, and tight."""
import math

import pytest
import torch

from torchrl_brsl.reach import (CappedVelocityServo, DataDrivenReach, DoubleIntegrator, Features, KinematicBicycle,
                                SaturatedThrustPoint, Unicycle, cells, hinges, leaf_distance, leaf_layout, point_bounds,
                                worst_noise_outside)
from torchrl_brsl.sets import Zonotope

from reach_support import fit, random_plans, sampled, shared_fit

SYSTEMS = {"bicycle": KinematicBicycle, "saturated_point": SaturatedThrustPoint, "double_integrator": DoubleIntegrator}


@pytest.mark.parametrize("num", [500, 2000])
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_sampled_true_states_lie_in_the_local_sets(name, num):
    """Every sampled state of every plan the model claims lies in its set (6 x up to 60,000 states)."""
    system = SYSTEMS[name]()
    result = sampled(system, shared_fit(system, num))
    assert result.covered.float().mean() >= 0.5, "most random plans of the data region should be claimed"
    assert result.violations == 0, f"{result.violations} of {result.checked} sampled states outside their sets"


def test_a_weakened_error_bound_is_caught_by_the_sampling():
    """Teeth: with the cells' model-error intervals scaled by 0.3, sampled true states fall
    outside (measured: 39, 214 and 3 of ~60,000; at 0.5 none do: the bound has that slack)."""
    caught = {}
    for name, system_type in SYSTEMS.items():
        system = system_type()
        reach = shared_fit(system, 2000)
        reach.cell_errors.mul_(0.3)
        caught[name] = sampled(system, reach).violations
    assert sum(caught.values()) > 0, caught


def edge_violations(system, reach, plan_seeds=(1, 2, 3)):
    """Sampled states outside ``reach``'s sets along 100 plans from starts near the data's edges, per plan seed."""
    return [sampled(system, reach, seed=seed, samples=100, spread=0.95, n_plans=100).violations for seed in plan_seeds]


def without_range_error(monkeypatch):
    """Leaves whose intervals need not reach the data's plateaus (:func:`~torchrl_brsl.reach.cells.range_error`)."""
    monkeypatch.setattr(cells, "range_error", lambda *args: torch.zeros((), dtype=torch.float64))


def without_end_span(monkeypatch):
    """Refined hinges kept however few points lie beyond their knots
    (:func:`~torchrl_brsl.reach.hinges.refine_hinges`)."""
    monkeypatch.setattr(hinges, "_spans_ends", lambda inputs, directions, knots: torch.ones(len(knots), dtype=bool))


def free_hinges(monkeypatch):
    """Hinges free in every input (``SPARSE_SHARE = 0``) and without the end span; no bend term and no range error
    (which cover part of what the first two leave)."""
    monkeypatch.setattr(hinges, "SPARSE_SHARE", 0.0)
    without_end_span(monkeypatch)
    without_range_error(monkeypatch)
    monkeypatch.setattr(cells, "bend_error", lambda low, high, features, points=None: low.new_zeros(low.shape[0]))


def test_starts_near_the_data_edges_are_sound_with_sparse_hinges(monkeypatch):
    """From starts near the data region's edges, where the plans leave the data, no sampled state falls outside the
    bicycle's body-frame sets from 500 or 2,000 steps (100 plans x 100 samples, plan seeds 1, 2, 3). Teeth: with
    hinges free in every input (:func:`free_hinges`), the model of another 500 steps (data seed 10) let 202, 254 and
    0 out (measured; which data the free hinges fail on follows the fit's rounding, as pinned in constraints.txt)."""
    system = KinematicBicycle()
    assert edge_violations(system, fit(system, 500, body_frame=system.body_frame)) == [0, 0, 0]
    assert edge_violations(system, fit(system, 2000, body_frame=system.body_frame)) == [0, 0, 0]
    free_hinges(monkeypatch)
    leaky = edge_violations(system, fit(system, 500, seed=10, body_frame=system.body_frame))
    assert sum(leaky) > 0, "the sampling should catch the free hinges' model near the edges"


def test_the_end_span_keeps_a_hinge_off_the_braking_corner(monkeypatch):
    """Data seed 5 (500 steps): refined without the end span (:func:`~torchrl_brsl.reach.hinges.refine_hinges`), the
    speed hinge left a few points on its side, in the corner where the speed clips at 0 under hard braking, and the
    model put the stopped bicycle up to 0.06 m/s beyond its bound: 131 and 912 of 10,000 sampled states from edge
    starts fell outside (plan seeds 2, 3), 0 with the end span. Both without the range error, which covers this
    corner too.
    (Plan seed 1 lets 27 out either way: at the heading's first step at full steer and 1.2 m/s, docs/limits.md.)"""
    without_range_error(monkeypatch)
    system = KinematicBicycle()
    assert edge_violations(system, fit(system, 500, seed=5, body_frame=system.body_frame), (2, 3)) == [0, 0]
    without_end_span(monkeypatch)
    assert min(edge_violations(system, fit(system, 500, seed=5, body_frame=system.body_frame), (2, 3))) > 0


def test_leaves_reach_the_plateau_where_the_speed_clips(monkeypatch):
    """Data seed 2 (500 steps) has no hinge along the clip at 0 and 10 points on its plateau: the leaf holding hard
    braking from rest extrapolated to -0.15 to -0.04 m/s where the bicycle stops, and 34 of 10,000 sampled states
    from edge starts fell outside (plan seed 3). Each leaf's interval now reaches the plateau at its corners
    (:func:`~torchrl_brsl.reach.cells.range_error`): the one-step set at the data's least speed under their hardest
    braking holds 0, and none falls outside."""
    system = KinematicBicycle()
    reach = fit(system, 500, seed=2, body_frame=system.body_frame)
    corner = reach._scaled_data.amin(0) * torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)  # (v, a, steer 0)
    prediction, errors, _ = point_bounds(reach._cells, reach._scaled_data, corner[None])
    assert prediction[0, 3] - errors[0, 3] <= 0.0 <= prediction[0, 3] + errors[0, 3]
    assert edge_violations(system, reach, (3,)) == [0]
    without_range_error(monkeypatch)
    assert edge_violations(system, fit(system, 500, seed=2, body_frame=system.body_frame), (3,))[0] > 0


def test_the_range_error_looks_at_the_vertices_where_a_hinge_kink_meets_a_leaf(monkeypatch):
    """The unicycle's speed clips at 0 under hard braking, and its 500-step model (data seed 0) has a hinge near the
    clip, slightly tilted from it. Below the hinge's kink, the leaf holding slow braking keeps a slope that
    extrapolates to -0.025 m/s where the unicycle stops, at the vertex where the kink meets the leaf's braking face,
    between the grid's corners and mid-edge points. With that vertex among the points the range error checks
    (:func:`~torchrl_brsl.reach.cells.leaf_vertices`), no one-step query of slow, hard braking leaves its set at the
    worst noise; without it, 355 of 2,000 did (measured), up to 0.014 m/s beyond."""
    system = Unicycle()
    gen = torch.Generator().manual_seed(1)
    states = system.sample_states(2000, gen)
    states[:, 3] = 0.15 * torch.rand(2000, generator=gen, dtype=torch.float64)
    actions = system.sample_actions(2000, generator=gen)
    actions[:, 0] = -0.5 - 0.5 * torch.rand(2000, generator=gen, dtype=torch.float64)

    def leaks():
        outside, claimed = worst_noise_outside(fit(system, 500), system.dynamics, states, actions)
        assert claimed.float().mean() > 0.9
        return int((outside & claimed).sum())

    assert leaks() == 0
    monkeypatch.setattr(cells, "leaf_vertices", lambda lo, *args: lo.new_zeros(0, len(lo)))
    assert leaks() > 0, "the grid alone should miss the vertex"


def test_a_noise_free_output_keeps_a_resolution_for_its_misplaced_kinks(monkeypatch):
    """The capped servo's positions have no noise, and its 2,000-step model finds their kinks (``u - v = 0.5``) to
    about a millionth: between the fitted and the true kink no data point shows the model's miss. With the bound's
    noise radius floored at :data:`~torchrl_brsl.reach.cells.RESOLUTION` of the output's range, no one-step query
    along the kink leaves its set at the worst noise; without the floor, 174 of 5,000 did (measured, 8 hinges), 1e-8 m
    beyond position bounds of about that size. With the 12 hinges now allowed the position gets 6, and 2 leave
    without the floor; the bend term that their same-sign pairs add (:func:`~torchrl_brsl.reach.cells.bend_error`)
    covers those, so the teeth take it off too."""
    system = CappedVelocityServo()
    gen = torch.Generator().manual_seed(1)
    states = system.sample_states(5000, gen) * 0.7
    actions = system.sample_actions(5000, generator=gen)
    actions[:, 0] = states[:, 2] + 0.49 + 0.03 * torch.rand(5000, generator=gen, dtype=torch.float64)

    def leaks():
        outside, claimed = worst_noise_outside(fit(system, 2000), system.dynamics, states, actions)
        assert claimed.all()
        return int(outside.sum())

    assert leaks() == 0
    monkeypatch.setattr(cells, "RESOLUTION", 0.0)
    monkeypatch.setattr(cells, "bend_error", lambda low, high, features, points=None: low.new_zeros(low.shape[0]))
    assert leaks() > 0, "without the floor, the sampling should catch the misplaced kink"


def test_leaf_vertices_are_the_corners_and_where_the_crossing_kinks_meet_the_faces():
    """A unit box cut by a face along ``z_0 + z_1 <= 1.5`` and a kink ``z_0 = 0.5``: the region's 5 corners and the
    kink's end on the lower face (its upper end is a corner); a kink beyond the box (``z_1 = 2``) adds none, and an
    input outside the support sits at the middle of its range."""
    directions = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0]],
                              dtype=torch.float64)
    low = torch.tensor([0.0, 0.0, 0.0, -torch.inf], dtype=torch.float64)
    high = torch.tensor([1.0, 1.0, 2.0, 1.5], dtype=torch.float64)
    lo, hi = low[:3], high[:3]
    kinks = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    support = torch.tensor([True, True, False])
    knots = torch.tensor([0.5, 2.0], dtype=torch.float64)
    z = cells.leaf_vertices(lo, hi, low, high, directions, support, kinks, knots)
    expected = {(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 0.5), (0.5, 1.0), (0.5, 0.0)}
    assert {tuple(round(v, 9) + 0.0 for v in point[:2].tolist()) for point in z} == expected
    assert torch.equal(z[:, 2], torch.ones(len(z), dtype=torch.float64))
    box = torch.ones(9, dtype=torch.float64)  # 18 faces in 9 inputs: 48,620 choices (a grid of 18^9 would not fit)
    corners = cells.leaf_vertices(-box, box, -box, box, torch.eye(9, dtype=torch.float64), box > 0,
                                  torch.zeros(0, 9, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    assert corners.shape == (512, 9) and bool((corners.abs() == 1).all())


def test_a_fit_shows_its_progress_over_the_outputs_and_fits_the_same_model(capsys):
    """``progress=True`` draws a bar over the outputs (one per state dim) on stderr and changes nothing else."""
    system = DoubleIntegrator()
    quiet = fit(system, 300)
    assert "local model" not in capsys.readouterr().err
    shown = fit(system, 300, progress=True)
    assert "local model" in capsys.readouterr().err.replace("\r", "\n").splitlines()[-1]
    assert torch.equal(quiet.cell_errors, shown.cell_errors) and torch.equal(quiet.cell_slopes, shown.cell_slopes)


def test_only_a_plateau_in_the_data_bounds_an_output():
    """More than ``d + 1`` points within ``2 w̄`` of the least (largest) value make it a bound; a lone extreme does
    not."""
    noise = torch.tensor(0.01, dtype=torch.float64)
    clipped = torch.cat((torch.zeros(6), torch.linspace(0.1, 1.0, 50))).double()
    lowest, highest = cells.observed_extremes(clipped, noise, 4)
    assert float(lowest) == 0.0 and float(highest) == torch.inf
    assert float(cells.observed_extremes(clipped, noise, 5)[0]) == -torch.inf


def test_held_out_check_warns_where_the_data_are_sparse_and_widens_those_leaves(monkeypatch):
    """``held_out_folds``: on the leaky model of free hinges (:func:`free_hinges`, data seed 10), transitions held out
    of the bicycle's 500-step fit fall outside their one-step bounds (a warning says so) and the leaves holding them are
    widened, which cuts the leaks from starts near the edges (measured, plan seeds 1, 2, 3: 202, 254 and 0 outside
    before, 5, 9 and 0 after); the other leaves keep their bounds."""
    free_hinges(monkeypatch)
    system = KinematicBicycle()
    plain = fit(system, 500, seed=10, body_frame=system.body_frame)
    with pytest.warns(UserWarning, match="held-out transitions fell outside"):
        checked = fit(system, 500, seed=10, body_frame=system.body_frame, held_out_folds=5)
    widened = checked.cell_errors > plain.cell_errors
    assert widened.any() and torch.equal(checked.cell_errors[~widened], plain.cell_errors[~widened])
    assert (checked.cell_lipschitz >= plain.cell_lipschitz).all()
    outside = {name: edge_violations(system, reach) for name, reach in (("plain", plain), ("checked", checked))}
    assert all(c <= p for c, p in zip(outside["checked"], outside["plain"])), outside
    assert sum(outside["checked"]) < sum(outside["plain"]), outside


def test_outputs_fitted_on_the_inputs_they_depend_on_are_tighter_and_sound(monkeypatch):
    """A capped servo's velocity depends on its own axis' velocity and command (inputs ``(vx, vy, ux, uy)``):
    :func:`select_inputs` finds them, and an output whose cells on them alone win weighs the other inputs 0.
    Measured, 500 steps: 2.41 times the sampled spread against 2.89 with every output on all inputs, 0 outside."""
    system = CappedVelocityServo()
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    reach = fit(system, 500)
    assert cells.select_inputs(reach._scaled_data, xp[:, 2] - x[:, 2]).tolist() == [True, False, True, False]
    assert cells.select_inputs(reach._scaled_data, xp[:, 3] - x[:, 3]).tolist() == [False, True, False, True]
    ignored = reach.cell_weights == 0  # [n, d]
    assert ignored.any(), "some output should keep its own inputs only"
    slopes = reach._cells.slopes[..., :ignored.shape[1]]  # [n, M, d]
    assert (slopes.masked_select(ignored.unsqueeze(1).expand_as(slopes)) == 0).all()
    selected = sampled(system, reach)
    monkeypatch.setattr(cells, "select_inputs", lambda inputs, target: torch.ones(inputs.shape[1], dtype=torch.bool))
    every_input = sampled(system, fit(system, 500))
    assert selected.violations == 0 and every_input.violations == 0
    assert selected.median_ratio < every_input.median_ratio, (selected.median_ratio, every_input.median_ratio)


def test_points_the_metric_cannot_tell_apart_but_whose_outputs_differ_get_no_bound():
    """Two data points at distance 0 in an output's metric (it weighs the input they differ in 0) whose residuals
    differ by more than the noise: no Lipschitz constant holds, and the leaf's error is infinite, never chosen."""
    z = torch.tensor([[0.1, 0.2], [0.1, 0.9], [0.5, 0.5], [0.8, 0.1]], dtype=torch.float64)
    residual = torch.tensor([0.0, 1.0, 0.3, 0.2], dtype=torch.float64)
    noise, floor = torch.tensor(0.01, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
    blind = cells._bound_cell(z, residual, noise, torch.tensor([1.0, 0.0], dtype=torch.float64), 1.5, floor)
    seeing = cells._bound_cell(z, residual, noise, torch.tensor([1.0, 1.0], dtype=torch.float64), 1.5, floor)
    assert math.isinf(blind[0]) and math.isinf(blind[2])
    assert math.isfinite(seeing[0]) and math.isfinite(seeing[2])


class SlippingDoubleIntegrator(DoubleIntegrator):
    """The double integrator whose acceleration slips by up to ``slip`` per axis at random (by exactly ``±slip`` where
    ``two_valued``: a wheel that grips or slips): a disturbance its declared noise (the example's, times
    ``noise_scale``) leaves out, whose cause its state does not hold."""

    def __init__(self, slip=0.2, two_valued=False, noise_scale=1.0):
        super().__init__()
        self.slip, self.two_valued = slip, two_valued
        self.noise_half_width = self.noise_half_width * noise_scale

    def step(self, x, u, generator=None):
        draw = torch.rand(u.shape, generator=generator, dtype=u.dtype) * 2 - 1
        push = (draw.sign() if self.two_valued else draw) * self.slip
        return super().step(x, u + push, generator)


def test_a_robot_with_hidden_noise_gets_sets_that_hold_its_sampled_states(monkeypatch):
    """A slip of up to 0.02 m/s a step beyond the declared 0.01 on the velocities: every nearby pair's difference used
    to be read as slope, and the sets left the data (measured: 0 of 20 plans claimed, first-step sets 9.0 times the
    sampled spread). With part of the scatter read as hidden noise: 18 of 20 claimed, the first step 7.6 times, and
    every sampled state of the slipping robot inside (the capped quadrotor's test in
    ``test_task_soundness.py`` shows the sampling catching a hidden noise read too far)."""
    system = SlippingDoubleIntegrator()
    hidden = sampled(system, fit(system, 2000))
    monkeypatch.setattr(cells, "HIDDEN_QUANTILES", ())
    slope_only = sampled(system, fit(system, 2000))
    assert hidden.violations == 0, f"{hidden.violations} of {hidden.checked} sampled states outside"
    assert hidden.covered.float().mean() >= 0.5 > slope_only.covered.float().mean()


def test_the_hidden_noise_counts_again_as_every_steps_draw_or_sampled_states_leave_the_sets(monkeypatch):
    """Teeth of the per-step ``h`` in a leaf's half-width (:func:`cells._bound_cell`): a robot whose acceleration slips
    by exactly ±0.2 at random (±0.02 m/s a step; declared noise a tenth of the example's), whose leaves read the slip
    as hidden noise and pin the step's mean down closely. With ``h`` added, every sampled state is inside; with it
    taken out again (the envelope of ``w̄ + h`` kept), the sampling catches states outside (measured: 0 and 300 of
    60,000, 20 of 20 plans claimed by both)."""
    system = SlippingDoubleIntegrator(two_valued=True, noise_scale=0.1)
    sound = sampled(system, fit(system, 1000))
    bound = cells._bound_cell

    def without_the_steps_draw(*args, **kwargs):
        half, centre, lipschitz, delta, hidden = bound(*args, **kwargs)
        return half - hidden, centre, lipschitz, delta, hidden

    monkeypatch.setattr(cells, "_bound_cell", without_the_steps_draw)
    weakened = sampled(system, fit(system, 1000))
    assert sound.covered.float().mean() >= 0.5 and weakened.covered.float().mean() >= 0.5
    assert sound.violations == 0, f"{sound.violations} of {sound.checked} sampled states outside"
    assert weakened.violations > 0, "the sampling should catch a bound without the hidden noise's own draw"


def test_a_leaf_keeps_the_hidden_noise_that_lowers_its_bound_without_raising_its_lipschitz_constant(monkeypatch):
    """A leaf whose residual jumps up by 0.02 at random (a two-valued hidden disturbance, none declared) around a
    gentle curve: read as slope, its nearest pairs make the constant steep; the leaf keeps a hidden noise instead,
    with a smaller half-width and constant."""
    gen = torch.Generator().manual_seed(0)
    z = torch.rand(200, 2, generator=gen, dtype=torch.float64)
    jump = 0.02 * torch.randint(0, 2, (200,), generator=gen).to(torch.float64)
    residual = 0.05 * (z[:, 0] - 0.5) ** 2 + jump
    noise = floor = torch.tensor(0.0, dtype=torch.float64)
    weights = torch.ones(2, dtype=torch.float64)
    half, _, lipschitz, _, hidden = cells._bound_cell(z, residual, noise, weights, 1.5, floor)
    monkeypatch.setattr(cells, "HIDDEN_QUANTILES", ())
    slope_half, _, slope_lipschitz, _, none = cells._bound_cell(z, residual, noise, weights, 1.5, floor)
    assert none == 0.0 and 0 < hidden < 0.011  # half the jump, and a little of the curve between nearest points
    assert half < slope_half and lipschitz <= slope_lipschitz, (half, slope_half, lipschitz, slope_lipschitz)


def test_a_candidate_whose_probe_error_is_nan_never_ranks_first():
    """A NaN leaf error (a lone hinge's empty leaf in a draft) makes a candidate's probe error ``inf``: ``min`` over the
    candidates would otherwise keep a NaN that comes first, as it did for a capped servo's position."""
    torch.manual_seed(0)
    z = torch.rand(300, 3, dtype=torch.float64)
    target = z[:, 0] + (z[:, 1] - z[:, 2]).clamp_min(0.2)
    n_states, noise = 2, torch.tensor(0.01, dtype=torch.float64)
    directions = cells.split_directions(n_states, 1, dtype=torch.float64)
    kinks = [cells.split_directions(n_states, 1, None, torch.float64, r) for r in (cells.HINGE_RATIOS[:1],
                                                                                  cells.HINGE_RATIOS)]
    axes = torch.zeros(directions.shape[0], dtype=torch.bool)
    axes[:3] = True
    candidates = cells._output_candidates(z, target, noise, 1, torch.ones(3, dtype=torch.bool),
                                          (directions, z @ directions.T, kinks, axes), (40, 0.15, 0.25, 1.0), True)
    parts, weights, option = candidates[0]
    assert math.isfinite(cells._probe_error(parts, weights, option, z, directions, n_states))
    parts = [part.clone() for part in parts]
    parts[4][0] = torch.nan  # one leaf's error
    assert cells._probe_error(parts, weights, option, z, directions, n_states) == math.inf


def test_the_leaves_slope_reach_covers_the_bicycles_heading_at_full_steer_and_speed(monkeypatch):
    """The bicycle's heading step ``v tan(steer)`` bends fastest at full steer and speed, where its 500-step model
    (body frame, data seed 0) holds one leaf of 63 points whose pairs show a residual slope of 0.017 only: the
    curvature there is of the noise's size. Its box reaches to the data's extended edge, where the slope has grown.
    With each leaf's constant floored by its quadratic surrogate's slope over the box
    (:func:`~torchrl_brsl.reach.cells.slope_reach`), no one-step query in that corner leaves its set at the worst
    noise; without it, 256 of these 4,000 did (measured; 15 of 100,000 over the inner 95 % of the region, up to
    0.0003 rad beyond)."""
    system = KinematicBicycle()
    gen = torch.Generator().manual_seed(3)
    states = system.sample_states(4000, gen)
    states[:, 3] = 1.35 + 0.11 * torch.rand(4000, generator=gen, dtype=torch.float64)
    actions = system.sample_actions(4000, generator=gen)
    actions[:, 1] = 0.47 + 0.03 * torch.rand(4000, generator=gen, dtype=torch.float64)

    def leaks():
        reach = fit(system, 500, body_frame=system.body_frame)
        outside, claimed = worst_noise_outside(reach, system.dynamics, states, actions)
        assert claimed.float().mean() > 0.9
        return int((outside & claimed).sum())

    assert leaks() == 0
    monkeypatch.setattr(cells, "slope_reach", lambda slopes, weights: slopes.new_zeros(()))
    assert leaks() > 0, "the pairs' slope alone should miss the corner's curvature"


def test_slope_reach_is_the_steepest_gradient_of_an_exact_quadratic_over_the_box():
    """On an exact quadratic residual the surrogate is exact: ``r = z0 z1 + z0²`` over ``[0, 1]²`` has its steepest
    gradient ``(2 z0 + z1, z0) = (3, 1)`` at the corner ``(1, 1)``; a weight divides its input's slope. Too few
    points, or points on a curve (a heading's cos and sin), give no surrogate."""
    gen = torch.Generator().manual_seed(0)
    z = torch.rand(60, 2, generator=gen, dtype=torch.float64)
    residual = z[:, 0] * z[:, 1] + z[:, 0] ** 2
    one, none = torch.ones(2, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)
    slopes = cells.corner_slopes(z, residual, one > 0, 0 * one, one, none)
    torch.testing.assert_close(cells.slope_reach(slopes, one), torch.tensor(10.0, dtype=torch.float64).sqrt())
    weighted = cells.slope_reach(slopes, torch.tensor([0.5, 1.0], dtype=torch.float64))
    torch.testing.assert_close(weighted, torch.tensor(37.0, dtype=torch.float64).sqrt())  # (3 / 0.5, 1)
    assert cells.corner_slopes(z[:10], residual[:10], one > 0, 0 * one, one, none).shape[0] == 0  # too few
    heading = torch.rand(60, generator=gen, dtype=torch.float64) * 6.28  # (cos, sin) on the circle: no quadratic
    circle = torch.stack((heading.cos(), heading.sin()), -1)
    on_circle = cells.corner_slopes(circle, circle[:, 0] * circle[:, 1], one > 0, -1.25 * one, 1.25 * one, none)
    assert on_circle.shape[0] == 0
    assert cells.slope_reach(z.new_zeros(0, 2), one) == 0


def test_the_curvature_floor_ignores_inputs_of_weight_zero_without_a_slope():
    low = torch.tensor([[0.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    high = torch.tensor([[1.0, 1.0], [2.0, 1.0]], dtype=torch.float64)
    slopes = torch.tensor([[1.0, 0.0], [3.0, 0.0]], dtype=torch.float64)  # touching leaves; input 1 has no slope
    both = cells.curvature_floor(low, high, slopes, torch.tensor([0.5, 0.0], dtype=torch.float64))
    torch.testing.assert_close(both, torch.tensor([2.0, 2.0], dtype=torch.float64))  # |3 - 1| / (2 * 0.5)
    slopes[1, 1] = 0.1  # a slope along an input the metric ignores: no constant bounds the residual
    assert torch.isinf(cells.curvature_floor(low, high, slopes, torch.tensor([0.5, 0.0], dtype=torch.float64))).all()


def test_leaves_span_the_data_range_along_the_inputs_they_do_not_split():
    """Cells on some inputs still end where the data do (extended by ``extend``) along the others, so a set beyond
    the data there is not covered."""
    features = torch.tensor([[0.0, 0.0], [1.0, 2.0], [0.5, 1.0], [0.2, 0.4]], dtype=torch.float64)
    root = torch.tensor([[0.0, -math.inf], [1.0, math.inf]], dtype=torch.float64)
    allowed, axes = torch.tensor([True, False]), torch.tensor([True, True])
    leaves = [(torch.tensor([0, 3]), torch.tensor([[0.0, -math.inf], [0.3, math.inf]], dtype=torch.float64)),
              (torch.tensor([1, 2]), torch.tensor([[0.3, -math.inf], [1.0, math.inf]], dtype=torch.float64))]
    boxes = cells._cell_boxes(features, root, leaves, overlap=0.0, extend=0.25, allowed=allowed, axes=axes)
    for low, high, _, _ in boxes:
        assert low[1] == -0.5 and high[1] == 2.5  # the data's range 0..2 extended by a quarter
    assert boxes[0][0][0] == -0.25 and boxes[1][1][0] == 1.25  # the split input as before


def test_the_one_step_claim_holds_at_the_worst_noise_thanks_to_the_bend_term(monkeypatch):
    """From 20,000 random states of the inner 70 % of the data region and random actions, no true successor of the
    saturated point (500 steps) with its noise at any vertex of ``W`` leaves its one-step set. Teeth: without
    :func:`~torchrl_brsl.reach.cells.bend_error` 90 do (measured): its 8 velocity hinges cut the tanh thrust into
    pieces, and the bend between their knots is below the noise, which the pairwise Lipschitz estimate cannot see;
    sampled along plans with uniform noise, none of those states fell outside."""
    system = SaturatedThrustPoint()
    gen = torch.Generator().manual_seed(1)
    states, actions = system.sample_states(20_000, gen) * 0.7, system.sample_actions(20_000, generator=gen)

    def outside(reach):
        worst, claimed = worst_noise_outside(reach, system.dynamics, states, actions)
        assert claimed.float().mean() > 0.99
        return int(worst[claimed].sum())

    assert outside(shared_fit(system, 500)) == 0
    monkeypatch.setattr(cells, "bend_error", lambda low, high, features, points=None: low.new_zeros(low.shape[0]))
    assert outside(fit(system, 500)) > 0, "the worst-noise check should catch the bound without the bend term"


def test_the_bend_term_covers_the_slabs_between_same_sign_parallel_knots_only():
    """Two parallel hinges whose slope changes share a sign (a smooth bend cut in pieces) add ``κ s² / 8`` to the
    leaves meeting the slab between their knots, ``κ`` the larger of the knots' slope change over their mean spacing;
    a wide gap beside a narrow one gets the narrow one's curvature; opposite signs (a servo's two saturations) and a
    lone hinge add nothing."""
    def features(directions, knots, coefficients):
        t = torch.float64
        return Features(torch.tensor(directions, dtype=t), torch.tensor(knots, dtype=t), torch.zeros(0, 2, 2, dtype=t),
                        torch.zeros(0, 2, dtype=t), torch.tensor(coefficients, dtype=t))

    low = torch.tensor([[-1.0, 0.0], [0.05, 0.0], [0.5, 0.0]], dtype=torch.float64)  # leaves along input 0
    high = torch.tensor([[-0.5, 1.0], [0.2, 1.0], [1.0, 1.0]], dtype=torch.float64)
    bend = cells.bend_error(low, high, features([[1.0, 0.0], [-2.0, 0.0]], [0.0, -0.8], [0.3, 0.2]))
    # hinge 1 is relu(-2 z + 0.8): its knot at z = 0.4, slope change 0.4 (κ = 0.4 / 0.4); hinge 0's 0.3 at 0
    torch.testing.assert_close(bend, torch.tensor([0.0, 1.0 * 0.4 ** 2 / 8, 0.0], dtype=torch.float64))
    # knots at 0, 0.1 and 0.4, slope changes 0.3 each: κ = 3, 1.5 (mean spacing 0.2) and 1; the slab 0.1..0.4 takes 1.5
    uneven = cells.bend_error(low, high, features([[1.0, 0.0]] * 3, [0.0, 0.1, 0.4], [0.3, 0.3, 0.3]))
    torch.testing.assert_close(uneven, torch.tensor([0.0, 1.5 * 0.3 ** 2 / 8, 0.0], dtype=torch.float64))
    servo = cells.bend_error(low, high, features([[1.0, 0.0], [1.0, 0.0]], [0.0, 0.4], [0.3, -0.3]))
    lone = cells.bend_error(low, high, features([[1.0, 0.0]], [0.0], [0.3]))
    assert not servo.any() and not lone.any()


def test_the_bend_term_shrinks_to_what_dense_data_leave_unseen():
    """With a leaf's data ``g`` apart along the hinges, a bend strays from them by at most ``κ g² / 8 + J g / 4``
    (``J`` the knots' slope change); the leaf takes that where it is below ``κ s² / 8``, and the knots' spacing
    where the data leave a wider gap (or none lie there)."""
    t = torch.float64
    chain = Features(torch.tensor([[1.0, 0.0]] * 3, dtype=t), torch.tensor([0.0, 0.1, 0.4], dtype=t),
                      torch.zeros(0, 2, 2, dtype=t), torch.zeros(0, 2, dtype=t), torch.tensor([0.3] * 3, dtype=t))
    low = torch.tensor([[0.05, 0.0], [0.25, 0.0]], dtype=t)  # leaf 0 meets both slabs, leaf 1 the second only
    high = torch.tensor([[0.2, 1.0], [0.35, 1.0]], dtype=t)
    spacing = cells.bend_error(low, high, chain)
    torch.testing.assert_close(spacing, torch.tensor([1.5 * 0.3 ** 2 / 8] * 2, dtype=t))  # as in the test above
    dense = torch.stack((torch.linspace(-1.0, 1.0, 201, dtype=t), torch.full((201,), 0.5, dtype=t)), dim=1)
    by_data = cells.bend_error(low, high, chain, [dense, dense])
    g = 0.01  # the slab 0..0.1 has κ = 3 (the narrow spacings), 0.1..0.4 κ = 1.5; J = 0.3 at every knot
    expected = [3.0 * g ** 2 / 8 + 0.3 * g / 4, 1.5 * g ** 2 / 8 + 0.3 * g / 4]
    torch.testing.assert_close(by_data, torch.tensor(expected, dtype=t))
    sparse = dense[::40]  # 0.4 apart: the gap meeting the slab is wider than the slab
    torch.testing.assert_close(cells.bend_error(low, high, chain, [sparse, dense[:0]]), spacing)
    lone = Features(chain.hinge_directions[:1], chain.hinge_knots[:1], *chain[2:4], chain.coefficients[:1])
    assert not cells.bend_error(low, high, lone, [dense, dense[:0]]).any()  # no bend, and no NaN from the empty leaf


def test_point_bounds_are_the_one_step_sets_of_a_point():
    """The held-out check's bounds at single inputs are what a one-step set from that point says."""
    system = SaturatedThrustPoint()
    reach = shared_fit(system, 500)
    x, _, u = system.offline_data(50, torch.Generator().manual_seed(3))
    sets, covered = reach.reach_covered(Zonotope.from_point(x), u.unsqueeze(1))
    z = torch.cat((x[:, reach.free_dims], u), dim=-1) / reach.input_scale
    prediction, errors, point_covered = point_bounds(reach._cells, reach._scaled_data, z)
    positions = torch.zeros_like(x)
    positions[:, list(system.translation_invariant_dims)] = x[:, list(system.translation_invariant_dims)]
    torch.testing.assert_close(sets.center[:, 0], positions + prediction + reach.noise_center)
    torch.testing.assert_close(sets.generators[:, 0].abs().sum(-1), errors + system.noise.generators.abs().sum(-1))
    assert torch.equal(point_covered, covered)


def test_local_sets_are_much_tighter_than_the_global_fit():
    """Width over sampled spread (geometric mean over dims, median over steps and plans).

    Measured with 2,000 steps: 5.3 (saturated point), 3.4 (double integrator), 7.3 (bicycle)
    against 28, 14 and 81 for the global fit; the limits leave room for other seeds.
    """
    for name, limit in (("saturated_point", 6.5), ("double_integrator", 4.5), ("bicycle", 9.0)):
        system = SYSTEMS[name]()
        local = sampled(system, shared_fit(system, 2000)).median_ratio
        global_ = sampled(system, fit(system, 2000, method="global")).median_ratio
        assert local < limit and local < global_ / 3, (name, local, global_)


def test_a_plan_leaving_the_data_is_not_covered():
    system = SaturatedThrustPoint()
    reach = shared_fit(system, 500)
    # the data span |v| <= 2 per axis, the leaves 25 % of that range beyond: 3.5 m/s is outside
    push = torch.tensor([1.0, 0.0], dtype=torch.float64).expand(1, 10, 2)
    _, covered = reach.reach_covered(Zonotope.from_point(torch.tensor([[0.0, 0.0, 3.5, 0.0]], dtype=torch.float64)),
                                     -push)
    assert not bool(covered)
    _, covered = reach.reach_covered(Zonotope.from_point(torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)),
                                     -push)
    assert bool(covered)


def test_local_model_is_the_default_and_survives_save_and_load(tmp_path):
    system = KinematicBicycle()
    reach = fit(system, 500, max_generators=16)
    assert reach.method == "local" and reach.plan_dependent
    reach.save(tmp_path / "reach.pt")
    loaded = DataDrivenReach.load(tmp_path / "reach.pt")
    x0, plans, _ = random_plans(system, n_plans=3)
    a, b = reach.reach(Zonotope.from_point(x0), plans), loaded.reach(Zonotope.from_point(x0), plans)
    assert loaded.method == "local"
    assert torch.equal(a.center, b.center) and torch.equal(a.generators, b.generators)
    assert a.generators.shape[-1] == 16


def test_sets_are_differentiable_in_the_plan():
    system = SaturatedThrustPoint()
    reach = shared_fit(system, 500)
    x0, plans, _ = random_plans(system, n_plans=2)
    plans.requires_grad_(True)
    reach.reach(Zonotope.from_point(x0), plans).center[..., :2].sum().backward()
    assert torch.isfinite(plans.grad).all() and plans.grad.abs().sum() > 0


def test_fit_rejects_bad_input_by_name():
    system = DoubleIntegrator()
    x, xp, u = system.offline_data(100, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="method"):
        DataDrivenReach.fit(x, xp, u, system.noise, method="nearest")
    bad = x.clone()
    bad[3, 2] = math.nan
    with pytest.raises(ValueError, match="x_minus"):
        DataDrivenReach.fit(bad, xp, u, system.noise)
    with pytest.raises(ValueError, match="noise"):
        DataDrivenReach.fit(x, xp, u, Zonotope(torch.zeros(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)))
    with pytest.raises(ValueError, match="at least"):
        DataDrivenReach.fit(x[:4], xp[:4], u[:4], system.noise)
    for folds, method in ((1, "local"), (5, "global")):
        with pytest.raises(ValueError, match="held_out_folds"):
            DataDrivenReach.fit(x, xp, u, system.noise, method=method, held_out_folds=folds)


@pytest.mark.parametrize("path", ["points", "grouped", "near"])
def test_leaf_distance_matches_a_brute_force_oracle(path):
    """``D_l`` = distance of the centre to leaf ``l``'s nearest data point + the box radius, per
    output in its weighted metric (checked against a loop over leaves and points), with and without
    the data grouped by leaf (:func:`leaf_layout`, the step's path); searching ``near`` leaves only,
    those are exact and the others upper bounds through their representative point."""
    system = SaturatedThrustPoint()
    reach = shared_fit(system, 500)
    cells, points = reach._cells, reach._scaled_data
    gen = torch.Generator().manual_seed(3)
    z = points[:7] + 0.2 * torch.randn(7, points.shape[1], generator=gen, dtype=torch.float64)
    radius = 0.05 * torch.rand(7, points.shape[1], generator=gen, dtype=torch.float64)
    layout = None if path == "points" else leaf_layout(cells, reach._weighted_data)
    n, n_leaves = cells.errors.shape
    near = torch.rand(7, n, n_leaves, generator=gen).argsort(-1)[..., :2] if path == "near" else None
    distance = leaf_distance(cells, points, z, radius, layout=layout, near=near)
    searched = torch.ones(7, n, n_leaves, dtype=torch.bool)
    if near is not None:
        searched = torch.zeros_like(searched).scatter_(-1, near, True)
    looser = 0
    for k in range(n):
        w = cells.weights[k]
        for leaf in range(n_leaves):
            mine = points[cells.members[k] == leaf]
            if len(mine) == 0:
                continue
            expected = ((z[:, None] - mine) * w).norm(dim=-1).amin(-1) + (radius * w).norm(dim=-1)
            exact = searched[:, k, leaf]
            assert torch.allclose(distance[exact, k, leaf], expected[exact]), (k, leaf)
            assert (distance[~exact, k, leaf] >= expected[~exact] - 1e-12).all(), (k, leaf)
            looser += int((distance[~exact, k, leaf] > expected[~exact] + 1e-9).sum())
    assert (looser > 0) == (path == "near")  # the bound of the leaves not searched is a bound, not exact


def test_the_error_budget_splits_each_steps_width_as_the_sets_grow():
    """:meth:`DataDrivenReach.error_budget` on the body-frame bicycle (hinges, products, rotation) and the world-frame
    saturated point: the radii are the sets' own, each is the width carried through the step plus the width it adds,
    and without a body frame the step adds its declared noise and exactly the four parts of its model error."""
    for system, options in ((KinematicBicycle(), {"body_frame": KinematicBicycle().body_frame}),
                            (SaturatedThrustPoint(), {})):
        reach = shared_fit(system, 500, max_generators=24, **options)
        x0, plans, _ = random_plans(system, n_plans=6)
        budget = reach.error_budget(Zonotope.from_point(x0), plans)
        sets, covered = reach.reach_covered(Zonotope.from_point(x0), plans)
        assert budget.batch_size == plans.shape[:-1] and budget["radius"].shape == sets.center.shape
        torch.testing.assert_close(budget["radius"], sets.radius(), rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(budget["carried"] + budget["added"], budget["radius"], rtol=1e-12, atol=1e-15)
        assert torch.equal(budget["covered"].all(-1), covered)
        assert (budget["added"] >= budget["noise"] - 1e-12).all()
        # a tensor of its own: torch's median over a dim of an expanded tensor returns garbage (torch 2.13, CPU)
        noise = reach.noise.generators.abs().sum(-1)
        assert torch.equal(budget["noise"].median(0).values, noise.expand(plans.shape[1], -1))
        parts = budget["leaf"] + budget["far"] + budget["between"] + budget["relaxation"]
        assert (parts > 0).all() and (budget["relaxation"] > 0).any() and (budget["between"] > 0).any()
        if reach.body_frame is None:
            torch.testing.assert_close(parts, budget["added"] - budget["noise"], rtol=1e-9, atol=1e-12)


def test_the_error_budget_says_when_a_set_leaves_the_data():
    """A start beyond the saturated point's data speeds: the step's error is mostly ``far`` (the Lipschitz term over
    the distance to the leaves' data) and the step is not covered; a start inside its data has no ``far`` at all.
    A global model has no budget to split."""
    system = SaturatedThrustPoint()
    reach = shared_fit(system, 500)
    inside = (system.state_low + system.state_high) / 2
    beyond = inside.clone()
    beyond[2:] = 1.5 * system.state_high[2:]
    plan = system.sample_actions(1, 3, generator=torch.Generator().manual_seed(0))[0]
    near, far = (reach.error_budget(Zonotope.from_point(x), plan) for x in (inside, beyond))
    assert near["covered"].all() and (near["far"][0] == 0).all()
    assert not far["covered"][0] and (far["far"][0] > far["leaf"][0]).all()
    with pytest.raises(ValueError, match="local model"):
        fit(system, 200, method="global").error_budget(Zonotope.from_point(inside), plan)
