"""Containment of the true MuJoCo robots in their fitted reachable sets, sampled ten times harder than the tests.

``tests/reach/test_task_soundness.py`` checks 40 plans per task; a violation that one plan in a hundred
meets passes it two times in three. Here the local model of each task (the quadrotor with its servo
caps on and the wheeled Turtlebot in its body frame, as the recipes run them; ``point_boxes`` with its
cap on; ``hexarotor_wind`` with the recipe's 50-step offline episodes, uncapped as the recipe runs it and with its
servo caps on, which no model claims yet: ``docs/limits.md``) is fitted from
``--data`` random offline steps and checked against ``--plans`` plans of one action then braking (the
recipes' layer: ``n_brk + 1`` steps) and of random actions, from states the robot reaches
(:func:`~torchrl_brsl.reach.env_trajectories`). Printed per task and data size: plans claimed, true
states outside their claimed sets, plans with one, and the worst excess of an outside state beyond its
set's interval half-width (with that half-width, its dim and step); then ``1-step worst``: one-step queries along a
random walk of the empty task (``--queries``, the offline data's distribution), their noiseless successors (the
next state less the task's ``last_noise``) with the noise at every vertex of ``W`` outside their one-step sets, over
the queries claimed (:func:`~torchrl_brsl.reach.worst_noise_outside`). ``--timing`` adds, per task, what the
data size costs: the time of a plan's sets (compiled, one CPU thread, at 1 and 10 plans a call), the
models of every data size timed in alternation.

Usage: ``python benchmarks/bench_task_soundness.py [--plans 400] [--data 500,2000] [--tasks quadrotor_nav,...]
[--queries 2000] [--timing] [--held-out-folds 5]``
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

import envs
from torchrl_brsl.reach import (BodyFrame, DataDrivenReach, collect_offline_data, env_trajectories,
                                noiseless_transitions, worst_noise_outside)
from torchrl_brsl.sets import Zonotope

# name -> (task, options of envs.make, fitted in the body frame, offline episode length)
TASKS = {
    "quadrotor_nav": ("quadrotor_nav", {}, False, None),
    "diffdrive_wheeled": ("diffdrive_nav", {"robot": "wheeled"}, True, None),
    "point_boxes": ("point_boxes", {}, False, None),
    "hexarotor_uncapped": ("hexarotor_wind", {"max_acceleration": None}, False, 50),
    "hexarotor_capped": ("hexarotor_wind", {}, False, 50),
}


def worst_noise(name: str, reach: DataDrivenReach, queries: int, seed: int) -> str:
    """``outside/claimed`` of ``queries`` one-step queries along a random walk of the empty task, at the worst noise."""
    task, options, _, episode = TASKS[name]
    env = envs.make(task, empty=True, seed=13, **options, **({"episode_steps": episode} if episode else {}))
    states, actions, successors = noiseless_transitions(env, queries, torch.Generator().manual_seed(seed))
    outside, claimed = worst_noise_outside(reach, successors, states, actions)
    return f"{int(outside[claimed].sum())}/{int(claimed.sum())}"


def fit_task(name: str, steps: int, seed: int, method: str = "local", **options) -> DataDrivenReach:
    """The model of task ``name`` from ``steps`` random offline transitions of its empty variant (torch seed ``seed``),
    in the body frame where the recipes fit it (a local model); ``options`` go to :meth:`DataDrivenReach.fit`."""
    task, env_options, body, episode = TASKS[name]
    info = envs.safety_info(task)
    torch.manual_seed(seed)
    offline = envs.make(task, empty=True, seed=11, **env_options, **({"episode_steps": episode} if episode else {}))
    data = collect_offline_data(offline, steps)
    frame = BodyFrame(info.position_dims, info.heading_dims) if body and method == "local" else None
    return DataDrivenReach.from_data(data, Zonotope(info.noise_center.double(), info.noise_generators.double()),
                                     translation_invariant_dims=info.position_dims, max_generators=30,
                                     body_frame=frame, method=method, **options)


def check(name: str, steps: int, plans: int, seed: int, held_out_folds: int = 0,
          queries: int = 2000) -> tuple[str, DataDrivenReach, Zonotope, torch.Tensor]:
    """One row: fit from ``steps`` offline transitions, sample ``plans`` true trajectories, count the states outside.
    Also the model, the plans' initial sets and their actions."""
    task, options, *_ = TASKS[name]
    info = envs.safety_info(task)
    reach = fit_task(name, steps, seed, held_out_folds=held_out_folds)
    env = envs.make(task, empty=True, seed=12, episode_steps=10_000, **options)
    x0, actions, visited = env_trajectories(env, plans, info.n_brk + 1, info.action_low, info.action_high,
                                            info.braking_action)
    initial = Zonotope.from_point(x0)
    sets, claimed = reach.reach_covered(initial, actions)
    outside = ~sets.contains(visited) & claimed[:, None]  # [P, H], the tests' criterion (exact, HiGHS beyond 3-D)
    worst = f"{'-':>34}"
    if outside.any():  # the largest excess of an outside state beyond its set's interval half-width
        radius = sets.generators.abs().sum(-1)  # [P, H, n]
        excess = ((visited - sets.center).abs() - radius) * outside.unsqueeze(-1)
        plan, step, dim = (int(i) for i in torch.unravel_index(excess.argmax(), excess.shape))
        worst = (f"{float(excess[plan, step, dim]):>10.2g} of {float(radius[plan, step, dim]):>8.2g}"
                 f"{f' (dim {dim}, step {step + 1})':>16}")
    row = (f"{name:<20}{steps:>6}{f'{int(claimed.sum())}/{plans}':>10}"
           f"{f'{int(outside.sum())}/{int(claimed.sum()) * outside.shape[1]}':>14}{int(outside.any(-1).sum()):>8}"
           f"{worst}{worst_noise(name, reach, queries, seed):>14}")
    return row, reach, initial, actions


def plan_times(models: dict[int, tuple[DataDrivenReach, Zonotope, torch.Tensor]], calls: int = 40) -> str:
    """Median ms of a plan's compiled sets per data size, at 1 and 10 plans a call, the sizes alternated."""
    for reach, *_ in models.values():
        reach.compile_steps()
    cells = []
    for batch in (1, 10):
        times = {steps: [] for steps in models}
        for _ in range(calls):
            for steps, (reach, initial, actions) in models.items():
                start = time.perf_counter()
                reach.reach_covered(initial[:batch], actions[:batch])
                times[steps].append(time.perf_counter() - start)
        cells.append(" / ".join(f"{1e3 * statistics.median(t[3:]):.1f}" for t in times.values()))
    return f"  a plan's compiled sets, ms for data {' / '.join(map(str, models))}: {cells[0]} (1 plan), {cells[1]} (10)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plans", type=int, default=400, help="sampled plans per task and data size")
    parser.add_argument("--data", default="500,2000", help="comma-separated offline steps")
    parser.add_argument("--tasks", default=",".join(TASKS), help=f"comma-separated, of {', '.join(TASKS)}")
    parser.add_argument("--seed", type=int, default=0, help="torch seed of the offline actions and the plans")
    parser.add_argument("--queries", type=int, default=2000, help="one-step queries of the worst-noise check")
    parser.add_argument("--timing", action="store_true", help="also time each data size's plan sets (compiles them)")
    parser.add_argument("--held-out-folds", type=int, default=0,
                        help="fit with DataDrivenReach.fit(held_out_folds=K): leaves widened where held-out "
                             "transitions fall outside (its warning is printed)")
    args = parser.parse_args()
    unknown = sorted(set(args.tasks.split(",")) - set(TASKS))
    if unknown:
        parser.error(f"unknown tasks {unknown}; choose from {sorted(TASKS)}")
    torch.set_num_threads(1)
    print(f"{'task':<20}{'data':>6}{'claimed':>10}{'outside':>14}{'plans':>8}{'worst excess of half-width':>34}"
          f"{'1-step worst':>14}")
    for name in args.tasks.split(","):
        models = {}
        for steps in (int(s) for s in args.data.split(",")):
            start = time.perf_counter()
            row, *models[steps] = check(name, steps, args.plans, args.seed, args.held_out_folds, args.queries)
            print(f"{row}   {time.perf_counter() - start:.0f} s", flush=True)
        if args.timing:
            print(plan_times(models), flush=True)


if __name__ == "__main__":
    main()
