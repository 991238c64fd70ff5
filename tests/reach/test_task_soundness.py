"""The fitted sets contain what the simulated robots actually do (the true MuJoCo system), and the recipes' robots'
sets are not much wider than what the robot does."""
import pytest
import torch

import envs
from torchrl_brsl.reach import (BodyFrame, DataDrivenReach, cells, collect_offline_data, env_sample_reach,
                                env_trajectories, hinges, noiseless_transitions, worst_noise_outside)
from torchrl_brsl.sets import Zonotope

# task options, the offline data, the horizon checked, the share of plans the model must claim
# (inside the data's leaves) and a bound on their final position radius (tight enough to
# navigate with). The uncapped servos are linear; with their caps on, the servos saturate.
CASES = {
    "diffdrive_nav": ({"max_acceleration": None, "max_turn_acceleration": None}, 2000, 4, 1.0, 0.1),
    "point_boxes": ({"max_acceleration": None}, 500, 4, 1.0, 0.1),
    "quadrotor_nav": ({"max_acceleration": None}, 500, 11, 1.0, 0.1),
    # world frame (the heading among the regressors; the body frame below is the recipes' choice): measured 31 of
    # 40 plans claimed, final radius 0.055 m median, 0.093 m at most (the turtlebot's 6 braking steps + 1); 38-39
    # of 40 while the hinge selection stopped at the noise's variance (hinges.STOP_SHARE = 1), 28 of 40 and 0.29 m
    # with the hinges on their grid of directions and knots. Its one-step claim at the worst noise can fail
    # (WORST_NOISE_GAPS)
    "diffdrive_nav:capped": ({}, 2000, 7, 0.75, 0.2),
    # fitted in the body frame (heading (cos θ, sin θ) out of the regressors): measured 40 of 40 claimed, final
    # radius 0.009 m median, 0.029 m at most (world frame: see above)
    "diffdrive_nav:capped:body": ({}, 2000, 7, 0.9, 0.05),
    # the wheeled robot (robot="wheeled": driven wheels on the floor, per-wheel speed ramps), body frame, held to
    # the kinematic robot's bar. The wheel speeds clip along (u_v - v) ± (track / 2)(u_ω - ω), which no grid
    # direction follows: the hinges find them once refined. Measured: 40 of 40 claimed, final radius 0.018 m
    # median, 0.040 m at most (0 of 40 claimed with the hinges on their grid)
    "diffdrive_nav:wheeled:body": ({"robot": "wheeled"}, 2000, 7, 0.9, 0.05),
    # the recipe's 2,000 offline steps, 400 plans (PLANS below). Measured: 400 of 400 claimed, final radius 0.11 m
    # median, 0.48 m at most; 500 steps leave the corners of the velocity box unvisited and put 6 of 4,389 true states
    # outside
    "quadrotor_nav:capped": ({}, 2000, 11, 0.9, 0.6),
    "point_boxes:capped": ({}, 500, 4, 0.9, 0.1),
    # a new wind every episode, not in the state: the data must see the range of winds (OFFLINE_EPISODE below).
    # Measured: 25 of 40 claimed, final radius 0.31 m median, 0.46 m at most. With the task's 400-step episodes
    # the 500 steps saw two winds: 32 of 40 were claimed, and a stronger wind put a sampled velocity 0.03 m/s
    # outside its first set (35 % beyond its radius)
    "hexarotor_wind": ({"max_acceleration": None}, 500, 11, 0.6, 0.5),
    # the rotor-driven multirotors (robot="rotor": rotors, attitude and an onboard cascaded controller), over their
    # n_plan = 17 steps, held to the kinematic robots' bars. Measured: 0 of 40 claimed for either; with 2,000
    # transitions the quadrotor's position radius is 0.28 m after one step and 4 of 40 plans stay covered for two
    "quadrotor_nav:rotor": ({"robot": "rotor"}, 500, 17, 0.9, 1.0),
    "hexarotor_wind:rotor": ({"robot": "rotor"}, 500, 17, 0.75, 0.45),
}


# offline episodes ended early, so that the data see many of what a reset draws (the recipes'
# task.offline.episode_steps)
OFFLINE_EPISODE = {"hexarotor_wind": 50}

# sampled plans (40 otherwise): the capped quadrotor's model from 500 offline steps passed 40 plans and let 6 states of
# 400 plans out (benchmarks/bench_task_soundness.py); 400 plans fail it (checked), the recipe's 2,000 steps pass them
PLANS = {"quadrotor_nav:capped": 400}


# cases whose claimed share falls short for a known reason (their claimed sets must still be sound):
# the rotor robots' attitude is hidden from the state: the same state and action lead to next velocities ~1 m/s apart
# (benchmarks/bench_rotor.py), so the one-step sets are wide and leave the data's leaves within two steps; measuring
# the tilt, rates or held command too, a shaped reference or a jerk-limited acceleration demand, still claims none
# (benchmarks/bench_rotor_state.py)
_HIDDEN_ATTITUDE = "hidden attitude: the next velocity depends on the tilt, not in the state"
KNOWN_GAPS = {"quadrotor_nav:rotor": _HIDDEN_ATTITUDE, "hexarotor_wind:rotor": _HIDDEN_ATTITUDE}

# cases whose one-step claim can fail at the worst noise for a known reason (their sampled plans are sound): the world
# frame fits the heading vector (cos θ, sin θ) on itself; its offline data reach sin θ = 0.89 at most, and the leaves,
# extended a quarter of the range beyond the data, claim headings up to sin θ = 1 with the slope of the data below.
# Whether the fit's leaves miss there follows its optimiser's rounding: measured 15 of 1,000 queries outside, all
# at sin θ = 0.994-0.9995, up to 0.016 beyond the bound on sin θ+ (11 of 1,000 on earlier releases of the
# dependencies, none with the hinges refined along autograd's gradient instead of the closed form). The recipes fit
# the body frame, without the heading among the inputs (docs/limits.md)
WORST_NOISE_GAPS = {"diffdrive_nav:capped": "world-frame heading vector beyond the data's headings"}


# one-step queries along a random walk checked at every vertex of the noise (worst_noise_outside): the claim itself,
# which plans sampled with uniform noise under-test
WORST_NOISE_QUERIES = 1000

# the recipes' robots: a bar on the sets' median width over the spread of 30 noisy copies of the robot along each of
# 10 plans (env_sample_reach). Measured here: 5.40 (capped quadrotor, 2,000 steps), 11.04 (wheeled Turtlebot, body
# frame), 4.01 (capped point_boxes, 500 steps), the bars 27-30 % above (fits differ slightly between CPUs); with 20
# plans of 100 copies (benchmarks/bench_task_tightness.py, which spread more) 4.5, 9.4 and 3.7. Before the hinges
# halfway between fitted ones they were 6.56, 11.07 and 4.20; with 8 hinges over 25 candidate knots 8.35, 11.7 and
# 6.4. The global model's sets are 120-460 times the spread there
WIDTH_BARS = {"quadrotor_nav:capped": 7.0, "diffdrive_nav:wheeled:body": 14.0, "point_boxes:capped": 5.2}


def sampled(name: str, options: dict, steps: int, horizon: int, n_plans: int, body: bool = False, seed: int = 0,
            model: list | None = None):
    """The task's model fitted from ``steps`` random offline steps (torch seed ``seed``), its sets along ``n_plans``
    sampled plans from reachable states, and whether the true states of the claimed plans lie in them: ``(sets,
    claimed [P], inside [C, H])`` (checked for those alone: exactly, by an LP per state beyond 3-D, which the wide
    sets of unclaimed plans make slow). ``model``: a list the fitted model is appended to."""
    torch.manual_seed(seed)
    info = envs.safety_info(name, robot=options.get("robot"))
    episode = {"episode_steps": OFFLINE_EPISODE[name]} if name in OFFLINE_EPISODE else {}
    data = collect_offline_data(envs.make(name, empty=True, seed=11, **options, **episode), steps)
    reach = DataDrivenReach.from_data(data, Zonotope(info.noise_center.double(), info.noise_generators.double()),
                                      translation_invariant_dims=info.position_dims, max_generators=30,
                                      body_frame=BodyFrame(info.position_dims, info.heading_dims) if body else None)
    env = envs.make(name, empty=True, seed=12, episode_steps=10_000, **options)
    x0, plans, visited = env_trajectories(env, n_plans, horizon, info.action_low, info.action_high,
                                          info.braking_action)
    sets, claimed = reach.reach_covered(Zonotope.from_point(x0), plans)  # [plans, H]
    if model is not None:
        model.append(reach)
    return sets, claimed, sets[claimed].contains(visited[claimed])


@pytest.mark.parametrize("case", list(CASES))
def test_sampled_true_trajectories_stay_in_the_reachable_sets(case):
    options, steps, horizon, min_claimed, max_radius = CASES[case]
    gap = KNOWN_GAPS.get(case)
    name = case.split(":")[0]
    info = envs.safety_info(name, robot=options.get("robot"))
    n_plans = PLANS.get(case, 40)
    model = []
    sets, claimed, inside = sampled(name, options, steps, horizon, n_plans, body=case.endswith(":body"), model=model)
    assert inside.all(), f"{int((~inside).sum())} of {inside.numel()} true states outside their sets"
    env = envs.make(name, empty=True, seed=13, **options)
    states, actions, successors = noiseless_transitions(env, WORST_NOISE_QUERIES, torch.Generator().manual_seed(0))
    worst, one_step = worst_noise_outside(model[0], successors, states, actions)
    message = f"{int(worst[one_step].sum())} of {int(one_step.sum())} one-step queries outside at the worst noise"
    assert case in WORST_NOISE_GAPS or not worst[one_step].any(), message
    if gap and claimed.float().mean() < min_claimed:
        pytest.xfail(f"{gap}: {int(claimed.sum())} of {n_plans} plans claimed")
    assert claimed.float().mean() >= min_claimed, f"{int(claimed.sum())} of {n_plans} plans claimed"
    radius = sets.generators[claimed, -1][:, list(info.position_dims)].abs().sum(-1).amax()
    assert radius < max_radius
    if case in WIDTH_BARS:
        torch.manual_seed(1)
        copies = env_sample_reach(model[0], envs.make(name, empty=True, seed=14, episode_steps=10_000, **options), 10,
                                  horizon, info.action_low, info.action_high, info.braking_action, samples=30)
        assert copies.violations == 0 and copies.median_ratio < WIDTH_BARS[case], (
            f"{copies.violations} of {copies.checked} copies' states outside; widths {copies.median_ratio:.2f} "
            f"times the spread")
    if case in WORST_NOISE_GAPS and worst[one_step].any():
        pytest.xfail(f"{WORST_NOISE_GAPS[case]}: {message}")


def test_hinge_selection_past_the_noise_variance_fits_the_quadrotors_bend(monkeypatch):
    """The capped quadrotor from 500 offline steps (torch seed 2), 400 sampled plans of one action then braking:
    no true state outside its set. Teeth: stopping the hinge selection once the whole residual is down to the
    noise's variance (``hinges.STOP_SHARE = 1``, as before) left the vertical servo's smooth bend cut by two
    hinges 0.046 m/s off, and let 2 of 4,389 states out (1.9 mm/s beyond a 0.059 m/s half-width). The bend term
    (:func:`~torchrl_brsl.reach.cells.bend_error`) covers that stray too: the teeth need it off. Teeth of the leaves'
    hidden noise (:data:`~torchrl_brsl.reach.cells.HIDDEN_QUANTILES`): read from the nearest pairs' largest excess
    too, it let 4 states out."""
    horizon = envs.safety_info("quadrotor_nav").n_brk + 1
    _, claimed, inside = sampled("quadrotor_nav", {}, 500, horizon, 400, seed=2)
    assert claimed.float().mean() >= 0.9 and inside.all(), f"{int((~inside).sum())} outside"
    with monkeypatch.context() as patch:  # a leaf's hidden noise read from its largest excess too: 4 outside
        patch.setattr(cells, "HIDDEN_QUANTILES", cells.HIDDEN_QUANTILES + (1.0,))
        _, _, inside = sampled("quadrotor_nav", {}, 500, horizon, 400, seed=2)
        assert not inside.all(), "the sampling should catch a hidden noise that takes a kink's pairs for noise"
    monkeypatch.setattr(hinges, "STOP_SHARE", 1.0)
    monkeypatch.setattr(cells, "bend_error", lambda low, high, features, points=None: low.new_zeros(low.shape[0]))
    _, claimed, inside = sampled("quadrotor_nav", {}, 500, horizon, 400, seed=2)
    assert not inside.all(), "the sampling should catch the bend the early stop leaves"


def test_the_positions_bend_term_from_their_data_is_needed(monkeypatch):
    """The capped quadrotor's position steps have no noise, and their ten hinges fit them to 3e-5 m; their bend term
    (:func:`~torchrl_brsl.reach.cells.bend_error`, bounded by their data's gaps where those are narrower than the
    knots' spacing) is still needed: without it, 7 of the 4,389 true states of the test above's 400 plans (torch seed
    2) fell outside their sets (5 in seed 0), at a quarter of it 1, at half of it none (measured)."""
    horizon = envs.safety_info("quadrotor_nav").n_brk + 1
    original = cells.bend_error
    monkeypatch.setattr(cells, "bend_error", lambda low, high, features, points=None: (
        original(low, high, features) if points is None else low.new_zeros(low.shape[0])))
    _, _, inside = sampled("quadrotor_nav", {}, 500, horizon, 400, seed=2)
    assert not inside.all(), "the sampling should catch the positions' sets without their bend term"


HEADING_CASES = {"diffdrive_nav": ("diffdrive_nav", {}),
                 "diffdrive_nav:wheeled": ("diffdrive_nav", {"robot": "wheeled"}),
                 **{name: (name, {}) for name in ("quadrotor_nav", "hexarotor_wind", "point_boxes", "point_circle")}}


@pytest.mark.parametrize("name, options", HEADING_CASES.values(), ids=HEADING_CASES.keys())
def test_the_fit_finds_the_heading_each_task_declares(name, options):
    """``BodyFrame.detect`` (what ``fit`` uses by default) on 500 random steps of each task: the body frame its
    ``SafetyInfo.heading_dims`` declare, or none where it declares none."""
    info = envs.safety_info(name)
    data = collect_offline_data(envs.make(name, empty=True, seed=1, **options), 500)
    found = BodyFrame.detect(data["x_minus"].double(), data["x_plus"].double(), data["u_minus"].double(),
                             info.position_dims)
    assert found == (BodyFrame(info.position_dims, info.heading_dims) if info.heading_dims else None)
