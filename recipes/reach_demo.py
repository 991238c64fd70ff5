"""``make demo``: data-driven reachable sets of a plan and their collision checks, plotted.

A planar double integrator with drag and saturation is a black box: 500 noisy random
transitions are all the reachability analysis sees. A plan that drives towards a box is
checked against it (exact closed form and the differentiable LP agree), adjusted by the
paper's projected gradient until every reachable set, braking tail included, is
collision-free, and both are drawn with 20,000 sampled true trajectories.

Usage: ``python -m recipes.reach_demo [--out runs/demo] [--seed 0]``
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchrl_brsl.collision import collision_value
from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import Failsafe, GradientAdjuster, PlanChecker
from torchrl_brsl.sets import Obstacles, Zonotope

N_PLAN, N_BRK = 5, 8


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/demo", help="output folder for the plot")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(args.seed)

    system = DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)
    x, xp, u = system.offline_data(500, gen)
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24)
    print(f"fitted on 500 transitions: Lipschitz of the residual per dim {reach.lipschitz.numpy().round(3)}, "
          f"covering radius {reach.covering_radius:.3f}")

    obstacle = Zonotope.from_interval(torch.tensor([1.1, -0.35], dtype=torch.float64),
                                      torch.tensor([1.5, 0.35], dtype=torch.float64))
    x0 = torch.tensor([0.0, 0.0, 0.6, 0.0], dtype=torch.float64)
    plan = torch.tensor([[1.0, 0.0]] * N_PLAN, dtype=torch.float64)
    horizon = N_PLAN + N_BRK
    checker = PlanChecker(reach, Failsafe(torch.zeros(2, dtype=torch.float64), N_BRK, system.braking), horizon,
                          stop_dims=(2, 3), stop_slack=0.1, action_low=system.action_low,
                          action_high=system.action_high)
    obstacles = Obstacles(obstacle.center.view(1, 1, 2), obstacle.generators.view(1, 1, 2, 2),
                          torch.ones(1, 1, dtype=torch.bool))
    before = checker.evaluate(x0[None], plan[None], obstacles)
    adjusted = GradientAdjuster(max_iterations=200, time_budget=None)(checker, x0[None], plan[None], obstacles)

    sets = {}
    for label, evaluation, proposal in (("proposed", before, plan[None]),
                                        ("adjusted", adjusted.evaluation, adjusted.plan)):
        sets[label] = checker.rollout_sets(x0[None], proposal)[1][0]  # plan-dependent (local model)
        projected = sets[label].project((0, 1))
        exact = collision_value(projected, obstacle, backend="closed_form")
        lp = collision_value(projected[:N_PLAN], obstacle, backend="lp")
        print(f"\n{label} plan: verified safe = {bool(evaluation.safe)}")
        print(f"{'step':>4} {'v* closed form':>15} {'v* LP':>10} {'collides':>9}")
        for j in range(horizon):
            lp_text = f"{lp[j].item():>10.4f}" if j < N_PLAN else f"{'':>10}"
            print(f"{j + 1:>4} {exact[j].item():>15.4f} {lp_text} {str(bool(exact[j] <= 1)):>9}")
    print(f"\nadjustment: {int(adjusted.iterations)} projected-gradient steps")

    # true trajectories of the adjusted plan (with its braking tail)
    actions = adjusted.evaluation.actions[0]
    states = x0.expand(20_000, -1)
    paths = [states]
    for action in actions:
        states = system.step(states, action, gen)
        paths.append(states)
    paths = torch.stack(paths)
    inside = all(bool(sets["adjusted"][j].project((0, 1)).contains(paths[j + 1, :, :2]).all())
                 for j in range(horizon))
    print(f"20,000 true trajectories inside the adjusted plan's sets at every step: {inside}")
    _plot(sets, obstacle, paths, Path(args.out))


def _plot(sets, obstacle, paths, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), sharey=True)
    for ax, (label, zonotopes) in zip(axes, sets.items()):
        zonotopes.project((0, 1)).plot(ax, facecolor="tab:blue", alpha=0.15)
        obstacle.plot(ax, facecolor="tab:red", alpha=0.6)
        if label == "adjusted":
            for path in paths[:, :200, :2].unbind(1):
                ax.plot(path[:, 0], path[:, 1], color="k", linewidth=0.3, alpha=0.3)
        ax.set_title(f"{label} plan: reachable sets (blue), obstacle (red)")
        ax.set_xlabel("x [m]")
    axes[0].set_ylabel("y [m]")
    fig.tight_layout()
    path = out / "reach_collision.png"
    fig.savefig(path, dpi=120)
    print(f"plot written to {path}")


if __name__ == "__main__":
    main()
