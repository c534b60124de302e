"""Pieces shared by the linearising set-membership filters (HSNSMF, MSZM, CDSMF, ESMF).

Nothing here is geometry or linearisation (those live in `diffsmf.sets` and
`diffsmf.linearize`); these helpers only wire a `System` to them:
the step function at the nominal parameter, the guaranteed remainder box of a step (model
remainder + parameter mismatch + float64 rounding margin), the measurement strips of Wang et al.
2022 Theorem 3, conversions of the initial set, and the sequential strip update with its
consistency flag.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.filters.base import MAX_SET_RADIUS, FilterState, SetFilter, state_batch
from diffsmf.filters.events import FilterEvent
from diffsmf.sets.base import ConvexSet, align, check_nonempty, where
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System

# Relative outward margin for float64 rounding in the affine parts (centres f(c), F T products,
# strip offsets). Rounding errors are ~1e-16 relative; 1e-12 covers accumulation with room.
ROUND_REL = 1e-12


def step_function(system: System, u: Tensor | None) -> Callable[[Tensor], Tensor]:
    """``x [..., n] -> f(x, u, theta_nom) [..., n]`` (the nominal model of one step).

    ``u [B, p]`` is closed over; `diffsmf.linearize` puts extra point dims (stencils,
    vertices) in *leading* positions, so ``u`` broadcasts against them.
    """
    from diffsmf.interval.engine import StepModel

    return StepModel(system.f, u, system.theta_nominal)


def remainder_events(R: Interval) -> Tensor:
    """`FilterEvent` code ``[...]`` (int64) of a remainder box ``R [..., n]``: ``DOMAIN`` where a
    bound is NaN (the model left its domain over the set: sqrt / log / power below 0,
    asin / acos outside [-1, 1], an atan2 branch cut; the model-evaluation engine returns NaN
    bounds there and never raises), else ``DIVERGED`` where a bound is +-inf or beyond
    `MAX_SET_RADIUS` (a pole of the model, or a set grown without
    bound: squaring such a radius, as the ellipsoidal covers do, would overflow before the
    guard sees the set), else 0. Branch-free, per element."""
    nan = (torch.isnan(R.lower) | torch.isnan(R.upper)).any(-1)
    big = MAX_SET_RADIUS
    ok = ((R.lower.abs() <= big) & (R.upper.abs() <= big)).all(-1)  # False for NaN and inf
    ev = torch.where(ok, 0, int(FilterEvent.DIVERGED))
    return torch.where(nan, int(FilterEvent.DOMAIN), ev)


def checked_remainder(R: Interval) -> tuple[Interval, Tensor]:
    """``(R', events)``: ``events [...]`` the `remainder_events` of ``R [..., n]``; ``R'`` is
    ``R`` where they are 0 and the box 0 elsewhere, so that no NaN / inf reaches the rest of
    the batch. The caller records the events (``FilterState.flag``), which marks those
    elements unbounded: no bounded guaranteed set exists for them."""
    ev = remainder_events(R)
    keep = (ev == 0).unsqueeze(-1)
    z = torch.zeros_like(R.lower)
    return Interval._make(torch.where(keep, R.lower, z), torch.where(keep, R.upper, z)), ev


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


def rounding_margin(*terms: Tensor) -> Tensor:
    """Outward margin ``ROUND_REL * (1 + sum |term|)`` broadcast over the given tensors."""
    total = 1.0
    for t in terms:
        total = total + t.abs()
    return ROUND_REL * total


def noise_generators(filt: SetFilter) -> tuple[Tensor, Tensor, Tensor | None]:
    """Process noise for the zonotope-type predictions (HSNSMF, MSZM) -> ``(center [n],
    box half-widths [n], generators [n, q] or None)``.

    A box W (the built-ins) is ``(c, r, None)`` as before (bit for bit); a zonotope or
    parallelotope W keeps its own generators (``(c, 0, G)``: exact Minkowski sum); an
    ellipsoid, which a zonotope cannot hold exactly, enters by its interval hull.
    """
    from diffsmf.sets.zonotope import Zonotope

    W = filt.process_noise_set()
    if isinstance(W, Zonotope):
        return W.center, torch.zeros_like(W.center), W.generators
    box = W if isinstance(W, Interval) else W.interval_hull()
    return box.center, box.radius, None


def noise_ellipsoid(filt: SetFilter) -> ConvexSet | None:
    """Process noise for the ellipsoidal predictions (CDSMF, ESMF): ``None`` for a box W (the
    filters keep their box sum with the remainder, as before), else the ellipsoid W itself or
    the covering ellipsoid of a zonotope W (`Ellipsoid.from_zonotope`, not its hull)."""
    from diffsmf.sets.ellipsoid import Ellipsoid

    W = filt.process_noise_set()
    if isinstance(W, Interval):
        return None
    return W if isinstance(W, Ellipsoid) else Ellipsoid.from_zonotope(W)


def zonotope_prediction(filt: SetFilter, fc: Tensor, FG: Tensor, E: Interval) -> ConvexSet:
    """The predicted zonotope of HSNSMF and MSZM: ``f(c) + F G (+) E (+) W`` (Wang et al. 2022, eq.
    20-21, Theorem 2; Alamo 2005) -> Zonotope ``[B]``.

    ``fc [B, n]`` the model at the centre, ``FG [B, n, q]`` the mapped generators, ``E`` the
    remainder box. A box W joins the remainder box (one diagonal block), a zonotope W adds
    its own generators (`noise_generators`); the diagonal is padded by the float64
    rounding margin of the affine part.
    """
    from diffsmf.sets.zonotope import Zonotope

    wc, wr, Gw = noise_generators(filt)
    rad = E.radius + wr  # Theorem 2: sum of two boxes
    rad = rad + rounding_margin(fc, E.center, FG.abs().sum(-1), rad)
    parts = [FG, torch.diag_embed(rad)]
    if Gw is not None:
        parts.append(Gw.expand(*FG.shape[:-1], Gw.shape[-1]))
    return Zonotope(fc + E.center + wc, torch.cat(parts, -1))


def widen(box: Interval, margin: Tensor) -> Interval:
    """``box`` enlarged by ``margin`` on both sides."""
    return Interval(box.lower - margin, box.upper + margin)


def prediction_remainder(
    system: System,
    remainder: Callable[..., Interval],
    fn: Callable[[Tensor], Tensor],
    S: ConvexSet,
    c: Tensor,
    J: Tensor,
    u: Tensor | None,
    margin: Tensor | None = None,
    events: bool = False,
) -> tuple[Interval, Tensor]:
    """Box ``[B, n]`` containing ``f(x, u, theta) - f(c, u, theta_nom) - J (x - c)`` on ``S``,
    and ``ok [B]``: False where no finite box exists (`sanitize_remainder`); with
    ``events=True`` the `FilterEvent` codes ``[B]`` instead (`checked_remainder`:
    ``DOMAIN`` / ``DIVERGED``, 0 where the box is finite), for ``FilterState.flag``.

    ``remainder`` is a `diffsmf.linearize` remainder bound (``dc_remainder`` for Wang et al.
    2022, ``lagrange_remainder`` for Song et al. 2017); when the system has mismatched parameters
    the deviation ``f(x, u, theta) - f(x, u, theta_nom)`` over ``S`` x ``parameters``
    (``linearize.parameter_deviation``, Song et al. 2017, eq. 18-21, evaluated over the whole set,
    not only at the centre as in the paper) is added. ``margin [n]`` (>= 0, the filters'
    ``remainder_margin``) then enlarges the computed box to ``[lo - m, hi + m]``
    (`add_remainder_margin`); it can only add to the guaranteed box, never replace it.
    Where the box is not finite (a singularity of the model over ``S``) it is returned as 0
    with ``ok`` False, and the caller flags those elements (``FilterState.and_bounded(ok)``).
    """
    from diffsmf.linearize import parameter_deviation

    R = remainder(fn, S, c, J)
    if system.parameters is not None:
        D = parameter_deviation(system.f, S, system.parameters, system.theta_nominal, u)
        R = Interval._make(R.lower + D.lower, R.upper + D.upper)
    R = add_remainder_margin(R, margin)
    return checked_remainder(R) if events else sanitize_remainder(R)


def add_remainder_margin(R: Interval, margin: Tensor | None) -> Interval:
    """``[lo - m, hi + m]``: the guaranteed remainder box ``R`` enlarged by ``margin >= 0``.

    ``None`` returns ``R`` itself. A zero margin gives bit-identical bounds (``x - 0 == x``).
    """
    if margin is None:
        return R
    return widen(R, margin)


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
    mask = system._angle_mask.to(device=spread.device)
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
    from diffsmf.sets.strip import Strip

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


def as_parallelotope(S: ConvexSet) -> ConvexSet:
    """Outer parallelotope of a set (itself, box, Chisci bound of a zonotope, or hull box)."""
    from diffsmf.sets.parallelotope import Parallelotope
    from diffsmf.sets.zonotope import Zonotope

    if isinstance(S, Parallelotope):
        return S
    if isinstance(S, (Interval, Zonotope)):
        return S.to_parallelotope()
    return S.interval_hull().to_parallelotope()


def as_zonotope(S: ConvexSet) -> ConvexSet:
    """Outer zonotope of a set (exact for boxes, parallelotopes, zonotopes; else hull box)."""
    from diffsmf.sets.parallelotope import Parallelotope
    from diffsmf.sets.zonotope import Zonotope

    if isinstance(S, Zonotope):
        return S
    if isinstance(S, (Interval, Parallelotope)):
        return S.to_zonotope()
    return S.interval_hull().to_zonotope()


def as_ellipsoid(S: ConvexSet) -> ConvexSet:
    """Outer ellipsoid of a set (itself, ``diag(n r^2)`` cover of a box, zonotope cover)."""
    from diffsmf.sets.ellipsoid import Ellipsoid

    if isinstance(S, Ellipsoid):
        return S
    if isinstance(S, Interval):
        return S.to_ellipsoid()
    return as_zonotope(S).to_ellipsoid()


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


def check_initial_set(name: str, S: ConvexSet | None, n: int) -> None:
    """Validate an ``initial_set`` override (a non-empty set of dim ``n``, batch shape ``[]``)."""
    if S is not None and (not isinstance(S, ConvexSet) or S.dim != n or S.batch_shape != ()):
        raise ValueError(f"{name}: must be a diffsmf set of dim {n} with empty batch shape")
    if S is not None:
        check_nonempty(name, S)


def expand_state_set(S: ConvexSet, batch: int | None) -> ConvexSet:
    """``S`` (batch shape ``[]``) broadcast to ``[batch]`` (default 1)."""
    return S.expand(state_batch(batch))


#: Default Stirling step of the linearising filters, relative to the set: ``h_j = 0.5 r_j`` with
#: ``r`` the half-widths of the interval hull of the set being linearised (Wang et al. 2022
#: give no value). Relative, so that a change of state units scales the step with the set
#: (scale invariance, docs/which_filter.md); an absolute step (a number in state units, the
#: earlier default 0.1) is still accepted.
DEFAULT_STIRLING_FACTOR = 0.5


def register_stirling_step(module: torch.nn.Module, value: float | Tensor | None, n: int) -> None:
    """Validate and register the learnable Stirling step ``[n]`` (Wang et al. 2022, eq. 12-13).

    ``value=None`` (the filters' default): relative mode, ``module.stirling_relative = True``,
    the registered ``stirling_step`` is the factor (default `DEFAULT_STIRLING_FACTOR`)
    and the step used is ``stirling_step * r`` with ``r`` the set's hull half-widths
    (`stirling_steps`). A number or tensor: an absolute step in state units, as given.
    """
    from diffsmf.utils import register_positive

    module.stirling_relative = value is None
    h = torch.as_tensor(DEFAULT_STIRLING_FACTOR if value is None else value, dtype=torch.float64)
    if (h <= 0).any() or h.dim() > 1:
        raise ValueError("stirling_step: must be a positive scalar or [n] tensor")
    register_positive(module, "stirling_step", h.expand(n).clone())


def stirling_steps(filt: torch.nn.Module, c: Tensor, radius: Tensor) -> Tensor:
    """The Stirling step ``h [..., n]`` that ``filt`` uses about ``c [..., n]`` on a set with
    hull half-widths ``radius [..., n]``: ``filt.stirling_step`` itself (absolute mode) or
    ``filt.stirling_step * max(radius, 1e-8 |c|)`` (relative mode; a flat direction falls
    back to a step relative to the centre, and to 1e-150 at 0). Both relative choices scale
    with the state's units, so the slopes of the scaled system are the scaled slopes. The
    radius enters without gradient (a choice of expansion, like the discrete choices of the
    sets; the factor ``stirling_step`` keeps its gradient), so a diverged element's infinite
    radius cannot reach the gradients of the others."""
    if not getattr(filt, "stirling_relative", False):
        return filt.stirling_step
    r = torch.maximum(radius.detach(), 1e-8 * c.detach().abs()).clamp(min=1e-150)
    r = torch.where(torch.isfinite(r), r, torch.ones_like(r))  # a diverged element
    return filt.stirling_step * r


def register_remainder(module: torch.nn.Module, name: str, n: int) -> None:
    """Validate ``remainder`` (a name of `diffsmf.linearize.REMAINDERS` or ``"auto"``)
    and set ``module.remainder`` (the resolved name) and ``module.remainder_fn``.

    ``"auto"``: the Wang et al. 2022 vertex method (``"dc-vertices"``) up to
    `AUTO_VERTEX_MAX_N` states, then the vertex-free bounds
    (``"lagrange"`` up to `AUTO_LAGRANGE_MAX_N`, ``"mean-value"``
    above; 2^n vertices are out of reach at n = 16, 32). Every choice is guaranteed.
    """
    from diffsmf.linearize import resolve_remainder

    if not isinstance(name, str):
        raise ValueError(f"remainder: expected a method name, got {name!r}")
    module.remainder, module.remainder_fn = resolve_remainder(name, n)


def register_remainder_margin(module: torch.nn.Module, value: float | Tensor, n: int) -> None:
    """Validate and register the learnable remainder margin ``m [n]`` (>= 0).

    The prediction remainder box becomes ``[lo - m, hi + m]`` (`add_remainder_margin`):
    an inflation for unmodelled dynamics and model error. The guarantee needs the computed
    remainder, so the margin can only add to it, never shrink it; 0 gives exactly the filter
    without it. It enters the predicted set the same way the process-noise box does; it is
    kept separate because the noise bound is a property of the data and the margin one of the
    model.

    ``margin = scale * softplus(raw)`` (`register_positive`), so it stays
    >= 0 and a component that starts at 0 stays exactly 0 (tune it from a positive start). A
    scalar broadcasts to ``[n]``. Raises ``ValueError`` for negative or NaN values or a shape
    other than ``[]``, ``[1]`` or ``[n]``.
    """
    from diffsmf.utils import register_positive

    try:
        m = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"remainder_margin: expected a number or a tensor, got {value!r}") from e
    if m.dim() > 1 or (m.dim() == 1 and m.shape[0] not in (1, n)):
        raise ValueError(
            f"remainder_margin: must be a scalar or a [{n}] tensor, got shape {tuple(m.shape)}"
        )
    if torch.isnan(m).any() or (m < 0).any() or torch.isinf(m).any():
        raise ValueError(
            f"remainder_margin: must be finite and non-negative, got {m.tolist()}"
        )
    register_positive(module, "remainder_margin", m.detach().expand(n).clone())


class EllipsoidalSetFilter(SetFilter):
    """Shared start of the ellipsoidal filters (CDSMF, ESMF): the covering ellipsoid of the
    initial set, and its interval hull kept in ``extras[X0_LOWER]`` / ``extras[X0_UPPER]`` so
    that the first remainder is bounded over (ellipsoid hull) ∩ (initial box), see
    `remainder_box`."""

    def __init__(self, system: System, initial_set: ConvexSet | None = None, **kw) -> None:
        super().__init__(system, **kw)
        check_initial_set("initial_set", initial_set, system.n)
        given = initial_set if initial_set is not None else system.x0_set
        self._x0 = as_ellipsoid(given)
        self._x0_box = given.interval_hull()

    def _initial_state(self, batch: int | None = None) -> FilterState:
        S = expand_state_set(self._x0, batch)
        ok = torch.ones(S.batch_shape, dtype=torch.bool)
        shape = (*S.batch_shape, self.system.n)
        lo, hi = self._x0_box.lower.expand(shape), self._x0_box.upper.expand(shape)
        return FilterState(set=S, consistent=ok, extras={X0_LOWER: lo, X0_UPPER: hi})


__all__ = [
    "ROUND_REL",
    "EllipsoidalSetFilter",
    "X0_LOWER",
    "X0_UPPER",
    "add_remainder_margin",
    "checked_remainder",
    "remainder_events",
    "angle_ambiguous",
    "register_remainder",
    "register_remainder_margin",
    "register_stirling_step",
    "as_ellipsoid",
    "as_parallelotope",
    "as_zonotope",
    "check_initial_set",
    "expand_state_set",
    "measurement_strips",
    "prediction_remainder",
    "noise_ellipsoid",
    "noise_generators",
    "rounding_margin",
    "sanitize_remainder",
    "zonotope_prediction",
    "sequential_strip_update",
    "spent_initial_box",
    "step_function",
    "stirling_steps",
    "stirling_strip_update",
    "DEFAULT_STIRLING_FACTOR",
    "widen",
]
