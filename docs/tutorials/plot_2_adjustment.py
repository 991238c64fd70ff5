"""
Reachable sets before and after adjustment
==========================================

A plan that drives a black-box robot towards a box is checked: its data-driven reachable
sets, braking tail included, meet the box. The paper's projected gradient on the collision
values (:class:`~torchrl_brsl.safety.GradientAdjuster`, Algorithm 3) and the facet-locked QP
(:class:`~torchrl_brsl.safety.FacetQPAdjuster`) each move the plan until every set is clear,
and sampled true trajectories of the adjusted plan are drawn inside its sets. This is the
computation behind ``make demo-reach`` (``recipes/reach_demo.py``).
"""

# %%
# A black box and its model
# -------------------------
#
# A planar double integrator with quadratic drag and saturation
# (:class:`~torchrl_brsl.reach.DoubleIntegrator`): the reachability analysis sees only 500
# noisy transitions from random states and actions.
import matplotlib.pyplot as plt
import torch

from torchrl_brsl.collision import collision_value
from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator
from torchrl_brsl.safety import FacetQPAdjuster, Failsafe, GradientAdjuster, PlanChecker
from torchrl_brsl.sets import Obstacles, Zonotope

torch.set_num_threads(1)
gen = torch.Generator().manual_seed(0)
system = DoubleIntegrator(drag=0.05, max_speed=3.0, data_speed=1.5)
x, x_next, u = system.offline_data(500, gen)
reach = DataDrivenReach.fit(x, x_next, u, system.noise, translation_invariant_dims=(0, 1), max_generators=24)

# %%
# The plan, the obstacle and the check
# ------------------------------------
#
# Five steps of full acceleration along ``x`` from ``(0, 0)`` at 0.6 m/s, then eight steps of
# the system's braking policy. :class:`~torchrl_brsl.safety.PlanChecker` rolls the sets out and
# computes each one's collision value ``v*`` against the box (``v* <= 1`` iff they meet).
N_PLAN, N_BRK = 5, 8
obstacle = Zonotope.from_interval(torch.tensor([1.1, -0.35], dtype=torch.float64),
                                  torch.tensor([1.5, 0.35], dtype=torch.float64))
obstacles = Obstacles(obstacle.center.view(1, 1, 2), obstacle.generators.view(1, 1, 2, 2),
                      torch.ones(1, 1, dtype=torch.bool))
x0 = torch.tensor([[0.0, 0.0, 0.6, 0.0]], dtype=torch.float64)
plan = torch.tensor([[[1.0, 0.0]] * N_PLAN], dtype=torch.float64)
checker = PlanChecker(reach, Failsafe(torch.zeros(2, dtype=torch.float64), N_BRK, system.braking), N_PLAN + N_BRK,
                      stop_dims=(2, 3), stop_slack=0.1, action_low=system.action_low,
                      action_high=system.action_high)
before = checker.evaluate(x0, plan, obstacles)
print(f"proposed plan verified safe: {bool(before.safe)}")

# %%
# Adjusting
# ---------
#
# Both adjusters return the adjusted plan and its exact re-check. The facet-locked QP starts
# from a *reference* plan that is already safe (in the layer: the previous safe plan, shifted
# by one step); here, coasting (zero acceleration) before the braking tail. It is a local
# method: it locks each set to the obstacle facet that separates it under the reference,
# projects the proposal onto those linear constraints, and backs off towards the reference
# while the exact check rejects the result, so a reference far from the proposal (full
# braking, say) gives a more cautious plan.
reference = torch.tensor([[[0.0, 0.0]] * N_PLAN], dtype=torch.float64)
print(f"reference plan verified safe: {bool(checker.evaluate(x0, reference, obstacles).safe)}")
adjusted = {
    "projected gradient": GradientAdjuster(max_iterations=200, time_budget=None)(checker, x0, plan, obstacles),
    "facet-locked QP": FacetQPAdjuster()(checker, x0, plan, obstacles, reference=reference),
}
for name, result in adjusted.items():
    print(f"{name}: verified safe {bool(result.evaluation.safe)} after {int(result.iterations)} iterations\n"
          f"    x accelerations {result.plan[0, :, 0].numpy().round(2)} (proposed {plan[0, :, 0].numpy()})")

# %%
# The collision values of each step
# ---------------------------------
#
# The exact closed form for 2-D zonotopes and the differentiable LP give the same ``v*``.
sets = {"proposed": checker.rollout_sets(x0, plan)[1][0].project((0, 1))}
for name, result in adjusted.items():
    sets[name] = checker.rollout_sets(x0, result.plan)[1][0].project((0, 1))
exact = {name: collision_value(s, obstacle, backend="closed_form") for name, s in sets.items()}
lp = collision_value(sets["proposed"], obstacle, backend="lp")
print("step  " + "  ".join(f"{name:>18}" for name in exact) + "   proposed (LP)")
for j in range(N_PLAN + N_BRK):
    print(f"{j + 1:>4}  " + "  ".join(f"{values[j].item():>18.3f}" for values in exact.values())
          + f"   {lp[j].item():>13.3f}")

# %%
# Sets and true trajectories
# --------------------------
#
# 2,000 noisy trajectories of the true system under each adjusted plan (with its braking tail)
# stay inside that plan's sets at every step.
fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), sharey=True)
for ax, (name, zonotopes) in zip(axes, sets.items()):
    zonotopes.plot(ax, facecolor="tab:blue", alpha=0.15)
    obstacle.plot(ax, facecolor="tab:red", alpha=0.6)
    ax.set_title(f"{name}: v* min {exact[name].min():.2f}")
    ax.set_xlabel("x [m]")
    ax.set_xlim(-0.05, 1.6)
    if name in adjusted:
        actions = adjusted[name].evaluation.actions[0]
        states, paths = x0.expand(2000, -1), [x0.expand(2000, -1)]
        for action in actions:
            states = system.step(states, action, gen)
            paths.append(states)
        paths = torch.stack(paths)
        inside = all(bool(zonotopes[j].contains(paths[j + 1, :, :2]).all()) for j in range(len(actions)))
        print(f"{name}: 2,000 true trajectories inside the sets at every step: {inside}")
        for path in paths[:, :100, :2].unbind(1):
            ax.plot(path[:, 0], path[:, 1], color="k", lw=0.3, alpha=0.3)
axes[0].set_ylabel("y [m]")
fig.tight_layout()
