"""Conversions between the set families, registered in this one module.

Every pair ``(From, To)`` is registered with `diffsmf.convex.register_conversion`, as
``torch.distributions`` registers its KL pairs: the modules of the families do not import
each other (the import order is base, strip, interval, ellipsoid, zonotope, parallelotope);
a family lower in that order reaches a higher one through `diffsmf.convex.convert` and
`diffsmf.convex.family`. The outer bounds `as_parallelotope`, `as_zonotope` and
`as_ellipsoid` return the set itself when it is of that family.
"""

from __future__ import annotations

from diffsmf.convex import ConvexSet, register_conversion
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.sets.interval import Interval
from diffsmf.sets.parallelotope import Parallelotope
from diffsmf.sets.zonotope import Zonotope

__all__ = [
    "as_ellipsoid",
    "as_parallelotope",
    "as_zonotope",
]

register_conversion(ConvexSet, Interval)(ConvexSet.interval_hull)
register_conversion(Interval, Zonotope)(Interval.to_zonotope)
register_conversion(Interval, Parallelotope)(Interval.to_parallelotope)
register_conversion(Interval, Ellipsoid)(Interval.to_ellipsoid)
register_conversion(Zonotope, Parallelotope)(Zonotope.to_parallelotope)
register_conversion(Zonotope, Ellipsoid)(Zonotope.to_ellipsoid)
register_conversion(Parallelotope, Zonotope)(Parallelotope.to_zonotope)
register_conversion(Parallelotope, Ellipsoid)(Parallelotope.to_ellipsoid)


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
