"""The safety decision of one step on plain tensors (no TensorDict, no env)."""
import pytest
import torch

from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import Adjustment, FacetQPAdjuster, Failsafe, PlanChecker, SafetyDecision
from torchrl_brsl.sets import Zonotope

from safety_support import obstacles_of

N_PLAN, N_BRK = 4, 8
D = torch.float64


@pytest.fixture(scope="module")
def decide():
    system = DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)
    x, xp, u = system.offline_data(2000, torch.Generator().manual_seed(0))
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24)
    failsafe = Failsafe(torch.zeros(2, dtype=D), N_BRK, system.braking)
    checker = PlanChecker(reach, failsafe, N_PLAN + N_BRK, stop_dims=(2, 3), stop_slack=0.1,
                          action_low=system.action_low, action_high=system.action_high)
    return SafetyDecision(checker, failsafe, FacetQPAdjuster())


def _scene(n_envs: int):
    """Robots moving at 0.6 m/s towards a wall 0.5 m ahead, proposing full thrust; a held safe plan."""
    x0 = torch.tensor([[0.0, 0.0, 0.6, 0.0]], dtype=D).repeat(n_envs, 1)
    proposal = torch.tensor([[1.0, 0.0]], dtype=D).repeat(n_envs, N_PLAN, 1)
    wall = Zonotope.from_interval(torch.tensor([0.5, -1.0], dtype=D), torch.tensor([0.7, 1.0], dtype=D))
    obstacles = obstacles_of(wall.center.expand(n_envs, 1, 2), wall.generators.expand(n_envs, 1, 2, 2),
                             torch.ones(n_envs, 1, dtype=torch.bool))
    safe_plan = torch.zeros(n_envs, N_PLAN + N_BRK, 2, dtype=D)
    return x0, proposal, safe_plan, torch.zeros(n_envs, dtype=torch.long), obstacles


def test_executed_action_starts_a_plan_the_checker_verifies(decide):
    x0, proposal, safe_plan, steps, obstacles = _scene(3)
    assert not decide.checker.evaluate(x0, proposal, obstacles).safe.any()
    step = decide(x0, proposal, safe_plan, steps, obstacles)
    assert step.diagnostics["intervened"].all()
    usable = step.safe_steps > 0
    assert usable.all(), "braking from 0.6 m/s, 0.5 m before the wall, verifies"
    chosen = torch.cat((step.executed.unsqueeze(1), step.safe_plan[:, :-1]), dim=1)  # the verified sequence
    assert decide.checker.evaluate(x0, chosen, obstacles).safe.all()
    assert (step.executed[:, 0] < 1.0).all()


def test_an_invalid_env_keeps_its_safe_plan_and_leaves_the_others_alone(decide):
    x0, proposal, safe_plan, steps, obstacles = _scene(2)
    safe_plan[:, :, 0] = -0.5
    steps[:] = 5
    alone = decide(x0[:1], proposal[:1], safe_plan[:1], steps[:1], obstacles[:1])
    x0[1, 2] = float("nan")
    both = decide(x0, proposal, safe_plan, steps, obstacles)
    assert both.diagnostics["invalid_input"].tolist() == [False, True]
    assert both.diagnostics["failsafe"][1] and not both.diagnostics["unverified_hold"][1]
    torch.testing.assert_close(both.executed[1], safe_plan[1, 0])
    assert both.safe_steps[1] == 4
    torch.testing.assert_close(both.executed[0], alone.executed[0], rtol=0, atol=1e-9)
    for name, value in alone.diagnostics.items():  # to rounding: batches of other sizes may round otherwise
        torch.testing.assert_close(both.diagnostics[name][0], value[0], rtol=0, atol=1e-9, msg=name)


def test_after_a_step_that_adjusted_every_env_the_references_ride_along_with_the_proposals(decide, monkeypatch):
    """Adjustments come in runs: after a step that adjusted every env, the proposals and the adjuster's references
    are rolled out in one batch (:meth:`FacetQPAdjuster.evaluate_paired`). The decision is the one made without."""
    x0, proposal, safe_plan, steps, obstacles = _scene(3)
    safe_plan[:, :2, 0] = -0.3
    paired = []
    evaluate_paired = decide.adjuster.evaluate_paired
    monkeypatch.setattr(decide.adjuster, "evaluate_paired", lambda *args: paired.append(1) or evaluate_paired(*args))
    decide._pair = False
    at_rest, still = x0.clone(), proposal.clone()
    at_rest[1, 2], still[1] = 0.0, 0.0  # env 1 stays at rest: a safe proposal
    decide(at_rest, still, safe_plan, steps, obstacles)
    assert not paired and not decide._pair  # env 1 was not adjusted
    alone = decide(x0, proposal, safe_plan, steps, obstacles)
    assert not paired and decide._pair and alone.diagnostics["intervened"].all()
    together = decide(x0, proposal, safe_plan, steps, obstacles)
    assert paired == [1]
    for got, want in zip(together[:3], alone[:3]):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    for name, value in alone.diagnostics.items():
        torch.testing.assert_close(together.diagnostics[name], value, rtol=0, atol=1e-9)
    x0[1, 2], proposal[1] = 0.0, 0.0  # paired again, and env 1 needs no adjustment: the others' parts are taken
    some = decide(x0, proposal, safe_plan, steps, obstacles)
    assert paired == [1, 1] and some.diagnostics["intervened"].tolist() == [True, False, True]
    decide._pair = False
    unpaired = decide(x0, proposal, safe_plan, steps, obstacles)
    assert paired == [1, 1]
    for got, want in zip(some[:3], unpaired[:3]):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    for name, value in unpaired.diagnostics.items():
        torch.testing.assert_close(some.diagnostics[name], value, rtol=0, atol=1e-9)


class _Broken:
    """A custom adjuster that adjusts with the facet QP, then spoils its result as ``spoil`` says."""

    def __init__(self, spoil):
        self.inner, self.spoil = FacetQPAdjuster(), spoil

    def __call__(self, checker, x0, plan, obstacles, start=None, reference=None):
        return self.spoil(self.inner(checker, x0, plan, obstacles, start=start, reference=reference))


def _first_action_of_env_0(value: float):
    """The spoiler that sets env 0's first action (first entry) to ``value``, leaving the verdict as it was."""
    def spoil(adjusted):
        actions = adjusted.evaluation.actions.clone()
        actions[0, 0, 0] = value
        return adjusted._replace(evaluation=adjusted.evaluation._replace(actions=actions))
    return spoil


@pytest.mark.parametrize("value", [float("nan"), -3.0], ids=["nan", "beyond the bounds"])
def test_an_adjusters_claim_on_a_plan_the_robot_would_not_receive_is_withdrawn(decide, value):
    """A custom adjuster's claim on a NaN action, or on one beyond the action bounds (the robot clips it, so the
    checked plan is not the one it would run), never reaches the robot: that env brakes, verified."""
    x0, proposal, safe_plan, steps, obstacles = _scene(2)
    x0[:, 2] = 0.3  # slow enough for an adjusted plan to verify
    honest = decide(x0, proposal, safe_plan, steps, obstacles)
    assert not honest.diagnostics["failsafe"].any()  # the facet QP verifies both envs' adjustments
    spoilt = SafetyDecision(decide.checker, decide.failsafe, _Broken(_first_action_of_env_0(value)))
    with pytest.warns(RuntimeWarning, match="claimed 1 plan"):
        step = spoilt(x0, proposal, safe_plan, steps, obstacles)
    low, high = decide.checker.action_low, decide.checker.action_high
    assert ((step.executed >= low) & (step.executed <= high)).all()
    assert step.diagnostics["failsafe"].tolist() == [True, False]
    torch.testing.assert_close(step.executed[1], honest.executed[1], rtol=0, atol=1e-12)
    braked = decide.checker.evaluate(x0[:1], decide.checker.brake(x0[:1]).unsqueeze(1), obstacles[:1])
    assert braked.safe.all() and step.safe_steps[0] > 0  # env 0 brakes, verified, from the measured state
    torch.testing.assert_close(step.executed[0], braked.actions[0, 0])


@pytest.mark.parametrize("spoil, error, message", [
    (lambda adjusted: adjusted.plan, TypeError, "must return an `Adjustment`"),
    (lambda adjusted: adjusted._replace(evaluation=adjusted.evaluation._replace(
        actions=adjusted.evaluation.actions[:, :-1])), ValueError, r"expected \[B=2\] and \[B=2, T=12, m=2\]"),
], ids=["a plan", "a short evaluation"])
def test_an_adjusters_result_of_the_wrong_kind_or_shape_is_a_clear_error(decide, spoil, error, message):
    x0, proposal, safe_plan, steps, obstacles = _scene(2)
    with pytest.raises(error, match=message):
        SafetyDecision(decide.checker, decide.failsafe, _Broken(spoil))(x0, proposal, safe_plan, steps, obstacles)


class _Diverges:
    """A custom adjuster whose iteration diverged: it checks the NaN plans it reached and reports their verdict."""

    def __call__(self, checker, x0, plan, obstacles, start=None, reference=None):
        lost = torch.full_like(plan, float("nan"))
        return Adjustment(lost, checker.evaluate(x0, lost, obstacles), torch.ones(len(x0), dtype=torch.long))


def test_an_adjuster_that_diverges_to_nan_plans_ends_in_the_verified_brake_not_an_error(decide):
    """Inside the decision the checks take what an adjuster tried, NaN included, without raising mid-episode: a NaN
    plan is never verified, and the env brakes from its measured state, verified."""
    x0, proposal, safe_plan, steps, obstacles = _scene(2)
    step = SafetyDecision(decide.checker, decide.failsafe, _Diverges())(x0, proposal, safe_plan, steps, obstacles)
    assert step.diagnostics["failsafe"].all() and (step.safe_steps > 0).all()
    braked = decide.checker.evaluate(x0, decide.checker.brake(x0).unsqueeze(1), obstacles)
    assert braked.safe.all()
    torch.testing.assert_close(step.executed, braked.actions[:, 0])
    with pytest.raises(ValueError, match="`plan` contains NaN"):  # outside a decision, a NaN plan is an error
        decide.checker.evaluate(x0, torch.full_like(proposal, float("nan")), obstacles)


class _BrakesHardLocally:
    """A custom adjuster that gives up under the main checker and, under the local domain's (bounds +-0.5), claims
    full braking at -0.8: inside the robot's bounds (+-1), beyond the domain's, verified by that checker."""

    def __call__(self, checker, x0, plan, obstacles, start=None, reference=None):
        if float(checker.action_high.max()) >= 1.0:  # the main checker: the proposal's own verdict
            return Adjustment(plan, checker.evaluate(x0, plan, obstacles), torch.zeros(len(x0), dtype=torch.long))
        braking = torch.zeros_like(plan)
        braking[..., 0] = -0.8
        return Adjustment(braking, checker.evaluate(x0, braking, obstacles), torch.ones(len(x0), dtype=torch.long))


def test_a_local_domains_adjustment_is_held_to_the_robots_bounds_not_the_domains(decide):
    """The local domain's checker verifies what its model covers; the robot clips at its own bounds. A claim of the
    local retry beyond the domain's bounds but inside the robot's is executed."""
    x0, proposal, safe_plan, steps, obstacles = _scene(1)
    x0[:, 2] = 0.3
    local = PlanChecker(decide.checker.reach, decide.failsafe, N_PLAN + N_BRK, stop_dims=(2, 3), stop_slack=0.1,
                        action_low=torch.full((2,), -0.5, dtype=D), action_high=torch.full((2,), 0.5, dtype=D))
    step = SafetyDecision(decide.checker, decide.failsafe, _BrakesHardLocally(), local_checker=local)(
        x0, proposal, safe_plan, steps, obstacles)
    assert step.diagnostics["local"].all() and not step.diagnostics["failsafe"].any()
    torch.testing.assert_close(step.executed[0], torch.tensor([-0.8, 0.0], dtype=D))
