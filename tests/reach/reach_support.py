"""Shared helpers of the reachability tests: fit an example system, sample it along random plans."""
import copy

import torch

from torchrl_brsl.reach import DataDrivenReach, sample_reach


def fit(system, num, seed=0, **kwargs):
    gen = torch.Generator().manual_seed(seed)
    x, xp, u = system.offline_data(num, gen)
    return DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=system.translation_invariant_dims,
                               **kwargs)


_SHARED = {}


def shared_fit(system, num, seed=0, **kwargs):
    """:func:`fit`, computed once per test process for the same system (class and parameters), data and options; a deep
    copy each call (a test may change its model). Only for tests that patch nothing the fit reads (the hinge selection's
    constants, its functions): their fits would be the unpatched ones."""
    key = (type(system).__qualname__, repr(sorted(vars(system).items())), num, seed, repr(sorted(kwargs.items())))
    if key not in _SHARED:
        _SHARED[key] = fit(system, num, seed, **kwargs)
    return copy.deepcopy(_SHARED[key])


def random_plans(system, n_plans=20, horizon=10, seed=1, spread=0.7):
    """Starts inside the data region (within ``spread`` of its half-range around its centre, positions at 0),
    uniformly random plans."""
    gen = torch.Generator().manual_seed(seed)
    center, half = (system.state_low + system.state_high) / 2, (system.state_high - system.state_low) / 2
    x0 = center + spread * half * (torch.rand(n_plans, center.shape[0], generator=gen, dtype=torch.float64) * 2 - 1)
    x0[:, list(system.translation_invariant_dims)] = 0.0
    return x0, system.sample_actions(n_plans, horizon, generator=gen), gen


def sampled(system, reach, seed=1, samples=300, spread=0.7, n_plans=20):
    x0, plans, gen = random_plans(system, n_plans=n_plans, seed=seed, spread=spread)
    return sample_reach(reach, lambda x, u: system.step(x, u, gen), x0, plans, samples)
