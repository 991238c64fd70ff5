"""The layer behind a random policy on a task, local against global model, servo caps on and off.

Per setting: collisions (MuJoCo contacts) per episode, mean speed against the same policy
without the layer, the shares of steps with intervention, failsafe, ``unverified_hold`` and
``out_of_data``, the median position radius of the final reachable set of the executed
plans, and the layer's median time per batched call (after ``N_WARMUP`` calls, which include
any compilation: ``--compile`` runs the local models' steps compiled). One-action proposals
(``n_plan = 1``) then the task's braking steps (``--n-brk`` for the uncapped servos), stop slack
0.15, the facet-QP adjuster (``--adjuster``), ``--steps`` offline transitions (in episodes of
``--offline-episode-steps``).

Usage: ``python benchmarks/bench_closed_loop.py [--task point_boxes] [--robot kinematic] [--steps 1000]
[--offline-episode-steps 50] [--episodes 40] [--servo capped|uncapped|both] [--models global,local,body]
[--compile] [--adjuster facet_qp]``
"""
from __future__ import annotations

import argparse
import functools
import statistics

import torch
from torchrl.envs import SerialEnv, TransformedEnv

import envs
from torchrl_brsl._malloc import malloc_name
from torchrl_brsl.reach import BodyFrame, DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import ADJUSTERS, BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

N_ENVS = 10
N_WARMUP = 20
UNCAPPED = {"diffdrive_nav": {"max_acceleration": None, "max_turn_acceleration": None}}


def run(task: str, options: dict, reach: DataDrivenReach | None, n_brk: int, episodes: int, episode: int,
        adjuster: str = "facet_qp") -> dict:
    info = envs.safety_info(task, robot=options.get("robot", "kinematic"))
    base = SerialEnv(N_ENVS, [functools.partial(envs.make, task, seed=100 + i, episode_steps=episode, **options)
                              for i in range(N_ENVS)])
    env = base
    if reach is not None:
        layer = BRSLSafetyLayer(reach, Failsafe(info.braking_action, n_brk), 1, stop_dims=info.velocity_dims,
                                stop_slack=0.15, action_low=info.action_low, action_high=info.action_high,
                                adjuster=adjuster)
        env = TransformedEnv(base, layer)
    torch.manual_seed(0)
    td = env.reset()
    collided, current, speeds, flags, radii, done_episodes = [], torch.zeros(N_ENVS, dtype=torch.bool), [], [], [], 0
    times = []
    while done_episodes < episodes:
        low, high = info.action_low, info.action_high
        td["action"] = low + (high - low) * torch.rand(N_ENVS, low.shape[-1])
        state = td["state"].double()
        td = env.step(td)
        if reach is not None and len(speeds) % 5 == 0:  # the executed action's sets, plan + braking tail
            executed = td["next", "safe_action"].double().unsqueeze(1)
            sets = _final_sets(layer, state, executed)
            radii.append(sets.generators[..., list(info.position_dims), :].abs().sum(-1).amax(-1))
        current |= td["next", "collision"].squeeze(-1)
        speeds.append(td["next", "speed"].squeeze(-1))
        if reach is not None:
            flags.append(torch.stack([td["next", "brsl", key].squeeze(-1).float()
                                      for key in ("intervened", "failsafe", "unverified_hold", "out_of_data")], -1))
            times.append(float(td["next", "brsl", "compute_time"].flatten()[0]))
        done = td["next", "done"].squeeze(-1)
        collided += current[done].tolist()
        done_episodes += int(done.sum())
        current[done] = False
        td = env.step_mdp(td)
        if done.any():
            td["_reset"] = done.unsqueeze(-1)
            td = env.reset(td)
    shares = torch.cat(flags).mean(0).tolist() if flags else [float("nan")] * 4
    return {"collisions": sum(collided), "episodes": len(collided), "speed": torch.cat(speeds).mean().item(),
            "intervened": shares[0], "failsafe": shares[1], "hold": shares[2], "out_of_data": shares[3],
            "radius": torch.cat(radii).median().item() if radii else float("nan"),
            "ms": 1e3 * statistics.median(times[N_WARMUP:]) if len(times) > N_WARMUP else float("nan")}


def _final_sets(layer: BRSLSafetyLayer, state, plan):
    """The final reachable sets ``[B]`` of one-action plans with the layer's braking tail."""
    checker = layer.checker
    if checker.plan_dependent:
        return checker.rollout_sets(state, plan)[1][:, -1]
    actions, _ = checker.rollout(state, plan)
    return layer.reach.reach(Zonotope.from_point(state), actions)[:, -1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="point_boxes")
    parser.add_argument("--robot", default="kinematic", help="the task's robot (e.g. wheeled, rotor)")
    parser.add_argument("--steps", type=int, default=1000, help="offline transitions")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--episode-steps", type=int, default=60)
    parser.add_argument("--offline-episode-steps", type=int, default=None,
                        help="episode length of the offline data (default: the task's; e.g. 50 on hexarotor_wind, "
                             "whose data must see many winds)")
    parser.add_argument("--n-brk", type=int, default=None, help="braking steps of the uncapped servos")
    parser.add_argument("--servo", choices=("capped", "uncapped", "both"), default="both")
    parser.add_argument("--models", default="global,local,body",
                        help="comma-separated: global, local, body (local in the body frame, robots with a heading)")
    parser.add_argument("--compile", action="store_true", help="compiled steps of the local models (compile_steps)")
    parser.add_argument("--adjuster", choices=sorted(ADJUSTERS), default="facet_qp")
    args = parser.parse_args()
    torch.set_num_threads(1)
    task = args.task
    info = envs.safety_info(task, robot=args.robot)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    print(f"{task} ({args.robot} robot), one CPU thread, {malloc_name()}")
    print(f"{'servo':<10}{'model':<8}{'collisions':>12}{'speed':>8}{'vs none':>9}{'interv.':>9}{'failsafe':>9}"
          f"{'hold':>7}{'no data':>9}{'radius':>9}{'ms/step':>9}")
    uncapped = UNCAPPED.get(task, {"max_acceleration": None})
    robot = {} if args.robot == "kinematic" else {"robot": args.robot}
    settings = (("capped", robot, info.n_brk), ("uncapped", {**uncapped, **robot}, args.n_brk or info.n_brk))
    for servo, options, n_brk in (s for s in settings if args.servo in (s[0], "both")):
        torch.manual_seed(0)
        offline_episode = {} if args.offline_episode_steps is None else {"episode_steps": args.offline_episode_steps}
        data = collect_offline_data(envs.make(task, empty=True, seed=1, **options, **offline_episode), args.steps)
        free = run(task, options, None, n_brk, args.episodes, args.episode_steps)
        print(f"{servo:<10}{'none':<8}{free['collisions']:>6}/{free['episodes']:<5}{free['speed']:>8.3f}")
        for method in args.models.split(","):
            if method == "body" and not info.heading_dims:
                continue
            frame = BodyFrame(info.position_dims, info.heading_dims) if method == "body" else None
            reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                              max_generators=30, method="global" if method == "global" else "local",
                                              body_frame=frame)
            if args.compile and reach.plan_dependent:
                reach.compile_steps()
            row = run(task, options, reach, n_brk, args.episodes, args.episode_steps, args.adjuster)
            print(f"{servo:<10}{method:<8}{row['collisions']:>6}/{row['episodes']:<5}{row['speed']:>8.3f}"
                  f"{row['speed'] / free['speed']:>9.2f}{row['intervened']:>9.2f}{row['failsafe']:>9.2f}"
                  f"{row['hold']:>7.2f}{row['out_of_data']:>9.2f}{row['radius']:>9.3g}{row['ms']:>9.1f}", flush=True)


if __name__ == "__main__":
    main()
