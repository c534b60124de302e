"""Measurement updates by strips (Wang et al. 2022, Theorem 3): the strips of a measurement,
the angle outputs whose residual may be on the wrong branch, and the sequential intersection
of a set with the strips with its consistency flag and events.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.filters.base import SetFilter
from diffsmf.filters.events import FilterEvent
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.remainders import checked_remainder, rounding_margin
from diffsmf.sets.base import ConvexSet, align, where
from diffsmf.sets.interval import Interval
from diffsmf.sets.strip import Strip
from diffsmf.systems.system import System

__all__ = [
    "angle_ambiguous",
    "measurement_strips",
    "sequential_strip_update",
    "stirling_strip_update",
]


def measurement_strips(
    h: Callable[[Tensor], Tensor],
    remainder: Callable[..., Interval],
    S: ConvexSet,
    c: Tensor,
    H: Tensor,
    y: Tensor,
    vbox: Interval,
    system: System | None = None,
    events: bool = False,
) -> tuple[Tensor, ...]:
    """Strips of Wang et al. 2022, Theorem 3 (eq. 23-29), one per measurement component.

    ``{x : |H_i x - (y_i - v_c,i - h_i(c) + H_i c - e_mid,i)| <= eps_v,i + e_rad,i}`` with
    ``[e_min, e_max]`` the remainder of ``h`` about ``c`` over ``S``. Written un-normalised
    (eq. 24-25 divide both sides by the half-width, the same set).

    Angle outputs (``system.angle_outputs``): ``y_i - h_i(c)`` is wrapped into ``[-pi, pi)``
    (`System.innovation`), i.e. the strip is built for ``y'_i = h_i(c) + wrap(y_i -
    h_i(c))``, the branch that the predicted measurement picks. That is the true branch
    whenever ``|h_i(x) - h_i(c) + v_i| < pi`` for every x in S and v in V, which holds when
    ``|H_i| |x - c| + |e|_max + |v|_max < pi`` over the hull (`angle_ambiguous`);
    where it does not, the strip is all of R^n (half-width inf: guaranteed, the measurement
    just cannot shrink the set).

    Returns normal ``[B, m, n]``, offset ``[B, m]``, halfwidth ``[B, m]`` and, with
    ``events=True``, the `FilterEvent` codes ``[B]`` of the remainder of ``h`` (``DOMAIN`` /
    ``DIVERGED``: its strips then have an infinite half-width, all of R^n: the measurement
    is skipped, the guarantee holds).
    """
    hc = h(c)
    E, ev = checked_remainder(remainder(h, S, c, H))
    ok = ev == 0
    Hc = (H @ c.unsqueeze(-1)).squeeze(-1)
    nu = y - hc if system is None else system.innovation(y, hc)
    offset = nu - vbox.center + Hc - E.center
    half = vbox.radius + E.radius
    half = half + rounding_margin(y, hc, Hc, E.center, half)
    if system is not None and system.angle_outputs:
        ok = ok.unsqueeze(-1) & ~angle_ambiguous(system, S, c, H, E, vbox)
    # unbounded remainder of h over S: the strip is all of R^n (half-width inf, skipped by
    # sequential_strip_update) -- guaranteed, the measurement just cannot shrink the set
    ok = ok.unsqueeze(-1) if ok.dim() < half.dim() else ok
    # a slope row that is 0 or not finite (a set so large that the model saturates or
    # overflows at the Stirling points) gives no strip: all of R^n, with a placeholder normal
    flat = ~(H.abs().sum(-1) > 0) | ~torch.isfinite(H).all(-1)  # [B, m]
    ev = ev | torch.where(flat.any(-1), int(FilterEvent.DEGENERATE_STRIP), 0)
    ok = ok & ~flat
    e0 = torch.zeros_like(H)
    e0[..., 0] = 1.0
    H = torch.where(flat.unsqueeze(-1), e0, H)
    offset = torch.where(flat, torch.zeros_like(offset), offset)
    half = torch.where(ok, half, torch.full_like(half, torch.inf))
    return (H, offset, half, ev) if events else (H, offset, half)


def angle_ambiguous(
    system: System, S: ConvexSet, c: Tensor, H: Tensor, E: Interval, vbox: Interval
) -> Tensor:
    """``[B, m]`` True for an angle output whose wrapped residual may be on the wrong branch:
    where ``|H_i| |x - c|_max + max|e_i| + max|v_i| >= pi`` over the hull of ``S`` (``e`` the
    remainder box of ``h`` about ``c``, ``v`` in ``vbox``); False for the other outputs. The
    filters then drop that measurement's strip (or update) for the element, which keeps the
    set guaranteed."""
    hull = S.interval_hull()
    dmax = torch.maximum((hull.lower - c).abs(), (hull.upper - c).abs())
    spread = (H.abs() * dmax.unsqueeze(-2)).sum(-1)
    spread = spread + torch.maximum(E.lower.abs(), E.upper.abs())
    spread = spread + torch.maximum(vbox.lower.abs(), vbox.upper.abs())
    mask = system.angle_mask.to(device=spread.device)
    return mask & ~(spread < math.pi)  # NaN spread: ambiguous


def sequential_strip_update(
    S: ConvexSet,
    normal: Tensor,
    offset: Tensor,
    half: Tensor,
    intersect: Callable[[ConvexSet, object], ConvexSet],
) -> tuple[ConvexSet, Tensor, Tensor]:
    """Intersect ``S`` with the m strips one by one (Wang et al. 2022, sec. 3.3).

    Returns the updated set, ``consistent [B]`` and the `FilterEvent` codes ``[B]``. Where some
    strip misses the current set (empty intersection: a fault, Wang et al. 2022, eq. 31-32) the
    input set is returned unchanged for that batch element and ``consistent`` is False. A
    strip of infinite half-width (an unbounded remainder of ``h``) is all of R^n and is
    skipped for that element. A degenerate strip (a zero or non-finite normal, a non-finite
    offset or a NaN half-width: the linearised output does not depend on the state there, or
    overflowed) is skipped too, with the event ``DEGENERATE_STRIP``; a zero normal with finite
    offset is still checked for consistency (``|offset| <= halfwidth``). Skipping a strip
    never loses the guarantee (the set is only not shrunk by it). Branch-free.
    """
    ok = torch.ones(S.batch_shape, dtype=torch.bool, device=S.device)
    ev = torch.zeros(S.batch_shape, dtype=torch.int64, device=S.device)
    cur = S
    for i in range(normal.shape[-2]):
        a, w, d = normal[..., i, :], half[..., i], offset[..., i]
        zero = (a == 0).all(-1)
        bad = ~torch.isfinite(a).all(-1) | ~torch.isfinite(d) | torch.isnan(w)
        degen = zero | bad
        inf = torch.isinf(w) & ~bad
        skip = inf | degen
        ev = ev | torch.where(degen & ~inf, int(FilterEvent.DEGENERATE_STRIP), 0)
        atol = rounding_margin(torch.where(bad, 0.0, d), torch.where(skip, 0.0, w)).detach()
        # a zero normal: the strip is R^n (|d| <= w) or empty -- checked, never intersected
        zero_ok = torch.where(zero & ~bad & ~inf, d.abs() <= w + atol, True)
        a = torch.where(degen.unsqueeze(-1), torch.ones_like(a), a)
        w = torch.where(skip, torch.ones_like(w), w)
        d = torch.where(skip, torch.zeros_like(d), d)
        strip = Strip(a, d, w)
        ok = ok & zero_ok & (skip | cur.intersects_strip(strip, atol=atol))
        nxt = intersect(cur, strip)
        a_, b_ = align([nxt, cur])
        cur = where(skip, b_, a_)
    return where(ok, cur, _like(S, cur)), ok, ev


def stirling_strip_update(
    filt: SetFilter,
    S: ConvexSet,
    region: ConvexSet,
    y: Tensor,
    intersect: Callable[[ConvexSet, object], ConvexSet],
) -> tuple[ConvexSet, Tensor, Tensor]:
    """Wang et al. 2022, Theorem 3 update shared by HSNSMF, MSZM and CDSMF: Stirling slopes of ``h``
    at the centre (eq. 13), DC remainder of ``h`` over ``region`` folded into the strips
    (eq. 23-29), strips intersected one by one with ``intersect`` -> (set, consistent ``[B]``,
    `FilterEvent` codes ``[B]``: ``DOMAIN`` / ``DIVERGED`` of the remainder of ``h``, whose
    update is then skipped, and ``DEGENERATE_STRIP``; none of them loses the guarantee).
    """
    from diffsmf.linearize import stirling_jacobian

    c = S.center
    H = stirling_jacobian(filt.system.h, c, stirling_steps(filt, c, region.interval_hull().radius))
    a, d, w, ev_h = measurement_strips(
        filt.system.h, filt.remainder_fn, region, c, H, y, filt.measurement_noise_box(),
        filt.system, events=True,
    )
    new, ok, ev = sequential_strip_update(S, a, d, w, intersect)
    return new, ok, ev | ev_h


def _like(S: ConvexSet, ref: ConvexSet) -> ConvexSet:
    """``S`` padded (zonotope generators) to the field shapes of ``ref``."""
    return align([S, ref])[0]
