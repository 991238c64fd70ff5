"""The facet tables of a batch of plans against their obstacles: planar split against each pair's own products.

Each control step of a plan-dependent (local) model builds the facet tables of ``Z(0, [G1, G2])``
for every reachable set of every env against every obstacle (``ZonotopeCollisionChecker`` with
``deduplicate=False, widen=True``, as the plan check does). In 2-D the checker splits the
support products into the sets' own, the obstacles' own and one cross product per pair
(:func:`~torchrl_brsl.collision.closed_form._planar_pair_facets`) and tests full-dimensionality
from the same crosses; the general path concatenates every pair's generators, takes their
singular values and the full ``[p, p]`` product. Layer-like shapes: ``T = 14`` sets of ``p1 = 30``
generators (``diffdrive_nav``'s plan and braking tail at ``max_generators = 30``), ``K = 6`` boxes.

Usage: ``python benchmarks/bench_facet_tables.py [--quick]``
"""
from __future__ import annotations

import argparse

import torch
from bench_collision import median_ms

from torchrl_brsl.collision import ZonotopeCollisionChecker, facet_table

T, K, P1 = 14, 6, 30
BATCHES = (1, 16, 64)


def shapes(batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(batch)
    sets = 0.05 * torch.randn(batch, T, 1, 2, P1, generator=gen, dtype=torch.float64)
    boxes = torch.diag_embed(0.1 + torch.rand(batch, 1, K, 2, generator=gen, dtype=torch.float64))
    return sets, boxes


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
    print(f"facet tables of B envs x {T} sets ({P1} generators) x {K} boxes, 2-D, one CPU thread, median ms")
    print(f"{'B':>4}{'pairs own products':>22}{'planar split':>16}{'ratio':>8}{'max |difference|':>20}")
    for batch in BATCHES:
        sets, boxes = shapes(batch)
        split = ZonotopeCollisionChecker(sets, boxes, deduplicate=False, widen=True).table
        difference = max(float((a - b).abs().max()) for a, b in zip(split, general(sets, boxes)))
        old = median_ms(lambda: general(sets, boxes), repeats, 2)
        new = median_ms(lambda: ZonotopeCollisionChecker(sets, boxes, deduplicate=False, widen=True), repeats, 2)
        print(f"{batch:>4}{old:>22.3f}{new:>16.3f}{old / new:>8.1f}{difference:>20.1e}")


if __name__ == "__main__":
    main()
