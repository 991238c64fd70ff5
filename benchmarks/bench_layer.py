"""Per-step latency of the safety layer, beside one env step and one actor forward pass.

``diffdrive_nav`` (Turtlebot-like) with 10 obstacles in range and ``n_plan = 10``
(``T = 16`` reachable sets with the braking tail; ``--n-plan 1`` is the recipes' default, one action
then braking, ``T = 7``), one CPU thread. Three regimes:

- safe proposals (no adjustment needed): a gentle constant plan in open space;
- adjustment: the plan drives at full speed towards a wall, so once the wall is within the
  braking distance every step needs an adjustment; both adjusters are timed;
each with the local reachability model (the default), the local model fitted in the robot's body
frame (``body``) and the global fit; with ``--compile`` also the local models with compiled steps
(``DataDrivenReach.compile_steps``; one untimed episode per layer first, which compiles).

The layer's own time is its ``compute_time`` diagnostic (read, check, adjust, write). Beside each
layer row, the shares of its timed steps that the layer adjusted and verified, that fell back to the
failsafe or to ``unverified_hold``, whose proposal was ``out_of_data``, and at which the robot stood at rest
(speed under 0.01 m/s): an adjusting row whose steps all end in the failsafe times the adjuster's budget, not its
speed, and one whose robot has stopped at the wall times the steps that keep it there (a robot that cannot reverse,
stopped a few mm nearer the wall, falls back wherever its stopped sets reach the wall). ``--data`` sets the
offline steps (the recipes fit the Turtlebot's body-frame model from 2,000).
Usage: ``python benchmarks/bench_layer.py [--quick] [--compile] [--data 500] [--n-plan 10]``
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
from torchrl.envs import TransformedEnv

import envs
from torchrl_brsl._malloc import malloc_name
from torchrl_brsl.reach import BodyFrame, DataDrivenReach, collect_offline_data
from torchrl_brsl.safety import BRSLSafetyLayer, FacetQPAdjuster, Failsafe, GradientAdjuster
from torchrl_brsl.sets import Zonotope

TASK, N_PLAN, N_OBSTACLES = "diffdrive_nav", 10, 10
METHODS = ("local", "body", "global")
COMPILED = ("local compiled", "body compiled")


def make_layer(reach, info, adjuster, n_plan: int):
    """The layer with open-loop braking (the zero command, which is this task's braking policy)."""
    return BRSLSafetyLayer(reach, Failsafe(info.braking_action, info.n_brk), n_plan,
                           stop_dims=info.velocity_dims, stop_slack=0.15,
                           action_low=info.action_low, action_high=info.action_high, adjuster=adjuster)


FLAGS = ("failsafe", "unverified_hold", "out_of_data")
VELOCITY_DIMS = list(envs.safety_info(TASK).velocity_dims[:1])  # the forward speed
REST_SPEED = 0.01
WALL, QUICK_WALL = 1.6, 0.8
"""How far ahead the adjusting scene's wall stands (m): at full speed the robot reaches it in about 64 steps, or 32,
so that ``--quick`` (30 steps, 12 untimed) times adjusting steps too."""


def episode_times(layer, steps: int, towards_wall: bool, seed: int,
                  flags: dict[str, list[bool]] | None = None, wall: float = WALL) -> list[float]:
    """The layer's ``compute_time`` of each step (s); ``flags``: filled with each step's ``intervened`` and
    :data:`FLAGS` diagnostics, and ``at_rest`` (the robot's speed before the step under :data:`REST_SPEED`);
    ``wall``: how far ahead the wall of ``towards_wall`` stands (m)."""
    env = TransformedEnv(envs.make(TASK, seed=seed, episode_steps=10_000), layer)
    td = env.reset()
    state = td["state"]
    mask = td["obstacles", "mask"].clone()
    mask[:] = False
    mask[:N_OBSTACLES] = True
    obstacles = td["obstacles"].clone()
    obstacles["mask"] = mask
    if towards_wall:  # put obstacle 0 (a wall) ahead of the robot
        obstacles["center"][0] = state[:2] + wall * state[2:4]
        speed = [0.25, 0.0]
    else:
        speed = [0.05, 0.0]
    times = []
    for _ in range(steps):
        td["obstacles"] = obstacles
        td["plan"] = torch.tensor([speed] * layer.n_plan)
        td["action"] = td["plan"][0]
        robot_speed = float(td["state"][..., VELOCITY_DIMS].norm())
        td = env.step(td)
        times.append(td["next", "brsl", "compute_time"].item())
        if flags is not None:
            for name in ("intervened", *FLAGS):
                flags.setdefault(name, []).append(bool(td["next", "brsl", name]))
            flags.setdefault("at_rest", []).append(robot_speed < REST_SPEED)
        td = env.step_mdp(td)
    return times


def step_shares(flags: dict[str, list[bool]], first: int) -> dict[str, float]:
    """Per cent of the steps from ``first`` on: ``verified`` (adjusted and verified), then each of :data:`FLAGS`."""
    def share(values):
        return 100 * sum(values[first:]) / max(len(values[first:]), 1)
    verified = [i and not f for i, f in zip(flags["intervened"], flags["failsafe"])]
    return {"verified": share(verified), **{name: share(flags[name]) for name in (*FLAGS, "at_rest")}}


def shares(flags: dict[str, list[bool]], first: int) -> str:
    """:func:`step_shares` as one row of columns."""
    return "".join(f"{value:>9.0f}" for value in step_shares(flags, first).values())


def offline_data(steps: int) -> tuple:
    """One thread, seeded: the task's safety info, its noise zonotope (float64) and ``steps`` offline transitions."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    info = envs.safety_info(TASK)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    return info, noise, collect_offline_data(envs.make(TASK, empty=True, seed=1), steps)


def stats(times: list[float]) -> tuple[float, float]:
    ordered = sorted(times)
    return 1e3 * statistics.median(ordered), 1e3 * ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--compile", action="store_true", help="add the local models with compiled steps")
    parser.add_argument("--data", type=int, default=500, help="offline steps")
    parser.add_argument("--n-plan", type=int, default=N_PLAN,
                        help="planned steps before braking (1: the recipes' default, one action then braking)")
    args = parser.parse_args()
    info, noise, data = offline_data(args.data)
    steps, wall = (30, QUICK_WALL) if args.quick else (120, WALL)
    rows, flag_shares = {}, {}
    methods = METHODS + (COMPILED if args.compile else ())
    for method in methods:
        frame = BodyFrame(info.position_dims, info.heading_dims) if method.startswith("body") else None
        reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                          max_generators=30, method="global" if method == "global" else "local",
                                          body_frame=frame)
        if method in COMPILED:
            reach.compile_steps()
        for name, adjuster in (("safe proposals (no adjustment)", None), ("adjusting every step: projected gradient",
                               GradientAdjuster()), ("adjusting every step: facet-locked QP", FacetQPAdjuster())):
            layer = make_layer(reach, info, adjuster or GradientAdjuster(), args.n_plan)
            if method in COMPILED:  # compile outside the timing
                episode_times(layer, 15, adjuster is not None, 0, wall=wall)
            flags = {}
            times = episode_times(layer, steps, adjuster is not None, 0, flags, wall)
            # adjusting: once the wall is within braking distance every step adjusts
            first = 12 if adjuster is not None else 5
            rows[f"{method}: layer, {name}"] = stats(times[first:])
            flag_shares[f"{method}: layer, {name}"] = shares(flags, first)

    base = envs.make(TASK, seed=0)
    td = base.reset()
    env_times = []
    for _ in range(steps):
        start = time.perf_counter()
        td = base.step(base.rand_action(td))
        env_times.append(time.perf_counter() - start)
        td = base.step_mdp(td) if not td["next", "done"].item() else base.reset()
    rows["one env step (MuJoCo + TorchRL wrapper)"] = stats(env_times)
    actor = torch.nn.Sequential(torch.nn.Linear(23, 256), torch.nn.ReLU(), torch.nn.Linear(256, 256),
                                torch.nn.ReLU(), torch.nn.Linear(256, 2), torch.nn.Tanh())
    obs = torch.randn(23)
    actor_times = []
    with torch.no_grad():
        for _ in range(steps * 5):
            start = time.perf_counter()
            actor(obs)
            actor_times.append(time.perf_counter() - start)
    rows["one actor forward (MLP 23-256-256-2)"] = stats(actor_times)

    print(f"{TASK}: {N_OBSTACLES} obstacles, n_plan = {args.n_plan}, n_brk = {info.n_brk}, one CPU thread, "
          f"{malloc_name()}, {args.data} offline steps; % of the timed steps")
    columns = "".join(f"{name:>9}" for name in ("adjusted", "failsafe", "hold", "no data", "at rest"))
    print(f"{'':<66}{'median ms':>12}{'p99 ms':>10}{columns}")
    for label, (median, p99) in rows.items():
        print(f"{label:<66}{median:>12.3f}{p99:>10.3f}{flag_shares.get(label, '')}")
    for method in methods:
        best = min(v[0] for k, v in rows.items() if "adjusting" in k and k.startswith(f"{method}:"))
        print(f"target ({method}): median <= 1.5 ms with adjustment: {'met' if best <= 1.5 else 'MISSED'} "
              f"(best {best:.2f} ms)")


if __name__ == "__main__":
    main()
