"""Steps per second of the tasks, on one thread.

Columns:
  dm_control   the raw ``control.Environment`` (``env.step(numpy action)``)
  torchrl      what ``envs.make`` returns (``SafetyTaskEnv``), ``step_and_maybe_reset``
  reference    ``DMControlWrapper`` + ``TransformedEnv(DoubleToFloat, RenameTransform)``,
               the generic route the ``SafetyTaskEnv`` replaces (flat obstacle keys
               renamed into the nested ``obstacles`` entry; flags stay bool)

Actions are uniform over the action box and episodes restart when they end (reset
time included). Usage:
``python benchmarks/bench_envs.py [--steps 3000] [--empty] [--tasks point_boxes ...] [--robot wheeled]``
(``--robot`` selects the robot of the tasks that have several: ``wheeled`` for ``diffdrive_nav``, ``rotor`` for
``quadrotor_nav`` and ``hexarotor_wind``; every task given must have it).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import envs
from envs._registry import _module

torch.set_num_threads(1)


def _actions(name: str, steps: int) -> np.ndarray:
    info = envs.safety_info(name)
    rng = np.random.RandomState(0)
    return rng.uniform(info.action_low.numpy(), info.action_high.numpy(), (steps, info.action_dim))


def bench_dm_control(name: str, steps: int, empty: bool, **options) -> float:
    environment = _module(name).build_environment(seed=0, empty=empty, **options)
    environment.reset()
    actions = _actions(name, steps)
    start = time.perf_counter()
    for action in actions:
        if environment.step(action).last():
            environment.reset()
    return steps / (time.perf_counter() - start)


def _bench_torchrl_env(env, name: str, steps: int) -> float:
    actions = torch.as_tensor(_actions(name, steps), dtype=torch.float32)
    td = env.reset()
    start = time.perf_counter()
    for action in actions:
        td["action"] = action
        _, td = env.step_and_maybe_reset(td)
    return steps / (time.perf_counter() - start)


def bench_torchrl(name: str, steps: int, empty: bool, **options) -> float:
    return _bench_torchrl_env(envs.make(name, seed=0, empty=empty, **options), name, steps)


def bench_reference(name: str, steps: int, empty: bool, **options) -> float:
    from torchrl.envs import Compose, DMControlWrapper, DoubleToFloat, RenameTransform, TransformedEnv

    keys = ["center", "generators", "mask"]
    env = TransformedEnv(
        DMControlWrapper(_module(name).build_environment(seed=0, empty=empty, **options)),
        Compose(
            DoubleToFloat(),
            RenameTransform([f"obstacles_{k}" for k in keys], [("obstacles", k) for k in keys]),
        ),
    )
    return _bench_torchrl_env(env, name, steps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--empty", action="store_true", help="benchmark the obstacle-free variants")
    parser.add_argument("--tasks", nargs="+", choices=envs.TASKS, default=envs.TASKS, help="tasks (default: all)")
    robots = {name: getattr(_module(name), "ROBOTS", ("kinematic",)) for name in envs.TASKS}
    parser.add_argument("--robot", choices=sorted(set().union(*robots.values())),
                        help="the robot of the tasks (default: each task's kinematic robot)")
    args = parser.parse_args()
    if args.robot is not None:
        without = [name for name in args.tasks if args.robot not in robots[name]]
        if without:
            parser.error(f"--robot {args.robot} is not a robot of {', '.join(without)}; pick the tasks with --tasks")
    options = {} if args.robot is None else {"robot": args.robot}
    print(f"steps/s, one thread, {args.steps} steps per entry{' (empty variants)' if args.empty else ''}")
    print(f"{'task':<16}{'dm_control':>12}{'torchrl':>12}{'reference':>12}")
    for name in args.tasks:
        benches = (bench_dm_control, bench_torchrl, bench_reference)
        for bench in benches:
            bench(name, 200, args.empty, **options)  # warm-up
        row = [bench(name, args.steps, args.empty, **options) for bench in benches]
        print(f"{name:<16}" + "".join(f"{value:>12.0f}" for value in row))


if __name__ == "__main__":
    main()
