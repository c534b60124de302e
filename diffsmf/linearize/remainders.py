"""Guaranteed remainder bounds of a linearisation over a set.

For ``fn : R^n -> R^k``, a set ``S`` (batch ``[...]``), an expansion point ``c [..., n]`` and
any slope matrix ``J [..., k, n]`` (autograd or Stirling), every function here returns an
`Interval` ``[..., k]`` that contains

    r(x) = fn(x) - fn(c) - J (x - c)      for every x in S

(in exact arithmetic of the computed float data; evaluation of ``fn`` in float64 at a few
points is padded by a small multiple of the rounding unit). All are batched over the set's
batch dims and differentiable w.r.t. the set's fields, ``c``, ``J`` and parameters closed over
by ``fn``. ``fn`` must be batch-elementwise (see `diffsmf.linearize.jacobians`).

The bounds are named types that carry their settings, as the filters take them
(``remainder=DCVertices(max_vertices=64)``); a name is shorthand for the type with its defaults
(``remainder="dc-vertices"``). `resolve_remainder` turns either into the bound a filter calls.

* `DCVertices`: the difference-of-convex bound at the set's vertices (`diffsmf.linearize.dc`);
* `Lagrange`: the interval-Hessian quadratic form (`diffsmf.linearize.lagrange`);
* `MeanValue`: the interval-Jacobian bound, first order, cheapest;
* `Auto`: one of the three by the state dimension.
"""


from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from torch import Tensor

from diffsmf.convex import ConvexSet
from diffsmf.interval.box import Interval
from diffsmf.linearize.bound_parts import Fn, float_padding, is_affine
from diffsmf.linearize.dc import (
    MAX_TANGENTS,
    MAX_VERTICES,
    dc_remainder,
    diagonal_shift,
    hessian_eig_lower_bound,
)
from diffsmf.linearize.lagrange import (
    lagrange_remainder,
    mean_value_remainder,
    parameter_deviation,
)
from diffsmf.utils import is_int

__all__ = [
    "AUTO_LAGRANGE_MAX_N",
    "AUTO_VERTEX_MAX_N",
    "Auto",
    "DCVertices",
    "Lagrange",
    "MAX_TANGENTS",
    "MAX_VERTICES",
    "MeanValue",
    "REMAINDERS",
    "RemainderBound",
    "dc_remainder",
    "diagonal_shift",
    "float_padding",
    "hessian_eig_lower_bound",
    "is_affine",
    "lagrange_remainder",
    "mean_value_remainder",
    "parameter_deviation",
    "resolve_remainder",
]

#: ``Auto`` uses the Wang et al. 2022 vertex method up to this state dimension (2^8 = 256 box
#: corners, `MAX_VERTICES`), the vertex-free Lagrange bound up to `AUTO_LAGRANGE_MAX_N` and the
#: mean-value bound above (its cost is O(k n) per jet operation instead of the Lagrange
#: bound's O(k n^2)).
AUTO_VERTEX_MAX_N = 8
AUTO_LAGRANGE_MAX_N = 16


class RemainderBound:
    """A guaranteed remainder bound: ``bound(fn, S, c, J) -> Interval [..., k]`` containing
    ``fn(x) - fn(c) - J (x - c)`` for every ``x`` in ``S`` (``J [..., k, n]`` any slope
    matrix; ``None``: the autograd Jacobian at ``c``)."""

    #: the name a filter's ``remainder=`` takes for this bound with its default settings
    name: ClassVar[str] = ""

    def __call__(self, fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
        raise NotImplementedError

    def for_dimension(self, n: int) -> RemainderBound:
        """The bound used for ``n`` states (itself; `Auto` picks one)."""
        return self


@dataclass(frozen=True)
class DCVertices(RemainderBound):
    """Wang et al. 2022, eq. 14-18 (with the erratum): the difference-of-convex bound at the
    set's vertices (`dc_remainder`).

    Args:
        max_vertices: above this many sign combinations of the set, the corners of its
            interval hull are used (and the Lagrange bound intersected).
        max_tangents: tangent planes at every vertex, not only at the centre, while the
            vertex count is at most this (tighter lower bounds, one batched autograd call).
    """

    max_vertices: int = MAX_VERTICES
    max_tangents: int = MAX_TANGENTS
    name: ClassVar[str] = "dc-vertices"

    def __post_init__(self) -> None:
        for field in ("max_vertices", "max_tangents"):
            v = getattr(self, field)
            if not is_int(v) or v < 1:
                raise ValueError(f"{field}: must be an integer >= 1, got {v!r}")

    def __call__(self, fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
        return dc_remainder(fn, S, c, J, max_vertices=self.max_vertices,
                            max_tangents=self.max_tangents)


@dataclass(frozen=True)
class Lagrange(RemainderBound):
    """Song et al. 2017, eq. 26-28: the Lagrange form with the interval Hessian over the hull of
    the set, vertex-free (`lagrange_remainder`)."""

    name: ClassVar[str] = "lagrange"

    def __call__(self, fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
        return lagrange_remainder(fn, S, c, J)


@dataclass(frozen=True)
class MeanValue(RemainderBound):
    """The mean-value bound with the interval Jacobian over the hull of the set: first order,
    the cheapest (`mean_value_remainder`)."""

    name: ClassVar[str] = "mean-value"

    def __call__(self, fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
        return mean_value_remainder(fn, S, c, J)


@dataclass(frozen=True)
class Auto(RemainderBound):
    """`DCVertices` up to ``vertex_max_n`` states (2^n vertices are out of reach at n = 16),
    `Lagrange` up to ``lagrange_max_n``, `MeanValue` above. Every choice is guaranteed."""

    vertex_max_n: int = AUTO_VERTEX_MAX_N
    lagrange_max_n: int = AUTO_LAGRANGE_MAX_N
    name: ClassVar[str] = "auto"

    def for_dimension(self, n: int) -> RemainderBound:
        if n <= self.vertex_max_n:
            return DCVertices()
        return Lagrange() if n <= self.lagrange_max_n else MeanValue()

    def __call__(self, fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None = None) -> Interval:
        return self.for_dimension(c.shape[-1])(fn, S, c, J)


#: The remainder bounds by name, with their default settings (``remainder="..."``).
REMAINDERS: dict[str, RemainderBound] = {
    "dc-vertices": DCVertices(),
    "lagrange": Lagrange(),
    "mean-value": MeanValue(),
}
#: Other spellings of the names (the papers': Wang et al. 2022's "DC" bound).
_ALIASES = {"dc": "dc-vertices", "mean_value": "mean-value", "dc_vertices": "dc-vertices"}


def resolve_remainder(
    spec: str | RemainderBound, n: int
) -> tuple[str, RemainderBound]:
    """``(name, bound)`` of the remainder bound ``spec`` for state dimension ``n``.

    ``spec`` is a `RemainderBound` (``DCVertices(max_vertices=64)``) or its name (the type with
    its defaults): ``"dc-vertices"`` (alias ``"dc"``), ``"lagrange"``, ``"mean-value"`` or
    ``"auto"`` (`Auto`: ``"dc-vertices"`` for ``n <= AUTO_VERTEX_MAX_N`` (8), ``"lagrange"``
    for ``n <= AUTO_LAGRANGE_MAX_N`` (16), ``"mean-value"`` above). Raises ``ValueError``
    naming ``remainder`` for an unknown name or another type.
    """
    if isinstance(spec, str):
        key = _ALIASES.get(spec, spec)
        if key == "auto":
            spec = Auto()
        elif key in REMAINDERS:
            spec = REMAINDERS[key]
        else:
            raise ValueError(f"remainder: unknown method {spec!r}; expected 'auto', one of "
                             f"{sorted(REMAINDERS)} or a RemainderBound (DCVertices(...), ...)")
    if not isinstance(spec, RemainderBound):
        raise ValueError(f"remainder: expected a method name or a RemainderBound "
                         f"(DCVertices(...), Lagrange(), MeanValue(), Auto(...)), got {spec!r}")
    bound = spec.for_dimension(n)
    return bound.name, bound
