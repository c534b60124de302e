"""Batched, differentiable convex sets: Interval (box), Zonotope, Parallelotope, Ellipsoid, Strip."""

from diffsmf.sets.base import ConvexSet, stack, where
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.sets.interval import Interval
from diffsmf.sets.parallelotope import Parallelotope
from diffsmf.sets.strip import Strip
from diffsmf.sets.zonotope import Zonotope

__all__ = [
    "ConvexSet",
    "Ellipsoid",
    "Interval",
    "Parallelotope",
    "Strip",
    "Zonotope",
    "stack",
    "where",
]
