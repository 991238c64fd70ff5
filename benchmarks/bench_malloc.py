"""A compiled plan's sets under the system malloc and under each caching allocator installed, side by side.

The allocator is chosen when a process starts (``LD_PRELOAD``), so each measurement runs in a child process:
per allocator ``--rounds`` children, the allocators alternated so that all see the same load. A child fits the
local model of an example black box (500 random offline steps; the body frame of the bicycle), compiles it,
and times the sets of ``T = 20``-step plans at batch 1 and 16 (one CPU thread, no gradients, median over
``--repeats`` calls after a warm-up). Printed: the medians over the children, in ms per plan, and their ratio to
the system malloc. The sets are checked equal across allocators (largest centre difference).

Usage: ``python benchmarks/bench_malloc.py [--system bicycle] [--rounds 2] [--repeats 300]``
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import torch

from torchrl_brsl._malloc import installed_allocators, malloc_name
from torchrl_brsl.reach import CappedVelocityServo, DataDrivenReach, KinematicBicycle, SaturatedThrustPoint
from torchrl_brsl.sets import Zonotope

SYSTEMS = {"bicycle": KinematicBicycle, "saturated_point": SaturatedThrustPoint, "capped_servo": CappedVelocityServo}
HORIZON, BATCHES = 20, (1, 16)


def child(name: str, repeats: int) -> dict:
    """Time one model's compiled plans in this process: ``{allocator, batch: ms per plan, centre sum}``."""
    torch.set_num_threads(1)
    system = SYSTEMS[name]()
    x, xp, u = system.offline_data(500, torch.Generator().manual_seed(0))
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=system.translation_invariant_dims,
                                max_generators=24, body_frame=system.body_frame).compile_steps()
    result = {"allocator": malloc_name()}
    with torch.no_grad():
        for batch in BATCHES:
            gen = torch.Generator().manual_seed(batch)
            initial = Zonotope.from_point(system.sample_states(batch, gen) * 0.5)
            plans = system.sample_actions(batch, HORIZON, generator=gen)
            for _ in range(20):  # compiles, then warms up
                sets = reach.reach(initial, plans)
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                reach.reach(initial, plans)
                times.append((time.perf_counter() - start) * 1e3 / batch)
            result[str(batch)] = statistics.median(times)
            result[f"centre {batch}"] = sets.center.tolist()
    return result


def run_child(name: str, repeats: int, library: str | None) -> dict:
    env = {key: value for key, value in os.environ.items() if key != "LD_PRELOAD"}
    if library is not None:
        env["LD_PRELOAD"] = library
    out = subprocess.run([sys.executable, __file__, "--child", "--system", name, "--repeats", str(repeats)],
                         env=env, capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", choices=sorted(SYSTEMS), default="bicycle")
    parser.add_argument("--rounds", type=int, default=2, help="child processes per allocator")
    parser.add_argument("--repeats", type=int, default=300, help="timed calls per batch size in a child")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.system, args.repeats)))
        return
    allocators = {"system malloc": None, **installed_allocators()}
    runs = {name: [] for name in allocators}
    for _ in range(args.rounds):
        for name, library in allocators.items():
            runs[name].append(run_child(args.system, args.repeats, library))
    print(f"{args.system}: one plan's compiled sets (T = {HORIZON}), one CPU thread, median ms per plan over "
          f"{args.rounds} processes each (their own medians in brackets)")
    print(f"{'allocator':<16}{'ran on':<16}" + "".join(f"{f'batch {b}':>28}{'ratio':>8}" for b in BATCHES))
    base = {b: statistics.median(r[str(b)] for r in runs["system malloc"]) for b in BATCHES}
    reference = runs["system malloc"][0]
    for name, results in runs.items():
        row = f"{name:<16}{results[0]['allocator']:<16}"
        for b in BATCHES:
            values = [r[str(b)] for r in results]
            cell = f"{statistics.median(values):.3f} ({', '.join(f'{v:.3f}' for v in values)})"
            row += f"{cell:>28}{base[b] / statistics.median(values):>7.2f}x"
        print(row)
        difference = max(float((torch.tensor(r[f"centre {b}"]) - torch.tensor(reference[f"centre {b}"])).abs().max())
                         for r in results for b in BATCHES)
        print(f"{'':<16}largest centre difference to the system malloc's sets: {difference:.1e}")
    if len(allocators) == 1:
        print("no caching allocator installed (e.g. `apt install libtcmalloc-minimal4`): nothing to compare")


if __name__ == "__main__":
    main()
