"""Braking, hovering and Markov-ness of the rotor-driven multirotors (``robot="rotor"``, :mod:`envs._rotor`).

Printed per task:
  braking   control steps until the zero command has stopped the robot for good (``safety_info().is_stopped``
            at every later step of 30), from reachable states: 1-3 random commands (30 % of them full-speed
            corners) held 1-12 steps each, process noise on; worst, median and how many exceed ``n_brk``
  hover     position drift of a stopped robot over 100 steps of the zero command after 40 to settle (fixed
            layout 0: for ``hexarotor_wind`` a 2.6 m/s wind), without and with the process noise
  markov    for the same (state, action), the spread of the next velocity when the hidden part of the state
            (attitude quaternion and body rates) is replaced by that of other reachable states whose velocity
            is within 0.25 m/s; max over 8 donors per pair, noise off. States from 6,000 steps of random
            commands (half held from the step before, 5 % zero)

Usage: ``python benchmarks/bench_rotor.py [--braking 400] [--pairs 300] [--tasks quadrotor_nav hexarotor_wind]``
(steps/s: ``python benchmarks/bench_envs.py --tasks quadrotor_nav hexarotor_wind --robot rotor``).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import envs
from envs._registry import _module

torch.set_num_threads(1)


def _free_env(name: str, **options):
    """The empty variant, never truncated for leaving the data region."""
    env = _module(name).build_environment(robot="rotor", seed=0, empty=True, episode_steps=10**7, **options)
    env.reset()
    env.task.data_region_low, env.task.data_region_high = np.full(3, -1e9), np.full(3, 1e9)
    return env


def braking(name: str, trials: int) -> str:
    env, info = _free_env(name), envs.safety_info(name, robot="rotor")
    rng, counts = np.random.RandomState(0), []
    for trial in range(trials):
        if trial % 10 == 0:
            env.reset()
        for _ in range(rng.randint(1, 4)):
            command = rng.uniform(-5, 5, 3)
            if rng.rand() < 0.3:
                command = 5.0 * np.sign(command)
            for _ in range(rng.randint(1, 13)):
                env.step(command)
        stopped = np.array([bool(info.is_stopped(torch.as_tensor(env.step(np.zeros(3)).observation["state"])))
                            for _ in range(30)])
        counts.append(0 if stopped.all() else len(stopped) - int(np.argmax(~stopped[::-1])) + 1)  # 31: never
    counts = np.array(counts)
    return (f"braking: worst {counts.max()} steps, median {np.median(counts):.0f}, over n_brk = {info.n_brk}: "
            f"{int((counts > info.n_brk).sum())} of {trials}")


def hover(name: str) -> str:
    drifts = []
    for noise in (0.0, 1.0):
        env = _free_env(name, layout=0)
        env.task.noise_scale = noise
        env.physics.data.qvel[:] = 0.0
        env.physics.forward()
        for _ in range(40):
            env.step(np.zeros(3))
        start = env.physics.data.qpos[:3].copy()
        drift = max(np.abs(env.step(np.zeros(3)).observation["state"][:3] - start).max() for _ in range(100))
        drifts.append(drift * 1e3)
    return f"hover: drift over 100 steps {drifts[0]:.3f} mm without noise, {drifts[1]:.1f} mm with it"


def markov(name: str, pairs: int, donors: int = 8, near: float = 0.25) -> str:
    env = _free_env(name, layout=0)
    task, physics = env.task, env.physics
    rng, samples = np.random.RandomState(0), []
    command = rng.uniform(-5, 5, 3)
    for _ in range(6000):
        if rng.rand() < 0.5:
            command = rng.uniform(-5, 5, 3)
        if rng.rand() < 0.05:
            command = np.zeros(3)
        offset = np.array(getattr(task, "offset", np.zeros(3)))
        samples.append((physics.data.qpos.copy(), physics.data.qvel.copy(), offset, command.copy()))
        env.step(command)
    task.noise_scale = 0.0
    velocities = np.array([sample[1][:3] for sample in samples])

    def next_velocity(target, donor):
        qpos, qvel = target[0].copy(), target[1].copy()
        qpos[3:7], qvel[3:6] = donor[0][3:7], donor[1][3:6]
        physics.data.qpos[:], physics.data.qvel[:] = qpos, qvel
        if hasattr(task, "offset"):
            task.offset = target[2]
        physics.forward()
        env.step(target[3])
        return physics.data.qvel[:3].copy()

    spreads = []
    for i in rng.permutation(len(samples)):
        close = np.flatnonzero(np.abs(velocities - velocities[i]).max(1) <= near)
        close = close[close != i]
        if len(close) < donors:
            continue
        own = next_velocity(samples[i], samples[i])
        others = [next_velocity(samples[i], samples[j]) for j in rng.choice(close, donors, replace=False)]
        spreads.append(np.abs(np.array(others) - own).max())
        if len(spreads) == pairs:
            break
    spreads = np.array(spreads)
    return (f"markov: next-velocity spread over hidden attitudes, {len(spreads)} pairs: median {np.median(spreads):.2f}"
            f" m/s, 95th percentile {np.percentile(spreads, 95):.2f}, max {spreads.max():.2f} (noise width 0.04)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--braking", type=int, default=400, help="reachable states braked from")
    parser.add_argument("--pairs", type=int, default=300, help="(state, action) pairs of the Markov check")
    parser.add_argument("--tasks", nargs="+", choices=("quadrotor_nav", "hexarotor_wind"),
                        default=("quadrotor_nav", "hexarotor_wind"))
    args = parser.parse_args()
    for name in args.tasks:
        start = time.perf_counter()
        for line in (braking(name, args.braking), hover(name), markov(name, args.pairs)):
            print(f"{name:<16}{line}", flush=True)
        print(f"{name:<16}({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
