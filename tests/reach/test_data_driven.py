import itertools

import pytest
import torch
from torch import Tensor

from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator, Unicycle
from torchrl_brsl.sets import Zonotope
from torchrl_brsl.sets.lp import gauge_lp

SYSTEMS = {"double_integrator": DoubleIntegrator, "unicycle": Unicycle}


def fit(system, num=500, seed=0, **kwargs):
    """The global model: this file tests its one-fit form (the local default is in test_cells.py)."""
    kwargs.setdefault("method", "global")
    gen = torch.Generator().manual_seed(seed)
    x, xp, u = system.offline_data(num, gen)
    return DataDrivenReach.fit(x, xp, u, system.noise,
                               translation_invariant_dims=system.translation_invariant_dims, **kwargs)


def containment_violations(sets: Zonotope, points: Tensor, n_directions=256, n_exact=12, seed=0):
    """Points of ``points`` [K, n] outside the unbatched set: exact for every 2-D coordinate
    projection, support-function check along random directions, and HiGHS on the most
    extreme points."""
    n = sets.dim
    outside = torch.zeros(len(points), dtype=torch.bool)
    for dims in itertools.combinations(range(n), 2):
        outside |= ~sets.project(dims).contains(points[:, list(dims)])
    gen = torch.Generator().manual_seed(seed)
    d = torch.randn(n_directions, n, generator=gen, dtype=points.dtype)
    support = d @ sets.center + (d @ sets.generators).abs().sum(-1)
    ratio = ((points - sets.center) @ d.T) / (support - d @ sets.center)
    outside |= (ratio > 1 + 1e-9).any(-1)
    extreme = ratio.amax(-1).topk(min(n_exact, len(points))).indices
    G = sets.generators.numpy()
    for i in extreme.tolist():
        outside[i] |= gauge_lp(G, (points[i] - sets.center).numpy()) > 1 + 1e-7
    return int(outside.sum())



@pytest.mark.parametrize("name", SYSTEMS)
def test_sampled_true_states_lie_in_reachable_sets(name, capsys):
    """>= 20,000 true states along random plans of length 10 lie in the computed sets."""
    system = SYSTEMS[name]()
    reach = fit(system, max_generators=24)
    gen = torch.Generator().manual_seed(1)
    n_plans, per_plan, horizon = 5, 4000, 10
    center = (system.state_low + system.state_high) / 2
    half = (system.state_high - system.state_low) / 2
    total = 0
    for _ in range(n_plans):
        # start well inside the data region so the plan stays in it
        x0 = center + 0.4 * half * (torch.rand(system.state_low.shape, generator=gen, dtype=torch.float64) * 2 - 1)
        x0[list(system.translation_invariant_dims)] = 0.0
        plan = system.sample_actions(horizon, generator=gen) * 0.8
        sets = reach.reach(Zonotope.from_point(x0), plan)
        x = x0.expand(per_plan, -1)
        for j in range(horizon):
            x = system.step(x, plan[j], gen)
            assert containment_violations(sets[j], x) == 0, f"step {j + 1}: true states outside R_{j + 1}"
            total += per_plan
        lo, hi = sets[-1].interval()
        ratio = (hi - lo) / (x.amax(0) - x.amin(0))
        with capsys.disabled():
            print(f"\n[{name}] R_{horizon} interval width / sampled hull width per dim: "
                  + ", ".join(f"{r:.2f}" for r in ratio.tolist()))
    assert total >= 20_000


@pytest.mark.parametrize("name", SYSTEMS)
def test_fitted_form_matches_literal_per_step_form(name):
    system = SYSTEMS[name]()
    reach = fit(system)
    gen = torch.Generator().manual_seed(3)
    x0 = system.sample_states(1, gen)[0]
    init = Zonotope(x0, 0.01 * torch.eye(system.state_low.numel(), dtype=torch.float64))
    plan = system.sample_actions(10, generator=gen)
    fitted = reach.reach(init, plan)
    literal = reach.reach_literal(init, plan)
    torch.testing.assert_close(fitted.center, literal.center, rtol=0, atol=1e-9)
    torch.testing.assert_close(fitted.generators, literal.generators, rtol=0, atol=1e-9)


def test_literal_form_is_the_papers_pinv_model():
    """The literal path really recomputes M_j: perturbing the data changes both paths alike."""
    system = DoubleIntegrator()
    reach = fit(system)
    M_global = torch.cat((reach.state_matrix[:, 2:], reach.input_matrix), dim=1)
    x, u = reach.x_minus, reach.u_minus
    x_star, u_star = x[7], u[3]
    target = reach.x_plus - reach.noise_center
    target[:, :2] -= x[:, :2]
    regressors = torch.cat((torch.ones(len(x), 1, dtype=x.dtype), x[:, 2:] - x_star[2:], u - u_star), dim=1)
    M_j = target.T @ torch.linalg.pinv(regressors.T)
    torch.testing.assert_close(M_j[:, 1:], M_global, rtol=0, atol=1e-9)


def test_batched_reach_matches_unbatched_and_broadcasts():
    system = DoubleIntegrator()
    reach = fit(system, max_generators=12)
    gen = torch.Generator().manual_seed(4)
    x0 = system.sample_states(3, gen)
    plans = system.sample_actions(2, 3, 7, generator=gen)
    sets = reach.reach(Zonotope.from_point(x0), plans)
    assert sets.batch_size == torch.Size([2, 3, 7])
    assert sets.generators.shape == (2, 3, 7, 4, 12)
    single = reach.reach(Zonotope.from_point(x0[1]), plans[0, 1])
    torch.testing.assert_close(sets[0, 1].center, single.center)
    torch.testing.assert_close(sets[0, 1].generators, single.generators)


def test_reduction_bounds_generator_count_and_stays_outer():
    system = DoubleIntegrator()
    full = fit(system)
    reduced = fit(system, max_generators=8)
    gen = torch.Generator().manual_seed(5)
    plan = system.sample_actions(30, generator=gen)
    x0 = torch.zeros(4, dtype=torch.float64)
    big = full.reach(Zonotope.from_point(x0), plan)
    small = reduced.reach(Zonotope.from_point(x0), plan)
    assert small.generators.shape[-1] == 8
    assert big.generators.shape[-1] == 30 * full.error_generators.shape[1]
    for j in (0, 9, 29):
        pts = big[j].sample(2000, gen)
        assert containment_violations(small[j], pts) == 0


def test_gradients_with_respect_to_actions_and_initial_centre():
    system = Unicycle()
    reach = fit(system)
    gen = torch.Generator().manual_seed(6)
    plan = system.sample_actions(6, generator=gen).requires_grad_()
    x0 = system.sample_states(1, gen)[0].requires_grad_()
    torch.autograd.gradcheck(lambda p, c: reach.reach(Zonotope.from_point(c), p).center, (plan, x0))


def test_save_and_load_roundtrip(tmp_path):
    system = Unicycle()
    reach = fit(system, max_generators=10)
    path = tmp_path / "reach.pt"
    reach.save(path)
    loaded = DataDrivenReach.load(path)
    plan = system.sample_actions(5, generator=torch.Generator().manual_seed(0))
    x0 = Zonotope.from_point(torch.zeros(4, dtype=torch.float64))
    a, b = reach.reach(x0, plan), loaded.reach(x0, plan)
    torch.testing.assert_close(a.center, b.center, rtol=0, atol=0)
    torch.testing.assert_close(a.generators, b.generators, rtol=0, atol=0)
    assert loaded.translation_invariant_dims == (0, 1) and loaded.covering_radius == reach.covering_radius


def test_load_state_dict_rebuilds_what_the_model_derived_from_its_buffers():
    """``load_state_dict`` copies into the buffers in place; the sets follow the loaded model, not tables derived from
    the old one (the global model's transfer matrices, the local model's leaf rows; both cached at the first reach)."""
    system = Unicycle()
    plan = system.sample_actions(5, generator=torch.Generator().manual_seed(0))
    x0 = Zonotope.from_point(torch.zeros(4, dtype=torch.float64))
    old, new = fit(system, 400, seed=0), fit(system, 400, seed=1)
    old.reach(x0, plan)
    old.load_state_dict(new.state_dict())
    got, want = old.reach(x0, plan), new.reach(x0, plan)
    torch.testing.assert_close(got.center, want.center, rtol=0, atol=0)
    torch.testing.assert_close(got.generators, want.generators, rtol=0, atol=0)
    local = fit(system, 400, method="local", max_generators=10)
    before = local.reach(x0, plan).center
    state = local.state_dict()
    state["cell_offset"] = state["cell_offset"] + 0.5  # every leaf's model moved by 0.5 on every output
    local.load_state_dict(state)
    torch.testing.assert_close(local.reach(x0, plan).center[0], before[0] + 0.5, rtol=0, atol=1e-12)


def test_translation_invariance_is_exact():
    system = DoubleIntegrator()
    reach = fit(system)
    plan = system.sample_actions(5, generator=torch.Generator().manual_seed(0))
    x0 = torch.tensor([0.0, 0.0, 0.3, -0.2], dtype=torch.float64)
    shift = torch.tensor([5.0, -3.0, 0.0, 0.0], dtype=torch.float64)
    a = reach.reach(Zonotope.from_point(x0), plan)
    b = reach.reach(Zonotope.from_point(x0 + shift), plan)
    torch.testing.assert_close(b.center - a.center, shift.expand_as(a.center))
    assert reach.state_matrix[:2, :2].equal(torch.eye(2, dtype=torch.float64))


def test_several_trajectories_and_data_distance():
    system = DoubleIntegrator()
    gen = torch.Generator().manual_seed(0)
    parts = [system.offline_data(200, gen) for _ in range(3)]
    reach = DataDrivenReach.fit([p[0] for p in parts], [p[1] for p in parts], [p[2] for p in parts], system.noise,
                                translation_invariant_dims=(0, 1))
    assert reach.x_minus.shape == (600, 4)
    inside = reach.data_distance(reach.x_minus[:5], reach.u_minus[:5])
    assert torch.all(inside == 0)
    far = reach.data_distance(torch.tensor([0.0, 0.0, 50.0, 50.0], dtype=torch.float64),
                              torch.zeros(2, dtype=torch.float64))
    assert far > reach.covering_radius


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(x_plus=torch.zeros(10, 3)), "x_plus"),
        (dict(u_minus=torch.zeros(9, 2)), "u_minus"),
        (dict(x_minus=torch.full((10, 4), float("nan"))), "x_minus"),
        (dict(x_minus=torch.zeros(10, 4, dtype=torch.long)), "x_minus"),
        (dict(noise=Zonotope(torch.zeros(2), torch.eye(2))), "noise"),
        (dict(translation_invariant_dims=(0, 7)), "translation_invariant_dims"),
    ],
)
def test_fit_rejects_bad_input(kwargs, match):
    args = dict(x_minus=torch.rand(10, 4), x_plus=torch.rand(10, 4), u_minus=torch.rand(10, 2),
                noise=Zonotope(torch.zeros(4), 0.01 * torch.eye(4)))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        DataDrivenReach.fit(**args)


def test_reach_rejects_bad_actions():
    reach = fit(DoubleIntegrator())
    with pytest.raises(ValueError, match="actions"):
        reach.reach(Zonotope.from_point(torch.zeros(4, dtype=torch.float64)), torch.zeros(5, 3))
    with pytest.raises(ValueError, match="actions"):
        reach.reach(Zonotope.from_point(torch.zeros(4, dtype=torch.float64)), torch.full((5, 2), float("nan")))



def _low_speed_domain(speed):
    """Double integrator ``(x, y, vx, vy, ax, ay)``: ``|vx|, |vy| <= speed``."""
    low = torch.full((6,), -torch.inf, dtype=torch.float64)
    high = torch.full((6,), torch.inf, dtype=torch.float64)
    low[2:4], high[2:4] = -speed, speed
    return low, high


def test_domain_model_drops_data_outside_and_has_tighter_sets():
    system = DoubleIntegrator(drag=1.0)  # quadratic drag: nearly linear only at low speed
    full = fit(system, num=2000, max_generators=12)
    slow = fit(system, num=4000, max_generators=12, domain=_low_speed_domain(0.5))
    assert not full.bounded_domain and slow.bounded_domain
    assert 0 < slow.x_minus.shape[0] < 4000 and bool((slow.x_minus[:, 2:].abs() <= 0.5).all())
    position = [e.abs().sum(-1)[:, :2].amax() for e in (full.error_generators_sequence(5),
                                                          slow.error_generators_sequence(5))]
    assert position[1] < 0.6 * position[0]


def test_domain_model_is_sound_inside_its_domain_and_in_domain_says_where():
    system = DoubleIntegrator(drag=1.0)
    slow = fit(system, num=4000, max_generators=12, domain=_low_speed_domain(0.5))
    gen = torch.Generator().manual_seed(3)
    horizon, per_plan, checked = 4, 2000, 0
    for _ in range(12):
        x0 = torch.zeros(4, dtype=torch.float64)
        x0[2:] = 0.2 * (torch.rand(2, generator=gen, dtype=torch.float64) * 2 - 1)
        plan = system.sample_actions(horizon, generator=gen)
        sets = slow.reach(Zonotope.from_point(x0), plan)
        starts = Zonotope(torch.cat((x0[None], sets.center[:-1])),
                          torch.cat((torch.zeros_like(sets.generators[:1]), sets.generators[:-1])))
        if not bool(slow.in_domain(starts, plan)):
            continue
        x = x0.expand(per_plan, -1)
        for j in range(horizon):
            x = system.step(x, plan[j], gen)
            assert containment_violations(sets[j], x) == 0, f"step {j + 1}: true states outside R_{j + 1}"
        checked += 1
    assert checked >= 3
    # accelerating past the domain's speed bound leaves it
    fast = torch.ones(horizon, 2, dtype=torch.float64)
    sets = slow.reach(Zonotope.from_point(torch.tensor([0.0, 0.0, 0.3, 0.0], dtype=torch.float64)), fast)
    assert not bool(slow.in_domain(sets, fast))


def test_domain_survives_save_and_load_and_bad_domains_are_rejected(tmp_path):
    system = DoubleIntegrator()
    slow = fit(system, num=1000, domain=_low_speed_domain(0.8))
    slow.save(tmp_path / "slow.pt")
    loaded = DataDrivenReach.load(tmp_path / "slow.pt")
    assert torch.equal(loaded.domain_high, slow.domain_high) and loaded.bounded_domain
    x, xp, u = system.offline_data(200, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="domain"):
        DataDrivenReach.fit(x, xp, u, system.noise, domain=(torch.zeros(6), torch.zeros(6)))
    with pytest.raises(ValueError, match="domain"):
        DataDrivenReach.fit(x, xp, u, system.noise, domain=(torch.zeros(4), torch.ones(4)))
    with pytest.raises(ValueError, match="in `domain`"):
        DataDrivenReach.fit(x, xp, u, system.noise, domain=_low_speed_domain(1e-6))


def test_from_env_draws_its_inputs_from_the_generator():
    import envs

    info = envs.safety_info("point_boxes")
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    fits = [DataDrivenReach.from_env(envs.make("point_boxes", empty=True, seed=3), noise, steps=40, method="global",
                                     generator=torch.Generator().manual_seed(seed),
                                     translation_invariant_dims=info.position_dims) for seed in (0, 0, 1)]
    assert torch.equal(fits[0].u_minus, fits[1].u_minus)
    assert not torch.equal(fits[0].u_minus, fits[2].u_minus)


def test_domain_from_the_data_is_their_box_with_the_invariant_dims_unbounded():
    system = DoubleIntegrator()
    x, xp, u = system.offline_data(300, torch.Generator().manual_seed(0))
    keep = (x[:, 2:].abs() <= 0.4).all(-1)  # low-speed data, as a user would collect for a local model
    slow = DataDrivenReach.fit(x[keep], xp[keep], u[keep], system.noise, translation_invariant_dims=(0, 1),
                               method="global", domain="data")
    points = torch.cat((x[keep], u[keep]), dim=1)
    assert slow.bounded_domain and slow.x_minus.shape[0] == int(keep.sum())  # nothing of its own data is dropped
    assert torch.isinf(slow.domain_low[:2]).all() and torch.isinf(slow.domain_high[:2]).all()
    assert torch.equal(slow.domain_low[2:], points.amin(0)[2:])
    assert torch.equal(slow.domain_high[2:], points.amax(0)[2:])
    fast = Zonotope.from_point(torch.tensor([0.0, 0.0, 1.5, 0.0], dtype=torch.float64))  # a speed it never saw
    assert not bool(slow.in_domain(fast.unsqueeze(0), u[:1]))
    with pytest.raises(ValueError, match="'data'"):
        DataDrivenReach.fit(x, xp, u, system.noise, domain="box")
    with pytest.raises(ValueError, match="do not vary on dims"):
        DataDrivenReach.fit(x, xp, torch.cat((u[:, :1], torch.zeros_like(u[:, 1:])), 1), system.noise, domain="data")
