import pytest
import torch

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data, load_offline_data, save_offline_data
from torchrl_brsl.sets import Zonotope


def test_collects_consecutive_transitions_and_restarts_outside_the_data_region():
    torch.manual_seed(0)
    env = envs.make("diffdrive_nav", empty=True, seed=3)
    data = collect_offline_data(env, steps=300)
    assert data.batch_size == torch.Size([300])
    assert data["x_minus"].shape == (300, 6) and data["u_minus"].shape == (300, 2)
    assert data["x_minus"].dtype == torch.float64
    low, high = envs.safety_info("diffdrive_nav").action_low, envs.safety_info("diffdrive_nav").action_high
    assert torch.all(data["u_minus"] >= low) and torch.all(data["u_minus"] <= high)
    # within an episode the next transition starts where the previous one ended
    chained = (data["x_plus"][:-1] - data["x_minus"][1:]).abs().amax(-1) < 1e-6
    assert chained.float().mean() > 0.9


def test_records_what_a_callable_reads_from_the_env_after_each_step():
    """``record``: here the noise each step added, which stays in W and varies from step to step."""
    env = envs.make("point_boxes", empty=True, seed=3)
    data = collect_offline_data(env, steps=50, generator=torch.Generator().manual_seed(0),
                                record=lambda stepped: stepped.task.last_noise)
    info = envs.safety_info("point_boxes")
    noise = data["recorded"]
    assert noise.shape == data["x_plus"].shape and noise.dtype == torch.float64
    radius = info.noise_generators.double().abs().sum(-1)
    assert ((noise - info.noise_center.double()).abs() <= radius + 1e-12).all()
    assert noise.std(0)[radius > 0].min() > 0


def test_save_load_roundtrip_and_fit(tmp_path):
    env = envs.make("diffdrive_nav", empty=True, seed=4)
    data = collect_offline_data(env, steps=100)
    save_offline_data(data, tmp_path / "data")
    loaded = load_offline_data(tmp_path / "data")
    for key in ("x_minus", "x_plus", "u_minus"):
        assert torch.equal(loaded[key], data[key])
    info = envs.safety_info("diffdrive_nav")
    reach = DataDrivenReach.from_data(loaded, Zonotope(info.noise_center.double(), info.noise_generators.double()),
                                      translation_invariant_dims=info.position_dims)
    assert reach.x_minus.shape == (100, 6)


def test_rejects_bad_arguments():
    env = envs.make("diffdrive_nav", empty=True)
    with pytest.raises(ValueError, match="steps"):
        collect_offline_data(env, steps=0)
