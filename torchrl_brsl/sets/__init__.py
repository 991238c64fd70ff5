"""Batched, differentiable set representations: zonotopes and constrained zonotopes."""
from torchrl_brsl.sets.constrained_zonotope import ConstrainedZonotope
from torchrl_brsl.sets.facets import facet_normals, facet_supports, gauge_from_facets, zonotope_gauge
from torchrl_brsl.sets.plotting import plot_polygons
from torchrl_brsl.sets.reduction import pad_generators, reduce_girard
from torchrl_brsl.sets.zonotope import Zonotope

__all__ = [
    "ConstrainedZonotope",
    "Zonotope",
    "facet_normals",
    "facet_supports",
    "gauge_from_facets",
    "pad_generators",
    "plot_polygons",
    "reduce_girard",
    "zonotope_gauge",
]
