"""Per-step latency of the safety layer with the constant brake against a state-dependent one.

Same setting as ``bench_layer.py`` (``diffdrive_nav``, 10 obstacles, ``n_plan = 10``, one CPU thread, the layer's
``compute_time``). The state-dependent brakes here return the zero command (``policy``), or ``1e-9`` times the
velocity (``linear policy``: the same actions to 1e-9, but a derivative that is not zero), i.e. the constant brake's
actions, so every difference in time is the code path: with a braking policy the braking tail is rolled out step by
step and the adjusters linearise it along that rollout (one ``n x n`` product per tail step where the policy's
derivative is not zero), where the constant brake makes every centre one affine map of (state, plan). The reachability
models of ``--models`` are timed: ``global``, ``local`` and ``body`` (the local model in the robot's body frame, as
the recipes fit the Turtlebot, from ``--data`` offline steps; the recipes use 2,000). Beside each row, the shares of
the timed steps (constant brake, then linear policy) that the layer adjusted and verified, and that fell back to the
failsafe: a row of failsafe steps may time the adjuster's budget (0.1 s) rather than the brake's cost (the world-frame
local model from 500 steps claims no plan of the wall scene); ``--quick`` (30 steps) puts the wall nearer
(``bench_layer.QUICK_WALL``), so that its adjusting rows adjust. ``--compile`` compiles the models
(``DataDrivenReach.compile_steps``): the global model's braking tails (one graph for the tail's rollout and one for
its Jacobian chain, compiled in the untimed first steps), the local model's plans with the braking policy's tail in
the same compiled loop, and the facet QP's linearisation along it (one graph each per policy, compiled when the layer
is built). ``--parts`` also times the parts a braking policy adds on the global model, per call (the best of 7 blocks
of 100 calls, which a loaded machine disturbs least): a plan's centres with its tail, the policy's Jacobian along the
tail and the centres' Jacobian the adjusters linearise with; with ``--compile``, the model there is compiled too (the
policy's tail rollout runs as one graph, its Jacobian chain of ``n_brk < 16`` steps stays eager).

Usage: ``python benchmarks/bench_failsafe.py [--quick] [--compile] [--models global,local,body] [--data 500]
[--parts]``
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
import envs  # noqa: E402
from bench_layer import N_PLAN, QUICK_WALL, TASK, WALL, episode_times, stats, step_shares  # noqa: E402
from torchrl_brsl.reach import BodyFrame, DataDrivenReach, collect_offline_data  # noqa: E402
from torchrl_brsl.safety import BRSLSafetyLayer, FacetQPAdjuster, Failsafe, GradientAdjuster, PlanChecker  # noqa: E402
from torchrl_brsl.safety.adjust import _feedback_jacobian  # noqa: E402
from torchrl_brsl.sets import Zonotope  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--compile", action="store_true", help="the models compiled (DataDrivenReach.compile_steps)")
    parser.add_argument("--models", default="global,local",
                        help="comma-separated: global, local, body (none: only `--parts`)")
    parser.add_argument("--data", type=int, default=500, help="offline steps")
    parser.add_argument("--parts", action="store_true", help="also time the parts a braking policy adds (global model)")
    args = parser.parse_args()
    models = [method for method in args.models.split(",") if method]
    if set(models) - {"global", "local", "body"}:
        parser.error(f"--models: unknown {sorted(set(models) - {'global', 'local', 'body'})}; use global, local, body")
    torch.set_num_threads(1)
    info = envs.safety_info(TASK)
    noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
    data = collect_offline_data(envs.make(TASK, empty=True, seed=1), args.data,
                                generator=torch.Generator().manual_seed(0))
    steps, wall = (30, QUICK_WALL) if args.quick else (120, WALL)
    zero = info.braking_action
    velocity = list(info.velocity_dims)
    brakes = {"constant": Failsafe(zero, info.n_brk),
              "policy": Failsafe(zero, info.n_brk, policy=lambda x: zero.to(x).expand(*x.shape[:-1], -1)),
              "linear": Failsafe(zero, info.n_brk, policy=lambda x: zero.to(x) + 1e-9 * x[..., velocity])}
    print(f"{TASK}: n_plan = {N_PLAN}, n_brk = {info.n_brk}, one CPU thread; median / p99 ms per step")
    if models:
        print(f"{'':<44}{'constant brake':>16}{'policy':>16}{'linear policy':>16}{'ratios':>12}"
              f"{'% adjusted / failsafe':>26}")
    for method in models:
        frame = BodyFrame(info.position_dims, info.heading_dims) if method == "body" else None
        reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims,
                                          max_generators=30, method="global" if method == "global" else "local",
                                          body_frame=frame)
        if args.compile:
            reach.compile_steps()
        for label, adjuster, towards_wall in (("safe proposals", GradientAdjuster, False),
                                              ("adjusting: projected gradient", GradientAdjuster, True),
                                              ("adjusting: facet-locked QP", FacetQPAdjuster, True)):
            row, outcome = {}, {}
            first = 12 if towards_wall else 5
            for name, brake in brakes.items():
                layer = BRSLSafetyLayer(reach, brake, N_PLAN, stop_dims=info.velocity_dims, stop_slack=0.15,
                                        action_low=info.action_low, action_high=info.action_high,
                                        adjuster=adjuster())
                flags = {}
                times = episode_times(layer, steps, towards_wall, 0, flags, wall)
                row[name], outcome[name] = stats(times[first:]), adjusted_and_failsafe(flags, first)
            (m0, p0), (m1, p1), (m2, p2) = row["constant"], row["policy"], row["linear"]
            print(f"{method + ': ' + label:<44}{m0:>9.2f} /{p0:>5.1f}{m1:>9.2f} /{p1:>5.1f}{m2:>9.2f} /{p2:>5.1f}"
                  f"{m1 / m0:>6.1f}{m2 / m0:>6.1f}{outcome['constant']:>13}{outcome['linear']:>13}")
    if args.parts:
        print_parts(info, data, noise, brakes, args.compile)


def adjusted_and_failsafe(flags: dict[str, list[bool]], first: int) -> str:
    """``"adjusted / failsafe"``: per cent of the steps from ``first`` on that the layer adjusted and verified, and
    that fell back to the failsafe."""
    share = step_shares(flags, first)
    return f"{share['verified']:.0f} / {share['failsafe']:.0f}"


def best_of_blocks(function, calls: int = 100, blocks: int = 7) -> float:
    """The fastest block's mean time of ``function()`` in microseconds."""
    function()
    best = float("inf")
    for _ in range(blocks):
        start = time.perf_counter()
        for _ in range(calls):
            function()
        best = min(best, (time.perf_counter() - start) / calls)
    return best * 1e6


def print_parts(info, data, noise, brakes, compiled: bool = False) -> None:
    """Per-call times of what a braking policy adds on the global model (a plan at full speed from rest)."""
    reach = DataDrivenReach.from_data(data, noise, translation_invariant_dims=info.position_dims, max_generators=30,
                                      method="global")
    if compiled:
        reach.compile_steps()
    x0 = torch.zeros(1, reach.state_dim, dtype=torch.float64)
    plan = info.action_high.double().expand(1, N_PLAN, -1)
    title = f"parts, global model{' (compiled)' if compiled else ''}, one plan, best of 7 x 100 calls (us):"
    print(f"{title:<70}{'constant brake':>16}{'linear policy':>16}")
    rows = {}
    for name in ("constant", "linear"):
        checker = PlanChecker(reach, brakes[name], N_PLAN + info.n_brk, stop_dims=info.velocity_dims,
                              stop_slack=0.15, action_low=info.action_low.double(),
                              action_high=info.action_high.double(), action_dtype=torch.float32)
        _, centers = checker.rollout(x0, plan)
        tail_states = centers[:, N_PLAN - 1:-1]
        rows[name] = {"centres of plan and tail (rollout)": best_of_blocks(lambda: checker.rollout(x0, plan))}
        if name == "linear":
            rows[name]["the policy's Jacobian along the tail"] = best_of_blocks(
                lambda: checker.brake_tangent(tail_states))
            rows[name]["the centres' Jacobian (with the chain)"] = best_of_blocks(
                lambda: _feedback_jacobian(checker, centers, N_PLAN))
    for part, value in rows["linear"].items():
        constant = rows["constant"].get(part)
        print(f"  {part:<68}{'-' if constant is None else f'{constant:.0f}':>16}{value:>16.0f}")


if __name__ == "__main__":
    main()
