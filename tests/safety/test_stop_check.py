"""The stop check's default tolerance, and a warning when the check certifies nothing."""
import warnings

import pytest
import torch

import envs
from torchrl_brsl.safety import DEFAULT_STOP_SLACK, BRSLSafetyLayer, Failsafe

from safety_support import fitted_reach

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
