"""The affine fast paths of plan verification and adjustment agree with the general ones."""
import copy

import numpy as np
import pytest
import torch
from scipy.optimize import nnls

from torchrl_brsl.collision import ZonotopeCollisionChecker
from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import FacetQPAdjuster, Failsafe, GradientAdjuster, PlanChecker
from torchrl_brsl.safety.adjust import (_centre_jacobian, _closed_form_gradient, _leaf_check, _project_polytope,
                                        _project_small)
from torchrl_brsl.sets import Zonotope

from safety_support import (N_BRK, N_PLAN, D, assert_closed_form_matches_autograd, bicycle_checker, obstacles_of,
                             scene)


@pytest.fixture(scope="module")
def reach():
    system = DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    return DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24,
                               method="global")  # the fast paths are those of the global model


def open_loop_checker(reach, hold=(0.0, 0.0), stop=0.5, **kwargs):
    horizon = N_PLAN + N_BRK
    radius = reach.error_generators_sequence(horizon)[-1, 2:].abs().sum(-1)
    return PlanChecker(reach, Failsafe(torch.tensor(hold, dtype=D), N_BRK), horizon, stop_dims=(2, 3),
                       stop_tolerance=(radius + stop).tolist(), action_low=-torch.ones(2, dtype=D),
                       action_high=torch.ones(2, dtype=D), **kwargs)


def reference_evaluation(checker, x0, plan, centers, generators, mask):
    """The check written out: explicit action sequence, recursion-free centres, per-pair values."""
    hold = checker.failsafe.hold_action.to(D).expand(plan.shape[0], checker.horizon - plan.shape[1], 2)
    actions = torch.cat((plan, hold), dim=1)
    c = checker.reach.reach_centers(x0, actions)
    pairs = ZonotopeCollisionChecker(checker.set_generators.unsqueeze(-3).unsqueeze(0), generators.unsqueeze(-4))
    values = pairs.value(c[..., checker.position_dims].unsqueeze(-2), centers.unsqueeze(-3))
    values = torch.where(mask.unsqueeze(-2), values, torch.full_like(values, float("inf")))
    stop = (c[:, -1, checker.stop_dims].abs() + checker.stop_radius - checker.stop_tolerance).amax(-1)
    safe = (values > 1 + checker.margin).flatten(1).all(-1) & (stop <= 0)
    return actions, c, values, stop, safe


@pytest.mark.parametrize("plan_steps", [1, 3, N_PLAN])
def test_affine_rollout_matches_the_reach_model(reach, plan_steps):
    checker = open_loop_checker(reach, hold=(0.3, -0.2))
    x0, plan, *_ = scene()
    plan = plan[:, :plan_steps]
    actions, centers = checker.rollout(x0, plan)
    assert actions.shape == (3, N_PLAN + N_BRK, 2)
    torch.testing.assert_close(actions[:, :plan_steps], plan, rtol=0, atol=0)
    torch.testing.assert_close(actions[:, plan_steps:], torch.tensor([0.3, -0.2], dtype=D).expand_as(
        actions[:, plan_steps:]), rtol=0, atol=0)
    torch.testing.assert_close(centers, reach.reach_centers(x0, actions), rtol=0, atol=1e-9)
    # differentiable like the general path
    plan = plan.clone().requires_grad_(True)
    checker.rollout(x0, plan)[1].sum().backward()
    assert plan.grad is not None and torch.isfinite(plan.grad).all()


def test_fast_evaluation_matches_the_explicit_check(reach):
    checker = open_loop_checker(reach)
    for seed in range(4):
        x0, plan, centers, generators, mask = scene(seed=seed)
        fast = checker.evaluate(x0, plan, obstacles_of(centers, generators, mask))
        actions, c, values, stop, safe = reference_evaluation(checker, x0, plan, centers, generators, mask)
        torch.testing.assert_close(fast.actions, actions, rtol=0, atol=0)
        torch.testing.assert_close(fast.centers, c, rtol=0, atol=1e-9)
        torch.testing.assert_close(fast.values, values, rtol=0, atol=1e-9)
        torch.testing.assert_close(fast.stop_excess, stop, rtol=0, atol=1e-9)
        assert torch.equal(fast.safe, safe)


def test_non_finite_or_overflowing_offsets_count_as_colliding(reach):
    checker = open_loop_checker(reach)
    x0, plan, centers, generators, mask = scene(n_envs=2)
    mask[:] = True
    centers = centers.clone()
    centers[0, 0, 0] = float("nan")
    centers[1, 0, 0] = 1e308  # finite, but the products overflow
    centers[1, 0, 1] = -1e308
    evaluation = checker.evaluate(x0, plan, obstacles_of(centers, generators, mask))
    assert torch.equal(evaluation.values[:, :, 0], torch.zeros(2, N_PLAN + N_BRK, dtype=D))
    assert not evaluation.safe.any()


def test_subset_checker_matches_the_full_batch(reach):
    checker = open_loop_checker(reach)
    x0, plan, centers, generators, mask = scene(n_envs=5)
    full = checker.evaluate(x0, plan, obstacles_of(centers, generators, mask))
    idx = torch.tensor([1, 4])
    sub = checker.subset(idx)
    part = sub.evaluate(x0[idx], plan[idx], obstacles_of(centers[idx], generators[idx], mask[idx]))
    for a, b in zip(part, full):  # (rounding may differ with the batch size of a product)
        torch.testing.assert_close(a, b[idx], rtol=0, atol=1e-12)
    assert sub._checker is not checker._checker and checker._obstacle_generators.shape[0] == 5


def test_affine_jacobians_match_finite_differences(reach):
    checker = open_loop_checker(reach, hold=(0.1, 0.0))
    x0, plan, *_ = scene()
    affine = checker.affine(N_PLAN)
    jacobian = _centre_jacobian(checker, x0, plan)  # [B, T, n, P, m]
    pos = jacobian[:, :, checker.position_dims].flatten(-2)
    stop = jacobian[:, -1, checker.stop_dims].flatten(-2)
    torch.testing.assert_close(pos, affine.position_jacobian.expand_as(pos), rtol=0, atol=1e-7)
    torch.testing.assert_close(stop, affine.stop_jacobian.expand_as(stop), rtol=0, atol=1e-7)


@pytest.mark.parametrize("iterations", [1, 4, 15])
def test_analytic_gradient_adjuster_matches_autograd(reach, iterations):
    checker = open_loop_checker(reach, stop=0.3)
    x0 = torch.tensor([[0.0, 0.0, 0.6, 0.05], [0.0, 0.1, 0.4, -0.1], [0.2, 0.0, 0.0, 0.0]], dtype=D)
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN, [[0.8, 0.3]] * N_PLAN, [[-0.2, 0.1]] * N_PLAN], dtype=D)
    centers = torch.tensor([[[1.3, 0.0], [0.5, 0.9]]] * 3, dtype=D)
    generators = torch.tensor([[[[0.2, 0.0, 0.05], [0.0, 0.35, 0.05]]] * 2] * 3, dtype=D)
    mask = torch.tensor([[True, True], [True, False], [True, True]])
    assert_closed_form_matches_autograd(checker, x0, plan, centers, generators, mask, iterations)


def test_facet_qp_accepts_only_verified_plans_on_the_fast_path(reach):
    checker = open_loop_checker(reach, stop=0.3)
    x0 = torch.tensor([[0.0, 0.0, 0.5, 0.0], [0.0, 0.0, 0.5, 0.0]], dtype=D)
    centers = torch.tensor([[[1.4, 0.0]], [[1.4, 0.3]]], dtype=D)
    generators = torch.tensor([[[[0.2, 0.0], [0.0, 0.35]]]] * 2, dtype=D)
    mask = torch.ones(2, 1, dtype=torch.bool)
    # reference: decelerate to a stop (safe), proposal: full throttle (unsafe)
    reference = torch.tensor([[[-1.0, 0.0]] * 5 + [[0.0, 0.0]] * 8] * 2, dtype=D)
    assert checker.evaluate(x0, reference[:, :N_PLAN], obstacles_of(centers, generators, mask)).safe.all()
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN] * 2, dtype=D)
    assert not checker.evaluate(x0, plan, obstacles_of(centers, generators, mask)).safe.any()
    result = FacetQPAdjuster()(checker, x0, plan, obstacles_of(centers, generators, mask), reference=reference)
    again = checker.evaluate(x0, result.plan, obstacles_of(centers, generators, mask))
    assert torch.equal(again.safe, result.evaluation.safe) and result.evaluation.safe.all()
    torch.testing.assert_close(again.values, result.evaluation.values, rtol=0, atol=0)
    assert torch.all(result.plan.abs() <= 1)
    assert not torch.equal(result.plan, reference[:, :N_PLAN])  # it moved towards the proposal


def test_projection_reaches_the_exact_quadratic_program():
    g = torch.Generator().manual_seed(3)
    for _ in range(5):
        n, rows = 6, 9
        A = torch.randn(1, rows, n, generator=g, dtype=D)
        b = torch.rand(1, rows, generator=g, dtype=D)
        target = torch.randn(1, n, generator=g, dtype=D) * 3
        z = _project_polytope(A, b, target, 3000)
        torch.testing.assert_close(z[0], _least_distance(A[0], b[0], target[0]), rtol=0, atol=1e-6)


def _least_distance(A: torch.Tensor, b: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``argmin ||z - target||`` s.t. ``A z <= b`` (one program, ``[C, N]``, ``[C]``, ``[N]``) by least-distance
    programming via NNLS (Lawson and Hanson): the slow, exact oracle."""
    An, bn, tn = A.numpy(), b.numpy(), target.numpy()
    E = np.vstack(((-An).T, (An @ tn - bn)[None]))
    f = np.zeros(A.shape[1] + 1)
    f[-1] = 1
    u, _ = nnls(E, f, maxiter=10_000)
    r = E @ u - f
    return torch.from_numpy(tn - r[:-1] / r[-1])


@pytest.mark.parametrize("n_vars", [1, 2])
def test_the_small_projection_is_the_exact_quadratic_program(n_vars):
    """Random polygons (intervals) around the reference ``z = 0`` with zero rows as padding, a batch of 400: the exact
    solver against the oracle; the batch holds optima inside, on an edge and (two variables) at a vertex, so a solver
    missing any kind of candidate fails."""
    g = torch.Generator().manual_seed(n_vars)
    A = torch.randn(400, 9, n_vars, generator=g, dtype=D)
    A[:, -2:] = 0.0  # padding rows
    b = torch.rand(400, 9, generator=g, dtype=D) * 0.5
    target = torch.randn(400, n_vars, generator=g, dtype=D) * 2
    z = _project_small(A, b, target)
    exact = torch.stack([_least_distance(A[k], b[k], target[k]) for k in range(400)])
    torch.testing.assert_close(z, exact, rtol=0, atol=1e-9)
    active = ((A @ z.unsqueeze(-1)).squeeze(-1) - b).abs() < 1e-9
    kinds = set(active.sum(-1).clamp_max(2).tolist())
    assert kinds == ({0, 1, 2} if n_vars == 2 else {0, 1}), kinds


@pytest.mark.parametrize("adjuster", [FacetQPAdjuster(), GradientAdjuster(max_iterations=20, time_budget=None)])
def test_layer_batch_with_some_envs_adjusted_matches_single_env_calls(reach, adjuster):
    from torchrl_brsl.safety import BRSLSafetyLayer

    horizon = N_PLAN + N_BRK
    radius = reach.error_generators_sequence(horizon)[-1, 2:].abs().sum(-1)
    layer = BRSLSafetyLayer(reach, Failsafe(torch.zeros(2, dtype=D), N_BRK), N_PLAN, stop_dims=(2, 3),
                            stop_tolerance=(radius + 0.3).tolist(), action_low=-torch.ones(2),
                            action_high=torch.ones(2), adjuster=adjuster)
    x0 = torch.tensor([[0.0, 0.0, 0.5, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.5, 0.0]], dtype=D)
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN, [[0.0, 0.0]] * N_PLAN, [[0.9, 0.1]] * N_PLAN], dtype=D)
    safe_plan = torch.tensor([[[-1.0, 0.0]] * 5 + [[0.0, 0.0]] * 8] * 3, dtype=D)
    centers = torch.tensor([[[1.4, 0.0]], [[1.4, 0.0]], [[1.4, 0.2]]], dtype=D)
    generators = torch.tensor([[[[0.2, 0.0], [0.0, 0.35]]]] * 3, dtype=D)
    mask = torch.ones(3, 1, dtype=torch.bool)
    steps = torch.full((3,), 5, dtype=torch.long)
    batched = layer.decision(x0, plan, safe_plan, steps, obstacles_of(centers, generators, mask), 0.0)
    assert batched[3]["intervened"].tolist() == [True, False, True]
    for i in range(3):
        single = layer.decision(x0[i:i + 1], plan[i:i + 1], safe_plan[i:i + 1], steps[i:i + 1],
                                obstacles_of(centers[i:i + 1], generators[i:i + 1], mask[i:i + 1]), 0.0)
        for k in range(3):
            torch.testing.assert_close(single[k][0], batched[k][i], rtol=0, atol=1e-9)
        for name, value in single[3].items():
            torch.testing.assert_close(value[0], batched[3][name][i], rtol=0, atol=1e-9)


@pytest.mark.parametrize("policy", [False, True])
def test_leaf_jacobian_of_a_local_model_matches_finite_differences(policy):
    """The facet QP linearises a local model along the reference's own sets (one rollout): on the drag-free
    range of a double integrator it is the finite-difference Jacobian, but where a set straddles a hinge's knot
    (finite differences also see the relaxation's slope move with the set, which the leaf Jacobian holds fixed:
    up to 1.3e-4 in 3 of 4,160 entries, 51 beyond 1e-5, where the probe error picks three hinges for the x velocity;
    4e-10 where it picked one, before the leaves' quadratic slope floor); on the bicycle's body frame exact at the
    first step (a point set) and a linearisation beyond."""
    system = DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24)
    failsafe = Failsafe(torch.zeros(2, dtype=D), N_BRK, system.braking if policy else None)
    checker = PlanChecker(reach, failsafe, N_PLAN + N_BRK, stop_dims=(2, 3), stop_slack=0.1,
                          action_low=system.action_low, action_high=system.action_high)
    gen = torch.Generator().manual_seed(1)
    x0, plan = system.sample_states(8, gen) * 0.3, system.sample_actions(8, N_PLAN, generator=gen) * 0.5
    obstacles = obstacles_of(*scene(8)[2:])
    torch.testing.assert_close(_leaf_check(checker, x0, plan, obstacles)[-1], _centre_jacobian(checker, x0, plan),
                               rtol=1e-4, atol=2e-4)
    bicycle, checker = bicycle_checker(policy)
    x0, plan = bicycle.sample_states(8, gen) * 0.3, bicycle.sample_actions(8, N_PLAN, generator=gen) * 0.5
    torch.testing.assert_close(_leaf_check(checker, x0, plan, obstacles)[-1][:, 0],
                               _centre_jacobian(checker, x0, plan)[:, 0], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("policy", [False, True])
def test_the_gradient_on_a_local_model_chains_the_loss_through_the_leaf_jacobian(policy):
    """The projected gradient's closed form on a local model is autograd's gradient of its loss in the centres (the
    sets' generators held fixed), chained with the centres' Jacobian along the plan's sets (:func:`_leaf_check`,
    which the tests above check against finite differences): one rollout with tangents per iteration."""
    bicycle, checker = bicycle_checker(policy)
    gen = torch.Generator().manual_seed(4)
    x0, plan = bicycle.sample_states(3, gen) * 0.3, bicycle.sample_actions(3, N_PLAN, generator=gen) * 0.5
    obstacles, threshold = obstacles_of(*scene()[2:]), 50.0  # every finite value below it: a gradient from each
    with torch.no_grad():
        evaluation, gauge, jacobian = _leaf_check(checker, x0, plan, obstacles)
        actions, sets, covered = checker.rollout_sets(x0, plan)
    jacobian = jacobian.flatten(-2)  # [B, T, n, N]
    closed = _closed_form_gradient(checker, evaluation, gauge, jacobian[:, :, checker.position_dims],
                                   jacobian[:, -1, checker.stop_dims], threshold)
    centers = sets.center.clone().requires_grad_(True)
    evaluated = checker.evaluate_with_gauge(x0, plan, obstacles, rollout=(actions, Zonotope(centers, sets.generators),
                                                                          covered))[0]
    values, stop_excess = evaluated.values, evaluated.stop_excess
    assert bool(((values < threshold) & (values > 0)).any()) and (policy or bool((stop_excess > 0).any()))
    loss = torch.relu(threshold - torch.nan_to_num(values, posinf=1e6)).sum((-1, -2)) + torch.relu(stop_excess)
    (in_centres,) = torch.autograd.grad(loss.sum(), centers)  # [B, T, n]
    torch.testing.assert_close(closed, torch.einsum("btn,btnk->bk", in_centres, jacobian), rtol=1e-9, atol=1e-12)
    adjuster = GradientAdjuster(max_iterations=1, target_margin=threshold - 1, time_budget=None)
    scale = checker.action_high - checker.action_low
    expected = adjuster._step(plan, closed.view_as(plan), ~evaluation.safe, checker.action_low, checker.action_high,
                              scale)
    assert not evaluation.safe.all()  # the adjuster takes this gradient's step
    torch.testing.assert_close(adjuster(checker, x0, plan, obstacles).plan, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("policy", [False, True])
@pytest.mark.parametrize("compiled", [False, True])
def test_the_leaf_check_is_the_checkers_evaluation(policy, compiled):
    """The adjusters take the reference's check from the rollout that linearises it: the same evaluation and gauge
    as :meth:`PlanChecker.evaluate_with_gauge` without tangents: bit for bit eagerly, to rounding compiled (both in
    the plan's loop, graphs of their own); ``tangents`` with a ``rollout`` of the caller's are refused."""
    bicycle, checker = bicycle_checker(policy)
    if compiled:
        checker = PlanChecker(copy.deepcopy(checker.reach).compile_steps(backend="aot_eager"), checker.failsafe,
                              checker.horizon, stop_dims=(3,), stop_slack=0.1, action_low=bicycle.action_low,
                              action_high=bicycle.action_high)
    gen = torch.Generator().manual_seed(1)
    x0, plan = bicycle.sample_states(3, gen) * 0.3, bicycle.sample_actions(3, N_PLAN, generator=gen) * 0.5
    obstacles = obstacles_of(*scene()[2:])
    evaluation, gauge, _ = _leaf_check(checker, x0, plan, obstacles)
    expected = checker.evaluate_with_gauge(x0, plan, obstacles)
    for new, old in zip((*evaluation, *gauge), (*expected[0], *expected[1])):
        torch.testing.assert_close(new, old, rtol=1e-12 if compiled else 0, atol=1e-12 if compiled else 0)
    with pytest.raises(ValueError, match="tangents.*own rollout"):
        checker.evaluate_with_gauge(x0, plan, obstacles, rollout=checker.rollout_sets(x0, plan),
                                    tangents=(x0.new_zeros(3, 4, 1), plan.new_zeros(*plan.shape, 1)))


def test_facet_qp_moves_along_a_constraint_the_reference_already_sits_on(reach):
    """At rest within the target margin of a wall (no room to approach it: ``A z <= 0`` on its rows), a
    proposal into and along the wall is projected to the motion along it; the dual's few iterations leave
    that row slightly violated, and without polishing the pull-back scaled the whole step to zero."""
    checker = open_loop_checker(reach, stop=0.3)
    x0 = torch.zeros(1, 4, dtype=D)
    reference = torch.zeros(1, N_PLAN + N_BRK, 2, dtype=D)
    generators = torch.tensor([[[[3.0, 0.0], [0.0, 0.1]]]], dtype=D)  # a long wall along x

    def wall(y):
        return obstacles_of(torch.tensor([[[0.0, y]]], dtype=D), generators, torch.ones(1, 1, dtype=torch.bool))

    low, high = 0.0, 2.0  # place it so that resting there has the value 1.03 (target margin 0.05)
    for _ in range(50):
        middle = (low + high) / 2
        low, high = (middle, high) if checker.evaluate(x0, reference[:, :N_PLAN], wall(middle)).values.min() < 1.03 \
            else (low, middle)
    obstacles = wall(high)
    plan = torch.tensor([[[1.0, 1.0]] * N_PLAN], dtype=D)  # into and along the wall
    assert not checker.evaluate(x0, plan, obstacles).safe.any()
    result = FacetQPAdjuster()(checker, x0, plan, obstacles, reference=reference)
    assert result.evaluation.safe.all() and checker.evaluate(x0, result.plan, obstacles).safe.all()
    assert result.plan[0, 0, 0] > 0.5 and result.plan[0, 0, 1] <= 0  # along the wall, not into it
    stuck = FacetQPAdjuster(polish=0)(checker, x0, plan, obstacles, reference=reference)
    assert torch.equal(stuck.plan, reference[:, :N_PLAN])  # the teeth: the unpolished step is scaled to nothing
