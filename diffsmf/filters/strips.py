"""Measurement updates by strips (Wang et al. 2022, Theorem 3): the strips of a measurement,
the angle outputs whose residual may be on the wrong branch, and the sequential intersection
of a set with the strips with its consistency flag and events.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, align, where
from diffsmf.filters.base import SetFilter
from diffsmf.filters.events import FilterEvent
from diffsmf.filters.params import stirling_steps
from diffsmf.filters.remainder_boxes import ROUND_REL, checked_remainder, rounding_margin
from diffsmf.linearize.remainders import float_padding, is_affine
from diffsmf.sets.interval import Interval
from diffsmf.sets.parallelotope import Parallelotope
from diffsmf.sets.strip import Strip
from diffsmf.systems.system import System

__all__ = [
    "angle_ambiguous",
    "linearised_strips",
    "measurement_strips",
    "sequential_strip_update",
    "simultaneous_strip_update",
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

    A degenerate strip (a slope row that is 0 or not finite, e.g. a set so large that the
    model saturates or overflows at the Stirling points, or a non-finite offset) is all of
    R^n: half-width inf, normal ``e_1``, offset 0, with the event ``DEGENERATE_STRIP``
    (`sequential_strip_update`'s rule for such rows, which also checks a zero row for
    consistency).

    Returns normal ``[B, m, n]``, offset ``[B, m]``, halfwidth ``[B, m]`` and, with
    ``events=True``, the `FilterEvent` codes ``[B]`` of the remainder of ``h`` (``DOMAIN`` /
    ``DIVERGED``: its strips then have an infinite half-width, all of R^n: the measurement
    is skipped, the guarantee holds) and of the degenerate strips.
    """
    H, offset, half, ev = _strips(h, remainder, S, c, H, y, vbox, system)
    degen, _, _, _, ev_d = _degenerate(H, offset, half)
    e0 = torch.zeros_like(H)
    e0[..., 0] = 1.0
    H = torch.where(degen.unsqueeze(-1), e0, H)
    offset = torch.where(degen, torch.zeros_like(offset), offset)
    half = torch.where(degen, torch.full_like(half, torch.inf), half)
    return (H, offset, half, ev | ev_d) if events else (H, offset, half)


def _strips(
    h: Callable[[Tensor], Tensor],
    remainder: Callable[..., Interval],
    S: ConvexSet,
    c: Tensor,
    H: Tensor,
    y: Tensor,
    vbox: Interval,
    system: System | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`measurement_strips` before the degenerate rows are replaced: normal ``[B, m, n]``
    (``H`` itself), offset, halfwidth ``[B, m]`` and the remainder's events ``[B]``."""
    hc = h(c)
    E, ev = checked_remainder(remainder(h, S, c, H))
    Hc = (H @ c.unsqueeze(-1)).squeeze(-1)
    offset, half = _offset_half(hc, E.center, E.radius, Hc, y, vbox, system)
    ok = ev == 0
    if system is not None and system.angle_outputs:
        ok = ok.unsqueeze(-1) & ~angle_ambiguous(system, S, c, H, E, vbox)
    # unbounded remainder of h over S: the strip is all of R^n (half-width inf, skipped by
    # sequential_strip_update) -- guaranteed, the measurement just cannot shrink the set
    ok = ok.unsqueeze(-1) if ok.dim() < half.dim() else ok
    half = torch.where(ok, half, torch.full_like(half, torch.inf))
    return H, offset, half, ev


def _offset_half(
    hc: Tensor,
    e_mid: Tensor | None,
    e_rad: Tensor,
    Hc: Tensor,
    y: Tensor,
    vbox: Interval,
    system: System | None,
) -> tuple[Tensor, Tensor]:
    """Offset ``y - v_c - h(c) + H c - e_mid`` and half-width ``eps_v + e_rad`` ``[B, m]``
    of eq. 23-29 (the innovation wrapped for angle outputs; ``Hc = H c [B, m]``), the
    half-width padded by the float64 rounding margin of the terms; ``e_mid = None`` stands
    for a remainder centred at 0 (the same values as ``e_mid = 0``, two calls fewer)."""
    nu = y - hc if system is None else system.innovation(y, hc)
    offset = nu - vbox.center + Hc
    half = vbox.radius + e_rad
    if e_mid is None:
        return offset, half + rounding_margin(y, hc, Hc, half)
    return offset - e_mid, half + rounding_margin(y, hc, Hc, e_mid, half)


def _affine_strips(
    h: Callable[[Tensor], Tensor],
    S: ConvexSet,
    c: Tensor,
    H: Tensor,
    y: Tensor,
    vbox: Interval,
    system: System,
    hc: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """`measurement_strips` of an affine ``h`` with its exact slopes ``H [B, m, n]`` (its
    autograd Jacobian): the remainder ``h(x) - h(c) - H (x - c)`` is 0 but for the float
    evaluation of ``h`` and of its slopes, enclosed by ``+-64 eps (|h(c)| + 2 |H| max(|lo|,
    |hi|))`` over the hull ``[lo, hi]`` of ``S`` (the padding with which
    `diffsmf.linearize.dc_remainder` bounds an affine function about its Stirling slopes,
    ``|J_exact| + |J|``; it cannot be unbounded, so no remainder events) -> normal, offset,
    halfwidth ``[B, m]`` (``hc``: ``h(c)`` where the caller has it)."""
    hc = h(c) if hc is None else hc
    with torch.no_grad():  # a padding: no gradient (no detach call)
        mag = _hull_magnitude(S)
        scale = hc.abs() + 2.0 * (H.abs() * mag.unsqueeze(-2)).sum(-1)
        tol = float_padding(scale)  # [B, m], the remainders' padding of an affine function
    Hc = (H * c.unsqueeze(-2)).sum(-1)
    offset, half = _offset_half(hc, None, tol, Hc, y, vbox, system)
    if system.angle_outputs:
        E = Interval._make(-tol, tol)
        amb = angle_ambiguous(system, S, c, H, E, vbox)
        half = torch.where(amb, torch.full_like(half, torch.inf), half)
    return H, offset, half


def _hull_magnitude(S: ConvexSet) -> Tensor:
    """``max(|lo|, |hi|) [..., n]`` over the interval hull ``[lo, hi]`` of ``S``; for a
    `Parallelotope`, whose hull is ``c +- r``, as ``|c| + r`` (the same floats: rounding is
    monotone and odd, so ``fl(|c| + r)`` is the larger of ``|fl(c - r)|`` and ``|fl(c + r)|``),
    without the hull's bounds."""
    if isinstance(S, Parallelotope):
        return S.center.abs() + S.T.abs().sum(-1)
    hull = S.interval_hull()
    return torch.maximum(hull.lower.abs(), hull.upper.abs())


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


def _degenerate(
    normal: Tensor, offset: Tensor, half: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The one rule for degenerate strips ``|normal . x - offset| <= half`` (``normal
    [..., m, n]``, ``offset``, ``half [..., m]``): a zero or non-finite normal, a non-finite
    offset or a NaN half-width (the linearised output does not depend on the state there, or
    overflowed).

    Returns ``degen [..., m]`` (such a strip is skipped: all of R^n, never a lost guarantee),
    ``skip [..., m]`` (``degen`` or an infinite half-width), ``zero_ok [..., m]`` (False only
    for a zero normal with a finite offset and half-width that no state meets, ``|offset| >
    half`` beyond the rounding margin: inconsistent data), the rounding margin ``atol [...,
    m]`` of the consistency checks and the events ``[...]`` (``DEGENERATE_STRIP`` where some
    strip is degenerate).
    """
    zero = (normal == 0).all(-1)
    # finite normal and offset (x - x is 0 exactly for a finite x, NaN otherwise: two calls
    # where isfinite takes four), half-width not NaN
    fin = ((normal - normal).sum(-1) + (offset - offset) == 0) & (half == half)
    degen = zero | ~fin
    skip = degen | (half == torch.inf)
    # the consistency margin (only used where the strip is not skipped, and for zero normals;
    # in comparisons only, so no gradient): rounding_margin(offset, half), |offset| shared
    oa = offset.abs()
    atol = ROUND_REL * (1.0 + oa + half.abs())
    # a zero normal: the strip is R^n (|d| <= w) or empty -- checked, never intersected
    zero_ok = ~(zero & fin & (oa > half + atol))
    ev = degen.any(-1) * int(FilterEvent.DEGENERATE_STRIP)
    return degen, skip, zero_ok, atol, ev


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
    degen, skip, ok, atol, ev = _degenerate(normal, offset, half)
    ok = ok.all(-1)
    # skipped strips become the finite placeholder |1 . x| <= 1 (intersected, then dropped)
    a = normal.masked_fill(degen.unsqueeze(-1), 1.0)  # torch.where with a scalar: 2 calls
    d = offset.masked_fill(skip, 0.0)
    w = half.masked_fill(skip, 1.0)
    cur = S
    rows = zip(a.unbind(-2), d.unbind(-1), w.unbind(-1), skip.unbind(-1), atol.unbind(-1))
    m = normal.shape[-2]
    for ai, di, wi, sk, tol in rows:
        strip = Strip._make(ai, di, wi)
        ok = ok & (sk | cur.intersects_strip(strip, atol=tol))
        nxt = intersect(cur, strip)
        if m == 1:  # one strip: its intersection where it is kept and consistent, else S
            return where(ok & ~sk, nxt, _like(S, nxt)), ok, ev
        a_, b_ = align([nxt, cur])
        cur = where(sk, b_, a_)
    return where(ok, cur, _like(S, cur)), ok, ev


def simultaneous_strip_update(
    S: ConvexSet,
    normal: Tensor,
    offset: Tensor,
    half: Tensor,
    gain: Callable[[ConvexSet, Tensor, Tensor], Tensor],
) -> tuple[ConvexSet, Tensor, Tensor]:
    """Intersect the zonotope ``S`` with all m strips at once, with one gain matrix
    (`Zonotope.intersect_strips`; Combastel 2015, Wang, Puig & Cembrano 2018).

    ``gain(S, A, w) -> L [B, n, m]`` from the strips' normals ``A [B, m, n]`` and half-widths
    ``w [B, m]``; a strip to skip (degenerate or of infinite half-width, the rules of
    `sequential_strip_update`) enters the gain as a zero row of ``A`` with half-width 1, and
    its column of ``L`` is zeroed, so it takes no part. Consistency: every kept strip meets
    ``S`` (checked against ``S``, not the partly intersected set). Returns the updated set,
    ``consistent [B]`` and the `FilterEvent` codes ``[B]``; an inconsistent element keeps
    ``S``. Branch-free.
    """
    degen, skip, ok, atol, ev = _degenerate(normal, offset, half)
    ok = ok.all(-1)
    a = normal.masked_fill(degen.unsqueeze(-1), 1.0)
    d = offset.masked_fill(skip, 0.0)
    w = half.masked_fill(skip, 1.0)
    for ai, di, wi, sk, tol in zip(a.unbind(-2), d.unbind(-1), w.unbind(-1), skip.unbind(-1),
                                   atol.unbind(-1)):
        ok = ok & (sk | S.intersects_strip(Strip._make(ai, di, wi), atol=tol))
    L = gain(S, a.masked_fill(skip.unsqueeze(-1), 0.0), w)
    L = L.masked_fill(skip.unsqueeze(-2), 0.0)
    new = S.intersect_strips(a, d, w, L)
    return where(ok, new, _like(S, new)), ok, ev


def stirling_strip_update(
    filt: SetFilter,
    S: ConvexSet,
    region: ConvexSet,
    y: Tensor,
    intersect: Callable[[ConvexSet, object], ConvexSet],
    gain: Callable[[ConvexSet, Tensor, Tensor], Tensor] | None = None,
) -> tuple[ConvexSet, Tensor, Tensor]:
    """Wang et al. 2022, Theorem 3 update shared by HSNSMF, MSZM and CDSMF: Stirling slopes of ``h``
    at the centre (eq. 13), DC remainder of ``h`` over ``region`` folded into the strips
    (eq. 23-29), strips intersected one by one with ``intersect`` (or, given ``gain``, all at
    once: `simultaneous_strip_update`) -> (set, consistent ``[B]``,
    `FilterEvent` codes ``[B]``: ``DOMAIN`` / ``DIVERGED`` of the remainder of ``h``, whose
    update is then skipped, and ``DEGENERATE_STRIP``; none of them loses the guarantee).

    An affine ``h`` (`is_affine`) takes its exact slopes instead (the Stirling
    slopes of an affine function, up to rounding) and a remainder that is the float padding
    alone (`_affine_strips`): the same strips to rounding, without the Stirling points and
    the remainder's machinery.
    """
    a, d, w, ev_h = linearised_strips(filt, S, region, y)
    new, ok, ev = _intersect_all(S, a, d, w, intersect, gain)
    return (new, ok, ev) if ev_h is None else (new, ok, ev | ev_h)


def linearised_strips(
    filt: SetFilter, S: ConvexSet, region: ConvexSet, y: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """The measurement strips of `stirling_strip_update` (Wang et al. 2022, Theorem 3): normal
    ``[B, m, n]``, offset and half-width ``[B, m]`` (``|normal_i . x - offset_i| <= half_i`` for
    every state consistent with ``y``), and the events ``[B]`` of the remainder of ``h`` over
    ``region``. Stirling slopes at ``S``'s centre; an affine ``h`` takes its exact slopes and a
    remainder that is the float padding alone (no events: None)."""
    from diffsmf.linearize import stirling_jacobian
    from diffsmf.linearize.jacobians import value_and_jacobian

    c = S.center
    h, system = filt.system.h, filt.system
    vbox = _measurement_box(filt)
    if is_affine(h, region):
        hc, H = value_and_jacobian(h, c)  # h(c) and the exact slopes from one call of h
        a, d, w = _affine_strips(h, region, c, H, y, vbox, system, hc=hc)
        return a, d, w, None
    H = stirling_jacobian(h, c, stirling_steps(filt, c, region.interval_hull().radius))
    return _strips(h, filt.remainder_fn, region, c, H, y, vbox, system)


def _intersect_all(
    S: ConvexSet, a: Tensor, d: Tensor, w: Tensor,
    intersect: Callable[[ConvexSet, object], ConvexSet],
    gain: Callable[[ConvexSet, Tensor, Tensor], Tensor] | None,
) -> tuple[ConvexSet, Tensor, Tensor]:
    if gain is None:
        return sequential_strip_update(S, a, d, w, intersect)
    return simultaneous_strip_update(S, a, d, w, gain)


def _measurement_box(filt: SetFilter) -> Interval | _NoiseBox:
    """The measurement-noise box V ``[m]`` of the strips: `SetFilter.measurement_noise_box`,
    read as its centre and half-width without forming the Interval where the filter keeps
    that method (as `diffsmf.filters.prediction.noise_generators` does for W), else the
    filter's own override."""
    if type(filt).measurement_noise_box is SetFilter.measurement_noise_box:
        return _NoiseBox(filt.measurement_noise_center, filt.measurement_half_widths)
    return filt.measurement_noise_box()


class _NoiseBox:
    """The measurement-noise box ``center +- radius [m]`` as `Interval` reads it (``center``,
    ``radius``, ``lower``, ``upper``), kept as its centre and half-width: the strips use
    those, so they are not recomputed from the bounds (the same values for a centre 0)."""

    def __init__(self, center: Tensor, radius: Tensor) -> None:
        self.center, self.radius = center, radius

    @property
    def lower(self) -> Tensor:
        return self.center - self.radius

    @property
    def upper(self) -> Tensor:
        return self.center + self.radius


def _like(S: ConvexSet, ref: ConvexSet) -> ConvexSet:
    """``S`` padded (zonotope generators) to the field shapes of ``ref``."""
    return align([S, ref])[0]
