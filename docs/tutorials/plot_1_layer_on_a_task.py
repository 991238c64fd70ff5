"""
The safety layer on a task, behind a random policy
==================================================

The layer needs no model of the robot: a few hundred random steps in an obstacle-free copy of
the task are all it sees. Here it protects ``point_boxes`` (a velocity-commanded point mass
among boxes crowded around its start, where random actions collide in most episodes) from a
uniformly random policy, and its per-step diagnostics are plotted.
"""

# %%
# The task and what the layer needs to know about it
# --------------------------------------------------
#
# :func:`envs.safety_info` describes a task for a safety layer (never its dynamics): where the
# position and velocity sit in the ``state``, the noise zonotope ``W``, the action bounds and
# the braking steps ``n_brk``. ``max_acceleration=None`` runs the servos without their force
# cap, where the global (affine) model is exact up to the noise and fits in milliseconds.
import matplotlib.pyplot as plt
import torch
from torchrl.envs import TransformedEnv

import envs
from torchrl_brsl.reach import DataDrivenReach
from torchrl_brsl.safety import BRSLSafetyLayer, Failsafe
from torchrl_brsl.sets import Zonotope

torch.set_num_threads(1)
TASK, OPTIONS = "point_boxes", {"max_acceleration": None}
info = envs.safety_info(TASK)
print(f"state {info.state_dim}-D, positions {info.position_dims}, velocities {info.velocity_dims}, "
      f"n_brk {info.n_brk}, actions in [{info.action_low.tolist()}, {info.action_high.tolist()}]")

# %%
# Offline data and the reachability model
# ---------------------------------------
#
# :meth:`DataDrivenReach.from_env <torchrl_brsl.reach.DataDrivenReach.from_env>` drives the
# empty copy of the task with random actions and fits the model; positions are translation
# invariant (paper Assumption 1).
torch.manual_seed(0)
noise = Zonotope(info.noise_center.double(), info.noise_generators.double())
reach = DataDrivenReach.from_env(envs.make(TASK, empty=True, seed=1, **OPTIONS), noise, steps=500,
                                 translation_invariant_dims=info.position_dims, max_generators=30,
                                 method="global")

# %%
# The layer
# ---------
#
# One action per step (no planner), completed by the task's braking steps; the last set counts
# as stopped when its velocity interval lies within its own radius plus ``stop_slack``.
def make_layer() -> BRSLSafetyLayer:
    """A layer belongs to one env (it keeps the env's safe plan): one per env."""
    return BRSLSafetyLayer(reach, Failsafe(info.braking_action, n_brk=info.n_brk), n_plan=1,
                           stop_dims=info.velocity_dims, stop_slack=0.15,
                           action_low=info.action_low, action_high=info.action_high, adjuster="facet_qp")


def rollouts(protected: bool, episodes: int = 4):
    """One rollout per layout seed, the same random proposals with and without the layer."""
    out = []
    for seed in range(episodes):
        env = envs.make(TASK, seed=10 + seed, **OPTIONS)
        if protected:
            env = TransformedEnv(env, make_layer())
        torch.manual_seed(seed)
        out.append(env.rollout(80, break_when_any_done=True))
    return out


with_layer, without = rollouts(True), rollouts(False)
hits = [int(r["next", "collision"].any()) for r in without]
print(f"episodes ending in a collision: {sum(hits)} of {len(hits)} without the layer, "
      f"{sum(int(r['next', 'collision'].any()) for r in with_layer)} of {len(with_layer)} with it")

# %%
# Paths
# -----
#
# Inflated obstacles in red, the path in blue, a red cross where the robot hit something.
# Without the layer the random walk ends at the first contact; with it the episodes run their
# 80 steps.
fig, axes = plt.subplots(2, 4, figsize=(12, 6.4))
for column, (safe, plain) in enumerate(zip(with_layer, without)):
    for row, rollout in enumerate((plain, safe)):
        ax = envs.plot_topdown(rollout, ax=axes[row, column])
        if rollout["next", "collision"].any():
            ax.plot(*rollout["next", "state"][-1, :2], "x", color="tab:red", ms=10, mew=2)
        ax.set_xlim(-1.0, 1.0)
        ax.set_ylim(-1.0, 1.0)
        ax.set_title(f"layout {column}, {'with' if row else 'without'} the layer: {len(rollout)} steps", fontsize=9)
fig.tight_layout()

# %%
# Diagnostics
# -----------
#
# Every step writes ``next["brsl"]``: whether the executed action differs from the proposal
# (``intervened``), whether nothing verified and the failsafe acted (``failsafe``), the smallest
# collision value ``v*`` of the checked sets (``v* > 1``: no set meets an obstacle), and the
# layer's time. Read the shares first: they say whether the layer is *useful*, not only safe.
brsl = torch.cat([r["next", "brsl"] for r in with_layer])
for name in ("intervened", "failsafe", "unverified_hold", "out_of_data", "invalid_input"):
    print(f"{name:>16}: {brsl[name].float().mean():.0%} of steps")
print(f"    compute_time: {1000 * brsl['compute_time'].median():.1f} ms per step (median)")

# %%
# Along one episode: the closest any checked set came to an obstacle, and the steps on which
# the layer replaced the proposal. It intervenes where ``v*`` nears 1, and only there.

episode = with_layer[0]["next", "brsl"]
steps = torch.arange(len(episode))
fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
top.plot(steps, episode["min_collision_value"].squeeze(-1).clamp(max=10), color="tab:blue")
top.axhline(1.0, color="tab:red", ls="--", lw=1, label="v* = 1: touching")
top.set_ylabel("min v* of the sets")
top.legend(loc="upper right")
for row, name in enumerate(("intervened", "failsafe", "out_of_data")):
    flags = episode[name].squeeze(-1)
    bottom.scatter(steps[flags], torch.full((int(flags.sum()),), row), marker="|", s=150)
bottom.set_yticks(range(3), ["intervened", "failsafe", "out_of_data"])
bottom.set_ylim(-0.5, 2.5)
bottom.set_xlabel("step of layout 0")
fig.tight_layout()
