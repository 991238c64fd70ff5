"""Does measuring more of a rotor multirotor's state let the local model claim its plans?

The rotor quadrotor's task state is ``(x, y, z, vx, vy, vz)``; its attitude and body rates are hidden,
and for the same (state, action) they move the next velocity by ~0.8 m/s (``bench_rotor.py``), so the
local model (``DataDrivenReach.fit(method="local")``) claims none of its plans. Here the task's state is
extended with what a real flight controller measures or remembers, and the same protocol as
``tests/reach/test_task_soundness.py`` runs on each variant: random offline steps in the empty task,
40 plans of ``n_plan + n_brk = 17`` steps (every other one a single action then the zero command) from
reachable states, their true trajectories sampled in MuJoCo.

Variants (appended after the velocity; they have no process noise of their own):
  base       the task's state
  tilt       + the body z axis' world x and y components (the thrust direction; heading is held at 0)
  rates      + tilt and the body roll and pitch rates
  command    + the command the controller held during the step (its only memory)
  both       + command and tilt

Printed per variant: plans claimed (of 40), sampled states outside a claimed plan's set, plans still
covered after 1, 2 and 3 steps, the median set radius after one step: position (m), velocity (m/s)
and the added dims, and ``L δ``: the share of the velocity leaves' error bound that is the Lipschitz
term (the residual's Lipschitz constant times the data's covering radius; median over leaves).

Usage: ``python benchmarks/bench_rotor_state.py [--steps 2000] [--variants base tilt rates command both]``
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import envs
from envs import quadrotor_nav
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data, env_trajectories
from torchrl_brsl.sets import Zonotope

EXTRA = {"base": 0, "tilt": 2, "rates": 4, "command": 3, "both": 5}
HORIZON = 17


def measured_task(variant: str) -> type:
    """The rotor quadrotor task with its state extended by ``variant``'s quantities."""
    base = quadrotor_nav.RotorQuadrotorNav
    extra = EXTRA[variant]

    class Measured(base):
        noise_center = np.zeros(6 + extra)
        noise_generators = np.concatenate([base.noise_generators, np.zeros((extra, base.noise_generators.shape[1]))])

        def state(self, physics):
            data = physics.data
            w, x, y, z = data.qpos[3:7]
            tilt = [2 * (x * z + w * y), 2 * (y * z - w * x)]  # body z axis, world x and y
            parts = [data.qpos[:3], data.qvel[:3]]
            if variant in ("command", "both"):
                parts.append(np.asarray(self._controller.command))
            if variant in ("tilt", "rates", "both"):
                parts.append(tilt)
            if variant == "rates":
                parts.append(data.qvel[3:5])
            return np.concatenate(parts)

    return Measured


def measure(variant: str, steps: int) -> str:
    quadrotor_nav.ROBOT_TASKS["rotor"] = task = measured_task(variant)
    try:
        info = task.safety_info()
        torch.manual_seed(0)
        data = collect_offline_data(envs.make("quadrotor_nav", empty=True, seed=11, robot="rotor"), steps)
        reach = DataDrivenReach.from_data(data, Zonotope(info.noise_center.double(), info.noise_generators.double()),
                                          translation_invariant_dims=info.position_dims, max_generators=30)
        env = envs.make("quadrotor_nav", empty=True, seed=12, episode_steps=10_000, robot="rotor")
        starts, plans, visited = env_trajectories(env, 40, HORIZON, info.action_low, info.action_high,
                                                  info.braking_action)
    finally:
        quadrotor_nav.ROBOT_TASKS["rotor"] = quadrotor_nav.RotorQuadrotorNav
    initial = Zonotope.from_point(starts)
    sets, claimed = reach.reach_covered(initial, plans)
    outside = int((~sets.contains(visited))[claimed].sum())
    covered = [int(reach.reach_covered(initial, plans[:, :h])[1].sum()) for h in (1, 2, 3)]
    radius = sets.generators[:, 0].abs().sum(-1).median(0).values  # [n], after one step
    added = " ".join(f"{float(r):.2f}" for r in radius[6:]) or "-"
    errors = reach.cell_errors[3:6]  # the velocity outputs' leaves: how much of their error is the Lipschitz term L δ
    real = torch.isfinite(errors) & (errors > 0)
    share = (reach.cell_lipschitz[3:6] * reach.cell_delta[3:6] / errors)[real].median()
    return (f"{variant:<9}{int(claimed.sum()):>5}/40{outside:>9}{str(covered):>14}"
            f"{float(radius[:3].max()):>10.2f}{float(radius[3:6].max()):>10.2f}{float(share):>8.2f}   {added}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="random offline steps")
    parser.add_argument("--variants", nargs="+", choices=tuple(EXTRA), default=list(EXTRA))
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"rotor quadrotor, {args.steps} offline steps, 40 plans of {HORIZON} steps; radii after one step (median)")
    print(f"{'variant':<9}{'claimed':>8}{'outside':>9}{'covered 1-3':>14}{'position':>10}{'velocity':>10}{'L δ':>8}"
          "   added dims")
    for variant in args.variants:
        start = time.perf_counter()
        row = measure(variant, args.steps)
        print(f"{row}   ({time.perf_counter() - start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
