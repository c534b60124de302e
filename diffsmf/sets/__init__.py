"""Batched, differentiable convex sets: Interval (box), Zonotope, Parallelotope, Ellipsoid,
Strip, ConstrainedZonotope, ZonotopeBundle."""

from diffsmf.convex import ConvexSet, align, cat, stack, where
from diffsmf.sets import conversions  # noqa: F401  (registers the conversions between families)
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.sets.interval import Interval, interval_eval
from diffsmf.sets.parallelotope import Parallelotope
from diffsmf.sets.strip import Strip
from diffsmf.sets.zonotope import Zonotope
from diffsmf.sets.zonotope_bundle import ZonotopeBundle

__all__ = [
    "ConstrainedZonotope",
    "ConvexSet",
    "Ellipsoid",
    "Interval",
    "Parallelotope",
    "Strip",
    "Zonotope",
    "ZonotopeBundle",
    "align",
    "cat",
    "interval_eval",
    "stack",
    "where",
]
