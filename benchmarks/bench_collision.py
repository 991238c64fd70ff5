"""Collision checks of one plan side by side: closed form (cached / uncached), CvxpyLayer LP, HiGHS.

One control step of the safety layer checks ``H`` reachable sets against ``K`` obstacles and
needs the gradient of every value w.r.t. the set centres. This script times that workload,
``H = 10`` steps x ``K = 10`` obstacles, in 2-D and 3-D on one CPU thread:

(a) closed form with a precomputed facet table (``ZonotopeCollisionChecker``): values + backward;
(b) closed form from the sets (``collision_value``, facets recomputed): values + backward;
(c) the LP of eq. (10) through ``CvxpyLayer`` (``backend="lp"``): values + backward;
(d) a loop of HiGHS solves (``torchrl_brsl.sets.lp.gauge_lp``): values only.

Reachable sets are Girard-reduced projections (2-D: 8 generators, 3-D: 12, of which ``n``
axis-aligned); obstacles are axis-aligned boxes (``n`` generators).

Usage: ``python benchmarks/bench_collision.py [--quick]``
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from torchrl_brsl.collision import ZonotopeCollisionChecker, collision_value
from torchrl_brsl.sets import Zonotope, reduce_girard
from torchrl_brsl.sets.lp import gauge_lp

H, K = 10, 10
SET_GENERATORS = {2: 8, 3: 12}


def scenario(n: int, seed: int = 0):
    """Set generators ``[H, 1, n, p1]``, obstacle generators ``[1, K, n, n]`` and centres."""
    gen = torch.Generator().manual_seed(seed)
    raw = 0.02 * torch.randn(H, 1, n, 40, generator=gen, dtype=torch.float64)
    raw = raw * torch.linspace(1.0, 3.0, H, dtype=torch.float64).view(H, 1, 1, 1)  # sets grow along the plan
    set_generators = reduce_girard(raw, SET_GENERATORS[n])
    obstacle_generators = torch.diag_embed(0.2 + 0.3 * torch.rand(1, K, n, generator=gen, dtype=torch.float64))
    path = torch.linspace(0.0, 3.0, H, dtype=torch.float64).view(H, 1, 1) * torch.ones(n, dtype=torch.float64)
    set_centers = path + 0.1 * torch.randn(H, 1, n, generator=gen, dtype=torch.float64)
    obstacle_centers = 5.0 * torch.rand(1, K, n, generator=gen, dtype=torch.float64) - 1.0
    return set_generators, obstacle_generators, set_centers, obstacle_centers


def median_ms(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def run(n: int, quick: bool) -> dict[str, float]:
    g1, g2, c1, c2 = scenario(n)
    fast_repeats, lp_repeats = (50, 2) if quick else (500, 5)
    obstacles = Zonotope(c2.expand(1, K, n).clone(), g2)

    start = time.perf_counter()
    checker = ZonotopeCollisionChecker(g1, g2)
    build_ms = 1e3 * (time.perf_counter() - start)

    def cached():
        centers = c1.clone().requires_grad_()
        value = checker.value(centers, c2)
        torch.autograd.grad(value.sum(), centers)
        return value

    def uncached():
        centers = c1.clone().requires_grad_()
        value = collision_value(Zonotope(centers, g1), obstacles)
        torch.autograd.grad(value.sum(), centers)
        return value

    def lp():
        centers = c1.clone().requires_grad_()
        value = collision_value(Zonotope(centers, g1), obstacles, backend="lp")
        torch.autograd.grad(value.sum(), centers)
        return value

    def highs():
        A = torch.cat([g1.expand(H, K, n, g1.shape[-1]), -g2.expand(H, K, n, n)], dim=-1).reshape(H * K, n, -1)
        b = (c2 - c1).reshape(H * K, n)
        return np.array([gauge_lp(a, d) for a, d in zip(A.numpy(), b.numpy())]).reshape(H, K)

    values = [cached().detach(), uncached().detach(), lp().detach(), torch.from_numpy(highs())]
    disagreement = max(float(((v - values[-1]) / values[-1]).abs().max()) for v in values[:-1])
    return {
        "cached": median_ms(cached, fast_repeats, 10),
        "uncached": median_ms(uncached, fast_repeats, 10),
        "lp": median_ms(lp, lp_repeats, 1),
        "highs": median_ms(highs, max(lp_repeats, 3), 1),
        "build": build_ms,
        "facets": checker.n_facets,
        "colliding": int((values[-1] <= 1).sum()),
        "disagreement": disagreement,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = {n: run(n, args.quick) for n in (2, 3)}

    print(f"{H} steps x {K} obstacles = {H * K} collision values, one CPU thread, median ms per call")
    print(f"{'method':<52}{'2-D':>10}{'3-D':>10}{'2-D x(a)':>10}{'3-D x(a)':>10}")
    rows = [
        ("(a) closed form, cached facets, values + backward", "cached"),
        ("(b) closed form from the sets, values + backward", "uncached"),
        ("(c) CvxpyLayer LP (eq. 10), values + backward", "lp"),
        ("(d) HiGHS loop, values only", "highs"),
    ]
    for label, key in rows:
        ms = [results[n][key] for n in (2, 3)]
        ratios = [results[n][key] / results[n]["cached"] for n in (2, 3)]
        print(f"{label:<52}{ms[0]:>10.3f}{ms[1]:>10.3f}{ratios[0]:>10.1f}{ratios[1]:>10.1f}")
    print(f"{'facet table build (once per fit x episode)':<52}{results[2]['build']:>10.3f}{results[3]['build']:>10.3f}")
    print(f"{'facet rows per pair after deduplication':<52}{results[2]['facets']:>10d}{results[3]['facets']:>10d}")
    print(f"{'colliding pairs (HiGHS)':<52}{results[2]['colliding']:>10d}{results[3]['colliding']:>10d}")
    worst = [results[n]["disagreement"] for n in (2, 3)]
    print(f"{'max relative disagreement with HiGHS':<52}{worst[0]:>10.1e}{worst[1]:>10.1e}")
    targets = {2: 1.0, 3: 3.0}
    for n in (2, 3):
        verdict = "met" if results[n]["cached"] <= targets[n] else "MISSED"
        print(f"target {n}-D (a) <= {targets[n]:.0f} ms: {verdict}")


if __name__ == "__main__":
    main()
