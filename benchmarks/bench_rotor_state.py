"""Does measuring more of a rotor multirotor's state let the local model claim its plans?

The rotor quadrotor's task state is ``(x, y, z, vx, vy, vz)``; its attitude and body rates are hidden,
and for the same (state, action) they move the next velocity by ~0.8 m/s (``bench_rotor.py``), so the
local model (``DataDrivenReach.fit(method="local")``) claims none of its plans. Here the task's state is
extended with what a real flight controller measures or remembers, and the same protocol as
``tests/reach/test_task_soundness.py`` runs on each variant: random offline steps in the empty task,
40 plans of ``n_plan + n_brk = 17`` steps (every other one a single action then the zero command) from
reachable states, their true trajectories sampled in MuJoCo.

Variants (appended after the velocity; they have no process noise of their own, except ``v - r``, which carries
the velocity's):
  base       the task's state
  tilt       + the body z axis' world x and y components (the thrust direction; heading is held at 0)
  rates      + tilt and the body roll and pitch rates
  command    + the command the controller held during the step (its only memory)
  both       + command and tilt
  shaped     the controller no longer tracks the command itself but a reference shaped from it, as ArduPilot's
             guided mode shapes velocity targets: the reference velocity ``r`` and acceleration ``a`` follow
             ``a_t = clip(SHAPE_GAIN (u - r), ±SHAPE_ACCELERATION)``, ``ȧ = SHAPE_LAG (a_t - a)``, ``ṙ = a`` at
             every 5 ms tick, and the velocity loop tracks ``r`` with ``a`` fed forward; ``+ r`` and ``a``
             (controller memory, 6 dims). The reference moves smoothly enough for the attitude to follow it,
             so the hidden attitude matters far less, at the price of a 12-dim regressor
  error      as ``shaped``, with the tracking error ``v - r`` reported instead of ``r`` (the same information,
             without two nearly equal inputs)
  jerk       the velocity loop runs at the command's rate, as PX4's smooth velocity setpoints: when a command comes
             it sets the target acceleration ``clip(k (u - v), ±8)`` (``k = 2`` /s), toward which the acceleration
             demand ``a`` ramps at 10 m/s³ at every 5 ms tick (:data:`JERK`); the attitude loops track ``a``. ``+ a``
             (the only controller memory, 3 dims)
  jerk-fast  as ``jerk`` with twice the gain and the jerk (4 /s, 20 m/s³)
  jerk-tilt  as ``jerk``, + the tilt as well (the attitude that lags the demand)
  gentle     the task's state, the velocity loop's acceleration limited to 3 m/s² per axis (PX4's default horizontal
             acceleration) and the tilt to 35° (:data:`GENTLE`): less attitude to hide; it brakes within 13 steps

Printed per variant: the median tracking error ``|v - r|`` after a step of the offline data (``-`` where the
velocity loop tracks the command), plans claimed (of 40), sampled states outside a claimed plan's set, plans still
covered after 1, 2, 3, 8 and 12 steps, the median position radius of the claimed plans' last sets (m), the median set
radius after one step: position (m), velocity (m/s) and the added dims, and ``L δ``: the share of the velocity
leaves' error bound that is the Lipschitz term (the residual's Lipschitz constant times the data's covering
radius; median over leaves).

``--method global`` fits the global model instead (``DataDrivenReach.fit(method="global")``).

Usage: ``python benchmarks/bench_rotor_state.py [--steps 2000] [--variants base tilt rates command both shaped error
jerk jerk-fast jerk-tilt gentle] [--method local]``
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

import envs
from envs import _rotor, quadrotor_nav
from torchrl_brsl.reach import DataDrivenReach, collect_offline_data, env_trajectories
from torchrl_brsl.sets import Zonotope

EXTRA = {"base": 0, "tilt": 2, "rates": 4, "command": 3, "both": 5, "shaped": 6, "error": 6, "jerk": 3,
         "jerk-fast": 3, "jerk-tilt": 5, "gentle": 0}
SHAPED = ("shaped", "error")
JERK = {"jerk": (2.0, 10.0), "jerk-fast": (4.0, 20.0), "jerk-tilt": (2.0, 10.0)}  # velocity gain (/s), jerk (m/s^3)
GENTLE = (3.0, math.radians(35.0))  # the velocity loop's acceleration limit (m/s^2) and tilt limit (rad)
HORIZON = 17
SHAPE_GAIN, SHAPE_ACCELERATION, SHAPE_LAG = 4.0, 4.0, 5.0  # /s, m/s^2, /s: from 5 m/s to rest in about 1.5 s


class ShapedController(_rotor.CascadeController):
    """The cascade controller tracking a shaped reference (variants ``shaped`` and ``error``): ``reference`` and
    ``acceleration`` are its memory, started at the measured velocity and zero."""

    def reset(self) -> None:
        super().reset()
        self.reference, self.acceleration = None, [0.0, 0.0, 0.0]

    def update(self) -> None:
        if self.reference is None:
            self.reference = self._data.qvel[:3].tolist()
        dt, held = _rotor.TIMESTEP, self.command
        targets = [max(-SHAPE_ACCELERATION, min(SHAPE_ACCELERATION, SHAPE_GAIN * (u - r)))
                   for u, r in zip(held, self.reference)]
        self.acceleration = [a + SHAPE_LAG * (t - a) * dt for a, t in zip(self.acceleration, targets)]
        self.reference = [r + a * dt for r, a in zip(self.reference, self.acceleration)]
        # the velocity loop's demand k (c - v) becomes a + k (r - v)
        self.command = [r + a / k for r, a, k in zip(self.reference, self.acceleration, _rotor.VELOCITY_GAIN)]
        try:
            super().update()
        finally:
            self.command = held


class JerkController(_rotor.CascadeController):
    """The cascade controller behind a jerk-limited acceleration demand (variants ``jerk`` and ``jerk-fast``):
    ``target`` is set when a command comes, ``demand`` (its memory, started at zero) ramps toward it."""

    def __init__(self, airframe, data, gain: float, jerk: float):
        self.gain, self.jerk = gain, jerk
        super().__init__(airframe, data)

    def reset(self) -> None:
        super().reset()
        self.target, self.demand = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]

    def set_command(self, command: list[float]) -> None:
        limit = _rotor.MAX_ACCELERATION
        self.command = command
        self.target = [max(-limit, min(limit, self.gain * (u - v))) for u, v in zip(command, self._data.qvel[:3])]

    def update(self) -> None:
        step, held = self.jerk * _rotor.TIMESTEP, self.command
        self.demand = [a + max(-step, min(step, t - a)) for a, t in zip(self.demand, self.target)]
        # the velocity loop's demand k (c - v) becomes the ramped demand
        self.command = [v + a / k for v, a, k in zip(self._data.qvel[:3], self.demand, _rotor.VELOCITY_GAIN)]
        try:
            super().update()
        finally:
            self.command = held


class GentleController(_rotor.CascadeController):
    """The cascade controller with the acceleration and tilt limits of :data:`GENTLE` (variant ``gentle``)."""

    def __init__(self, airframe, data):
        super().__init__(airframe, data)
        self._tan_tilt, self._cos_tilt = math.tan(GENTLE[1]), math.cos(GENTLE[1])

    def update(self) -> None:
        limit, _rotor.MAX_ACCELERATION = _rotor.MAX_ACCELERATION, GENTLE[0]  # read by the velocity loop
        try:
            super().update()
        finally:
            _rotor.MAX_ACCELERATION = limit


def measured_task(variant: str) -> type:
    """The rotor quadrotor task with its state extended by ``variant``'s quantities."""
    base = quadrotor_nav.RotorQuadrotorNav
    extra = EXTRA[variant]

    generators = np.concatenate([base.noise_generators, np.zeros((extra, base.noise_generators.shape[1]))])
    if variant == "error":  # v - r carries the velocity's noise: the same generators
        generators[6:9] = base.noise_generators[3:6]

    class Measured(base):
        noise_center = np.zeros(6 + extra)
        noise_generators = generators

        def _bind(self, physics) -> None:
            super()._bind(physics)
            if variant in SHAPED:
                self._controller = ShapedController(self.airframe, self._data)
            if variant in JERK:
                self._controller = JerkController(self.airframe, self._data, *JERK[variant])
            if variant == "gentle":
                self._controller = GentleController(self.airframe, self._data)

        def _apply_action(self, action, physics) -> None:
            if variant in JERK:
                self._controller.set_command(action.tolist())
            else:
                super()._apply_action(action, physics)

        def state(self, physics):
            data = physics.data
            w, x, y, z = data.qpos[3:7]
            tilt = [2 * (x * z + w * y), 2 * (y * z - w * x)]  # body z axis, world x and y
            if variant in JERK:
                parts = [data.qpos[:3], data.qvel[:3], self._controller.demand]
                return np.concatenate(parts + ([tilt] if variant == "jerk-tilt" else []))
            if variant in SHAPED:
                reference = np.asarray(self._controller.reference or data.qvel[:3])
                memory = reference if variant == "shaped" else data.qvel[:3] - reference
                return np.concatenate([data.qpos[:3], data.qvel[:3], memory, self._controller.acceleration])
            parts = [data.qpos[:3], data.qvel[:3]]
            if variant in ("command", "both"):
                parts.append(np.asarray(self._controller.command))
            if variant in ("tilt", "rates", "both"):
                parts.append(tilt)
            if variant == "rates":
                parts.append(data.qvel[3:5])
            return np.concatenate(parts)

    return Measured


def measure(variant: str, steps: int, method: str) -> str:
    quadrotor_nav.ROBOT_TASKS["rotor"] = task = measured_task(variant)
    try:
        info = task.safety_info()
        torch.manual_seed(0)
        data = collect_offline_data(envs.make("quadrotor_nav", empty=True, seed=11, robot="rotor"), steps)
        reach = DataDrivenReach.from_data(data, Zonotope(info.noise_center.double(), info.noise_generators.double()),
                                          translation_invariant_dims=info.position_dims, max_generators=30,
                                          method=method)
        env = envs.make("quadrotor_nav", empty=True, seed=12, episode_steps=10_000, robot="rotor")
        starts, plans, visited = env_trajectories(env, 40, HORIZON, info.action_low, info.action_high,
                                                  info.braking_action)
    finally:
        quadrotor_nav.ROBOT_TASKS["rotor"] = quadrotor_nav.RotorQuadrotorNav
    initial = Zonotope.from_point(starts)
    sets, claimed = reach.reach_covered(initial, plans)
    outside = int((~sets.contains(visited))[claimed].sum())
    covered = [int(reach.reach_covered(initial, plans[:, :h])[1].sum()) for h in (1, 2, 3, 8, 12)]
    radius = sets.generators[:, 0].abs().sum(-1).median(0).values  # [n], after one step
    added = " ".join(f"{float(r):.2f}" for r in radius[6:]) or "-"
    final = sets.generators[:, -1, :3].abs().sum(-1)[claimed]  # position radius of the claimed plans' last sets
    final = f"{float(final.median()):.2f}" if len(final) else "-"
    tracking = "-"
    if variant in SHAPED:
        error = data["x_plus"][:, 6:9] if variant == "error" else data["x_plus"][:, 3:6] - data["x_plus"][:, 6:9]
        tracking = f"{float(error.norm(dim=-1).median()):.3f}"
    share = "-"
    if method == "local":  # the velocity outputs' leaves: how much of their error is the Lipschitz term L δ
        errors = reach.cell_errors[3:6]
        real = torch.isfinite(errors) & (errors > 0)
        share = f"{float((reach.cell_lipschitz[3:6] * reach.cell_delta[3:6] / errors)[real].median()):.2f}"
    return (f"{variant:<10}{tracking:>9}{int(claimed.sum()):>5}/40{outside:>9}{str(covered):>24}{final:>7}"
            f"{float(radius[:3].max()):>10.2f}{float(radius[3:6].max()):>10.2f}{share:>8}   {added}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="random offline steps")
    parser.add_argument("--variants", nargs="+", choices=tuple(EXTRA), default=list(EXTRA))
    parser.add_argument("--method", choices=("local", "global"), default="local", help="the reachability model")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"rotor quadrotor, {args.steps} offline steps, {args.method} model, 40 plans of {HORIZON} steps; "
          "radii after one step (median)")
    print(f"{'variant':<10}{'tracking':>9}{'claimed':>8}{'outside':>9}{'covered 1, 2, 3, 8, 12':>24}{'final':>7}"
          f"{'position':>10}{'velocity':>10}{'L δ':>8}   added dims")
    for variant in args.variants:
        start = time.perf_counter()
        row = measure(variant, args.steps, args.method)
        print(f"{row}   ({time.perf_counter() - start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
