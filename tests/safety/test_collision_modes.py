"""The plan checker's two collision checks: the closed form and the LP (polytopes, any dimension)."""
import pytest
import torch
from tensordict import TensorDict

from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import BRSLSafetyLayer, FacetQPAdjuster, Failsafe, PlanChecker
from torchrl_brsl.sets import ConstrainedZonotope, Obstacles, Zonotope, obstacle_batch

from safety_support import obstacles_of

N_PLAN, N_BRK = 3, 8
D = torch.float64


@pytest.fixture(scope="module")
def system():
    return DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)


@pytest.fixture(scope="module", params=["global", "local"])
def reach(system, request):
    x, xp, u = system.offline_data(2000, torch.Generator().manual_seed(0))
    return DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24,
                               method=request.param)


def checker_for(reach, system, collision, position_dims=(0, 1)):
    failsafe = Failsafe(torch.zeros(2, dtype=D), N_BRK, system.braking)
    return PlanChecker(reach, failsafe, N_PLAN + N_BRK, stop_dims=(2, 3), stop_slack=0.1, collision=collision,
                       action_low=system.action_low, action_high=system.action_high, position_dims=position_dims)


def _box_obstacles(n_envs: int) -> Obstacles:
    wall = Zonotope.from_interval(torch.tensor([0.3, -0.4], dtype=D), torch.tensor([0.5, 0.4], dtype=D))
    return obstacles_of(wall.center.expand(n_envs, 1, 2), wall.generators.expand(n_envs, 1, 2, 2),
                        torch.ones(n_envs, 1, dtype=torch.bool))


def test_closed_form_and_lp_agree_on_zonotope_obstacles(reach, system):
    gen = torch.Generator().manual_seed(2)
    x0 = torch.zeros(16, 4, dtype=D)
    x0[:, 2:] = torch.rand(16, 2, generator=gen, dtype=D) * 0.8 - 0.2
    plan = system.sample_actions(16, N_PLAN, generator=gen)
    obstacles = _box_obstacles(16)
    exact = checker_for(reach, system, "exact").evaluate(x0, plan, obstacles)
    lp = checker_for(reach, system, "lp").evaluate(x0, plan, obstacles)
    torch.testing.assert_close(lp.values, exact.values, rtol=1e-5, atol=1e-6)
    assert torch.equal(lp.safe, exact.safe)
    assert exact.safe.any() and not exact.safe.all(), "the scene should mix verdicts"


def test_auto_takes_the_lp_beyond_three_dims_and_exact_refuses(reach, system):
    """An obstacle in (position, velocity) space: no closed form in 4-D."""
    with pytest.raises(ValueError, match="exact"):
        checker_for(reach, system, "exact", position_dims=(0, 1, 2, 3))
    checker = checker_for(reach, system, "auto", position_dims=(0, 1, 2, 3))
    fast = Zonotope.from_interval(torch.tensor([-5.0, -5.0, 0.9, -5.0], dtype=D),
                                  torch.tensor([5.0, 5.0, 5.0, 5.0], dtype=D))  # forward speed above 0.9
    obstacles = obstacles_of(fast.center.view(1, 1, 4).expand(2, 1, 4), fast.generators.view(1, 1, 4, 4).expand(
        2, 1, 4, 4), torch.ones(2, 1, dtype=torch.bool))
    x0 = torch.tensor([[0.0, 0.0, 0.7, 0.0]], dtype=D).expand(2, 4)
    plan = torch.tensor([[[1.0, 0.0]] * N_PLAN, [[-0.5, 0.0]] * N_PLAN], dtype=D)  # speed up to ~1.0, or slow down
    evaluation = checker.evaluate(x0, plan, obstacles)
    assert checker.uses_lp(obstacles)
    assert evaluation.safe.tolist() == [False, True]


def test_polytope_obstacles_need_the_lp(reach, system):
    triangle = ConstrainedZonotope.from_polytope(torch.tensor([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]], dtype=D),
                                                 torch.tensor([-0.3, 0.3, 0.6], dtype=D))
    obstacles = Obstacles(**obstacle_batch([triangle])).reshape(1)
    x0, plan = torch.zeros(1, 4, dtype=D), torch.zeros(1, N_PLAN, 2, dtype=D)
    with pytest.raises(ValueError, match="polytopes"):
        checker_for(reach, system, "exact").evaluate(x0, plan, obstacles)
    assert checker_for(reach, system, "auto").evaluate(x0, plan, obstacles).safe.item()


def test_layer_keeps_the_true_robot_off_polytope_obstacles(system):
    """Closed loop: the layer (polytope obstacles through its TensorDict entry, the facet-QP adjuster falling
    back to projected gradient) behind a policy that drives at the obstacles, on the true sampled system
    (without the layer the same actions enter the first triangle at step 11)."""
    x, xp, u = system.offline_data(2000, torch.Generator().manual_seed(0))
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24)
    H = torch.tensor([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]], dtype=D)
    triangles = [(H, torch.tensor([-0.6, 0.2, 1.1], dtype=D)), (H, torch.tensor([-0.6, 0.7, 0.6], dtype=D))]
    entry = obstacle_batch([ConstrainedZonotope.from_polytope(*t) for t in triangles])
    layer = BRSLSafetyLayer(reach, Failsafe(torch.zeros(2, dtype=D), N_BRK, system.braking), N_PLAN,
                            stop_dims=(2, 3), stop_slack=0.1, action_low=system.action_low,
                            action_high=system.action_high, adjuster=FacetQPAdjuster(), plan_key="unused_plan")
    gen = torch.Generator().manual_seed(4)
    state = torch.zeros(1, 4, dtype=D)
    td = TensorDict(state=state, obstacles=entry.expand(1).clone(), batch_size=[1])
    speeds, intervened = [], 0
    for _ in range(30):
        td["action"] = torch.tensor([[1.0, 0.0]], dtype=D) + 0.3 * torch.randn(1, 2, generator=gen, dtype=D)
        out = layer.inv(td.clone())
        intervened += int(out["brsl", "intervened"].item())
        state = system.step(state, out["action"], gen)
        inside = [bool((H @ state[0, :2] <= h).all()) for H, h in triangles]
        assert not any(inside), f"the true robot entered an obstacle at {state[0, :2].tolist()}"
        speeds.append(float(state[0, 2:].norm()))
        td = out.set("state", state)
    assert intervened > 0, "the policy drives at the obstacles: the layer must have stepped in"
    assert max(speeds) > 0.2, "the robot must move, not freeze"
