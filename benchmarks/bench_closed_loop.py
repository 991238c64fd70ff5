"""The layer behind a random policy on point_boxes, local against global model, servo cap on and off.

Per setting: collisions (MuJoCo contacts) per episode, mean speed against the same policy
without the layer, and the shares of steps with intervention, failsafe and
``unverified_hold``. One-action proposals (``n_plan = 1``), stop slack 0.15, the facet-QP
adjuster, ``--steps`` offline transitions.

Usage: ``python benchmarks/bench_closed_loop.py [--steps 1000] [--episodes 40]``
"""
from __future__ import annotations

import argparse
import functools

import torch
from torchrl.envs import SerialEnv, TransformedEnv

import envs
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

TASK, N_ENVS, EPISODE = "point_boxes", 10, 60


def run(options: dict, reach: DataDrivenReach | None, episodes: int) -> dict:
    info = envs.safety_info(TASK)
    base = SerialEnv(N_ENVS, [functools.partial(envs.make, TASK, seed=100 + i, episode_steps=EPISODE, **options)
                              for i in range(N_ENVS)])
    env = base
    if reach is not None:
        layer = BRSLSafetyLayer(reach, Failsafe(info.braking_action, info.n_brk), 1, stop_dims=info.velocity_dims,
                                stop_slack=0.15, action_low=info.action_low, action_high=info.action_high,
                                adjuster="facet_qp")
        env = TransformedEnv(base, layer)
    torch.manual_seed(0)
    td = env.reset()
    collided, current, speeds, flags, done_episodes = [], torch.zeros(N_ENVS, dtype=torch.bool), [], [], 0
    while done_episodes < episodes:
        td["action"] = torch.rand(N_ENVS, 2) * 2 - 1
        td = env.step(td)
        current |= td["next", "collision"].squeeze(-1)
        speeds.append(td["next", "speed"].squeeze(-1))
        if reach is not None:
            flags.append(torch.stack([td["next", "brsl", key].squeeze(-1).float()
                                      for key in ("intervened", "failsafe", "unverified_hold")], -1))
        done = td["next", "done"].squeeze(-1)
        collided += current[done].tolist()
        done_episodes += int(done.sum())
        current[done] = False
        td = env.step_mdp(td)
        if done.any():
            td["_reset"] = done.unsqueeze(-1)
            td = env.reset(td)
    shares = torch.cat(flags).mean(0).tolist() if flags else [float("nan")] * 3
    return {"collisions": sum(collided), "episodes": len(collided), "speed": torch.cat(speeds).mean().item(),
            "intervened": shares[0], "failsafe": shares[1], "hold": shares[2]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000, help="offline transitions")
    parser.add_argument("--episodes", type=int, default=40)
    args = parser.parse_args()
    torch.set_num_threads(1)
    info = envs.safety_info(TASK)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    print(f"{'servo':<10}{'model':<8}{'collisions':>12}{'speed':>8}{'vs none':>9}{'interv.':>9}{'failsafe':>9}"
          f"{'hold':>7}")
    for servo, options in (("capped", {}), ("uncapped", {"max_acceleration": None})):
        torch.manual_seed(0)
        data = collect_offline_data(envs.make(TASK, empty=True, seed=1, **options), args.steps)
        free = run(options, None, args.episodes)
        print(f"{servo:<10}{'none':<8}{free['collisions']:>6}/{free['episodes']:<5}{free['speed']:>8.3f}")
        for method in ("global", "local"):
            reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                              max_generators=30, method=method)
            row = run(options, reach, args.episodes)
            print(f"{servo:<10}{method:<8}{row['collisions']:>6}/{row['episodes']:<5}{row['speed']:>8.3f}"
                  f"{row['speed'] / free['speed']:>9.2f}{row['intervened']:>9.2f}{row['failsafe']:>9.2f}"
                  f"{row['hold']:>7.2f}", flush=True)


if __name__ == "__main__":
    main()
