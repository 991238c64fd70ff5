"""The compiled step of the local model (``DataDrivenReach.compile_steps``): the eager sets, sound, and
never a crash when the compiler fails. Most tests trace with the ``aot_eager`` backend (the same
capture, guards and symbolic shapes, no code generation); one runs the default backend."""
import copy
import re
import shutil

import pytest
import torch
from torch._dynamo.utils import counters
from torch._subclasses.fake_tensor import FakeTensorMode

from torchrl_brsl.reach import KinematicBicycle
from torchrl_brsl.sets import Zonotope

from reach_support import fit, random_plans, sampled


@pytest.fixture(scope="module")
def bicycle():
    """The bicycle and its body-frame local model (the step with every part: hinges, products, rotation)."""
    system = KinematicBicycle()
    model = fit(system, 400, method="local", max_generators=24, body_frame=system.body_frame)
    yield system, model
    model.compile_steps(False)


@pytest.fixture(scope="module")
def traced(bicycle):
    """``(system, eager, compiled)``: copies of the bicycle's model, eager and traced with ``aot_eager`` (one
    warm-up for the tests that compare the compiled paths with the eager ones)."""
    system, model = bicycle
    eager = copy.deepcopy(model).compile_steps(False)
    return system, eager, copy.deepcopy(eager).compile_steps(backend="aot_eager")


def _sets(model, x0, plans):
    sets, covered = model.reach_covered(Zonotope.from_point(x0), plans)
    return sets.center, sets.generators.abs().sum(-1), covered


def _assert_same(compiled, eager):
    torch.testing.assert_close(compiled[0], eager[0], rtol=0, atol=1e-12)  # centres
    torch.testing.assert_close(compiled[1], eager[1], rtol=1e-9, atol=1e-12)  # interval radii
    assert torch.equal(compiled[2], eager[2])


def _step_of(model):
    return model._cache[("step",)]


def test_compiled_steps_give_the_eager_sets_and_the_sampling_has_teeth(bicycle):
    system, model = bicycle
    x0, plans, _ = random_plans(system, n_plans=6, horizon=12)
    batches = (1, 6, 3)  # batch 1 is a graph of its own; later sizes reuse the symbolic graph
    eager = [_sets(model.compile_steps(False), x0[:b], plans[:b]) for b in batches]
    misses = FakeTensorMode.cache_misses
    model.compile_steps(backend="aot_eager")  # compiles the checking and linearisation graphs (warm-up)
    step, compiled_frames = _step_of(model), counters["frames"]["ok"]
    assert FakeTensorMode.cache_misses == misses  # traced without the fake-tensor cache (quick_tracing)
    for batch, expected in zip(batches, eager):
        _assert_same(_sets(model, x0[:batch], plans[:batch]), expected)
    generators = x0.new_zeros(6, x0.shape[-1], 24)
    model.step_sets(x0, generators, plans[:, 0], (generators[..., :5], plans[:, 0].unsqueeze(-1).expand(6, 2, 5)))
    _sets(model, x0[:4].clone(), plans[:4].clone())  # inputs that are not views (the warm-up's are)
    assert counters["frames"]["ok"] == compiled_frames  # no step compiled after the warm-up
    assert model.compile_steps(backend="aot_eager") is model and _step_of(model) is step  # kept
    start = x0[:2].clone().requires_grad_(True)
    model.reach(Zonotope.from_point(start), plans[:2]).center.sum().backward()
    assert counters["frames"]["ok"] > compiled_frames  # teeth: the counter sees a new graph (gradients)
    assert FakeTensorMode.cache_misses > misses  # teeth: one compiled outside a warm-up traces with the cache
    assert sampled(system, model).violations == 0
    errors = model.cell_errors.clone()
    try:  # teeth: the leaves' error intervals scaled by 0.3 (as in the body-frame test) let states out
        model.cell_errors.mul_(0.3)
        assert sampled(system, model).violations > 0
    finally:
        model.cell_errors.copy_(errors)
    assert _step_of(model)._compiled is not None  # the compiled paths ran throughout: no fallback
    assert _step_of(model)._compiled_loop is not None


def test_compiled_tangents_and_gradients_are_the_eager_ones(traced):
    system, eager_model, compiled_model = traced
    x0, plans, _ = random_plans(system, n_plans=4, horizon=6)
    generators = x0.new_zeros(4, x0.shape[-1], 0)
    tangents = (torch.randn(4, x0.shape[-1], 3, dtype=x0.dtype), torch.randn(4, 2, 3, dtype=x0.dtype))
    plan_tangents = (tangents[0], torch.randn(4, 6, 2, 3, dtype=x0.dtype))  # every action's directions
    results = []
    for model in (eager_model, compiled_model):
        moved = model.step_sets(x0, generators, plans[:, 0], tangents)[-1]
        along_plan = model.reach_covered(Zonotope.from_point(x0), plans, plan_tangents)[-1]  # [4, 6, n, 3]
        start, plan = x0.clone().requires_grad_(True), plans.clone().requires_grad_(True)
        model.reach(Zonotope.from_point(start), plan).center.sum().backward()
        results.append((moved, along_plan, start.grad, plan.grad))
    for compiled, eager in zip(results[1], results[0]):
        torch.testing.assert_close(compiled, eager, rtol=1e-9, atol=1e-12)
    assert _step_of(model)._compiled is not None and _step_of(model)._compiled_loop is not None
    assert _step_of(eager_model)._compiled is None and _step_of(eager_model)._compiled_loop is None
    # the plan's tangents are the steps' chained: the first step's are those of the single step
    torch.testing.assert_close(results[0][1][:, 0], model.step_sets(
        x0, generators, plans[:, 0], (tangents[0], plan_tangents[1][:, 0]))[-1], rtol=1e-12, atol=1e-14)


def test_a_braking_policys_tail_runs_in_the_plans_loop(traced):
    """``reach_covered(..., brake=(policy, steps))``: the tail's actions are the policy's at each set's centre, the
    same as eagerly, and the sets are those of the plan followed by those actions (whose soundness the sampling
    tests show)."""
    system, eager_model, model = traced
    x0, plans, _ = random_plans(system, n_plans=5, horizon=4)
    initial = Zonotope.from_point(x0)
    eager = eager_model.reach_covered(initial, plans, brake=(system.braking, 6))
    frames = counters["frames"]["ok"]
    for batch in (5, 3):  # the policy's graph compiles once, for every batch
        compiled = model.reach_covered(Zonotope.from_point(x0[:batch]), plans[:batch], brake=(system.braking, 6))
        _assert_same(_sets_of(compiled), _sets_of(eager, batch))
        torch.testing.assert_close(compiled[2], eager[2][:batch], rtol=0, atol=1e-12)
    assert counters["frames"]["ok"] == frames + 1 and _step_of(model)._compiled_loop is not None
    actions = eager[2]  # [5, 10, 2]: the plan, then the braking actions at the centres
    assert actions.shape == (5, 10, 2) and torch.equal(actions[:, :4], plans)
    torch.testing.assert_close(actions[:, 4:], system.braking(eager[0].center[:, 3:-1]), rtol=0, atol=0)
    _assert_same(_sets_of(model.reach_covered(initial, actions)), _sets_of(eager))
    with pytest.raises(ValueError, match="brake.*tangents.*tangent map"):
        model.reach_covered(initial, plans, (x0.new_zeros(5, 4, 1), plans.unsqueeze(-1)), brake=(system.braking, 2))
    with pytest.raises(ValueError, match="brake.*local model"):
        fit(system, 200, method="global").reach_covered(initial, plans, brake=(system.braking, 2))


def test_a_braking_policys_tail_is_linearised_in_the_plans_loop(traced):
    """``reach_covered(..., tangents, brake=(policy, steps, policy_tangent))``: compiled, one graph for every batch
    with the eager directions, sets and actions; the tail's actions move with the centres (the policy's
    derivative fed back), and without that feedback the directions differ."""
    system, eager_model, model = traced
    x0, plans, _ = random_plans(system, n_plans=4, horizon=3)
    gen = torch.Generator().manual_seed(3)
    tangents = (torch.randn(4, 4, 2, generator=gen, dtype=x0.dtype), torch.randn(4, 3, 2, 2, generator=gen,
                                                                                   dtype=x0.dtype))

    def policy(x):  # a brake whose derivative is not zero
        return torch.stack((-0.5 * x[..., 3], 0.2 * torch.sin(x[..., 2])), -1)

    def policy_tangent(x, directions):  # exact: d policy / dx @ directions
        rows = torch.zeros(*x.shape, 2, dtype=x.dtype)
        rows[..., 3, 0], rows[..., 2, 1] = -0.5, 0.2 * torch.cos(x[..., 2])
        return rows.transpose(-1, -2) @ directions

    brake = (policy, 5, policy_tangent)
    eager = eager_model.reach_covered(Zonotope.from_point(x0), plans, tangents, brake)
    frames = counters["frames"]["ok"]
    for batch in (4, 2):
        compiled = model.reach_covered(Zonotope.from_point(x0[:batch]), plans[:batch],
                                       tuple(t[:batch] for t in tangents), brake)
        _assert_same(_sets_of(compiled), _sets_of(eager, batch))
        for new, old in zip(compiled[2:], eager[2:]):  # directions [B, 8, n, 2], actions [B, 8, 2]
            torch.testing.assert_close(new, old[:batch], rtol=1e-9, atol=1e-12)
    assert counters["frames"]["ok"] == frames + 1 and _step_of(model)._compiled_loop is not None
    directions, actions = eager[2:]
    assert directions.shape == (4, 8, 4, 2) and torch.equal(actions[:, :3], plans)
    torch.testing.assert_close(actions[:, 3:], policy(eager[0].center[:, 2:-1]), rtol=0, atol=0)
    open_loop = model.reach_covered(Zonotope.from_point(x0), actions, (tangents[0], torch.cat(
        (tangents[1], tangents[1].new_zeros(4, 5, 2, 2)), 1)))[2]
    torch.testing.assert_close(open_loop[:, :3], directions[:, :3], rtol=1e-12, atol=1e-14)  # the plan's steps
    assert (open_loop[:, 3:] - directions[:, 3:]).abs().amax() > 1e-3  # the tail's feedback matters


def test_a_policy_the_compiler_cannot_trace_runs_step_by_step_and_keeps_the_loop_for_plans(bicycle):
    system, model = bicycle
    x0, plans, _ = random_plans(system, n_plans=3, horizon=4)
    initial = Zonotope.from_point(x0)

    @torch.compiler.disable
    def opaque(x):  # not traceable: a graph break, which a while_loop body does not allow
        return system.braking(x)

    eager = model.compile_steps(False).reach_covered(initial, plans, brake=(opaque, 3))
    model.compile_steps(backend="aot_eager")
    with pytest.warns(RuntimeWarning, match="plan loop with a braking policy's tail failed.*step by step"):
        compiled = model.reach_covered(initial, plans, brake=(opaque, 3))
    _assert_same(_sets_of(compiled), _sets_of(eager))
    assert torch.equal(compiled[2], eager[2])
    assert _step_of(model)._compiled_loop is not None  # plans without a policy still run as one loop
    _assert_same(_sets_of(model.reach_covered(initial, eager[2])), _sets_of(eager))


def _finished(centers, generators, covered, offset, scale):
    """A ``finish``: the final centre moved by a batched ``offset``, the radii scaled by a constant, ``covered``."""
    return centers[..., -1, :] + offset, generators.abs().sum(-1) * scale, covered


def test_a_finish_runs_in_the_plans_loop(traced, monkeypatch):
    """``reach_covered(..., finish=(function, batched, args))``: compiled, what the function computes from the sets
    in the plan's own graph (one plan, several, with a braking policy's tail) is what it computes from the eager
    sets. A function with a graph break runs after the loop's graph; where the loop with it fails to compile, it runs
    after the loop, with a warning, the same."""
    system, eager_model, model = traced
    x0, plans, _ = random_plans(system, n_plans=5, horizon=4)
    offset = torch.randn(5, x0.shape[-1], generator=torch.Generator().manual_seed(1), dtype=x0.dtype)
    wanted = {}
    for brake in (None, (system.braking, 3)):
        sets, covered, *actions = eager_model.reach_covered(Zonotope.from_point(x0), plans, brake=brake)
        want = wanted.setdefault(brake, (sets.center[:, -1] + offset, 2.0 * sets.generators.abs().sum(-1), covered,
                                         *actions))
        for batch in (5, 1, 3):
            got = model.reach_covered(Zonotope.from_point(x0[:batch]), plans[:batch], brake=brake,
                                      finish=(_finished, (offset[:batch],), (2.0,)))
            assert len(got) == len(want)
            for new, old in zip(got, want):
                torch.testing.assert_close(new, old[:batch], rtol=1e-9, atol=1e-12)
    step, want = _step_of(model), wanted[None]
    opaque = torch.compiler.disable(_finished)
    got = model.reach_covered(Zonotope.from_point(x0), plans, finish=(opaque, (offset,), (2.0,)))
    for new, old in zip(got, want):
        torch.testing.assert_close(new, old, rtol=1e-9, atol=1e-12)

    def failing(*args, **kwargs):
        raise RuntimeError("no C++ compiler on this machine")

    monkeypatch.setattr(step, "_compiled_loop", (*step._compiled_loop[:2], failing, failing))
    monkeypatch.setattr(step, "_finish_in_loop", True)  # the fixture's model is shared: restored after the test
    with pytest.warns(RuntimeWarning, match="plan loop with a `finish` failed.*no C.. compiler.*after the loop"):
        got = model.reach_covered(Zonotope.from_point(x0), plans, finish=(_finished, (offset,), (2.0,)))
    for new, old in zip(got, want):
        torch.testing.assert_close(new, old, rtol=1e-9, atol=1e-12)
    assert not step._finish_in_loop and step._compiled_loop[0] is not failing  # plans without one keep the loop
    with pytest.raises(ValueError, match="finish.*local model"):
        fit(system, 200, method="global").reach_covered(Zonotope.from_point(x0), plans,
                                                         finish=(_finished, (offset,), (2.0,)))


def _sets_of(result, batch=None):
    sets, covered = result[:2]
    return sets.center[:batch], sets.generators.abs().sum(-1)[:batch], covered[:batch]


def test_tangents_need_a_local_model(bicycle):
    system, _ = bicycle
    x0, plans, _ = random_plans(system, n_plans=2, horizon=3)
    model = fit(system, 200, method="global")
    with pytest.raises(ValueError, match="tangents.*local model"):
        model.reach_covered(Zonotope.from_point(x0), plans, (x0.new_zeros(2, x0.shape[-1], 1), plans.unsqueeze(-1)))


def _default_backend_error() -> str | None:
    """Why the default backend cannot build code here (``None`` when it can): no C++ compiler, or a
    trivial function failing to compile. The layer then warns and runs eagerly (tested below)."""
    if shutil.which("c++") is None and shutil.which("g++") is None:
        return "no C++ compiler"
    try:
        torch.compile(lambda x: x * 2 + 1)(torch.ones(3, dtype=torch.float64))
    except Exception as error:  # the backend's own failure, whatever its type
        return f"{type(error).__name__}: {error}"
    return None


def test_the_default_backend_gives_sound_eager_sets_without_recompiling(bicycle):
    reason = _default_backend_error()
    if reason is not None:
        pytest.skip(f"the default compiler backend does not work on this machine ({reason})")
    system, model = bicycle
    x0, plans, _ = random_plans(system, n_plans=8, horizon=10)
    tangents = (torch.randn(8, x0.shape[-1], 4, dtype=x0.dtype), torch.randn(8, 10, 2, 4, dtype=x0.dtype))
    eager = _sets(model.compile_steps(False), x0, plans)
    eager_tangents = model.reach_covered(Zonotope.from_point(x0), plans, tangents)[-1]
    model.compile_steps()  # warmed up on views of the offline data
    compiled_frames = counters["frames"]["ok"]
    _assert_same(_sets(model, x0.clone(), plans.clone()), eager)  # inputs that are not views
    compiled_tangents = model.reach_covered(Zonotope.from_point(x0), plans, tangents)[-1]
    torch.testing.assert_close(compiled_tangents, eager_tangents, rtol=1e-9, atol=1e-12)
    assert counters["frames"]["ok"] == compiled_frames  # no recompilation
    result = sampled(system, model)
    assert result.violations == 0 and result.checked > 10_000
    assert _step_of(model)._compiled is not None  # no fallback: the generated code was checked
    assert _step_of(model)._compiled_loop is not None


def test_a_failing_compiler_falls_back_to_eager_steps_with_a_warning(bicycle, monkeypatch):
    def compile_that_fails(function, **kwargs):
        def call(*args):
            raise RuntimeError("no C++ compiler on this machine")
        return call

    system, model = bicycle
    x0, plans, _ = random_plans(system, n_plans=3, horizon=5)
    eager = _sets(model.compile_steps(False), x0, plans)
    monkeypatch.setattr(torch, "compile", compile_that_fails)
    with pytest.warns(RuntimeWarning) as record:
        model.compile_steps()  # the warm-up meets the failure, on the step and on the plan's loop
    messages = sorted(str(w.message) for w in record)
    assert len(messages) == 2
    assert re.match("the compiled reachable sets of a plan failed .*no C.. compiler.*step by step", messages[0])
    assert re.match("the compiled reachable-set step failed .*no C.. compiler.*eagerly", messages[1])
    _assert_same(_sets(model, x0, plans), eager)
    assert _step_of(model)._compiled is None and _step_of(model)._compiled_loop is None


def test_compiling_needs_a_fixed_generator_width(bicycle):
    _, model = bicycle
    width, model.max_generators = model.max_generators, None
    try:
        with pytest.raises(ValueError, match="max_generators"):
            model.compile_steps()
    finally:
        model.max_generators = width


def test_without_the_loop_plans_run_as_compiled_steps(bicycle):
    system, model = bicycle
    x0, plans, _ = random_plans(system, n_plans=3, horizon=5)
    eager = _sets(model.compile_steps(False), x0, plans)
    model.compile_steps(backend="aot_eager", loop=False)
    assert _step_of(model)._compiled is not None and _step_of(model)._compiled_loop is None
    _assert_same(_sets(model, x0, plans), eager)
    model.compile_steps(backend="aot_eager")  # the same arguments but the loop: rebuilt with it
    assert _step_of(model)._compiled_loop is not None


def test_an_empty_batch_of_plans_gives_empty_sets(traced):
    """Zero plans (a filtered batch that kept none) give zero sets, eager and compiled, not a reshape error."""
    system, eager, compiled = traced
    x0, plans, _ = random_plans(system, n_plans=0)
    for model in (eager, compiled):
        center, radius, covered = _sets(model, x0, plans)
        assert center.shape == (0, 10, 4) and radius.shape == (0, 10, 4) and covered.shape == (0,)
