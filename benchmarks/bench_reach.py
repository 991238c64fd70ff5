"""Reachable sets of one plan: the paper's literal per-step form, the one-fit global form and the local default.

Algorithm 2 recomputes a pseudo-inverse of the data matrix at every plan step; the global
model (``DataDrivenReach.fit(..., method="global")``) fits once and propagates the plan
through precomputed matrices. The local model (the default) picks a regression-tree leaf per
step and set, so its generators depend on the plan. This script times one plan of
``T = 20`` actions from a measured state, on one CPU thread, for the example black-box
systems (500 offline transitions each):

(a) global model, full sets (centres + precomputed generators, as a ``Zonotope``);
(b) global model, centres only;
(c) literal per-step pseudo-inverse form (``DataDrivenReach.reach_literal``, the global model's reference);
(d) local model (the default), full sets, eager;
(e) local model, its steps compiled (``compile_steps``).

Then where (e)'s time goes: its time at plan lengths 2, 10 and 20 fitted as ``per call + per step * T``,
beside one call of a compiled function that adds up ``k`` small tensors (inductor, C++ wrapper; ``k`` = 1
and 40, about the count of the model's tensors the plan's loop takes): the compiler's own floor per call,
which every compiled plan pays before its first step.

Usage: ``python benchmarks/bench_reach.py [--quick]``
"""
from __future__ import annotations

import argparse

import torch
from bench_collision import median_ms

from torchrl_brsl._compiling import inductor_kwargs
from torchrl_brsl._malloc import malloc_name
from torchrl_brsl.reach import DataDrivenReach, DoubleIntegrator, Unicycle
from torchrl_brsl.sets import Zonotope

N_PLAN = 20
TARGET_MS = 0.3
LENGTHS = (2, 10, 20)
FLOOR_INPUTS = (1, 40)


def run(system, quick: bool) -> dict[str, float]:
    gen = torch.Generator().manual_seed(0)
    x, xp, u = system.offline_data(500, gen)
    dims = system.translation_invariant_dims
    reach = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=dims, method="global",
                                max_generators=24)
    exact = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=dims, method="global")
    local = DataDrivenReach.fit(x, xp, u, system.noise, translation_invariant_dims=dims, max_generators=24)
    x0 = system.sample_states(1, gen)[0]
    plan = system.sample_actions(N_PLAN, generator=gen)
    initial = Zonotope.from_point(x0)
    fitted, literal = exact.reach(initial, plan), exact.reach_literal(initial, plan)
    disagreement = max(float((fitted.center - literal.center).abs().max()),
                       float((fitted.generators - literal.generators).abs().max()))
    repeats = 50 if quick else 1000
    eager = median_ms(lambda: local.reach(initial, plan), max(repeats // 5, 10), 3)
    local.compile_steps()  # the same model, its steps compiled from here on
    return {
        "sets": median_ms(lambda: reach.reach(initial, plan), repeats, 5),
        "centers": median_ms(lambda: reach.reach_centers(x0, plan), repeats, 5),
        "literal": median_ms(lambda: exact.reach_literal(initial, plan), max(repeats // 20, 5), 1),
        "local": eager,
        "compiled": median_ms(lambda: local.reach(initial, plan), max(repeats // 5, 10), 3),
        "disagreement": disagreement,
        "lengths": [median_ms(lambda t=t: local.reach(initial, plan[:t]), max(repeats // 5, 10), 3) for t in LENGTHS],
    }


def call_floor(inputs: int, repeats: int) -> float:
    """Median ms of one call of a compiled function that adds up ``inputs`` tensors of 4 doubles (inductor, C++ wrapper,
    the plan loop's options): what a compiled call costs before any work of its own."""
    tensors = [torch.zeros(4, dtype=torch.float64) for _ in range(inputs)]

    def total(*xs):
        out = xs[0] + 1
        for x in xs[1:]:
            out = out + x
        return out

    compiled = torch.compile(total, **inductor_kwargs({}, cpp_wrapper=True))
    return median_ms(lambda: compiled(*tensors), repeats, 20)


def per_step(times: list[float]) -> tuple[float, float]:
    """Least-squares ``(per call, per step)`` ms of ``times`` at the plan lengths :data:`LENGTHS`."""
    fit = torch.linalg.lstsq(torch.tensor([[1.0, t] for t in LENGTHS], dtype=torch.float64),
                             torch.tensor(times, dtype=torch.float64).unsqueeze(-1)).solution.squeeze(-1)
    return float(fit[0]), float(fit[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    systems = {"double integrator (n=4)": DoubleIntegrator(), "unicycle (n=4)": Unicycle()}
    results = {name: run(system, args.quick) for name, system in systems.items()}
    names = list(results)
    print(f"reachable sets of one plan (T = {N_PLAN}), one CPU thread, {malloc_name()}, median ms per call")
    print(f"{'method':<44}" + "".join(f"{n:>26}" for n in names))
    for label, key in (("(a) global model, full sets", "sets"), ("(b) global model, centres only", "centers"),
                       ("(c) literal per-step pinv (paper)", "literal"), ("(d) local model (default), eager", "local"),
                       ("(e) local model, compiled steps", "compiled")):
        print(f"{label:<44}" + "".join(f"{results[n][key]:>26.4f}" for n in names))
    print(f"{'speed-up (c)/(a)':<44}" + "".join(f"{results[n]['literal'] / results[n]['sets']:>26.1f}" for n in names))
    print(f"{'max |fitted - literal| (no reduction)':<44}" + "".join(f"{results[n]['disagreement']:>26.1e}"
                                                                     for n in names))
    print(f"{'local (e) / global (a)':<44}" + "".join(f"{results[n]['compiled'] / results[n]['sets']:>26.1f}"
                                                     for n in names))
    print(f"{'(e) at T = ' + ' / '.join(map(str, LENGTHS)):<44}" + "".join(
        f"{' / '.join(f'{ms:.3f}' for ms in results[n]['lengths']):>26}" for n in names))
    fits = {n: per_step(results[n]["lengths"]) for n in names}
    print(f"{'(e) fitted: per call + per step':<44}" + "".join(
        f"{f'{fits[n][0]:.3f} + {fits[n][1]:.4f} T':>26}" for n in names))
    floors = [call_floor(k, 200 if args.quick else 2000) for k in FLOOR_INPUTS]
    print("a compiled call that only adds up k tensors (the compiler's floor per call): " + ", ".join(
        f"k = {k}: {ms:.3f} ms" for k, ms in zip(FLOOR_INPUTS, floors)))
    for n in names:
        fastest = min(results[n]["local"], results[n]["compiled"])
        print(f"target one plan's sets <= {TARGET_MS} ms ({n}): global {_verdict(results[n]['sets'])}, "
              f"local {_verdict(fastest)} ({fastest:.2f} ms)")


def _verdict(ms: float) -> str:
    return "met" if ms <= TARGET_MS else "MISSED"


if __name__ == "__main__":
    main()
