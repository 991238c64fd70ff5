"""Width of the MuJoCo robots' reachable sets over the spread of their sampled true states, local against global fit.

The example black boxes' figure (``bench_reach_tightness.py``) on the simulated robots: each task's model (as
``bench_task_soundness.py`` fits it: the quadrotor with its servo caps on and the wheeled Turtlebot in its body frame,
as the recipes run them; ``point_boxes`` with its cap on; ``hexarotor_wind`` uncapped and capped, 50-step offline
episodes) from ``--data`` random offline steps, against ``--plans`` plans of ``n_brk + 1`` steps (random actions, or
one action then braking, from states the robot reaches), each run by ``--samples`` copies of the robot that differ
only by their process noise (:func:`~torchrl_brsl.reach.env_sample_reach`). Printed per task, data size and model:
plans claimed, the median over the claimed plans' steps of the sets' interval widths over the samples' spread
(geometric mean over the state dims, as ``bench_reach_tightness.py``), the same after the first step and at the
last, and the sampled states outside their claimed sets; with ``--per-dim`` also each state dim's median ratio
(over the claimed plans' steps where the samples spread in it). The same plans, starts and noise for both models.
``--noise vertices`` holds each copy's noise at a random vertex of ``W`` for the whole plan, a constant worst case:
the ratio then compares the sets with (nearly) the true reachable set's extent instead of typical noise's spread.
``--budget`` also prints where a local model's sets get their width at the plans' first and last steps
(:meth:`~torchrl_brsl.reach.DataDrivenReach.error_budget`, medians over the claimed plans): per state dim the radius,
the part carried through the step, the part the step adds and the noise's; per output the model error's parts.

Usage: ``python benchmarks/bench_task_tightness.py [--plans 20] [--samples 100] [--data 500,2000]
[--tasks quadrotor_nav,...] [--models local,global] [--per-dim] [--noise vertices] [--budget]``
"""
from __future__ import annotations

import argparse
import time

import torch
from bench_task_soundness import TASKS, fit_task

import envs
from torchrl_brsl.reach import SampledReach, env_sample_reach
from torchrl_brsl.sets import Zonotope

MODELS = ("local", "global")


def sampled(name: str, reach, plans: int, samples: int, seed: int, noise: str = "uniform") -> SampledReach:
    """The task's plans (the same for every model: torch seed ``seed``, env seed 12) run by ``samples`` copies."""
    task, options, *_ = TASKS[name]
    info = envs.safety_info(task)
    env = envs.make(task, empty=True, seed=12, episode_steps=10_000, **options)
    torch.manual_seed(seed)
    return env_sample_reach(reach, env, plans, info.n_brk + 1, info.action_low, info.action_high,
                            info.braking_action, samples=samples, noise=noise)


def row(name: str, steps: int, model: str, result: SampledReach) -> str:
    claimed = result.covered
    ratios = result.width_ratio[claimed]  # [claimed plans, H]

    def median(values) -> str:
        return f"{float(values.median()):.2f}" if values.numel() else "-"

    outside = f"{result.violations}/{result.checked}"
    return (f"{name:<20}{steps:>6}{model:>8}{f'{int(claimed.sum())}/{claimed.numel()}':>10}{median(ratios):>10}"
            f"{median(ratios[:, :1]):>10}{median(ratios[:, -1:]):>10}{outside:>16}")


BUDGET_PARTS = ("radius", "carried", "added", "noise", "leaf", "far", "between", "relaxation")


def budget_rows(reach, result: SampledReach) -> list[str]:
    """The error budget's parts at the first and the last step, medians over the claimed plans, a line each."""
    claimed = result.covered
    budget = reach.error_budget(Zonotope.from_point(result.starts[claimed]), result.plans[claimed])
    rows = []
    for step, label in ((0, "first"), (-1, "last")):
        for part in BUDGET_PARTS:
            values = budget[part][:, step].median(0).values
            rows.append(f"{'':<20}{label:>6} {part:<11}{' '.join(f'{v:9.2e}' for v in values.tolist())}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plans", type=int, default=20, help="sampled plans per task and data size")
    parser.add_argument("--samples", type=int, default=100, help="true trajectories per plan")
    parser.add_argument("--data", default="500,2000", help="comma-separated offline steps")
    parser.add_argument("--tasks", default=",".join(TASKS), help=f"comma-separated, of {', '.join(TASKS)}")
    parser.add_argument("--models", default=",".join(MODELS), help="comma-separated, of local, global")
    parser.add_argument("--seed", type=int, default=0, help="torch seed of the offline actions and the plans")
    parser.add_argument("--per-dim", action="store_true", help="also each state dim's median width ratio")
    parser.add_argument("--noise", choices=("uniform", "vertices"), default="uniform",
                        help="the copies' noise: the task's, or each copy's at a random vertex of W throughout "
                             "(the spread then approaches the reachable set's extent)")
    parser.add_argument("--budget", action="store_true",
                        help="also where a local model's sets get their width (DataDrivenReach.error_budget)")
    args = parser.parse_args()
    unknown = sorted(set(args.tasks.split(",")) - set(TASKS)) + sorted(set(args.models.split(",")) - set(MODELS))
    if unknown:
        parser.error(f"unknown tasks or models {unknown}; tasks: {sorted(TASKS)}, models: {list(MODELS)}")
    torch.set_num_threads(1)
    print(f"{'task':<20}{'data':>6}{'model':>8}{'claimed':>10}{'width/spr':>10}{'step 1':>10}{'last':>10}"
          f"{'outside':>16}")
    for name in args.tasks.split(","):
        for steps in (int(s) for s in args.data.split(",")):
            for model in args.models.split(","):
                start = time.perf_counter()
                reach = fit_task(name, steps, args.seed, method=model)
                result = sampled(name, reach, args.plans, args.samples, args.seed + 1, args.noise)
                print(f"{row(name, steps, model, result)}   {time.perf_counter() - start:.0f} s", flush=True)
                if args.per_dim and bool(result.covered.any()):
                    print(f"{'':<20}per dim: {', '.join(f'{v:.2f}' for v in result.median_dim_ratio.tolist())}")
                if args.budget and model == "local" and bool(result.covered.any()):
                    print("\n".join(budget_rows(reach, result)))


if __name__ == "__main__":
    main()
