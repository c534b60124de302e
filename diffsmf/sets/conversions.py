"""Outer bounds of a set in another set family: `as_parallelotope`, `as_zonotope`,
`as_ellipsoid` (the set itself when it is of that family).
"""

from __future__ import annotations

from diffsmf.sets.base import ConvexSet
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.sets.interval import Interval
from diffsmf.sets.parallelotope import Parallelotope
from diffsmf.sets.zonotope import Zonotope

__all__ = [
    "as_ellipsoid",
    "as_parallelotope",
    "as_zonotope",
]


def as_parallelotope(S: ConvexSet) -> ConvexSet:
    """Outer parallelotope of a set (itself, box, Chisci bound of a zonotope, or hull box)."""

    if isinstance(S, Parallelotope):
        return S
    if isinstance(S, (Interval, Zonotope)):
        return S.to_parallelotope()
    return S.interval_hull().to_parallelotope()


def as_zonotope(S: ConvexSet) -> ConvexSet:
    """Outer zonotope of a set (exact for boxes, parallelotopes, zonotopes; else hull box)."""

    if isinstance(S, Zonotope):
        return S
    if isinstance(S, (Interval, Parallelotope)):
        return S.to_zonotope()
    return S.interval_hull().to_zonotope()


def as_ellipsoid(S: ConvexSet) -> ConvexSet:
    """Outer ellipsoid of a set (itself, ``diag(n r^2)`` cover of a box, zonotope cover)."""

    if isinstance(S, Ellipsoid):
        return S
    if isinstance(S, Interval):
        return S.to_ellipsoid()
    return as_zonotope(S).to_ellipsoid()
