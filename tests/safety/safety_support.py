"""Shared pieces of the safety-layer tests: a fitted model per task and the layer built on it, and the fast paths'
scenes and bicycle checker."""
import functools

import torch

import envs
from torchrl_brsl.reach import DataDrivenReach, KinematicBicycle
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe, GradientAdjuster, PlanChecker
from torchrl_brsl.sets import Obstacles, Zonotope


#: task options used for both the offline data and the episodes. ``point_boxes`` without its
#: acceleration cap has linear dynamics, where the data-driven sets stay tight.
TASK_OPTIONS = {"point_boxes": {"max_acceleration": None}}

#: the fast-path tests' plans: planned steps, braking steps, dtype
N_PLAN, N_BRK = 5, 8
D = torch.float64


def make_env(task: str, **kwargs):
    """``envs.make`` with the task options of these tests."""
    return envs.make(task, **TASK_OPTIONS.get(task, {}), **kwargs)


@functools.lru_cache(maxsize=None)
def fitted_reach(task: str, steps: int = 500, seed: int = 0, method: str = "global") -> DataDrivenReach:
    """Offline data from the task's empty variant, fitted once per test session.

    The transform's mechanics are tested on the global model, whose sets of the capped
    diffdrive servos from 500 steps are wide but claimed everywhere; the local model's layer
    behaviour is tested with ``method="local"`` where its data cover the plans.
    """
    info = envs.safety_info(task)
    torch.manual_seed(seed)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    return DataDrivenReach.from_env(make_env(task, empty=True, seed=seed + 1), noise, steps=steps,
                                    translation_invariant_dims=info.position_dims, max_generators=30, method=method)


def make_layer(task: str, **kwargs) -> BRSLSafetyLayer:
    """The safety layer for ``task`` with a stop tolerance just above the final set's radius.

    The tasks used here are velocity-commanded: braking is the open-loop zero command.
    """
    info = envs.safety_info(task)
    reach = fitted_reach(task)
    horizon = info.n_plan + info.n_brk
    radius = reach.error_generators_sequence(horizon)[-1, list(info.velocity_dims)].abs().sum(-1)
    options = dict(stop_dims=info.velocity_dims, stop_tolerance=(radius + 0.15).tolist(),
                   action_low=info.action_low, action_high=info.action_high)
    options.update(kwargs)
    return BRSLSafetyLayer(reach, Failsafe(info.braking_action, info.n_brk), info.n_plan,
                           **options)


def obstacles_of(centers, generators, mask) -> Obstacles:
    """The :class:`Obstacles` of loose ``center [B, K, d]``, ``generators [B, K, d, p]`` and ``mask [B, K]``."""
    return Obstacles(centers, generators, mask)


def assert_closed_form_matches_autograd(checker, x0, plan, centers, generators, mask, iterations: int) -> None:
    """The gradient adjuster's closed-form iteration takes the same steps as autograd (to 1e-9)."""
    assert not checker.evaluate(x0, plan, obstacles_of(centers, generators, mask)).safe.all()
    fast = GradientAdjuster(max_iterations=iterations, time_budget=None)
    slow = GradientAdjuster(max_iterations=iterations, time_budget=None)
    slow._analytic = False
    a = fast(checker, x0, plan, obstacles_of(centers, generators, mask))
    b = slow(checker, x0, plan, obstacles_of(centers, generators, mask))
    assert torch.equal(a.iterations, b.iterations) and a.iterations.max() > 0
    torch.testing.assert_close(a.plan, b.plan, rtol=0, atol=1e-9)
    for x, y in zip(a.evaluation, b.evaluation):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-9)


def scene(n_envs=3, n_obstacles=4, seed=0):
    """A random batch of double-integrator-sized states, plans and zonotope obstacles (2-D, 3 generators)."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.cat((torch.randn(n_envs, 2, generator=g, dtype=D) * 0.1,
                    torch.randn(n_envs, 2, generator=g, dtype=D) * 0.3), dim=1)
    plan = torch.rand(n_envs, N_PLAN, 2, generator=g, dtype=D) * 2 - 1
    centers = torch.randn(n_envs, n_obstacles, 2, generator=g, dtype=D) * 0.8
    generators = torch.randn(n_envs, n_obstacles, 2, 3, generator=g, dtype=D) * 0.15
    mask = torch.rand(n_envs, n_obstacles, generator=g) > 0.25
    return x0, plan, centers, generators, mask


def bicycle_checker(policy):
    """A local model of the bicycle in its body frame (500 steps) and its checker, braking open loop or by policy."""
    bicycle = KinematicBicycle()
    x, xp, u = bicycle.offline_data(500, torch.Generator().manual_seed(0))
    reach = DataDrivenReach.fit(x, xp, u, bicycle.noise, translation_invariant_dims=(0, 1), max_generators=24,
                                body_frame=bicycle.body_frame)
    return bicycle, PlanChecker(reach, Failsafe(torch.zeros(2, dtype=D), N_BRK, bicycle.braking if policy else None),
                                N_PLAN + N_BRK, stop_dims=(3,), stop_slack=0.1, action_low=bicycle.action_low,
                                action_high=bicycle.action_high)
