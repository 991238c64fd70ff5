"""A compiled local model's check in the plan's own compiled loop, against the check after the loop.

``diffdrive_nav`` (the Turtlebot-like task) with its body-frame local model (``--data`` offline steps, 2,000 as
the recipes collect), compiled, and 10 obstacles: what the layer checks, plans of one action then braking (``T =
7`` sets). The check runs in the loop that computes the plan's sets (:meth:`PlanChecker.evaluate_with_gauge`
hands them to a traced ``finish``: one compiled call), or after it (``PlanChecker._fused_checks = False``: the
loop's call, its sets, then the check's own compiled call). Both ways alternate in one process (this machine's
load drifts), one CPU thread:

- ``PlanChecker.evaluate`` of 1, 2 and 4 plans, and the adjusters' linearised check (the same with the plans'
  tangents, :func:`torchrl_brsl.safety.adjust._leaf_check`) of 2 and 4: median µs per call;
- the layer on ``bench_layer.py``'s scenes (safe proposals; the facet QP adjusting every step): median ms per
  step, with the shares of adjusted, failsafe, hold and out-of-data steps.

Usage: ``python benchmarks/bench_check.py [--data 2000] [--calls 500] [--repeats 3]``
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torchrl.envs import TransformedEnv

sys.path.insert(0, str(Path(__file__).parent))
import envs  # noqa: E402
from bench_layer import N_OBSTACLES, TASK, episode_times, make_layer, offline_data, shares, stats  # noqa: E402
from torchrl_brsl._malloc import malloc_name  # noqa: E402
from torchrl_brsl.reach import BodyFrame, DataDrivenReach  # noqa: E402
from torchrl_brsl.safety import FacetQPAdjuster, GradientAdjuster, PlanChecker  # noqa: E402
from torchrl_brsl.safety.adjust import _leaf_check  # noqa: E402
from torchrl_brsl.sets import Obstacles  # noqa: E402

WAYS = {"in the loop": True, "after it": False}


def per_call_us(function, calls: int) -> float:
    """Median over five rounds of ``calls / 5`` calls each: µs per call."""
    rounds = []
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(max(calls // 5, 1)):
            function()
        rounds.append((time.perf_counter() - start) / max(calls // 5, 1) * 1e6)
    return statistics.median(rounds)


def alternated(function, calls: int, repeats: int) -> dict[str, float]:
    """``function()``'s median µs per call each way, the ways alternated ``repeats`` times."""
    times = {way: [] for way in WAYS}
    for _ in range(repeats):
        for way, fused in WAYS.items():
            PlanChecker._fused_checks = fused
            function()  # compiles where this way has not yet
            times[way].append(per_call_us(function, calls))
    PlanChecker._fused_checks = True
    return {way: statistics.median(values) for way, values in times.items()}


def check_inputs(layer, env, plans: int, generator: torch.Generator):
    """``plans`` random one-action plans from the env's reset state, against its obstacles (10 in range)."""
    td = env.reset()
    checker = layer.checker
    low, high = checker.action_low, checker.action_high
    x0 = td["state"].to(low).expand(plans, -1)
    plan = low + (high - low) * torch.rand(plans, 1, low.shape[0], generator=generator, dtype=low.dtype)
    mask = torch.zeros_like(td["obstacles", "mask"], dtype=torch.bool)
    mask[:N_OBSTACLES] = True
    obstacles = Obstacles(*(td["obstacles", key].to(low).expand(plans, *td["obstacles", key].shape)
                            for key in ("center", "generators")), mask.expand(plans, -1))
    return checker, x0, plan, obstacles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=int, default=2000, help="offline steps")
    parser.add_argument("--calls", type=int, default=500, help="calls per timing round of a check")
    parser.add_argument("--repeats", type=int, default=3, help="times each way is timed, alternated")
    args = parser.parse_args()
    info, noise, data = offline_data(args.data)
    reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims, max_generators=30,
                                      body_frame=BodyFrame(info.position_dims, info.heading_dims)).compile_steps()
    probe, safe, adjusting = (make_layer(reach, info, adjuster, 1)
                              for adjuster in (FacetQPAdjuster(), GradientAdjuster(), FacetQPAdjuster()))
    start = time.perf_counter()
    env = TransformedEnv(envs.make(TASK, seed=0, episode_steps=10_000), probe)  # compiles the checks
    print(f"{TASK}, body-frame local model ({args.data} offline steps), compiled; one CPU thread, {malloc_name()}; "
          f"the layer's checks compiled in {time.perf_counter() - start:.0f} s")
    print(f"{'':<44}" + "".join(f"{way:>14}" for way in WAYS) + f"{'ratio':>9}")
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for plans in (1, 2, 4):
            checker, x0, plan, obstacles = check_inputs(probe, env, plans, generator)
            row = alternated(lambda: checker.evaluate(x0, plan, obstacles), args.calls, args.repeats)
            print(f"{f'check of {plans} plan(s), µs':<44}" + "".join(f"{t:>14.0f}" for t in row.values())
                  + f"{row['after it'] / row['in the loop']:>9.2f}")
        for plans in (2, 4):
            checker, x0, plan, obstacles = check_inputs(probe, env, plans, generator)
            row = alternated(lambda: _leaf_check(checker, x0, plan, obstacles), args.calls, args.repeats)
            print(f"{f'linearised check of {plans} plans, µs':<44}" + "".join(f"{t:>14.0f}" for t in row.values())
                  + f"{row['after it'] / row['in the loop']:>9.2f}")
    for name, layer, towards_wall in (("safe proposals", safe, False), ("facet QP adjusting", adjusting, True)):
        first = 12 if towards_wall else 5
        times, flags = {way: [] for way in WAYS}, {}
        for _ in range(args.repeats):
            for way, fused in WAYS.items():
                PlanChecker._fused_checks = fused
                episode_times(layer, 15, towards_wall, 0)  # compiles where this way has not yet
                flags = {}
                times[way].append(stats(episode_times(layer, 120, towards_wall, 0, flags)[first:])[0])
        PlanChecker._fused_checks = True
        row = {way: statistics.median(values) for way, values in times.items()}
        print(f"{f'layer step, {name}, ms':<44}" + "".join(f"{t:>14.2f}" for t in row.values())
              + f"{row['after it'] / row['in the loop']:>9.2f}   % adjusted, failsafe, hold, no data:"
              + shares(flags, first))


if __name__ == "__main__":
    main()
