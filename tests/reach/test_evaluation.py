"""Checking fitted sets against the true system: the worst-noise one-step check, the containment test, and sampled
trajectories of a simulated robot."""
import types

import pytest
import torch

import envs
from torchrl_brsl.reach import (DataDrivenReach, DoubleIntegrator, env_sample_reach, noiseless_transitions,
                                points_outside, sample_reach, worst_noise_outside)
from torchrl_brsl.sets import Zonotope

from reach_support import shared_fit


def _queries(system, num=400, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return system.sample_states(num, gen) * 0.7, system.sample_actions(num, generator=gen)


def test_a_successor_past_the_set_by_a_hair_at_a_noise_vertex_is_caught_where_uniform_noise_misses_it():
    """A fake true system puts ``f + W`` inside the one-step set but for its last state dim, 1e-6 past the set's
    edge at one corner of ``W``: every query is flagged, and the same system sampled with uniform noise (300 draws
    per query) is flagged on none."""
    system = DoubleIntegrator()
    reach = shared_fit(system, 500, method="global")
    states, actions = _queries(system)
    sets = reach.reach(Zonotope.from_point(states), actions.unsqueeze(1))[:, 0]
    noise = reach.noise
    edge = sets.generators.abs().sum(-1) - noise.generators.abs().sum(-1)  # [Q, n] room left for f around the centre

    inside = sets.center - noise.center
    past = inside.clone()
    past[:, -1] += edge[:, -1] + 1e-6

    outside, claimed = worst_noise_outside(reach, inside, states, actions)
    assert claimed.all() and not outside.any()
    outside, _ = worst_noise_outside(reach, past, states, actions)
    assert outside.all()

    gen = torch.Generator().manual_seed(2)
    caught = 0
    for index in range(0, len(states), 40):
        def uniform_step(x, u, nominal=past[index]):
            return nominal + (torch.rand(x.shape, generator=gen, dtype=x.dtype) * 2 - 1) @ noise.generators.T + \
                noise.center

        result = sample_reach(reach, uniform_step, states[index:index + 1], actions[index:index + 1, None], 300)
        caught += result.violations
    assert caught == 0, "a hair past one corner of W should be all but invisible to uniform noise"


def test_given_successors_check_as_the_dynamics_in_chunks():
    system = DoubleIntegrator()
    reach = shared_fit(system, 500, method="global")
    states, actions = _queries(system)
    shifted = system.dynamics(states, actions)
    shifted[::3, -1] += 1.0  # every third query far past its set
    assert not worst_noise_outside(reach, system.dynamics, states, actions)[0].any()
    given = worst_noise_outside(reach, shifted, states, actions, chunk=64)
    assert torch.equal(given[0], torch.arange(len(states)) % 3 == 0) and given[1].all()


def test_worst_noise_outside_and_noiseless_transitions_reject_bad_input_by_name():
    system = DoubleIntegrator()
    reach = shared_fit(system, 500, method="global")
    states, actions = _queries(system)
    with pytest.raises(ValueError, match="`states` must be"):
        worst_noise_outside(reach, system.dynamics, states, actions[:-1])
    with pytest.raises(ValueError, match="`dynamics` as successors"):
        worst_noise_outside(reach, states[:-1], states, actions)
    with pytest.raises(TypeError, match="`env` must be a task"):
        noiseless_transitions(types.SimpleNamespace(), 10)


def test_points_outside_checks_a_dim_of_zero_width_exactly_without_an_lp(monkeypatch):
    """Sets exact in one of four dims (a rotor robot's idle offset): a point 1e-9 off in that dim, or past the edge
    of another, is outside; the rest inside. Pairs with the exact dim are segments, for which the closed form does
    not hold: they are left to the axes, so no LP runs."""
    import torchrl_brsl.sets.zonotope as zonotope

    def no_lp(*args):
        raise AssertionError("an LP ran")

    monkeypatch.setattr(zonotope, "gauge_lp", no_lp)
    gen = torch.Generator().manual_seed(0)
    generators = torch.randn(5, 4, 6, generator=gen, dtype=torch.float64)
    generators[:, 3] = 0.0
    sets = Zonotope(torch.randn(5, 4, generator=gen, dtype=torch.float64), generators)
    inside = sets.sample(50, generator=gen)  # [50, 5, 4]
    off_exact, past_edge = inside.clone(), inside.clone()
    off_exact[..., 3] += 1e-9
    past_edge[..., 0] = sets.center[..., 0] + 1.001 * generators[:, 0].abs().sum(-1)
    assert not points_outside(sets, inside).any()
    assert points_outside(sets, off_exact).all() and points_outside(sets, past_edge).all()


def test_env_sample_reach_spreads_copies_of_a_mujoco_robot_by_their_noise_alone():
    """Each plan's trajectories start from one reached state in copies of the env that differ only by their noise's
    seed: the local model's sets hold them with widths a few times their spread; without noise every copy takes the
    same path (no spread: no ratio); with the noise at a vertex of ``W`` throughout, the first step's samples spread
    over all of ``W``; sets shrunk (leaves' errors and noise to 0.3) let states out."""
    info = envs.safety_info("point_boxes")
    torch.manual_seed(0)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    reach = DataDrivenReach.from_env(envs.make("point_boxes", empty=True, seed=1), noise, steps=500,
                                     translation_invariant_dims=info.position_dims, max_generators=30)
    bounds = (info.action_low, info.action_high, info.braking_action)
    horizon = info.n_brk + 1

    def run(kind="uniform"):  # the same starts and plans for every call
        torch.manual_seed(1)
        env = envs.make("point_boxes", empty=True, seed=2, episode_steps=10_000)
        return env, env_sample_reach(reach, env, 6, horizon, *bounds, samples=30, noise=kind)

    env, result = run()
    assert result.outside.shape == result.width_ratio.shape == (6, horizon) and result.samples == 30
    assert result.checked >= 3 * horizon * 30 and result.violations == 0
    assert 1.0 <= result.median_ratio < 10.0
    assert result.starts.shape == (6, 4) and result.plans.shape == (6, horizon, 2)  # what was sampled, to re-check
    assert torch.equal(reach.reach_covered(Zonotope.from_point(result.starts), result.plans)[1], result.covered)
    velocities = result.median_dim_ratio[2:]  # the noise enters there: they spread from the first step
    assert result.dim_ratio.shape == (6, horizon, 4) and bool(((velocities >= 1) & (velocities < 10)).all())
    vertices = run("vertices")[1]  # each copy's noise at a vertex of W: the first step spreads over all of W
    claimed = result.covered & vertices.covered
    assert vertices.violations == 0 and bool(claimed.any())
    assert bool((vertices.dim_ratio[claimed, 0, 2:] < result.dim_ratio[claimed, 0, 2:]).all())
    env.task.noise_scale = 0.0
    assert env_sample_reach(reach, env, 2, horizon, *bounds, samples=5).median_ratio == float("inf")
    env.task.noise_scale = 1.0
    errors, widths = reach.cell_errors.clone(), reach.noise_generators.clone()
    try:
        reach.cell_errors.mul_(0.3)
        reach.noise_generators.mul_(0.3)
        assert env_sample_reach(reach, env, 6, horizon, *bounds, samples=30).violations > 0
    finally:
        reach.cell_errors.copy_(errors)
        reach.noise_generators.copy_(widths)
    with pytest.raises(TypeError, match="`env` must be a task of `envs`"):
        env_sample_reach(reach, types.SimpleNamespace(), 1, horizon, *bounds)
    with pytest.raises(ValueError, match="`noise` must be"):
        env_sample_reach(reach, env, 1, horizon, *bounds, noise="gaussian")


def test_env_sample_reach_checks_the_plans_as_the_robot_applies_them():
    """The env applies float32 actions; the sets are of the same values. The global model of the uncapped hexarotor
    keeps its height and vertical offset exact (zero width: no noise there), which a float64 plan's rounding put
    about 5e-9 outside at every sample."""
    info = envs.safety_info("hexarotor_wind")
    torch.manual_seed(0)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    reach = DataDrivenReach.from_env(envs.make("hexarotor_wind", empty=True, seed=1, max_acceleration=None,
                                               episode_steps=50), noise, steps=300, method="global",
                                     translation_invariant_dims=info.position_dims)
    env = envs.make("hexarotor_wind", empty=True, seed=2, episode_steps=10_000, max_acceleration=None)
    result = env_sample_reach(reach, env, 2, 3, info.action_low, info.action_high, info.braking_action, samples=10)
    assert result.checked == 2 * 3 * 10 and result.violations == 0
