"""Remainder boxes of a filter step: the float64 rounding margin, the events of a remainder
that is not finite (``DOMAIN`` / ``DIVERGED``) and its sanitising, the user's margin, and the
box over which the ellipsoidal filters bound their remainders (their initial box).
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet
from diffsmf.filters.base import MAX_SET_RADIUS
from diffsmf.filters.events import FilterEvent
from diffsmf.sets.interval import Interval
from diffsmf.utils import eager_constant

__all__ = [
    "ROUND_REL",
    "X0_LOWER",
    "X0_UPPER",
    "add_remainder_margin",
    "checked_remainder",
    "remainder_box",
    "remainder_events",
    "rounding_margin",
    "sanitize_remainder",
    "spent_initial_box",
    "widen",
]


# Relative outward margin for float64 rounding in the affine parts (centres f(c), F T products,
# strip offsets). Rounding errors are ~1e-16 relative; 1e-12 covers accumulation with room.
ROUND_REL = 1e-12


def rounding_margin(*terms: Tensor) -> Tensor:
    """Outward margin ``ROUND_REL * (1 + sum |term|)`` broadcast over the given tensors."""
    total = 1.0
    for t in terms:
        total = total + t.abs()
    return ROUND_REL * total


def remainder_events(R: Interval) -> Tensor:
    """`FilterEvent` code ``[...]`` (int64) of a remainder box ``R [..., n]``: ``DOMAIN`` where a
    bound is NaN (the model left its domain over the set: sqrt / log / power below 0,
    asin / acos outside [-1, 1], an atan2 branch cut; the model-evaluation engine returns NaN
    bounds there and never raises), else ``DIVERGED`` where a bound is +-inf or beyond
    `MAX_SET_RADIUS` (a pole of the model, or a set grown without
    bound: squaring such a radius, as the ellipsoidal covers do, would overflow before the
    guard sees the set), else 0. Branch-free, per element."""
    return _events_ok(R)[0]


def _events_ok(R: Interval) -> tuple[Tensor, Tensor]:
    """`remainder_events` and ``ok [...]`` (True where they are 0)."""
    m = torch.maximum(R.lower.abs(), R.upper.abs())  # NaN where a bound is NaN
    nan = torch.isnan(m).any(-1)
    ok = (m <= MAX_SET_RADIUS).all(-1)  # False for NaN and inf
    ev = torch.where(nan, *_event_codes(m.device))
    return ev.masked_fill(ok, 0), ok


_CODES: dict = {}


def _event_codes(device: torch.device) -> tuple[Tensor, Tensor]:
    """The codes ``DOMAIN`` and ``DIVERGED`` as 0-dim int64 tensors (cached eagerly: constants,
    not ops per call)."""
    return eager_constant(_CODES, device, lambda: tuple(
        torch.tensor(int(e), dtype=torch.int64, device=device)
        for e in (FilterEvent.DOMAIN, FilterEvent.DIVERGED)))


def checked_remainder(R: Interval) -> tuple[Interval, Tensor]:
    """``(R', events)``: ``events [...]`` the `remainder_events` of ``R [..., n]``; ``R'`` is
    ``R`` where they are 0 and the box 0 elsewhere, so that no NaN / inf reaches the rest of
    the batch. The caller records the events (``FilterState.flag``), which marks those
    elements unbounded: no bounded guaranteed set exists for them."""
    ev, ok = _events_ok(R)
    drop = ~ok.unsqueeze(-1)
    return Interval._make(R.lower.masked_fill(drop, 0.0), R.upper.masked_fill(drop, 0.0)), ev


def sanitize_remainder(R: Interval) -> tuple[Interval, Tensor]:
    """``(R', ok)``: `checked_remainder` with ``ok = events == 0`` (``[...]`` bool: False where
    the remainder box ``R [..., n]`` is NaN, infinite or beyond
    `MAX_SET_RADIUS`); there ``R'`` is 0. The caller must mark those
    elements unbounded (``FilterState.and_bounded(ok)``, or ``FilterState.flag`` with the
    events of `checked_remainder`, which also says why). Branch-free; the bounds of the other
    elements are returned unchanged.
    """
    R2, ev = checked_remainder(R)
    return R2, ev == 0


def widen(box: Interval, margin: Tensor) -> Interval:
    """``box`` enlarged by ``margin`` on both sides."""
    return Interval(box.lower - margin, box.upper + margin)


def add_remainder_margin(R: Interval, margin: Tensor | None) -> Interval:
    """``[lo - m, hi + m]``: the guaranteed remainder box ``R`` enlarged by ``margin >= 0``.

    ``None`` returns ``R`` itself. A zero margin gives bit-identical bounds (``x - 0 == x``).
    """
    if margin is None:
        return R
    return widen(R, margin)


#: ``state.extras`` keys of the ellipsoidal filters' initial box (private: ``collect`` does not
#: stack ``_``-prefixed extras into the result).
X0_LOWER, X0_UPPER = "_x0_lower", "_x0_upper"


def remainder_box(state_set: ConvexSet, extras: dict) -> Interval:
    """Box over which an ellipsoidal filter bounds its remainders.

    The interval hull of the ellipsoid, intersected with the box ``extras[X0_LOWER]`` /
    ``extras[X0_UPPER]`` ``[B, n]``: at k = 0 the hull of the *given* initial set (the true x0
    lies in that set, and the covering ellipsoid of a box is ``sqrt(n)`` times wider per axis:
    it may reach a singularity of f that the box does not, e.g. the fermenter's ``mu`` pole),
    from k = 1 on all of R^n (`spent_initial_box`; ``max(l, -inf) = l`` exactly), so
    that every step has the same inputs and one compiled graph serves them all.
    """
    box = state_set.interval_hull()
    lo, hi = extras.get(X0_LOWER), extras.get(X0_UPPER)
    if lo is not None and hi is not None:
        box = box.intersect(Interval._make(lo, hi))
    return box


def spent_initial_box(extras: dict) -> dict:
    """The initial-box extras after the first prediction: the box of all of R^n (``[B, n]``
    of -inf / +inf), or ``{}`` when the state carries none."""
    out = {}
    for key, val in ((X0_LOWER, -torch.inf), (X0_UPPER, torch.inf)):
        if key in extras:
            out[key] = torch.full_like(extras[key], val)
    return out
