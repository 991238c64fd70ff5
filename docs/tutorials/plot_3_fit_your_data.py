"""
Fitting reachability on your own data, and checking containment
================================================================

The reachability model needs transitions ``(x, u) -> x+`` of the robot, a bound on its noise
and nothing else. This tutorial fits it on logged transitions of a robot it knows nothing
about, then checks what the guarantee rests on: sampled true trajectories must lie inside the
sets of every plan the model claims. Run this check on your robot before trusting the layer.
"""

# %%
# The robot, as a black box
# -------------------------
#
# A unicycle ``(x, y, θ, v)`` commanded by ``(acceleration, yaw rate)``, from
# :mod:`torchrl_brsl.reach.examples`. Only its ``step`` (true dynamics plus bounded noise) is
# used below, as a real robot would be driven; the model never reads its equations. Replace
# ``system.step`` by your robot, or the logs of it.
import matplotlib.pyplot as plt
import torch

from torchrl_brsl.reach import DataDrivenReach, Unicycle, sample_reach
from torchrl_brsl.sets import Zonotope

torch.set_num_threads(1)
gen = torch.Generator().manual_seed(0)
system = Unicycle()

# %%
# Logged transitions and the noise bound
# --------------------------------------
#
# 1,000 transitions from random states and actions of the operating region. In your own code
# ``x_minus``, ``x_plus`` and ``u_minus`` are ``[N, n]``, ``[N, n]`` and ``[N, m]`` tensors (or
# :func:`~torchrl_brsl.reach.collect_offline_data` on a TorchRL env, saved with
# :func:`~torchrl_brsl.reach.save_offline_data`). ``W`` is a zonotope that contains every
# noise vector, here the box of the noise's half-widths.
x_minus = system.sample_states(1000, gen)
u_minus = system.sample_actions(1000, generator=gen)
x_plus = system.step(x_minus, u_minus, gen)
noise = Zonotope(torch.zeros(4, dtype=torch.float64), torch.diag(system.noise_half_width))
print(f"{len(x_minus)} transitions, noise half-widths {system.noise_half_width.tolist()}")

# %%
# Three models
# ------------
#
# * ``method="global"``: the paper's one affine fit with a Lipschitz error bound;
# * ``method="local"`` (the default): affine fits on the leaves of a regression tree of the
#   data, each with its own error bound;
# * the local model in the robot's body frame: a unicycle moves the same way whatever way it
#   faces, so naming its heading (state dim 2) lets the model fit the motion without it.
#
# Positions are translation invariant (paper Assumption 1) in all three.
fit = dict(translation_invariant_dims=(0, 1))
models = {
    "global": DataDrivenReach.fit(x_minus, x_plus, u_minus, noise, method="global", **fit),
    "local": DataDrivenReach.fit(x_minus, x_plus, u_minus, noise, **fit),
    "local, body frame": DataDrivenReach.fit(x_minus, x_plus, u_minus, noise, body_frame=system.body_frame, **fit),
}

# %%
# Containment
# -----------
#
# :func:`~torchrl_brsl.reach.sample_reach` rolls 200 noisy trajectories of the true system
# along each of 10 random 8-step plans from states of the data and compares them with the sets.
# A model *claims* a plan when the data cover its sets (the layer refuses the others and flags
# them ``out_of_data``); only claimed plans carry the guarantee. ``width_ratio`` is the set's
# width over the sampled spread: 1 would be a perfect enclosure.
x0 = system.sample_states(10, gen)
plans = system.sample_actions(10, 8, generator=gen)
results = {}
for name, reach in models.items():
    results[name] = result = sample_reach(reach, lambda x, u: system.step(x, u, gen), x0, plans, samples=200)
    print(f"{name:>17}: {int(result.covered.sum())}/10 plans claimed, {result.violations} of {result.checked} "
          f"states outside, width / spread {result.median_ratio:.1f}")
    assert result.violations == 0

# %%
# One plan's sets
# ---------------
#
# The position sets of the first plan under each model, with the sampled trajectories.
states, paths = x0[:1].expand(200, -1), [x0[:1].expand(200, -1)]
for action in plans[0]:
    states = system.step(states, action, gen)
    paths.append(states)
paths = torch.stack(paths)  # [9, 200, 4]
fig, axes = plt.subplots(1, 3, figsize=(13, 4.4))
for ax, (name, reach) in zip(axes, models.items()):
    sets = reach.reach(Zonotope.from_point(x0[:1]), plans[:1])[0].project((0, 1))
    sets.plot(ax, facecolor="tab:blue", alpha=0.15)
    for path in paths[:, :60, :2].unbind(1):
        ax.plot(path[:, 0], path[:, 1], color="k", lw=0.3, alpha=0.4)
    ax.set_title(f"{name}: width / spread {results[name].median_ratio:.1f}")
    ax.set_xlabel("x [m]")
    ax.set_aspect("equal")
axes[0].set_ylabel("y [m]")
fig.tight_layout()

# %%
# Width along the plan
# --------------------
#
# The median width ratio per step over the claimed plans: how much room the sets cost the robot.
fig, ax = plt.subplots(figsize=(7, 3.6))
for name, result in results.items():
    if result.covered.any():
        ax.plot(range(1, 9), result.width_ratio[result.covered].median(0).values, marker="o", label=name)
ax.set_yscale("log")
ax.set_xlabel("step of the plan")
ax.set_ylabel("set width / sampled spread")
ax.legend()
fig.tight_layout()
