import copy

import pytest
import torch

from torchrl_brsl.models import Normalizer


def test_identity_before_data():
    norm = Normalizer(3)
    x = torch.randn(10, 3)
    assert torch.equal(norm.normalize(x), x)
    assert torch.equal(norm.denormalize(x), x)


def test_fit_standardises_and_inverts():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5000, 4, generator=g) * torch.tensor([0.01, 1.0, 100.0, 3.0]) + torch.tensor([5.0, -2.0, 0.0, 1e3])
    norm = Normalizer(4).fit(x)
    z = norm.normalize(x)
    torch.testing.assert_close(z.mean(0), torch.zeros(4), atol=1e-3, rtol=0)
    torch.testing.assert_close(z.std(0, unbiased=False), torch.ones(4), atol=1e-3, rtol=0)
    torch.testing.assert_close(norm.denormalize(z), x, atol=1e-3, rtol=1e-5)


def test_constant_dims_are_centred_not_divided():
    x = torch.stack((torch.full((100,), 7.0), torch.arange(100.0)), dim=-1)
    norm = Normalizer(2).fit(x)
    assert norm.std[0] == 1.0
    assert torch.all(norm.normalize(x)[:, 0] == 0)


def test_running_update_matches_one_fit():
    g = torch.Generator().manual_seed(1)
    chunks = [torch.randn(n, 3, generator=g) * (i + 1) + i for i, n in enumerate((7, 300, 1, 50))]
    running = Normalizer(3)
    for chunk in chunks:
        running.update(chunk)
    batch = Normalizer(3).fit(torch.cat(chunks))
    torch.testing.assert_close(running.mean, batch.mean, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(running.std, batch.std, atol=1e-5, rtol=1e-5)
    assert int(running.count) == 358


def test_leading_dims_are_samples():
    x = torch.randn(4, 25, 2)
    a, b = Normalizer(2).fit(x), Normalizer(2).fit(x.reshape(100, 2))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.std, b.std)


def test_statistics_are_buffers():
    norm = Normalizer(2).fit(torch.randn(50, 2) + 3)
    state = norm.state_dict()
    assert {"mean", "std", "var", "count"} <= set(state)
    assert not list(norm.parameters())
    restored = Normalizer(2)
    restored.load_state_dict(state)
    assert torch.equal(restored.mean, norm.mean) and torch.equal(restored.std, norm.std)
    assert torch.equal(copy.deepcopy(norm).mean, norm.mean)


def test_bad_input():
    with pytest.raises(ValueError):
        Normalizer(3).fit(torch.randn(10, 2))
    with pytest.raises(ValueError):
        Normalizer(3).fit(torch.randn(0, 3))
