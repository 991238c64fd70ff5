import pytest
import torch

from torchrl_brsl.collision import collision_value, intersects
from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import FacetQPAdjuster, Failsafe, GradientAdjuster, PlanChecker
from torchrl_brsl.safety.adjust import _first_safe
from torchrl_brsl.sets import Zonotope

from safety_support import obstacles_of

N_PLAN, N_BRK = 5, 8


@pytest.fixture(scope="module")
def system():
    return DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)


@pytest.fixture(scope="module")
def reach(system):
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    return DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24,
                               method="global")  # these tests compare against its matrices


@pytest.fixture(scope="module")
def local_reach(system):
    x, xp, u = system.offline_data(2000, torch.Generator().manual_seed(0))
    return DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24)


@pytest.mark.parametrize("policy", [False, True])
def test_local_model_verdict_matches_its_explicit_sets(local_reach, system, policy):
    """With plan-dependent sets, a plan is safe only if its sets (plan + braking tail,
    recomputed step by step) are covered, miss the obstacle and end stopped (the checker's
    reduced projections can only be more cautious)."""
    checker = make_checker(local_reach, system, policy=policy, stop_tolerance=None, stop_slack=0.1)
    gen = torch.Generator().manual_seed(3)
    x0 = torch.zeros(16, 4, dtype=torch.float64)
    x0[:, 2:] = torch.rand(16, 2, generator=gen, dtype=torch.float64) * 0.6 - 0.3
    plan = system.sample_actions(16, N_PLAN, generator=gen) * 0.5
    c, g, mask, obstacle = box([0.25, -1.0], [0.6, 1.0])
    evaluation = checker.evaluate(x0, plan, obstacles_of(c.expand(16, 1, 2), g.expand(16, 1, 2, 2),
                                                         mask.expand(16, 1)))
    sets, covered = local_reach.reach_covered(Zonotope.from_point(x0), evaluation.actions)
    torch.testing.assert_close(sets.center, evaluation.centers)
    hit = intersects(sets.project([0, 1]), obstacle).any(-1)
    stopped = ((sets.center[:, -1, 2:].abs() <= 0.1)).all(-1)
    assert not (evaluation.safe & (hit | ~covered | ~stopped)).any()
    assert torch.equal(evaluation.covered, covered)
    assert evaluation.safe.any() and hit.any()


@pytest.mark.parametrize("bad", ["x0", "plan"])
def test_a_local_models_checker_rejects_a_non_finite_start_or_plan_by_name(local_reach, system, bad):
    """The layer sanitises its inputs before a check; a direct call gets a clear error, not sets of NaN."""
    checker = make_checker(local_reach, system)
    inputs = {"x0": torch.zeros(2, 4, dtype=torch.float64), "plan": torch.zeros(2, N_PLAN, 2, dtype=torch.float64)}
    inputs[bad][1, 0] = float("nan")
    c, g, mask, _ = box([0.25, -1.0], [0.6, 1.0])
    with pytest.raises(ValueError, match=f"`{bad}` contains NaN"):
        checker.evaluate(inputs["x0"], inputs["plan"], obstacles_of(c.expand(2, 1, 2), g.expand(2, 1, 2, 2),
                                                                    mask.expand(2, 1)))


def make_checker(reach, system, policy=True, **kwargs):
    horizon = N_PLAN + N_BRK
    radius = reach.error_generators_sequence(horizon)[-1, 2:].abs().sum(-1)
    failsafe = Failsafe(torch.zeros(2, dtype=torch.float64), N_BRK, system.braking if policy else None)
    options = dict(stop_dims=(2, 3), stop_tolerance=(radius + 0.1).tolist(), action_low=system.action_low,
                   action_high=system.action_high)
    options.update(kwargs)
    return PlanChecker(reach, failsafe, horizon, **options)


def box(lo, hi):
    z = Zonotope.from_interval(torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64))
    return z.center.view(1, 1, 2), z.generators.view(1, 1, 2, 2), torch.ones(1, 1, dtype=torch.bool), z


def test_braking_tail_follows_the_policy_on_the_nominal_trajectory(reach, system):
    checker = make_checker(reach, system)
    x0 = torch.tensor([[0.0, 0.0, 0.6, -0.3]], dtype=torch.float64)
    plan = torch.tensor([[[1.0, 0.5]] * N_PLAN], dtype=torch.float64)
    actions, centers = checker.rollout(x0, plan)
    assert actions.shape == (1, N_PLAN + N_BRK, 2) and centers.shape == (1, N_PLAN + N_BRK, 4)
    torch.testing.assert_close(actions[:, :N_PLAN], plan)
    c = centers[:, N_PLAN - 1]
    for j in range(N_PLAN, N_PLAN + N_BRK):
        expected = system.braking(c).clamp(-1, 1).to(torch.float64)
        torch.testing.assert_close(actions[:, j], expected)
        c = c @ reach.state_matrix.T + expected @ reach.input_matrix.T + reach.offset
        torch.testing.assert_close(centers[:, j], c)


def test_values_match_collision_checks_of_the_explicit_sets(reach, system):
    checker = make_checker(reach, system)
    x0 = torch.tensor([[0.0, 0.0, 0.6, 0.0]], dtype=torch.float64)
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN], dtype=torch.float64)
    centers, generators, mask, obstacle = box([1.1, -0.35], [1.5, 0.35])
    evaluation = checker.evaluate(x0, plan, obstacles_of(centers, generators, mask))
    actions = evaluation.actions[0]
    sets = reach.reach(Zonotope.from_point(x0[0]), actions).project((0, 1))
    # the checker reduces the projected generators; its sets contain the explicit ones, so its
    # collision values can only be smaller (more conservative)
    explicit = collision_value(sets, obstacle, backend="closed_form")
    assert torch.all(evaluation.values[0, :, 0] <= explicit + 1e-9)
    unreduced = make_checker(reach, system, set_generators=sets.generators.shape[-1])
    unreduced_values = unreduced.evaluate(x0, plan, obstacles_of(centers, generators, mask)).values
    torch.testing.assert_close(unreduced_values[0, :, 0], explicit)
    assert not evaluation.safe.item()


def test_masked_obstacles_are_ignored(reach, system):
    checker = make_checker(reach, system)
    x0 = torch.tensor([[0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    plan = torch.zeros(1, N_PLAN, 2, dtype=torch.float64)
    centers, generators, mask, _ = box([-0.1, -0.1], [0.1, 0.1])  # on top of the robot
    assert not checker.evaluate(x0, plan, obstacles_of(centers, generators, mask)).safe.item()
    free = checker.evaluate(x0, plan, obstacles_of(centers, generators, ~mask))
    assert free.safe.item() and torch.isinf(free.values).all()


def test_stop_condition_rejects_a_plan_that_cannot_stop(reach, system):
    checker = make_checker(reach, system, policy=False)  # hold zero acceleration: never brakes
    x0 = torch.tensor([[0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    no_obstacles = obstacles_of(torch.zeros(1, 0, 2, dtype=torch.float64), torch.zeros(1, 0, 2, 2, dtype=torch.float64),
                                torch.zeros(1, 0, dtype=torch.bool))
    evaluation = checker.evaluate(x0, torch.zeros(1, N_PLAN, 2, dtype=torch.float64), no_obstacles)
    assert evaluation.stop_excess.item() > 0 and not evaluation.safe.item()


@pytest.mark.parametrize("adjuster", [GradientAdjuster(max_iterations=200, time_budget=None), FacetQPAdjuster()])
def test_adjusters_turn_an_unsafe_plan_into_a_verified_one(reach, system, adjuster):
    checker = make_checker(reach, system)
    x0 = torch.tensor([[0.0, 0.0, 0.6, 0.0]], dtype=torch.float64)
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN], dtype=torch.float64)
    centers, generators, mask, _ = box([1.1, -0.35], [1.5, 0.35])
    assert not checker.evaluate(x0, plan, obstacles_of(centers, generators, mask)).safe.item()
    # the reference for the facet-locked QP: brake at once (verified safe here)
    reference = checker.rollout(x0, torch.tensor([[[-1.0, 0.0]] * N_PLAN], dtype=torch.float64))[0]
    assert checker.evaluate(x0, reference[:, :N_PLAN], obstacles_of(centers, generators, mask)).safe.item()
    result = adjuster(checker, x0, plan, obstacles_of(centers, generators, mask), reference=reference)
    assert result.evaluation.safe.item()
    again = checker.evaluate(x0, result.plan, obstacles_of(centers, generators, mask))
    assert again.safe.item() and torch.all(again.values > 1)
    assert torch.all(result.plan >= -1) and torch.all(result.plan <= 1)
    # the adjusted plan still moves forward: it is not simply the braking reference
    assert result.plan[0, 0, 0] > -1 + 1e-3


def test_facet_qp_needs_a_reference(reach, system):
    checker = make_checker(reach, system)
    centers, generators, mask, _ = box([1.1, -0.35], [1.5, 0.35])
    with pytest.raises(ValueError, match="reference"):
        FacetQPAdjuster()(checker, torch.zeros(1, 4, dtype=torch.float64), torch.zeros(1, N_PLAN, 2,
                                                                                       dtype=torch.float64),
                          obstacles_of(centers, generators, mask))


def test_failsafe_validates_its_arguments():
    with pytest.raises(ValueError, match="hold_action"):
        Failsafe(torch.zeros(2, 2), 3)
    with pytest.raises(ValueError, match="n_brk"):
        Failsafe(torch.zeros(2), 0)
    with pytest.raises(ValueError, match="policy"):
        Failsafe(torch.zeros(2), 3, policy=5)
    brake = Failsafe(torch.tensor([0.5, -0.5]), 3)
    assert torch.equal(brake.actions(torch.zeros(4, 6)), torch.tensor([[0.5, -0.5]] * 4))


def test_facet_qp_checks_its_halvings_in_one_batch_once_few_adjustments_take_the_full_or_half_step(
        local_reach, system, monkeypatch):
    """The facet QP checks the full and the half step first while most adjustments take one of them, and every
    halving in one batch once a running share of fewer than ``EARLY_SHARE`` did (the verdicts are the same)."""
    from torchrl_brsl.safety import adjust

    checker = make_checker(local_reach, system, stop_tolerance=None, stop_slack=0.1)
    x0 = torch.tensor([[0.0, 0.0, 0.3, 0.0]], dtype=torch.float64)
    c, g, mask, _ = box([0.35, -1.0], [0.6, 1.0])
    obstacles = obstacles_of(c, g, mask)
    plan, reference = torch.ones(1, N_PLAN, 2, dtype=torch.float64), torch.zeros(1, N_PLAN, 2, dtype=torch.float64)
    batches, first_safe = [], adjust._first_safe

    def deep(*args, first_batch=None, **kwargs):  # as if every adjustment had needed the last halving
        batches.append(first_batch)
        found = first_safe(*args, first_batch=first_batch, **kwargs)
        return found._replace(iterations=torch.full_like(found.iterations, 5))

    monkeypatch.setattr(adjust, "_first_safe", deep)
    adjuster = FacetQPAdjuster()
    for _ in range(4):
        adjuster(checker, x0, plan, obstacles, reference=reference)
    assert batches == [2, 2, 2, 5]  # the running share: 1, 0.8, 0.64, 0.512 < EARLY_SHARE


def test_local_model_of_a_restricted_domain_claims_nothing_outside_it(system):
    """A local (cell) model fitted on low speeds: plans that speed up past the domain are unverified."""
    x, xp, u = system.offline_data(2000, torch.Generator().manual_seed(0))
    inf = float("inf")
    domain = (torch.tensor([-inf, -inf, -0.4, -0.4, -inf, -inf]), torch.tensor([inf, inf, 0.4, 0.4, inf, inf]))
    slow = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24,
                               domain=domain)
    checker = make_checker(slow, system, policy=False, stop_tolerance=None, stop_slack=0.2)
    x0 = torch.zeros(1, 4, dtype=torch.float64)
    far = torch.full((1, 1, 2), 50.0, dtype=torch.float64), torch.eye(2, dtype=torch.float64).view(1, 1, 2, 2)
    mask = torch.ones(1, 1, dtype=torch.bool)
    faster = torch.tensor([[[1.0, 0.0]] * N_PLAN], dtype=torch.float64)  # 5 x 0.1 s x 1 m/s^2 = 0.5 m/s
    assert not checker.evaluate(x0, faster, obstacles_of(*far, mask)).covered.item()
    assert checker.evaluate(x0, torch.zeros(1, N_PLAN, 2, dtype=torch.float64), obstacles_of(*far, mask)).safe.item()


def test_flat_plan_dependent_sets_against_empty_obstacle_slots_never_raise(system):
    """A local model whose first set is flat in position (no model error, no position noise,
    as on a velocity-commanded robot) against a masked slot with zero generators: the check
    must still answer (it raised mid-episode that the closed form does not apply)."""
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    velocity_noise = Zonotope(torch.zeros(4, dtype=torch.float64), torch.diag(system.noise_half_width * torch.tensor(
        [0.0, 0.0, 1.0, 1.0], dtype=torch.float64)))
    flat = DataDrivenReach.fit(x, xp, u, velocity_noise, translation_invariant_dims=(0, 1), max_generators=24)
    flat.cell_errors.zero_()
    checker = make_checker(flat, system, policy=False, stop_tolerance=None, stop_slack=0.2)
    c, g, mask, _ = box([0.5, -0.2], [0.7, 0.2])
    centers = torch.cat((c, torch.zeros(1, 1, 2, dtype=torch.float64)), dim=1)
    generators = torch.cat((g, torch.zeros(1, 1, 2, 2, dtype=torch.float64)), dim=1)
    masks = torch.tensor([[True, False]])
    x0 = torch.zeros(1, 4, dtype=torch.float64)
    evaluation = checker.evaluate(x0, torch.zeros(1, N_PLAN, 2, dtype=torch.float64),
                                  obstacles_of(centers, generators, masks))
    assert evaluation.safe.item()
    assert torch.isinf(evaluation.values[..., 1]).all()


@pytest.mark.parametrize("first_batch", [None, 2, 1])
def test_batched_backtracking_takes_the_first_safe_halving(local_reach, system, first_batch):
    """A local model's candidates ``reference + step / 2^a`` are checked in one batch, or the first ``first_batch``
    and then the rest for the envs where none was safe; each env takes the first safe one, as checking them in
    turn would (the reference's evaluation when none is)."""
    checker = make_checker(local_reach, system, stop_tolerance=None, stop_slack=0.1)
    gen = torch.Generator().manual_seed(5)
    n_envs = 12
    x0 = torch.zeros(n_envs, 4, dtype=torch.float64)
    x0[:, 2] = torch.rand(n_envs, generator=gen, dtype=torch.float64) * 0.4
    reference = torch.zeros(n_envs, N_PLAN, 2, dtype=torch.float64)
    step = torch.zeros_like(reference)
    step[..., 0] = torch.rand(n_envs, 1, generator=gen, dtype=torch.float64) * 2  # towards the wall, some too hard
    c, g, mask, _ = box([0.35, -1.0], [0.6, 1.0])
    obstacles = obstacles_of(c.expand(n_envs, 1, 2), g.expand(n_envs, 1, 2, 2), mask.expand(n_envs, 1))
    ref_eval = checker.evaluate(x0, reference, obstacles)
    result = _first_safe(checker, x0, reference, step, obstacles, ref_eval, backtracking=4, first_batch=first_batch)
    firsts = []
    for i in range(n_envs):
        safe = [bool(checker.evaluate(x0[i:i + 1], reference[i:i + 1] + step[i:i + 1] / 2 ** a,
                                      obstacles[i:i + 1]).safe) for a in range(5)]
        first = next((a for a, ok in enumerate(safe) if ok), None)
        firsts.append(first)
        expected = reference[i] if first is None else reference[i] + step[i] / 2 ** first
        torch.testing.assert_close(result.plan[i], expected)
        assert bool(result.evaluation.safe[i]) == (first is not None or bool(ref_eval.safe[i]))
        assert int(result.iterations[i]) == (5 if first is None else first + 1)
    assert len(set(firsts)) >= 3, f"the scene should mix outcomes, got first safe halvings {firsts}"
