"""Per-trajectory numerical events of a filter run, and what an unbounded set means.

A filter never raises mid-run for a numerical reason (a set that leaves the model's domain,
meets a branch cut, grows without bound or overflows): the batch element where it happens is
flagged, with a reason, and the other trajectories carry on unchanged.

- ``FilterResult.events`` ``[B, T+1]`` (``int64``): the bitwise OR of the `FilterEvent` codes
  met by trajectory ``b`` at or before step ``k`` (sticky, as ``bounded`` is; 0 = none).
  ``describe_events(res.events)`` turns them into text, one line per trajectory and event,
  with the first step where it occurred.
- An element whose guaranteed set is all of R^n (``bounded`` False: `FilterEvent.DIVERGED`,
  `FilterEvent.DOMAIN` or `FilterEvent.NON_FINITE`) is reported as such everywhere: its
  ``lower`` / ``upper`` are -inf / +inf, its ``volume`` inf, ``res.sets.contains(x)`` is True,
  and no measurement is flagged inconsistent against it (see `mark_unbounded`).
- `FilterEvent.DEGENERATE_STRIP` keeps the guarantee: the measurement strip that could not be
  formed is skipped (the set is not shrunk by it).
"""

from __future__ import annotations

import enum
import sys
from typing import Any

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, family
from diffsmf.utils import numerical_events, tracing

__all__ = [
    "LOSES_BOUND",
    "MAX_SET_RADIUS",
    "FilterEvent",
    "all_small",
    "describe_events",
    "event_text",
    "finite_fields",
    "hull_radius",
    "is_marked",
    "mark_unbounded",
]


class FilterEvent(enum.IntFlag):
    """Codes of ``FilterResult.events`` (bit flags: several may be set for one element).

    Attributes:
        NONE: nothing happened.
        DIVERGED: a remainder bound or the set became infinite or larger than
            ``MAX_SET_RADIUS`` (the set grew without bound, or reached a pole of the model):
            no bounded guaranteed set exists from this step on (``bounded`` False).
        DOMAIN: the set left the domain of the model (sqrt, log or a real power of a set
            reaching below 0, asin / acos outside [-1, 1], atan2 meeting its branch cut, or
            the box on which a fitted PWL model's error is certified): the model's enclosure
            is NaN there, so no bound holds (``bounded`` False).
        DEGENERATE_STRIP: a measurement strip had a zero or non-finite normal (the
            linearised output does not depend on the state there, or overflowed): it was
            skipped, so the measurement did not shrink the set (the guarantee holds).
        NON_FINITE: the set itself became NaN / inf (an overflow in a set operation):
            ``bounded`` False from this step on.
        MEASUREMENT_SKIPPED: the measurement function could not be bounded over the set (it
            left its domain, met an atan2 branch cut, or its remainder was unbounded): that
            update was skipped, so the measurement did not shrink the set (the guarantee
            holds).
    """

    NONE = 0
    DIVERGED = 1
    DOMAIN = 2
    DEGENERATE_STRIP = 4
    NON_FINITE = 8
    MEASUREMENT_SKIPPED = 16


#: The events after which no bounded guaranteed set exists (``bounded`` turns False).
LOSES_BOUND = int(FilterEvent.DIVERGED | FilterEvent.DOMAIN | FilterEvent.NON_FINITE)

_TEXT = {
    FilterEvent.DIVERGED: "the set became unbounded (a remainder or the set grew without "
    "bound, e.g. at a pole of the model); bounds are -inf/+inf from here",
    FilterEvent.DOMAIN: "the set left the model's domain (sqrt/log/power below 0, asin/acos "
    "outside [-1, 1], an atan2 branch cut, or a PWL model's certified domain); bounds are "
    "-inf/+inf from here",
    FilterEvent.DEGENERATE_STRIP: "a measurement strip was degenerate (zero or non-finite "
    "normal) and was skipped; the bounds stay guaranteed",
    FilterEvent.NON_FINITE: "the set became NaN/inf (overflow); bounds are -inf/+inf from here",
    FilterEvent.MEASUREMENT_SKIPPED: "the measurement function could not be bounded over the "
    "set (domain exit, atan2 branch cut or unbounded remainder of h); the update was skipped, "
    "the bounds stay guaranteed",
}


def event_text(code: int) -> str:
    """The reasons of one event code (an int, bits of `FilterEvent`) as text; ``"none"`` for 0."""
    code = int(code)
    parts = [_TEXT[e] for e in _TEXT if code & int(e)]
    return "; ".join(parts) if parts else "none"


def describe_events(events: Tensor) -> list[str]:
    """One readable line per trajectory and event: ``"trajectory b, step k: <reason>"``,
    with ``k`` the first step where that event occurred.

    Args:
        events: ``[B, T+1]`` (``FilterResult.events``) or ``[T+1]`` (one trajectory).

    Returns:
        The lines, ordered by trajectory then step; empty when nothing happened.
    """
    ev = torch.as_tensor(events).detach().cpu()
    if ev.dim() == 1:
        ev = ev.unsqueeze(0)
    lines: list[tuple[int, int, str]] = []
    for e in _TEXT:
        hit = (ev & int(e)) != 0  # [B, T+1]
        for b in hit.any(-1).nonzero().flatten().tolist():
            k = int(hit[b].nonzero()[0])
            lines.append((b, k, f"trajectory {b}, step {k}: {e.name.lower()}: {_TEXT[e]}"))
    return [text for _, _, text in sorted(lines)]


# ------------------------------------------------------------------ unbounded sets
class _Unbounded:
    """Mixin of `mark_unbounded`: the elements where ``bounded`` is False are all of R^n."""

    bounded: Tensor

    def _plain(self) -> Any:
        return self._base._from_tensors(self._tensors())  # type: ignore[attr-defined]

    def _rebuild(self, tensors: Any) -> Any:  # derived sets are plain sets of the base type
        return self._base._from_tensors(tensors)  # type: ignore[attr-defined]

    def contains(self, x: Tensor, *args: Any, **kw: Any) -> Tensor:
        return super().contains(x, *args, **kw) | ~self.bounded  # type: ignore[misc]

    def support(self, d: Tensor, *args: Any, **kw: Any) -> Tensor:
        h = super().support(d, *args, **kw)  # type: ignore[misc]
        return torch.where(self.bounded, h, torch.full_like(h, torch.inf))

    def interval_hull(self, *args: Any, **kw: Any) -> Any:
        from diffsmf.sets.interval import Interval

        hull = self._plain().interval_hull(*args, **kw)
        b = self.bounded.unsqueeze(-1)
        inf = torch.full_like(hull.lower, torch.inf)
        return Interval._make(torch.where(b, hull.lower, -inf), torch.where(b, hull.upper, inf))

    def volume(self, *args: Any, **kw: Any) -> Tensor:
        v = self._plain().volume(*args, **kw)
        return torch.where(self.bounded, v, torch.full_like(v, torch.inf))

    def __getitem__(self, idx: Any) -> Any:
        b = self.bounded[idx if isinstance(idx, tuple) else (idx,)]
        return mark_unbounded(self._plain()[idx], b)

    def expand(self, *batch_shape: Any) -> Any:
        if len(batch_shape) == 1 and isinstance(batch_shape[0], (tuple, list, torch.Size)):
            batch_shape = tuple(batch_shape[0])
        return mark_unbounded(self._plain().expand(*batch_shape), self.bounded.expand(batch_shape))

    def to(self, *args: Any, **kwargs: Any) -> Any:
        S = self._plain().to(*args, **kwargs)
        return mark_unbounded(S, self.bounded.to(S.device))

    def detach(self) -> Any:
        return mark_unbounded(self._plain().detach(), self.bounded)

    def __repr__(self) -> str:
        n_unb = int((~self.bounded).sum())
        return f"{super().__repr__()[:-1]}, unbounded elements={n_unb})"


_TYPES: dict[type, type] = {}


def _unbounded_type(base: type) -> type:
    """The subclass of the set type ``base`` with the `_Unbounded` behaviour (one per type,
    registered in this module under ``Unbounded<Base>`` so that results pickle)."""
    cls = _TYPES.get(base)
    if cls is None:
        name = f"Unbounded{base.__name__}"
        cls = type(name, (_Unbounded, base), {"_base": base, "__module__": __name__})
        cls.__qualname__ = name
        setattr(sys.modules[__name__], name, cls)
        _TYPES[base] = cls
    return cls


def mark_unbounded(S: Any, bounded: Tensor | None) -> Any:
    """``S`` where ``bounded`` is True, all of R^n where it is False.

    Returns an instance of a subclass of ``type(S)`` (``isinstance`` checks and every field
    are unchanged) whose ``contains`` is True, ``support`` and ``volume`` are inf and
    ``interval_hull`` is -inf / +inf at the unbounded elements; indexing, ``expand``, ``to`` and
    ``detach`` keep the mask. Other operations (``linear_map``, ``minkowski_sum``, ...) act
    on the stored fields and return plain sets (the stored fields of an unbounded element
    are a finite placeholder, not an estimate). ``bounded`` None or all True: ``S`` itself.

    Args:
        S: a set with batch shape ``[*B]``.
        bounded: ``[*B]`` bool.
    """
    if bounded is None:
        return S
    base = getattr(type(S), "_base", type(S))
    if type(S) is not base:
        S = S._plain()
    if not torch.is_tensor(bounded) or bool(bounded.all()):
        return S
    obj = _unbounded_type(base)._from_tensors(S._tensors())
    object.__setattr__(obj, "bounded", bounded.to(torch.bool))
    return obj


def is_marked(S: Any) -> bool:
    """Whether ``S`` is a set returned by `mark_unbounded` with some unbounded element."""
    return isinstance(S, _Unbounded)


# ------------------------------------------------------------------ the boundedness guard

#: A set whose interval hull has a half-width above this (or any non-finite field) is
#: *unbounded*: flagged ``bounded=False`` from then on, its bounds reported as +-inf.
MAX_SET_RADIUS = 1e100


def finite_fields(S: ConvexSet) -> Tensor:
    """``[*B]`` bool: every field of ``S`` finite (``t * 0`` is NaN exactly at a NaN or an
    infinite entry, and a sum of zeros cannot overflow)."""
    nb = len(S.batch_shape)
    z = None
    for t in S._tensors():
        zt = (t * 0).sum(tuple(range(nb, t.dim()))) if t.dim() > nb else t * 0
        z = zt if z is None else z + zt
    return z == 0


def hull_radius(S: ConvexSet) -> Tensor:
    """Half-widths ``[*B, n]`` of the interval hull of ``S`` (for a zonotope or a
    parallelotope ``sum_j |G_ij|`` directly, else ``S.interval_hull().radius``)."""
    if type(S) is family("Zonotope"):
        return S.generators.abs().sum(-1)
    if type(S) is family("Parallelotope"):
        return S.T.abs().sum(-1)
    if tracing():
        return S.interval_hull().radius
    with numerical_events():  # the hull of a non-finite set: NaN, flagged, never raised
        return S.interval_hull().radius


def all_small(r: Tensor, c: Tensor) -> bool:
    """Whether every half-width ``r`` is at most `MAX_SET_RADIUS` and every centre ``c`` is
    finite (one host read: ``r + 0 c`` is NaN at a NaN / inf centre, the max propagates NaN);
    read without the gradient, so no warning while autograd records."""
    with torch.no_grad():
        return float(torch.add(r, c, alpha=0).max()) <= MAX_SET_RADIUS
