import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded

from torchrl_brsl.modules import DampedGaussianModule


def _spec():
    return Bounded(low=torch.tensor([0.0, -0.5]), high=torch.tensor([0.25, 0.5]), shape=(2,))


def test_scale_decays_geometrically_to_the_floor():
    noise = DampedGaussianModule(_spec(), sigma_init=0.8, sigma_end=0.05, annealing_num_steps=1000)
    noise.step(500)
    assert noise.sigma.item() == pytest.approx(math.sqrt(0.8 * 0.05), rel=1e-5)  # geometric mean half way
    noise.step(100)
    ratio = noise.sigma.item() / math.sqrt(0.8 * 0.05)
    assert ratio == pytest.approx(noise.decay ** 100, rel=1e-5)
    noise.step(10_000)
    assert noise.sigma.item() == pytest.approx(0.05)


def test_stepping_in_batches_equals_stepping_frame_by_frame():
    batched = DampedGaussianModule(_spec(), sigma_init=0.7, sigma_end=0.01, annealing_num_steps=300)
    single = DampedGaussianModule(_spec(), sigma_init=0.7, sigma_end=0.01, annealing_num_steps=300)
    batched.step(37)
    for _ in range(37):
        single.step()
    assert batched.sigma.item() == pytest.approx(single.sigma.item(), rel=1e-5)


def test_noisy_actions_stay_in_the_spec_and_shrink_with_sigma():
    torch.manual_seed(0)
    spec = _spec()
    noise = DampedGaussianModule(spec, sigma_init=1.0, sigma_end=1e-4, annealing_num_steps=10, std=0.3)
    centre = torch.tensor([0.125, 0.0]).expand(4000, 2)
    wide = noise(TensorDict(action=centre.clone(), batch_size=[4000]))["action"]
    assert spec.is_in(wide) and (wide - centre).abs().mean() > 0.05
    noise.step(10)
    narrow = noise(TensorDict(action=centre.clone(), batch_size=[4000]))["action"]
    assert (narrow - centre).abs().max() < 1e-2


@pytest.mark.parametrize("kwargs, name", [({"sigma_init": 0.0}, "sigma_init"), ({"sigma_end": 2.0}, "sigma_end"),
                                          ({"sigma_end": 0.0}, "sigma_end"),
                                          ({"annealing_num_steps": 0}, "annealing_num_steps")])
def test_bad_arguments_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        DampedGaussianModule(_spec(), **{"sigma_init": 1.0, "sigma_end": 0.1, **kwargs})
