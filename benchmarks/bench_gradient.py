"""The projected-gradient adjuster on a local model: its closed form along the leaf Jacobian against autograd.

Behind a random policy (``N_ENVS`` envs of the task in one layer, one-action plans, the task's braking steps,
stop slack 0.15, as ``bench_closed_loop.py``), two layers on the same model run alternately, call by call, in one
process (this machine's load drifts): ``GradientAdjuster`` as it is, whose iterations on a local model take the
gradient from one rollout with tangents (the sets' generators held fixed,
:func:`torchrl_brsl.safety.adjust._leaf_check`), and the same adjuster differentiating through the steps by
autograd (``_analytic = False``, its path on local models before). Per variant: the median time per batched
call, the calls that adjusted and their median time, the gradient iterations per adjusted env, and the failsafe
share of the env steps. The local model is compiled unless ``--eager`` (``DataDrivenReach.compile_steps``).

Usage: ``python benchmarks/bench_gradient.py [--task quadrotor_nav] [--steps 500] [--calls 200] [--eager]``
"""
from __future__ import annotations

import argparse
import functools
import statistics

import torch
from torchrl.envs import SerialEnv, TransformedEnv

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe, GradientAdjuster
from torchrl_brsl.sets import Zonotope

N_ENVS = 10
N_WARMUP = 20  # calls left out of the figures (the first adjustments compile)


def variant(task: str, reach: DataDrivenReach, autograd: bool) -> dict:
    """A layer on ``reach`` with the gradient adjuster (by ``autograd`` or not) behind ``N_ENVS`` envs."""
    info = envs.safety_info(task)
    adjuster = GradientAdjuster()
    adjuster._analytic = not autograd
    base = SerialEnv(N_ENVS, [functools.partial(envs.make, task, seed=100 + i, episode_steps=500)
                              for i in range(N_ENVS)])
    layer = BRSLSafetyLayer(reach, Failsafe(info.braking_action, info.n_brk), 1, stop_dims=info.velocity_dims,
                            stop_slack=0.15, action_low=info.action_low, action_high=info.action_high,
                            adjuster=adjuster)
    env = TransformedEnv(base, layer)
    return dict(env=env, td=env.reset(), generator=torch.Generator().manual_seed(0), info=info,
                times=[], adjusting=[], iterations=[], failsafe=[])


def call(run: dict, record: bool) -> None:
    """One batched step of ``run`` under random actions; its figures kept if ``record``."""
    low, high = run["info"].action_low, run["info"].action_high
    td = run["td"]
    td["action"] = low + (high - low) * torch.rand(N_ENVS, low.shape[-1], generator=run["generator"])
    td = run["env"].step(td)
    flags = td["next", "brsl"]
    if record:
        ms = 1e3 * float(flags["compute_time"].flatten()[0])
        iterations = flags["adjust_iterations"].flatten()
        run["times"].append(ms)
        if bool((iterations > 0).any()):
            run["adjusting"].append(ms)
            run["iterations"] += iterations[iterations > 0].tolist()
        run["failsafe"] += flags["failsafe"].flatten().float().tolist()
    done = td["next", "done"].squeeze(-1)
    td = run["env"].step_mdp(td)
    if done.any():
        td["_reset"] = done.unsqueeze(-1)
        td = run["env"].reset(td)
    run["td"] = td


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="quadrotor_nav")
    parser.add_argument("--steps", type=int, default=500, help="offline transitions")
    parser.add_argument("--calls", type=int, default=200, help="batched layer calls per variant")
    parser.add_argument("--eager", action="store_true", help="the local model's steps eager (not compiled)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    info = envs.safety_info(args.task)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    data = collect_offline_data(envs.make(args.task, empty=True, seed=1), args.steps,
                                generator=torch.Generator().manual_seed(0))
    reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                      max_generators=30, method="local")
    if not args.eager:
        reach.compile_steps()
    runs = {"closed form (leaf Jacobian)": variant(args.task, reach, False),
            "autograd through the steps": variant(args.task, reach, True)}
    for index in range(args.calls):
        for run in runs.values():
            call(run, index >= N_WARMUP)
    mode = "eager" if args.eager else "compiled"
    print(f"{args.task}: {N_ENVS} envs in one layer, random policy, local model ({mode}, {args.steps} offline steps),"
          f" {args.calls - N_WARMUP} calls each, alternated")
    print(f"{'':<30}{'ms/call':>9}{'adjusting calls':>17}{'their ms':>10}{'iterations':>12}{'failsafe':>10}")
    for name, run in runs.items():
        print(f"{name:<30}{statistics.median(run['times']):>9.1f}{len(run['adjusting']):>17}"
              f"{statistics.median(run['adjusting'] or [float('nan')]):>10.1f}"
              f"{statistics.mean(run['iterations'] or [float('nan')]):>12.1f}"
              f"{100 * statistics.mean(run['failsafe']):>9.1f}%")


if __name__ == "__main__":
    main()
