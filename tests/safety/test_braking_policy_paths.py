"""With a state-dependent braking policy on a global model, the adjusters linearise the braking
tail along the nominal rollout instead of differentiating through it: same gradients as
autograd, every accepted plan still checked exactly."""
import copy
import warnings

import pytest
import torch
from torch._dynamo.utils import counters

from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import FacetQPAdjuster, Failsafe, PlanChecker
from torchrl_brsl.safety.adjust import _brake_jacobian, _centre_jacobian, _feedback_jacobian
from torchrl_brsl.safety.plan_check import FUSE_FROM_STEPS

from safety_support import assert_closed_form_matches_autograd, obstacles_of

N_PLAN, N_BRK = 5, 8
D = torch.float64


def brake_policy(x):
    """Full deceleration, saturating at 0.8 (the clip is active at high speed only)."""
    return (-4.0 * x[..., 2:]).clamp(-0.8, 0.8)


def autograd_derivative(policy, states, low=-1.0, high=1.0):
    """The oracle: ``d clip(policy) / d state`` ``[..., m, n]`` by one backward pass per action dim."""
    states = states.detach().requires_grad_(True)
    raw = policy(states).to(states.dtype)
    rows = [torch.autograd.grad(raw[..., i].sum(), states, retain_graph=True)[0] for i in range(raw.shape[-1])]
    unclipped = (raw > low) & (raw < high)
    return torch.stack(rows, dim=-2).detach() * unclipped.detach().unsqueeze(-1)


@pytest.fixture(scope="module")
def checker():
    system = DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24,
                                method="global")
    return PlanChecker(reach, Failsafe(torch.zeros(2, dtype=D), N_BRK, policy=brake_policy), N_PLAN + N_BRK,
                       stop_dims=(2, 3), stop_slack=0.3, action_low=-torch.ones(2, dtype=D),
                       action_high=torch.ones(2, dtype=D))


def scene():
    x0 = torch.tensor([[0.0, 0.0, 0.6, 0.05], [0.0, 0.1, 0.4, -0.1], [0.2, 0.0, 0.0, 0.0]], dtype=D)
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN, [[0.8, 0.3]] * N_PLAN, [[-0.2, 0.1]] * N_PLAN], dtype=D)
    centers = torch.tensor([[[1.3, 0.0], [0.5, 0.9]]] * 3, dtype=D)
    generators = torch.tensor([[[[0.2, 0.0, 0.05], [0.0, 0.35, 0.05]]] * 2] * 3, dtype=D)
    mask = torch.tensor([[True, True], [True, False], [True, True]])
    return x0, plan, centers, generators, mask


@pytest.mark.parametrize("plan_steps", [1, 3, N_PLAN])
def test_linearised_tail_matches_finite_differences(checker, plan_steps):
    x0, plan, *_ = scene()
    plan = plan[:, :plan_steps] * 0.5
    _, centres = checker.rollout(x0, plan)
    raw = brake_policy(centres[:, plan_steps - 1:-1])
    assert bool((raw.abs() == 0.8).any()) and bool((raw.abs() < 0.8).any())  # both regimes of the clip
    exact = _feedback_jacobian(checker, centres, plan_steps)
    numeric = _centre_jacobian(checker, x0, plan).flatten(-2)
    torch.testing.assert_close(exact, numeric, rtol=0, atol=1e-6)


@pytest.mark.parametrize("precision", [torch.float64, torch.float32])
def test_the_brake_tangent_is_the_policys_derivative(checker, precision):
    """``PlanChecker.brake_tangent`` (central differences, what the local model's compiled loop can trace) is the
    autograd derivative along the directions: zero where the bounds clip the action or a direction is zero;
    to rounding for a float64 policy, to the float32 policy's step-size error otherwise."""
    def policy(x):  # smooth, and beyond the bounds (+-1) at high speed
        return 3.0 * torch.tanh(-x[..., 2:].to(precision) - 0.3 * x[..., :2].to(precision) ** 2)

    smooth = PlanChecker(checker.reach, Failsafe(torch.zeros(2, dtype=D), N_BRK, policy=policy), N_PLAN + N_BRK,
                         stop_dims=(2, 3), stop_slack=0.3, action_low=-torch.ones(2, dtype=D),
                         action_high=torch.ones(2, dtype=D))
    gen = torch.Generator().manual_seed(0)
    states = torch.randn(64, 4, generator=gen, dtype=D) * torch.tensor([0.5, 0.5, 0.4, 0.4], dtype=D)
    directions = torch.randn(64, 4, 3, generator=gen, dtype=D) * torch.tensor([1.0, 1e-3, 0.0])  # one column zero
    raw = policy(states).to(D)
    assert bool((raw.abs() > 1).any()) and bool((raw.abs() < 1).any())  # both sides of the bounds
    expected = autograd_derivative(policy, states) @ directions
    tolerance = dict(rtol=1e-8, atol=1e-10) if precision == D else dict(rtol=2e-3, atol=2e-4)
    torch.testing.assert_close(smooth.brake_tangent(states, directions), expected, **tolerance)
    assert bool((expected[..., 0] != 0).any()) and bool((smooth.brake_tangent(states, directions)[..., 2] == 0).all())


def test_saturated_tail_takes_the_open_loop_jacobian(checker):
    """Braking clipped along the whole tail: the cached open-loop Jacobian, still the rollout's own."""
    x0 = torch.tensor([[0.0, 0.0, 2.8, -2.8], [0.3, 0.0, -2.9, 2.9]], dtype=D)
    plan = torch.tensor([[[1.0, -1.0]] * N_PLAN, [[-1.0, 1.0]] * N_PLAN], dtype=D)
    _, centres = checker.rollout(x0, plan)
    assert bool((brake_policy(centres[:, N_PLAN - 1:-1]).abs() == 0.8).all())
    exact = _feedback_jacobian(checker, centres, N_PLAN)
    torch.testing.assert_close(exact, _centre_jacobian(checker, x0, plan).flatten(-2), rtol=0, atol=1e-6)


@pytest.mark.parametrize("iterations", [1, 4, 15])
def test_gradient_adjuster_with_a_braking_policy_matches_autograd(checker, iterations):
    x0, plan, centers, generators, mask = scene()
    assert_closed_form_matches_autograd(checker, x0, plan, centers, generators, mask, iterations)


def test_facet_qp_with_a_braking_policy_accepts_only_verified_plans(checker):
    x0 = torch.tensor([[0.0, 0.0, 0.5, 0.0], [0.0, 0.0, 0.5, 0.0]], dtype=D)
    centers = torch.tensor([[[1.4, 0.0]], [[1.4, 0.3]]], dtype=D)
    generators = torch.tensor([[[[0.2, 0.0], [0.0, 0.35]]]] * 2, dtype=D)
    mask = torch.ones(2, 1, dtype=torch.bool)
    reference = torch.tensor([[[-1.0, 0.0]] * N_PLAN] * 2, dtype=D)  # decelerate: safe
    assert checker.evaluate(x0, reference, obstacles_of(centers, generators, mask)).safe.all()
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN] * 2, dtype=D)
    assert not checker.evaluate(x0, plan, obstacles_of(centers, generators, mask)).safe.any()
    result = FacetQPAdjuster()(checker, x0, plan, obstacles_of(centers, generators, mask), reference=reference)
    again = checker.evaluate(x0, result.plan, obstacles_of(centers, generators, mask))
    assert torch.equal(again.safe, result.evaluation.safe) and result.evaluation.safe.all()
    assert not torch.equal(result.plan, reference)  # it moved towards the proposal


LONG = N_PLAN + FUSE_FROM_STEPS + 2  # a horizon whose braking tails run compiled


def _checker_on(reach, checker, horizon):
    return PlanChecker(reach, checker.failsafe, horizon, stop_dims=checker.stop_dims, stop_slack=0.3,
                       action_low=checker.action_low, action_high=checker.action_high)


def _compiled(checker):
    return [key for key in checker._memo if key[0] == "compiled"]


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
@pytest.mark.parametrize("n_envs", [1, 3])
def test_compiled_braking_tail_matches_the_eager_one(checker, n_envs):
    """With compiled steps the long tail's rollout and its Jacobian chain run as one graph each: same values."""
    eager = _checker_on(checker.reach, checker, LONG)
    compiled = _checker_on(copy.deepcopy(checker.reach).compile_steps(backend="aot_eager"), checker, LONG)
    x0, plan, *_ = scene()
    x0, plan = x0[:n_envs], plan[:n_envs, :2] * 0.5
    for got, want in zip(compiled.rollout(x0, plan), eager.rollout(x0, plan)):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    centres = eager.rollout(x0, plan)[1]
    assert bool((brake_policy(centres[:, 1:-1]).abs() < 0.8).any())  # the chain runs, not the open-loop shortcut
    torch.testing.assert_close(_feedback_jacobian(compiled, centres, 2), _feedback_jacobian(eager, centres, 2),
                               rtol=0, atol=1e-12)
    assert len(_compiled(compiled)) == 2  # the tail and the chain, both compiled


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
def test_the_adjusters_prepare_the_long_tails_jacobian_chain(checker):
    """A checker whose tail has ``FUSE_FROM_STEPS`` or more steps: the adjuster's ``prepare`` compiles the chain
    along it, so the first linearisation of a plan compiles nothing."""
    reach = copy.deepcopy(checker.reach).compile_steps(backend="aot_eager")
    failsafe = Failsafe(torch.zeros(2, dtype=D), FUSE_FROM_STEPS + 2, policy=brake_policy)
    long = PlanChecker(reach, failsafe, N_PLAN + failsafe.n_brk, stop_dims=(2, 3), stop_slack=0.3,
                       action_low=checker.action_low, action_high=checker.action_high)
    assert len(_compiled(long)) == 1  # the tail's rollout, at construction
    FacetQPAdjuster().prepare(long)
    assert len(_compiled(long)) == 2  # and its Jacobian chain
    frames = counters["frames"]["ok"]
    x0, plan, *_ = scene()
    centres = long.rollout(x0, plan * 0.5)[1]
    assert bool(_feedback_jacobian(long, centres, N_PLAN).isfinite().all())
    assert counters["frames"]["ok"] == frames


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
@pytest.mark.parametrize("horizon", [N_BRK, N_BRK - 1])
def test_a_horizon_no_longer_than_the_brake_warms_up_the_one_step_tail(checker, horizon):
    """``horizon <= n_brk`` leaves no plan before the tail (``plan_steps <= 0``): the warm-up compiles the tail after
    a single action only (a plan of no step has no graph), and a plan of one action is checked as eagerly."""
    reach = copy.deepcopy(checker.reach).compile_steps(backend="aot_eager")
    short = PlanChecker(reach, checker.failsafe, horizon, stop_dims=(2, 3), stop_slack=0.3,
                        action_low=checker.action_low, action_high=checker.action_high)
    assert short.plan_steps == horizon - N_BRK and len(_compiled(short)) == 1
    x0, plan, *_ = scene()
    eager = PlanChecker(checker.reach, checker.failsafe, horizon, stop_dims=(2, 3), stop_slack=0.3,
                        action_low=checker.action_low, action_high=checker.action_high)
    for a, b in zip(short.rollout(x0, plan[:, :1] * 0.5), eager.rollout(x0, plan[:, :1] * 0.5)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no fallback to eager
def test_short_braking_tails_roll_out_compiled_and_their_chain_stays_eager(checker):
    """A tail of ``n_brk = 8`` steps: its rollout is one graph, compiled with the checker for the tails the layer
    checks (a whole plan's, braking from the state), so no control step compiles; its Jacobian chain is eager."""
    reach = copy.deepcopy(checker.reach).compile_steps(backend="aot_eager")
    compiled = _checker_on(reach, checker, checker.horizon)
    assert len(_compiled(compiled)) == 1  # the tail's rollout, at construction
    frames = counters["frames"]["ok"]
    x0, plan, *_ = scene()
    for got, want in zip(compiled.rollout(x0, plan), checker.rollout(x0, plan)):  # tail of n_brk
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    braking = compiled.brake(x0).unsqueeze(1)
    for got, want in zip(compiled.rollout(x0, braking), checker.rollout(x0, braking)):  # tail of horizon - 1
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert counters["frames"]["ok"] == frames  # compiled when the checker was built
    centres = checker.rollout(x0, plan * 0.5)[1]
    chains = [_feedback_jacobian(on, centres, N_PLAN) for on in (compiled, checker)]
    torch.testing.assert_close(*chains, rtol=0, atol=0)  # the chain ran eagerly: the same operations
    assert len(_compiled(compiled)) == 1
    plan = plan.clone().requires_grad_(True)  # under autograd the tail runs eagerly (no backward graph to compile)
    compiled.rollout(x0, plan)[1].sum().backward()
    assert counters["frames"]["ok"] == frames and plan.grad is not None


def test_a_failing_compilation_warns_and_runs_eagerly(checker):
    reach = copy.deepcopy(checker.reach).compile_steps(backend="no_such_backend")
    with pytest.warns(RuntimeWarning, match="compiled _policy_tail failed"):  # at the warm-up
        compiled = _checker_on(reach, checker, LONG)
    x0, plan, *_ = scene()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once, then eager
        got = compiled.rollout(x0, plan)
    for got_part, want in zip(got, _checker_on(checker.reach, checker, LONG).rollout(x0, plan)):
        torch.testing.assert_close(got_part, want, rtol=0, atol=0)


def test_the_tails_brake_jacobian_is_the_policys_derivative(checker):
    """The global model's tail linearisation takes the policy's Jacobian by central differences: autograd's to
    rounding, on both sides of the clip."""
    states = torch.randn(3, 6, 4, generator=torch.Generator().manual_seed(1), dtype=D) * 0.3
    assert bool((brake_policy(states).abs() == 0.8).any()) and bool((brake_policy(states).abs() < 0.8).any())
    torch.testing.assert_close(_brake_jacobian(checker, states), autograd_derivative(brake_policy, states),
                               rtol=1e-8, atol=1e-9)
