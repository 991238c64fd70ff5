"""The safety layer's time per step against the number of envs it serves in one batched call.

A user running many envs (a ``ParallelEnv`` of 16-64) puts one layer outside them: every step
is one call over the whole batch. Here the layer's inverse pass runs on a batch of ``B``
``diffdrive_nav`` states (the robot at the centre of layout 0, each env with its own heading
and speed), for ``B`` = 1, 4, 16, 64, in two regimes:

- safe proposals: a gentle forward plan in open space (check only);
- adjusting: a wall ahead of every robot and a full-speed proposal, so every env is adjusted
  (facet-locked QP) or falls back to braking.

Every batch holds the first ``B`` of the same 64 robots; ``B = 1`` is the mean over the first 8, one
at a time (a single robot's work depends on its heading and speed: one wall ahead is adjusted,
another passes at once). Printed per model (global fit, body-frame local model, the same compiled:
``body-compiled`` runs a plan's sets as one compiled loop, ``body-steps`` as compiled steps one by
one): the median time of one call, its ratio to one env, the time per env, and the
share of envs in the failsafe at ``B = 64``. The goal is 64 envs in at most 4x the time of one.

Usage: ``python benchmarks/bench_layer_batch.py [--quick] [--device cpu|cuda]
[--models global,body,body-compiled,body-steps]``
"""
from __future__ import annotations

import argparse
import math
import statistics

import torch
from tensordict import TensorDict

import envs
from torchrl_brsl._malloc import malloc_name
from torchrl_brsl.reach import BodyFrame, DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

TASK, N_PLAN, BATCHES = "diffdrive_nav", 8, (1, 4, 16, 64)
SINGLES = 8  # B = 1: the mean over this many of the envs, one at a time


def make_layer(reach: DataDrivenReach, info, adjuster: str | None, device: torch.device) -> BRSLSafetyLayer:
    return BRSLSafetyLayer(reach.to(device), Failsafe(info.braking_action.double().to(device), info.n_brk), N_PLAN,
                           stop_dims=info.velocity_dims, stop_slack=0.15, action_low=info.action_low.to(device),
                           action_high=info.action_high.to(device), adjuster=adjuster)


def batch_inputs(info, envs_: slice, towards_wall: bool, device: torch.device) -> TensorDict:
    """One step's TensorDict for the robots ``envs_`` of 64 at the origin with their own headings and speeds
    (the same 64 for every batch size, so that a batch holds the same work as its envs one by one)."""
    td = envs.make(TASK, seed=0, layout=0).reset()
    gen = torch.Generator().manual_seed(0)
    heading = (2 * math.pi * torch.rand(BATCHES[-1], generator=gen, dtype=torch.float64))[envs_]
    speed = (0.05 + 0.15 * torch.rand(BATCHES[-1], generator=gen, dtype=torch.float64))[envs_]
    n_envs = heading.shape[0]
    state = torch.stack((torch.zeros_like(speed), torch.zeros_like(speed), heading.cos(), heading.sin(), speed,
                         torch.zeros_like(speed)), dim=-1)
    obstacles = td["obstacles"].expand(n_envs).clone()
    if towards_wall:  # obstacle 0 (a wall) 0.7 m ahead of every robot
        obstacles["center"][:, 0] = 0.7 * state[:, 2:4]
        command = [0.25, 0.0]
    else:
        obstacles["mask"][:] = False
        obstacles["mask"][:, 4:] = True  # the walls of the arena are far; inner obstacles stay
        command = [0.05, 0.0]
    plan = torch.tensor([command] * N_PLAN).expand(n_envs, N_PLAN, 2)
    return TensorDict(state=state.float(), plan=plan.clone(), action=plan[:, 0].clone(), obstacles=obstacles,
                      batch_size=[n_envs]).to(device)


def median_ms(layer: BRSLSafetyLayer, td: TensorDict, calls: int) -> tuple[float, float]:
    """The median time of one call (ms) and the share of envs in the failsafe at the last."""
    times = []
    for _ in range(calls + 2):
        out = layer.inv(td.clone())
        times.append(float(out["brsl", "compute_time"][0]))
        td.set("safe_plan", out["safe_plan"])
        td.set("safe_plan_steps", out["safe_plan_steps"])
    failsafe = float(out["brsl", "failsafe"].float().mean())
    return 1e3 * statistics.median(times[2:]), failsafe  # the first calls build the caches


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer calls (a smoke run)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--models", default="global,body",
                        help="comma-separated: global, body, body-compiled, body-steps (DataDrivenReach.compile_steps,"
                             " with loop=False)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    device = torch.device(args.device)
    info = envs.safety_info(TASK)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    data = collect_offline_data(envs.make(TASK, empty=True, seed=1), 2000)
    calls = 3 if args.quick else 10
    print(f"{TASK}, n_plan = {N_PLAN}, n_brk = {info.n_brk}, one CPU thread, {malloc_name()}, device {device}")
    print(f"{'model / regime':<38}" + "".join(f"{f'B={b} ms':>12}" for b in BATCHES)
          + f"{'64 / 1':>9}{'ms per env at 64':>18}{'failsafe':>10}")
    for model in args.models.split(","):
        frame = BodyFrame(info.position_dims, info.heading_dims) if model.startswith("body") else None
        reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                          max_generators=30, method="global" if model == "global" else "local",
                                          body_frame=frame)
        if model in ("body-compiled", "body-steps"):
            reach.compile_steps(loop=model == "body-compiled")
        for regime, towards_wall, adjuster in (("safe proposals", False, None), ("adjusting", True, "facet_qp")):
            runs = [median_ms(make_layer(reach, info, adjuster, device),
                              batch_inputs(info, slice(0, b), towards_wall, device), calls) for b in BATCHES]
            singles = [median_ms(make_layer(reach, info, adjuster, device),
                                 batch_inputs(info, slice(i, i + 1), towards_wall, device), calls)[0]
                       for i in range(SINGLES)]
            row = [statistics.mean(singles)] + [t for t, _ in runs[1:]]
            print(f"{f'{model}: {regime}':<38}" + "".join(f"{t:>12.2f}" for t in row)
                  + f"{row[-1] / row[0]:>9.1f}{row[-1] / BATCHES[-1]:>18.3f}{runs[-1][1]:>10.0%}")
    print("goal: 64 envs in <= 4x the time of one")


if __name__ == "__main__":
    main()
