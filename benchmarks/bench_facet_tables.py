"""The facet tables of a batch of plans against their obstacles: split by owner against each pair's own products.

Each control step of a plan-dependent (local) model builds the facet tables of ``Z(0, [G1, G2])``
for every reachable set of every env against every obstacle (``ZonotopeCollisionChecker`` with
``deduplicate=False, widen=True``, as the plan check does). In 2-D and 3-D the checker splits the
support products into the sets' own, the obstacles' own and the per-pair crosses
(:data:`~torchrl_brsl.collision.closed_form._PAIR_FACETS`) and tests full-dimensionality
from the same products; the general path concatenates every pair's generators, takes their
singular values and every normal's product with every generator. Layer-like shapes, sets of
``p1 = 30`` generators (``max_generators = 30``) against boxes: 2-D ``T = 14`` sets x ``K = 6``
(``diffdrive_nav``'s plan and braking tail), 3-D ``T = 21`` x ``K = 8`` (``quadrotor_nav``'s).

Usage: ``python benchmarks/bench_facet_tables.py [--quick]``
"""
from __future__ import annotations

import argparse

import torch
from bench_collision import median_ms

from torchrl_brsl.collision import ZonotopeCollisionChecker, facet_table
from torchrl_brsl.collision.closed_form import facet_clearances, gauge_values

P1 = 30
SHAPES = {2: (14, 6), 3: (21, 8)}  # sets T and boxes K per dimension
BATCHES = (1, 16, 64)


def shapes(n: int, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(batch)
    steps, boxes = SHAPES[n]
    sets = 0.05 * torch.randn(batch, steps, 1, n, P1, generator=gen, dtype=torch.float64)
    return sets, torch.diag_embed(0.1 + torch.rand(batch, 1, boxes, n, generator=gen, dtype=torch.float64))


def general(sets: torch.Tensor, boxes: torch.Tensor):
    """The pairs' own products (the path 3-D sets and flat pairs take)."""
    batch = torch.broadcast_shapes(sets.shape[:-2], boxes.shape[:-2])
    return facet_table(ZonotopeCollisionChecker._widened(sets, boxes, batch, True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    repeats = 10 if args.quick else 50
    print(f"facet tables of B envs x T sets ({P1} generators) x K boxes, one CPU thread, median ms")
    print(f"{'n':>2}{'T x K':>8}{'B':>4}{'pairs own products':>22}{'split by owner':>16}{'ratio':>8}"
          f"{'max |difference|':>20}")
    for n, batch in ((n, batch) for n in SHAPES for batch in BATCHES):
        sets, boxes = shapes(n, batch)
        split = ZonotopeCollisionChecker(sets, boxes, deduplicate=False, widen=True).table
        offsets = torch.randn(16, *split.weights.shape[:-2], n, dtype=torch.float64)
        difference = max(float((f(offsets, split) - f(offsets, general(sets, boxes))).abs().max())
                         for f in (gauge_values, facet_clearances))
        old = median_ms(lambda: general(sets, boxes), repeats, 2)
        new = median_ms(lambda: ZonotopeCollisionChecker(sets, boxes, deduplicate=False, widen=True), repeats, 2)
        print(f"{n:>2}{'%d x %d' % SHAPES[n]:>8}{batch:>4}{old:>22.3f}{new:>16.3f}{old / new:>8.1f}{difference:>20.1e}")


if __name__ == "__main__":
    main()
