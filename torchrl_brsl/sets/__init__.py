"""Batched, differentiable set representations: zonotopes and constrained zonotopes."""
from torchrl_brsl.sets.constrained_zonotope import ConstrainedZonotope
from torchrl_brsl.sets.facets import facet_normals, facet_supports, gauge_from_facets, zonotope_gauge
from torchrl_brsl.sets.obstacles import (Obstacles, inflate_box, inflate_disc, inflate_polygon, obstacle_batch,
                                         regular_polygon_generators)
from torchrl_brsl.sets.plotting import plot_polygons
from torchrl_brsl.sets.reduction import pad_generators, reduce_girard
from torchrl_brsl.sets.zonotope import Zonotope

__all__ = [
    "ConstrainedZonotope",
    "Obstacles",
    "Zonotope",
    "facet_normals",
    "facet_supports",
    "gauge_from_facets",
    "inflate_box",
    "inflate_disc",
    "inflate_polygon",
    "obstacle_batch",
    "pad_generators",
    "plot_polygons",
    "reduce_girard",
    "regular_polygon_generators",
    "zonotope_gauge",
]
