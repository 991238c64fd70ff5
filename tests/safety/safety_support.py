"""Shared pieces of the safety-layer tests: a fitted model per task and the layer built on it."""
import functools

import torch

import envs
from torchrl_brsl.reach import DataDrivenReach
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe, GradientAdjuster
from torchrl_brsl.sets import Obstacles, Zonotope


#: task options used for both the offline data and the episodes. ``point_boxes`` without its
#: acceleration cap has linear dynamics, where the data-driven sets stay tight.
TASK_OPTIONS = {"point_boxes": {"max_acceleration": None}}


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
