"""The stop check's default tolerance, its cap on a low-speed model, and a warning when the check certifies nothing."""
import warnings

import pytest
import torch

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import DEFAULT_STOP_SLACK, BRSLSafetyLayer, Failsafe, PlanChecker
from torchrl_brsl.sets import Zonotope

from safety_support import fitted_reach, make_env

TASK = "point_boxes"
INFO = envs.safety_info(TASK)


def layer(method="global", **kwargs):
    return BRSLSafetyLayer(fitted_reach(TASK, method=method), Failsafe(INFO.braking_action, INFO.n_brk), INFO.n_plan,
                           stop_dims=INFO.velocity_dims, action_low=INFO.action_low, action_high=INFO.action_high,
                           **kwargs)


def test_without_a_tolerance_the_default_slack_applies_and_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the default on point_boxes is a meaningful check
        checker = layer().checker
    assert torch.equal(checker.stop_slack, torch.full((2,), DEFAULT_STOP_SLACK, dtype=torch.float64))
    assert torch.allclose(checker.stop_tolerance, checker.stop_radius + DEFAULT_STOP_SLACK)
    assert checker.vacuous_stop_dims() == []


def test_both_tolerance_and_slack_are_refused():
    with pytest.raises(ValueError, match="at most one of `stop_tolerance` and `stop_slack`"):
        layer(stop_tolerance=0.5, stop_slack=0.1)


@pytest.mark.parametrize("method", ["global", "local"])
def test_a_tolerance_beyond_the_top_speed_warns_that_the_check_certifies_nothing(method):
    top = torch.cat((fitted_reach(TASK, method=method).x_minus, fitted_reach(TASK, method=method).x_plus))
    top = top[:, list(INFO.velocity_dims)].abs().amax(0)  # ~1 m/s on this task
    with pytest.warns(UserWarning, match=r"certifies nothing on stop dims \[2, 3\]") as record:
        checker = layer(method, stop_slack=float(top.max()) + 0.01).checker
    assert "largest |value| in the offline data" in str(record[0].message)
    assert checker.vacuous_stop_dims() == [2, 3]
    # one dim only: a per-dim tolerance beyond the top speed there
    with pytest.warns(UserWarning, match=r"stop dims \[3\]"):
        layer(method, stop_slack=[0.1, float(top[1]) + 0.01])


def test_a_low_speed_model_caps_the_slack_at_half_its_top_speed_and_does_not_warn():
    noise = Zonotope(INFO.noise_center.double(), INFO.noise_generators.double())
    gen = torch.Generator().manual_seed(0)
    data = collect_offline_data(make_env(TASK, empty=True, seed=3), 600,
                                policy=lambda td: td.set("action", (torch.rand(2, generator=gen) * 2 - 1) * 0.12))
    slow = data[(data["x_minus"][:, 2:].abs() <= 0.15).all(-1)]  # the starts of the empty task are fast
    failsafe = Failsafe(INFO.braking_action, INFO.n_brk)
    kwargs = dict(stop_dims=INFO.velocity_dims, action_low=INFO.action_low.double(),
                  action_high=INFO.action_high.double())
    unbounded = DataDrivenReach.from_data(slow, noise, translation_invariant_dims=INFO.position_dims, method="global")
    top = torch.cat((unbounded.x_minus, unbounded.x_plus))[:, list(INFO.velocity_dims)].abs().amax(0)
    assert bool((top < DEFAULT_STOP_SLACK).all())  # the default slack would call every state of these data stopped
    with pytest.warns(UserWarning, match="certifies nothing"):
        PlanChecker(unbounded, failsafe, INFO.n_plan + INFO.n_brk, **kwargs)
    local = DataDrivenReach.from_data(slow, noise, translation_invariant_dims=INFO.position_dims, method="global",
                                      domain="data")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        checker = PlanChecker(local, failsafe, INFO.n_plan + INFO.n_brk, **kwargs)
    assert torch.allclose(checker.stop_slack, top / 2)
    assert checker.vacuous_stop_dims() == []
