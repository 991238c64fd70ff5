"""Per-step latency of the safety layer with the constant brake against a state-dependent one.

Same setting as ``bench_layer.py`` (``diffdrive_nav``, 10 obstacles, ``n_plan = 10``, one CPU
thread, the layer's ``compute_time``). The state-dependent brake here returns the zero command,
i.e. the same actions as the constant brake, so every difference in time is the code path:
with a braking policy the braking tail is rolled out step by step and the gradient adjuster
differentiates through it, where the constant brake makes every centre one affine map of
(state, plan). Both reachability models are timed; only the global one has that fast path.

Usage: ``python benchmarks/bench_failsafe.py [--quick]``
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
import envs  # noqa: E402
from bench_layer import N_PLAN, TASK, episode_times, stats  # noqa: E402
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data  # noqa: E402
from torchrl_brsl.safety import BRSLSafetyLayer, FacetQPAdjuster, Failsafe, GradientAdjuster  # noqa: E402
from torchrl_brsl.sets import Zonotope  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    info = envs.safety_info(TASK)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    data = collect_offline_data(envs.make(TASK, empty=True, seed=1), 500, generator=torch.Generator().manual_seed(0))
    steps = 30 if args.quick else 120
    zero = info.braking_action
    brakes = {"constant": Failsafe(zero, info.n_brk),
              "policy": Failsafe(zero, info.n_brk, policy=lambda x: zero.to(x).expand(*x.shape[:-1], -1))}
    print(f"{TASK}: n_plan = {N_PLAN}, n_brk = {info.n_brk}, one CPU thread; median / p99 ms per step")
    print(f"{'':<52}{'constant brake':>18}{'braking policy':>18}{'ratio':>8}")
    for method in ("global", "local"):
        reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                          max_generators=30, method=method)
        for label, adjuster, towards_wall in (("safe proposals", GradientAdjuster, False),
                                              ("adjusting: projected gradient", GradientAdjuster, True),
                                              ("adjusting: facet-locked QP", FacetQPAdjuster, True)):
            row = {}
            for name, brake in brakes.items():
                layer = BRSLSafetyLayer(reach, brake, N_PLAN, stop_dims=info.velocity_dims, stop_slack=0.15,
                                        action_low=info.action_low, action_high=info.action_high,
                                        adjuster=adjuster())
                times = episode_times(layer, steps, towards_wall, 0)
                row[name] = stats(times[12:] if towards_wall else times[5:])
            (m0, p0), (m1, p1) = row["constant"], row["policy"]
            print(f"{method + ': ' + label:<52}{m0:>9.2f} /{p0:>6.1f}{m1:>11.2f} /{p1:>6.1f}{m1 / m0:>8.1f}")


if __name__ == "__main__":
    main()
