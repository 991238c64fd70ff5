"""The local model's reachable sets: eager, compiled steps, and a plan compiled as one loop.

For each example black box (500 random offline transitions; the body-frame model where the
system has a heading) and batch size: the time of one plan's sets (``T = 20`` steps, one CPU
thread, no gradients) three ways, timed in alternation so that all see the same load: eager
steps; compiled steps called one by one (``step_sets``, what the adjusters' linearisation
runs); and ``reach`` on the compiled model, which runs the whole plan as one compiled
``while_loop`` (the checking path). Then the ratios, the warm-up's compile time (seconds, the
on-disk cache decides), and how far the compiled plan's sets are from the eager ones (largest
centre difference, extreme ratios of the interval radii).

``--vectors`` instead times the compiled loop with the package's vector width (256 bits where
inductor would use AVX-512, :func:`torchrl_brsl._compiling.vector_options`) against inductor's own
choice, alternated in one process, and how far their sets differ.

Usage: ``python benchmarks/bench_compiled_step.py [--quick] [--vectors]``
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from torchrl_brsl._compiling import vector_options
from torchrl_brsl._malloc import malloc_name
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


def timed(function) -> float:
    start = time.perf_counter()
    function()
    return (time.perf_counter() - start) * 1e3


def stepwise(reach: DataDrivenReach, initial: Zonotope, plans: torch.Tensor) -> None:
    center, generators = initial.center, initial.generators
    for action in plans.unbind(-2):
        center, generators, _ = reach.step_sets(center, generators, action)


def compare(system, batch: int, repeats: int) -> dict[str, float]:
    eager, compiled = fit(system), fit(system)
    start = time.perf_counter()
    compiled.compile_steps()
    first = time.perf_counter() - start
    gen = torch.Generator().manual_seed(batch)
    initial = Zonotope.from_point(system.sample_states(batch, gen) * 0.5)
    plans = system.sample_actions(batch, HORIZON, generator=gen)
    runs = {"eager": lambda: eager.reach(initial, plans), "steps": lambda: stepwise(compiled, initial, plans),
            "loop": lambda: compiled.reach(initial, plans)}
    times = {name: [] for name in runs}
    with torch.no_grad():
        for _ in range(repeats):  # alternate, so that all see the same load
            for name, run in runs.items():
                times[name].append(timed(run))
        a, b = eager.reach(initial, plans), compiled.reach(initial, plans)
    ratio = b.generators.abs().sum(-1) / a.generators.abs().sum(-1).clamp_min(1e-300)
    return {**{name: statistics.median(t) / batch for name, t in times.items()}, "first": first,
            "center": float((a.center - b.center).abs().max()), "low": float(ratio.min()), "high": float(ratio.max())}


def compare_vectors(system, batch: int, repeats: int) -> dict[str, float]:
    """The compiled loop with the package's vector width against inductor's own (``--vectors``)."""
    narrow, wide = fit(system).compile_steps(), fit(system).compile_steps(options={"cpp_wrapper": True})
    gen = torch.Generator().manual_seed(batch)
    initial = Zonotope.from_point(system.sample_states(batch, gen) * 0.5)
    plans = system.sample_actions(batch, HORIZON, generator=gen)
    times = {"narrow": [], "wide": []}
    with torch.no_grad():
        for _ in range(repeats):
            for name, reach in (("narrow", narrow), ("wide", wide)):
                times[name].append(timed(lambda: reach.reach(initial, plans)))
        a, b = narrow.reach(initial, plans), wide.reach(initial, plans)
    return {**{name: statistics.median(t) / batch for name, t in times.items()},
            "center": float((a.center - b.center).abs().max()),
            "generators": float((a.generators - b.generators).abs().max())}


def main_vectors(batches: tuple[int, ...], repeats: int) -> None:
    options = vector_options()
    if not options:
        print("inductor vectorises at most 256 bits on this CPU: the package keeps its choice, nothing to compare")
        return
    print(f"the compiled loop, median ms per plan (T = {HORIZON}): the package's {options} against inductor's own")
    print(f"{'system':<20}{'batch':>6}{'256-bit':>9}{'own':>9}{'own/256':>9}{'|Δ centre|':>12}{'|Δ generators|':>16}")
    for name, system_type in SYSTEMS.items():
        for batch in batches:
            row = compare_vectors(system_type(), batch, repeats)
            print(f"{name:<20}{batch:>6}{row['narrow']:>9.3f}{row['wide']:>9.3f}{row['wide'] / row['narrow']:>8.2f}x"
                  f"{row['center']:>12.1e}{row['generators']:>16.1e}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and batch sizes")
    parser.add_argument("--vectors", action="store_true", help="the loop's vector width: the package's and inductor's")
    args = parser.parse_args()
    torch.set_num_threads(1)
    batches, repeats = ((1, 16), 5) if args.quick else ((1, 4, 16, 64), 20)
    if args.vectors:
        return main_vectors(batches, repeats)
    print(f"one plan's sets (T = {HORIZON}), one CPU thread, {malloc_name()}, no gradients, median ms per plan; "
          "the three alternated")
    print(f"{'system':<20}{'batch':>6}{'eager':>9}{'steps':>9}{'loop':>9}{'eager/loop':>12}{'steps/loop':>12}"
          f"{'compile s':>11}{'|Δ centre|':>12}{'radius ratio':>18}")
    for name, system_type in SYSTEMS.items():
        for batch in batches:
            row = compare(system_type(), batch, repeats)
            print(f"{name:<20}{batch:>6}{row['eager']:>9.3f}{row['steps']:>9.3f}{row['loop']:>9.3f}"
                  f"{row['eager'] / row['loop']:>11.1f}x{row['steps'] / row['loop']:>11.1f}x{row['first']:>11.1f}"
                  f"{row['center']:>12.1e}{row['low']:>9.4f}-{row['high']:.4f}", flush=True)
    print("target (issue): one plan's sets <= 0.3 ms")


if __name__ == "__main__":
    main()
