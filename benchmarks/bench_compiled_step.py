"""The local model's reachable sets, eager against compiled (``DataDrivenReach.compile_steps``).

For each example black box (500 random offline transitions; the body-frame model where the
system has a heading) and batch size: the time of one plan's sets (``T = 20`` steps, one CPU
thread) with eager steps and with compiled ones, timed in alternation so that both see the
same load, their ratio, the first compiled call (compilation; seconds, the on-disk cache
decides), and how far the compiled sets are from the eager ones (largest centre difference,
extreme ratios of the interval radii).

Usage: ``python benchmarks/bench_compiled_step.py [--quick]``
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from torchrl_brsl.reach import (CappedVelocityServo, DataDrivenReach, DoubleIntegrator, KinematicBicycle,
                                SaturatedThrustPoint, Unicycle)
from torchrl_brsl.sets import Zonotope

SYSTEMS = {"bicycle (body)": KinematicBicycle, "saturated point": SaturatedThrustPoint,
           "capped servo": CappedVelocityServo, "double integrator": DoubleIntegrator, "unicycle (body)": Unicycle}
HORIZON = 20


def fit(system) -> DataDrivenReach:
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    return DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=system.translation_invariant_dims,
                               max_generators=24, body_frame=system.body_frame)


def timed(reach: DataDrivenReach, initial: Zonotope, plans: torch.Tensor) -> float:
    start = time.perf_counter()
    reach.reach(initial, plans)
    return (time.perf_counter() - start) * 1e3


def compare(system, batch: int, repeats: int) -> dict[str, float]:
    eager, compiled = fit(system), fit(system).compile_steps()
    gen = torch.Generator().manual_seed(batch)
    initial = Zonotope.from_point(system.sample_states(batch, gen) * 0.5)
    plans = system.sample_actions(batch, HORIZON, generator=gen)
    first = timed(compiled, initial, plans) / 1e3
    eager_ms, compiled_ms = [], []
    for _ in range(repeats):  # alternate, so that both see the same load
        eager_ms.append(timed(eager, initial, plans))
        compiled_ms.append(timed(compiled, initial, plans))
    a, b = eager.reach(initial, plans), compiled.reach(initial, plans)
    ratio = b.generators.abs().sum(-1) / a.generators.abs().sum(-1).clamp_min(1e-300)
    return {"eager": statistics.median(eager_ms) / batch, "compiled": statistics.median(compiled_ms) / batch,
            "first": first, "center": float((a.center - b.center).abs().max()),
            "low": float(ratio.min()), "high": float(ratio.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and batch sizes")
    args = parser.parse_args()
    torch.set_num_threads(1)
    batches, repeats = ((1, 16), 5) if args.quick else ((1, 4, 16, 64), 20)
    print(f"one plan's sets (T = {HORIZON}), one CPU thread, median ms per plan; eager and compiled alternated")
    print(f"{'system':<20}{'batch':>6}{'eager':>10}{'compiled':>10}{'ratio':>8}{'compile s':>11}"
          f"{'|Δ centre|':>12}{'radius ratio':>18}")
    for name, system_type in SYSTEMS.items():
        for batch in batches:
            row = compare(system_type(), batch, repeats)
            print(f"{name:<20}{batch:>6}{row['eager']:>10.3f}{row['compiled']:>10.3f}"
                  f"{row['eager'] / row['compiled']:>7.1f}x{row['first']:>11.1f}{row['center']:>12.1e}"
                  f"{row['low']:>9.4f}-{row['high']:.4f}", flush=True)
    print("target (issue): one plan's sets <= 0.3 ms")


if __name__ == "__main__":
    main()
