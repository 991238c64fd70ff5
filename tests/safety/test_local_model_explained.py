"""A local low-speed model that can never verify a plan says why, at construction."""
import functools
import warnings

import pytest
import torch

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

from safety_support import fitted_reach, make_env

TASK = "point_boxes"
INFO = envs.safety_info(TASK)
INF = float("inf")


@functools.lru_cache(maxsize=None)
def slow_data(slow: float):
    gen = torch.Generator().manual_seed(0)
    return collect_offline_data(make_env(TASK, empty=True, seed=3), 800,
                                policy=lambda td: td.set("action", (torch.rand(2, generator=gen) * 2 - 1) * slow))


def local_model(slow: float, speed_cap: float) -> DataDrivenReach:
    noise = Zonotope(INFO.noise_center.double(), INFO.noise_generators.double())
    domain = (torch.tensor([-INF, -INF, -speed_cap, -speed_cap, -slow, -slow]),
              torch.tensor([INF, INF, speed_cap, speed_cap, slow, slow]))
    return DataDrivenReach.from_data(slow_data(slow), noise, domain=domain, translation_invariant_dims=INFO.position_dims,
                                     max_generators=30, method="global")


def layer(local):
    return BRSLSafetyLayer(fitted_reach(TASK), Failsafe(INFO.braking_action, INFO.n_brk), INFO.n_plan,
                           stop_dims=INFO.velocity_dims, action_low=INFO.action_low, action_high=INFO.action_high,
                           local_reach=local)


def test_a_domain_narrower_than_the_models_one_step_error_is_explained():
    local = local_model(0.05, 0.02)  # speeds within 0.02 m/s; the noise alone moves them 0.01 per step
    radius = float(local.error_generators_sequence(1)[0, 2].abs().sum())
    assert radius > 0.02
    with pytest.warns(UserWarning, match=r"`local_reach` will never verify a plan: braking from rest, its set after "
                                         r"1 step\(s\) spans .* on state dim 2, outside its domain \[-0.02, 0.02\]"):
        built = layer(local)
    assert "one-step error alone is" in built.local_model_unusable()


def test_a_usable_local_model_raises_no_such_warning():
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        built = layer(local_model(0.3, 0.4))
    assert built.local_model_unusable() == ""
    assert not [w for w in record if "local_reach" in str(w.message)]
