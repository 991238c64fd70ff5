"""Collision checks between (constrained) zonotopes: exact closed form and a differentiable LP.

:func:`check_collision`, :func:`collision_value`, :func:`intersects` and :func:`clearance`
share one interface and choose the back end; :class:`ZonotopeCollisionChecker` caches the
facet data of fixed generators for the per-step hot path of the safety layer; :func:`pair_facets` and
:func:`pair_gauge` check sets whose generators change at every step without forming each pair's table.
"""
from torchrl_brsl.collision.api import BACKENDS, LP_TOL, check_collision, clearance, collision_value, intersects
from torchrl_brsl.collision.closed_form import (FacetTable, PairFacets, ZonotopeCollisionChecker, facet_table,
                                                is_full_dimensional, pair_facets, pair_gauge, split_pair_facets)
from torchrl_brsl.collision.lp import SOLVER_ARGS, solve_distance, solve_gauge
from torchrl_brsl.collision.result import CollisionResult, CollisionStatus

__all__ = [
    "BACKENDS",
    "LP_TOL",
    "SOLVER_ARGS",
    "CollisionResult",
    "CollisionStatus",
    "FacetTable",
    "PairFacets",
    "ZonotopeCollisionChecker",
    "check_collision",
    "clearance",
    "collision_value",
    "facet_table",
    "intersects",
    "is_full_dimensional",
    "pair_facets",
    "pair_gauge",
    "solve_distance",
    "solve_gauge",
    "split_pair_facets",
]
