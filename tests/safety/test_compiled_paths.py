"""The compiled paths of a local model's checks and adjustments give the eager ones' results, compiled before the first
control step."""
import copy

import pytest
import torch
from torch._dynamo.utils import counters

from torchrl_brsl.reach import hinges
from torchrl_brsl.safety import FacetQPAdjuster, PlanChecker, SafetyDecision, adjust, plan_check
from torchrl_brsl.safety.adjust import _leaf_check
from torchrl_brsl.sets import Zonotope

from safety_support import D, N_PLAN, bicycle_checker, obstacles_of, scene


@pytest.fixture(scope="module")
def program():
    """``(bicycle, eager, checker, adjuster, starts, scenes, rest)``: the bicycle's local model eagerly and compiled
    (``aot_eager``), its compiled checks and facet QP prepared for 8 envs' scenes (``prepare_checks`` and
    ``prepare_obstacles``, which the layer calls), slow, heading along x, a box ahead at 0.2-0.6 m (speeding up
    collides), and full braking as every env's reference. The model is the fit of 8 hinges over 25 knots without
    the hinges halfway between fitted ones, on which the scenes were chosen (the adjuster's steps stop between the
    reference and the proposal, at envs' different halvings)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(hinges, "MAX_HINGES", 8)
        patch.setattr(hinges, "KNOTS", 25)
        patch.setattr(hinges, "midpoint_hinges", lambda directions, knots, signs: (directions[:0], knots[:0]))
        bicycle, eager = bicycle_checker(policy=False)
    reach = copy.deepcopy(eager.reach).compile_steps(backend="aot_eager")
    checker = PlanChecker(reach, eager.failsafe, eager.horizon, stop_dims=(3,), stop_slack=0.1,
                          action_low=bicycle.action_low, action_high=bicycle.action_high)
    n = 8
    starts = torch.tensor([0.0, 0.0, 0.0, 0.1], dtype=D).expand(n, 4)
    centers = torch.stack((torch.linspace(0.2, 0.6, n, dtype=D), torch.linspace(-0.2, 0.2, n, dtype=D)), -1)
    scenes = obstacles_of(centers.unsqueeze(1), torch.tensor([[0.05, 0.0], [0.0, 0.1]], dtype=D).expand(n, 1, 2, 2),
                          torch.ones(n, 1, dtype=torch.bool))
    rest = torch.tensor([-1.0, 0.0], dtype=D).expand(n, eager.horizon, 2).clone()
    adjuster = FacetQPAdjuster()
    checker.prepare_checks(scenes)  # the shapes the layer's env gives
    frames = counters["frames"]["ok"]
    adjuster.prepare_obstacles(checker, scenes)  # one action and N_PLAN (the checker's plan steps)
    assert counters["frames"]["ok"] > frames
    return bicycle, eager, checker, adjuster, starts, scenes, rest


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
def test_the_compiled_program_is_the_eager_one(program, monkeypatch):
    """On a compiled local model the facet QP sets up and solves its program as one compiled graph (exactly for one
    action, by dual iterations for five), prepared for the obstacles' shapes and padded to ``LOCKED_ROWS`` rows an
    env: the eager adjuster's plans to rounding, at one env and at eight. An env that needs more rows is solved
    eagerly (the teeth: with no row allowed, the compiled program gives up, and the plans stay the same)."""
    bicycle, eager, checker, adjuster, starts, scenes, rest = program
    n, solved, kept = starts.shape[0], [], adjust.LOCKED_ROWS
    real = FacetQPAdjuster._compiled_step
    monkeypatch.setattr(FacetQPAdjuster, "_compiled_step", lambda *args: solved.append(real(*args)) or solved[-1])
    for steps in (1, N_PLAN):
        proposals = torch.tensor([[[1.0, 0.3]]], dtype=D).expand(n, steps, 2)
        assert not eager.evaluate(starts, proposals, scenes).safe.any()
        for envs, rows in ((slice(2, 3), kept), (slice(None), kept), (slice(None), 0)):
            monkeypatch.setattr(adjust, "LOCKED_ROWS", rows)
            x0, plan, reference, obstacles = (value[envs] for value in (starts, proposals, rest, scenes))
            frames, solved[:] = counters["frames"]["ok"], []
            got = adjuster(checker, x0, plan, obstacles, reference=reference)
            want = FacetQPAdjuster()(eager, x0, plan, obstacles, reference=reference)
            torch.testing.assert_close(got.plan, want.plan, rtol=0, atol=1e-9)
            assert torch.equal(got.evaluation.safe, want.evaluation.safe)
            assert (solved[0] is None) == (rows == 0)
            if rows > 1:
                assert counters["frames"]["ok"] == frames  # prepared: nothing compiled at a control step
            moved = ((got.plan != plan) & (got.plan != reference[:, :steps])).flatten(1).all(-1)
            assert moved.any()  # a step between the reference and the proposal was taken


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
def test_a_paired_step_checks_the_programs_first_candidates_in_its_graph(program, monkeypatch):
    """After a step that adjusted every env, a compiled local model's decision checks the proposals and the
    references, solves the facet QP from each reference and checks its first halvings in one graph
    (:meth:`FacetQPAdjuster._ahead`, prepared by ``prepare_obstacles`` for the scenes' 8 envs): each candidate's
    evaluation is the checker's of the same plan, and the decision is the one made without pairing (its own program
    and checks), at eight envs and at one (a graph of its own), where the envs' halvings and outcomes differ."""
    bicycle, eager, checker, adjuster, starts, scenes, rest = program
    decide, made = SafetyDecision(checker, checker.failsafe, adjuster), []
    real = FacetQPAdjuster._ahead
    monkeypatch.setattr(FacetQPAdjuster, "_ahead", lambda *args: made.append(real(*args)) or made[-1])
    for steps in (1, N_PLAN):
        proposals = torch.tensor([[[1.0, 0.3]]], dtype=D).repeat(starts.shape[0], steps, 1)
        proposals[1::2] = torch.tensor([-0.8, -0.3], dtype=D)  # near the reference
        for envs in (slice(2, 3), slice(None)):
            x0, plan, safe_plan, obstacles = (value[envs] for value in (starts, proposals, rest, scenes))
            held = torch.zeros(x0.shape[0], dtype=torch.long)
            decide._pair, made[:], frames = True, [], counters["frames"]["ok"]
            together = decide(x0, plan, safe_plan, held, obstacles)
            assert len(made) == 1 and made[0][3] is not None  # the program's step and candidates came ahead
            if x0.shape[0] > 1:
                assert counters["frames"]["ok"] == frames  # prepared: nothing compiled at a control step
            step, candidates = made[0][3:]
            halving = 0.5 ** torch.arange(candidates.safe.shape[1], dtype=D)
            tried = safe_plan[:, :steps] + halving.view(-1, 1, 1, 1) * step.view(-1, steps, 2)  # [A, B, P, m]
            want = checker.evaluate(x0.repeat(len(halving), 1), tried.flatten(0, 1), obstacles.repeat(len(halving)))
            for got, expected in zip(candidates, want):  # [B, A, ...] env by env
                torch.testing.assert_close(got.transpose(0, 1).flatten(0, 1), expected, rtol=0, atol=1e-9)
            decide._pair = False
            alone = decide(x0, plan, safe_plan, held, obstacles)
            assert len(made) == 1
            for got, expected in zip(together[:3], alone[:3]):
                torch.testing.assert_close(got, expected, rtol=0, atol=1e-9)
            for name, value in alone.diagnostics.items():
                torch.testing.assert_close(together.diagnostics[name], value, rtol=0, atol=1e-9, msg=name)
        assert together.diagnostics["intervened"].any()
        assert together.diagnostics["adjust_iterations"].unique().numel() > 1  # the envs' outcomes differ


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
def test_the_compiled_linearisation_along_a_braking_policy_is_prepared_with_the_checks():
    """With a compiled local model and a braking policy, the adjusters' linearisation runs in the plan's compiled loop
    with the check, with the eager values, and its graph is compiled with the checks
    (:meth:`PlanChecker.prepare_checks`, which the layer calls), not at a control step. The paired check that solves
    the facet QP and checks its first candidates in the same graph (:meth:`FacetQPAdjuster._ahead`) checks the
    policy's tail of each candidate as the checker does."""
    bicycle, eager = bicycle_checker(policy=True)
    reach = copy.deepcopy(eager.reach).compile_steps(backend="aot_eager")
    checker = PlanChecker(reach, eager.failsafe, eager.horizon, stop_dims=(3,), stop_slack=0.1,
                          action_low=bicycle.action_low, action_high=bicycle.action_high)
    SafetyDecision(checker, checker.failsafe, FacetQPAdjuster())
    checker.prepare_checks(obstacles_of(*scene(2, 4)[2:]))
    frames = counters["frames"]["ok"]
    gen = torch.Generator().manual_seed(2)
    for n_envs, steps in ((3, N_PLAN), (1, 1)):
        x0 = bicycle.sample_states(n_envs, gen) * 0.3
        plan = bicycle.sample_actions(n_envs, steps, generator=gen) * 0.5
        obstacles = obstacles_of(*scene(n_envs, 4, seed=n_envs)[2:])
        got, expected = _leaf_check(checker, x0, plan, obstacles), _leaf_check(eager, x0, plan, obstacles)
        for new, old in zip((*got[0], *got[1], got[2]), (*expected[0], *expected[1], expected[2])):
            torch.testing.assert_close(new, old, rtol=1e-9, atol=1e-12)
    assert counters["frames"]["ok"] == frames  # compiled with the checks
    # the paired check with the program's candidates in one graph: the policy's tail as each plan's own loop takes it
    starts, plans, paired = torch.cat((x0, x0)), torch.cat((plan, torch.zeros_like(plan))), obstacles.repeat(2)
    evaluation, gauge, jacobian, step, candidates = FacetQPAdjuster()._ahead(checker, starts, plans, paired)
    want = _leaf_check(checker, starts, plans, paired)
    for new, old in zip((*evaluation, *gauge, jacobian), (*want[0], *want[1], want[2])):
        torch.testing.assert_close(new, old, rtol=1e-9, atol=1e-12)
    halving = 0.5 ** torch.arange(candidates.safe.shape[1], dtype=D)
    tried = (halving.view(-1, 1, 1, 1) * step.view_as(plan)).flatten(0, 1)  # from the zero plan: [A B, P, m]
    want = checker.evaluate(x0.repeat(len(halving), 1), tried, obstacles.repeat(len(halving)))
    for new, old in zip(candidates, want):
        torch.testing.assert_close(new.transpose(0, 1).flatten(0, 1), old, rtol=1e-9, atol=1e-12)


def test_pairs_the_loops_check_cannot_certify_are_checked_eagerly(monkeypatch):
    """Where the check in the plan's compiled loop cannot certify every pair as full-dimensional, the plan is checked
    eagerly from the loop's sets, as the eager checker checks them, without running the compiled gauge again."""
    bicycle, eager = bicycle_checker(policy=False)
    reach = copy.deepcopy(eager.reach).compile_steps(backend="aot_eager")
    checker = PlanChecker(reach, eager.failsafe, eager.horizon, stop_dims=(3,), stop_slack=0.1,
                          action_low=bicycle.action_low, action_high=bicycle.action_high)
    real = plan_check._checked_sets

    def uncertified(*args):
        *checked, full = real(*args)
        return (*checked, torch.zeros_like(full))

    compiled = []
    monkeypatch.setattr(plan_check, "_checked_sets", uncertified)
    monkeypatch.setattr(checker, "_compiled", lambda function, *args, **kwargs: compiled.append(function))
    gen = torch.Generator().manual_seed(5)
    x0, plan = bicycle.sample_states(3, gen) * 0.3, bicycle.sample_actions(3, N_PLAN, generator=gen) * 0.5
    obstacles = obstacles_of(*scene()[2:])
    got, got_gauge = checker.evaluate_with_gauge(x0, plan, obstacles)
    want, want_gauge = eager.evaluate_with_gauge(x0, plan, obstacles, rollout=checker.rollout_sets(x0, plan))
    assert bool(((want.values > 0) & torch.isfinite(want.values)).any())
    for new, old in zip((*got, *got_gauge), (*want, *want_gauge)):
        torch.testing.assert_close(new, old, rtol=1e-12, atol=1e-12)
    assert not compiled  # the loop's gauge said no: not asked again


@pytest.mark.parametrize("dims", [2, 3])
def test_compiled_plan_gauge_equals_the_eager_check(dims):
    """The closed-form check of plan-dependent sets compiled as one graph (inductor, no graph break) gives the
    eager check's values, attaining facets and weights, and certifies every pair but a flat one: a set flat in the
    obstacle space but for its small floor box beside a segment along the same line, which the compiled graph
    cannot certify without a branch on values (the checker then checks eagerly, widening it)."""
    from torchrl_brsl._compiling import inductor_kwargs, own_code
    from torchrl_brsl.collision import pair_facets, pair_gauge
    from torchrl_brsl.safety.plan_check import _plan_gauge, _projected_generators

    gen = torch.Generator().manual_seed(dims)
    n, index, width = 5, slice(1, 1 + dims), 4 * dims
    generators = torch.randn(3, 7, n, 12, generator=gen, dtype=D) * 0.1
    generators[0, 0, 1:1 + dims] = 0.0
    generators[0, 0, 1, 0] = 50.0  # one long generator: the pair's own minors hardly clear the floor
    centers = torch.randn(3, 7, n, generator=gen, dtype=D)
    obstacle_centers = torch.randn(3, 4, dims, generator=gen, dtype=D)
    obstacle_generators = torch.randn(3, 4, dims, 5, generator=gen, dtype=D) * 0.3
    obstacle_generators[0, 0] = 0.0
    obstacle_generators[0, 0, 0, 0] = 2.0  # a segment along the set's long generator: a flat pair
    compiled = torch.compile(own_code(_plan_gauge), **inductor_kwargs({}, cpp_wrapper=True))
    breaks = counters["graph_break"].copy()
    with torch.no_grad():
        *fused, full = compiled(generators, centers, obstacle_centers, obstacle_generators, index, width)
    assert counters["graph_break"] == breaks
    flat = torch.zeros_like(full)
    flat[0, 0, 0] = True
    assert torch.equal(full, ~flat)
    projected = _projected_generators(generators, index, width).unsqueeze(-3)
    facets = pair_facets(projected, obstacle_generators.unsqueeze(-4), widen=True)
    offsets = obstacle_centers.unsqueeze(-3) - centers[..., index].unsqueeze(-2)
    for got, want in zip(fused, pair_gauge(offsets, facets)):
        torch.testing.assert_close(got[full], want[full], rtol=1e-12, atol=1e-12)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
def test_compiled_checker_checks_a_local_models_plans_as_the_eager_one():
    """A compiled local model's checker runs its closed-form checks as one graph, compiled by ``prepare_checks``
    before the first check: the same verdicts, values and gauges as the eager checker's, at one env (padded to
    two) and at three; with gradients wanted it checks eagerly, differentiable. Checked in the plan's own compiled
    loop (no ``rollout`` given), the same as after it."""
    bicycle, eager = bicycle_checker(policy=False)
    reach = copy.deepcopy(eager.reach).compile_steps(backend="aot_eager")
    checker = PlanChecker(reach, eager.failsafe, eager.horizon, stop_dims=(3,), stop_slack=0.1,
                          action_low=bicycle.action_low, action_high=bicycle.action_high)
    gen, frames = torch.Generator().manual_seed(3), counters["frames"]["ok"]
    checker.prepare_checks(obstacles_of(*scene(2, 6)[2:]))
    assert counters["frames"]["ok"] > frames  # compiled now, for 6 obstacles of 3 generators
    frames = counters["frames"]["ok"]
    for n_envs in (1, 3):
        x0, plan = bicycle.sample_states(n_envs, gen) * 0.3, bicycle.sample_actions(n_envs, N_PLAN, generator=gen)
        obstacles = obstacles_of(*scene(n_envs, 6, seed=n_envs)[2:])
        rollout = eager.rollout_sets(x0, plan)
        got, got_gauge = checker.evaluate_with_gauge(x0, plan, obstacles, rollout=rollout)
        want, want_gauge = eager.evaluate_with_gauge(x0, plan, obstacles, rollout=rollout)
        assert bool(((want.values > 0) & torch.isfinite(want.values)).any())
        for new, old in zip((*got, *got_gauge), (*want, *want_gauge)):
            torch.testing.assert_close(new, old, rtol=1e-12, atol=1e-12)
        fused, fused_gauge = checker.evaluate_with_gauge(x0, plan, obstacles)
        after, after_gauge = checker.evaluate_with_gauge(x0, plan, obstacles, rollout=checker.rollout_sets(x0, plan))
        for new, old in zip((*fused, *fused_gauge), (*after, *after_gauge)):
            torch.testing.assert_close(new, old, rtol=1e-12, atol=1e-12)
    assert counters["frames"]["ok"] == frames  # nothing compiled at a check
    centers = rollout[1].center.clone().requires_grad_(True)
    values = checker.evaluate_with_gauge(x0, plan, obstacles, rollout=(rollout[0], Zonotope(
        centers, rollout[1].generators), rollout[2]))[0].values
    torch.nan_to_num(values, posinf=0.0).sum().backward()
    assert centers.grad is not None and bool(centers.grad.abs().sum() > 0)
