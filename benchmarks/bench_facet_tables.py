"""The collision check of a batch of plans against their obstacles: three ways to the same values.

Each control step of a plan-dependent (local) model checks every reachable set of every env
against every obstacle with sets it has never seen, so the facet data of ``Z(0, [G1, G2])`` is
built anew for every pair and used once. Timed here, each as build plus one evaluation at the
pairs' centre offsets:

- *pairs' own products*: each pair's generators concatenated, singular values, every normal's
  product with every generator, a ``[K, n]`` table per pair (the general path);
- *split table*: :class:`~torchrl_brsl.collision.ZonotopeCollisionChecker`'s table, its supports
  split into the sets' own products, the obstacles' own and the per-pair crosses;
- *pair gauge* (what the layer runs): :func:`~torchrl_brsl.collision.pair_facets` and
  :func:`~torchrl_brsl.collision.pair_gauge`, the normals kept per owner and never formed per pair,
  the 3-D mixed rows' supports from the triple product.

Layer-like shapes, sets of ``p1`` generators (30 in 2-D, 12 in 3-D, the layer's reduced width) against
boxes: 2-D ``T = 14`` sets x ``K = 6`` (``diffdrive_nav``'s plan and braking tail), 3-D ``T = 21`` x
``K = 8`` (``quadrotor_nav``'s). The last column is the largest difference of the three's values.

Usage: ``python benchmarks/bench_facet_tables.py [--quick]``
"""
from __future__ import annotations

import argparse

import torch
from bench_collision import median_ms

from torchrl_brsl.collision import ZonotopeCollisionChecker, facet_table, pair_facets, pair_gauge
from torchrl_brsl.collision.closed_form import gauge_values, widened_pairs

SHAPES = {2: (14, 6, 30), 3: (21, 8, 12)}  # sets T, boxes K and set generators p1 per dimension
BATCHES = (1, 16, 64)


def shapes(n: int, batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(batch)
    steps, boxes, p1 = SHAPES[n]
    sets = 0.05 * torch.randn(batch, steps, 1, n, p1, generator=gen, dtype=torch.float64)
    boxes = torch.diag_embed(0.1 + torch.rand(batch, 1, boxes, n, generator=gen, dtype=torch.float64))
    return sets, boxes, 0.3 * torch.randn(batch, steps, boxes.shape[2], n, generator=gen, dtype=torch.float64)


def own_products(sets: torch.Tensor, boxes: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    batch = torch.broadcast_shapes(sets.shape[:-2], boxes.shape[:-2])
    return gauge_values(offsets, facet_table(widened_pairs(sets, boxes, batch, True)))


def split_table(sets: torch.Tensor, boxes: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    return gauge_values(offsets, ZonotopeCollisionChecker(sets, boxes, deduplicate=False, widen=True).table)


def gauge(sets: torch.Tensor, boxes: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    return pair_gauge(offsets, pair_facets(sets, boxes, widen=True))[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    repeats = 10 if args.quick else 50
    print("check of B envs x T sets x K boxes (build + one evaluation), one CPU thread, median ms")
    print(f"{'n':>2}{'T x K':>8}{'B':>4}{'own products':>14}{'split table':>13}{'pair gauge':>12}"
          f"{'own / gauge':>13}{'table / gauge':>15}{'max |diff|':>12}")
    for n, batch in ((n, batch) for n in SHAPES for batch in BATCHES):
        args_ = shapes(n, batch)
        values = [f(*args_) for f in (own_products, split_table, gauge)]
        difference = max(float((v - values[0]).abs().max()) for v in values[1:])
        times = [median_ms(lambda f=f: f(*args_), repeats, 2) for f in (own_products, split_table, gauge)]
        print(f"{n:>2}{'%d x %d' % SHAPES[n][:2]:>8}{batch:>4}{times[0]:>14.2f}{times[1]:>13.2f}{times[2]:>12.2f}"
              f"{times[0] / times[2]:>13.1f}{times[1] / times[2]:>15.1f}{difference:>12.1e}", flush=True)


if __name__ == "__main__":
    main()
