"""The parts every remainder bound of `diffsmf.linearize.remainders` is built from: affine
detection, the outward padding of float evaluations, the hull of a set and its expansion point,
the exact range of a linear map over a set, and the first-order bounds that every bound is
intersected with (`_lower_order`).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.convex import ConvexSet
from diffsmf.interval.arith import Stacked
from diffsmf.interval.box import Interval
from diffsmf.linearize.jacobians import jacobian, value_and_jacobian
from diffsmf.linearize.jets import Enclosure, JetError, jet_eval
from diffsmf.utils import tracing

__all__ = ["float_padding", "is_affine"]

Fn = Callable[[Tensor], Tensor]


#: Padding of float evaluations, in units of eps times the magnitudes involved.
_PAD_ULPS = 64.0


#: Functions whose interval jet had a structurally zero Hessian (True: affine on all of R^n,
#: the jets build a Hessian for every non-affine operation) or not (False), so later calls
#: skip the jets.
_AFFINE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _known_affine(fn: Fn) -> bool:
    if tracing():  # the cache is host state; the traced graph takes the general path
        return False
    try:
        return bool(_AFFINE.get(fn, False))
    except TypeError:  # unhashable callable
        return False


def is_affine(fn: Fn, S: ConvexSet) -> bool:
    """Whether ``fn`` is affine on all of R^n: its interval jet over the interval hull of the
    set ``S`` has a structurally zero Hessian (a property of the function, not of the set;
    the hull is only computed for the probe). Probed once per
    function and remembered (weakly, by identity) with what the remainder bounds learn, so
    that the first call and every later one agree; False for an unhashable callable and for a
    function the engine cannot enclose. While traced the probe runs every time and nothing is
    remembered (no host state); the flag is structural, and the probe's tensors are dead code
    that the compiler drops."""
    if tracing():
        try:
            return jet_eval(fn, S.interval_hull(), order=2).hess_is_zero
        except JetError:
            return False
    try:
        known = _AFFINE.get(fn)
    except TypeError:  # unhashable callable
        return False
    if known is None:
        try:
            known = jet_eval(fn, S.interval_hull(), order=2).hess_is_zero
        except JetError:
            known = False
        _AFFINE[fn] = known
    return known


def _remember(fn: Fn, jet: Enclosure) -> bool:
    """Record ``fn`` as affine when ``jet``'s Hessian is structurally zero -> that flag."""
    if jet.hess_is_zero and not tracing():
        try:
            _AFFINE[fn] = True
        except TypeError:
            pass
    return jet.hess_is_zero


def _affine_remainder(fn: Fn, S: ConvexSet, c: Tensor, J: Tensor | None) -> Interval:
    """Remainder of an affine ``fn``: exactly ``(J_exact - J)(x - c)`` over ``S`` (support
    function), padded by the float error of evaluating ``fn`` and ``J (x - c)`` on the hull."""
    fc, Jx = value_and_jacobian(fn, c)  # [..., k (, n)], Jx constant for affine fn
    box = _hull_with(S, c)
    mag = box.lower.abs().maximum(box.upper.abs())
    scale = fc.abs() + ((Jx.abs() + (0.0 if J is None else J.abs())) * mag.unsqueeze(-2)).sum(-1)
    if J is None:
        z = torch.zeros_like(scale)
        return _padded(z, z, scale)
    R = _linear_range(S, Jx - J, c)
    return _padded(R.lower, R.upper, scale)


def _eps(t: Tensor) -> float:
    return torch.finfo(t.dtype).eps


def _check(S: ConvexSet, c: Tensor, J: Tensor | None) -> tuple[Tensor, Tensor | None]:
    if not isinstance(S, ConvexSet):
        raise ValueError("S: expected a diffsmf set")
    c = torch.as_tensor(c, dtype=S.dtype, device=S.device)
    if c.shape[-1:] != (S.dim,):
        raise ValueError(f"c: expected shape [..., {S.dim}], got {tuple(c.shape)}")
    if J is not None:
        J = torch.as_tensor(J, dtype=S.dtype, device=S.device)
        if J.dim() < 2 or J.shape[-1] != S.dim:
            raise ValueError(f"J: expected shape [..., k, {S.dim}], got {tuple(J.shape)}")
    return c, J


def float_padding(scale: Tensor) -> Tensor:
    """``_PAD_ULPS * eps * scale + tiny`` (``scale`` detached): the outward padding of a
    bound for the float error of terms of magnitude at most ``scale`` (also the strips'
    padding of an affine measurement function, `diffsmf.filters.strips`)."""
    fi = torch.finfo(scale.dtype)
    return (_PAD_ULPS * fi.eps) * _nograd(scale) + fi.tiny


def _padded(lo: Tensor, hi: Tensor, scale: Tensor) -> Interval:
    """``[lo - tol, hi + tol]`` with ``tol = float_padding(scale)``."""
    tol = float_padding(scale)
    # internal bounds (lo <= hi by construction): no validation, and no host sync, per call;
    # a NaN propagates to the filters' guard (sanitize_remainder), which flags the element
    return Interval._make(lo - tol, hi + tol)


def _nograd(t: Tensor) -> Tensor:
    """``t`` detached (no op when it carries no gradient)."""
    return t.detach() if t.requires_grad else t


def _hull_with(S: ConvexSet, c: Tensor) -> Interval:
    """Interval hull of ``S`` and ``c`` (so the segments [c, x] lie inside), padded outward."""
    box = S.interval_hull()
    lo = torch.minimum(box.lower, c)
    hi = torch.maximum(box.upper, c)
    scale = lo.abs() + hi.abs()
    return _padded(lo, hi, scale)


def _linear_range(S: ConvexSet, D: Tensor, c: Tensor) -> Interval:
    """Exact range of ``D (x - c)`` over ``S`` via the support function -> ``[..., k]``."""
    Dk = D.movedim(-2, 0)  # [k, ..., n] so the batch dims align with S's
    Dc = (D * c.unsqueeze(-2)).sum(-1)  # [..., k]
    up = S.support(Dk).movedim(0, -1) - Dc
    lo = -S.support(-Dk).movedim(0, -1) - Dc
    box = S.interval_hull()
    mag = box.lower.abs() + box.upper.abs() + c.abs()
    scale = (D.abs() * mag.unsqueeze(-2)).sum(-1)
    return _padded(lo, up, scale)


def _quad_form(H: Interval, d: Interval) -> Interval:
    """Enclosure of ``d' H d`` for ``H [..., k, n, n]``, ``d [..., n]`` -> ``[..., k]``.

    Diagonal terms use the exact square ``d_j^2``; symmetric off-diagonal pairs are kept as
    they are (both copies hold the same interval).
    """
    n = d.shape[-1]
    dd = d.unsqueeze(-1) * d.unsqueeze(-2)  # [..., n, n]
    sq = d.square()
    eye = torch.eye(n, dtype=torch.bool, device=d.lower.device)
    dd = Interval._make(  # exact squares on the diagonal (field-wise: no Interval dispatch)
        torch.where(eye, torch.diag_embed(sq.lower), dd.lower),
        torch.where(eye, torch.diag_embed(sq.upper), dd.upper),
    )
    return (H * dd.unsqueeze(-3)).sum((-2, -1))


def _lagrange(
    jet: Enclosure, box: Interval, S: ConvexSet, c: Tensor, J: Tensor | None, D: Tensor | None
) -> Interval:
    """Song et al. 2017, eq. 26-28 from the jet over ``box``; ``D = J_exact(c) - J`` or None."""
    d = box.__sub__(c)  # [..., n] (outward rounded; the method call traces under Dynamo)
    R = _quad_form(jet.hess, d) * 0.5
    if D is not None and (tracing() or not bool((D.detach() == 0).all())):
        R = R + _linear_range(S, D, c)
    # float evaluation of fn(x) - fn(c) - J (x - c) is padded by its rounding scale
    Jm = 0.0 if J is None else (J.abs() * d.upper.abs().maximum(d.lower.abs()).unsqueeze(-2))
    scale = _abs_max(jet.val) + (Jm if J is None else Jm.sum(-1))
    return _padded(R.lower, R.upper, scale)


def _lower_order(
    fn: Fn, jet: Enclosure, box: Interval, S: ConvexSet, c: Tensor, J: Tensor | None, R: Interval,
    jv: Tensor | None = None, d: tuple[Tensor, Tensor, Tensor] | None = None,
) -> Interval:
    """``R`` intersected with the bounds of lower order, per output.

    First order (mean value with the interval Jacobian, which encloses the Clarke generalised
    Jacobian of a non-smooth model, Lebourg's theorem): ``r in ([J_fn] - J)(box - c)``, with
    ``[J_fn]`` for ``J`` when ``J`` is None (the exact Jacobian at ``c`` lies in it). It bounds
    the outputs whose Hessian enclosure is infinite (a kink of relu, abs, clamp, max or a PWL
    model inside the set). Where the Jacobian enclosure itself is infinite (a branch on the
    state that may jump), zeroth order: ``r in [f](box) - f(c) - J (S - c)``. ``jv`` is
    ``_abs_max(jet.val)`` and ``d`` the triple ``(box.lower - c, box.upper - c, max |box - c|)``
    when the caller has them.

    The interval product is evaluated in plain float: ``box`` contains ``c``, so
    ``d = box - c`` has ``d_lo <= 0 <= d_hi`` and ``[a, b] [d_lo, d_hi]`` is
    ``[min(a d_hi, b d_lo), max(a d_lo, b d_hi)]``; its rounding (the subtractions, the
    products and the sum, at most ``(n + 2) eps sum_j (|a_j| + |b_j|) |d_j|``) is covered by
    the padding, whose scale includes ``2 (hi - lo) >= sum_j (|a_j| + |b_j|) max|d_j|`` (each
    term's lower bound is <= 0 <= its upper bound, and ``|a_j| max|d_j|`` is at most the
    largest of its four products).
    """
    dl, du, mag = (box.lower - c, box.upper - c, None) if d is None else d
    dl = dl.unsqueeze(-2)  # [..., 1, n], <= 0
    du = du.unsqueeze(-2)  # >= 0
    gl, gu = jet.grad.lower, jet.grad.upper
    # infinite Jacobian bounds are masked out of the products and put back in the result, so
    # that no 0 * inf reaches the gradients of the other batch elements
    finite = (gu - gl) < torch.inf  # False for an infinite bound (and NaN): gu - gl >= 0
    # eagerly, one host read: all finite (the usual case) needs no masks
    all_finite = not tracing() and bool(finite.all())
    Jl, Ju = (gu, gl) if J is None else (J, J)  # J = None: [J_fn] - [J_fn]
    a, b = gl - Jl, gu - Ju  # [..., k, n]: [a, b] = [J_fn] - J
    if not all_finite:
        inf_g = ~finite
        a, b = a.masked_fill(inf_g, 0.0), b.masked_fill(inf_g, 0.0)
    lo = linalg.small_reduce(torch.minimum(a * du, b * dl), "sum")  # [..., k]
    hi = linalg.small_reduce(torch.maximum(a * dl, b * du), "sum")
    jv = _abs_max(jet.val) if jv is None else jv  # the caller's, when it has it
    scale = jv + _nograd(hi - lo) * 2.0
    if J is not None:  # the float evaluation of J (x - c)
        mag = torch.maximum(-dl, du) if mag is None else mag.unsqueeze(-2)
        scale = scale + _nograd(linalg.small_dot(J.abs(), mag))
    R1 = _padded(lo, hi, scale)
    if all_finite:
        return R.intersect(R1)
    rows = finite.all(-1)
    R = Interval._make(torch.where(rows, torch.maximum(R.lower, R1.lower), R.lower),
                       torch.where(rows, torch.minimum(R.upper, R1.upper), R.upper))
    Jc = jacobian(fn, c) if J is None else J
    fc = fn(c)
    L = _linear_range(S, Jc, c)
    R0 = jet.val.__sub__(fc).__sub__(L)
    scale0 = jv + fc.abs().detach() + _abs_max(L)
    both = R.intersect(_padded(R0.lower, R0.upper, scale0))
    # only the outputs without a finite first-order bound (the same result eager and traced)
    use = ~rows
    return Interval._make(torch.where(use, both.lower, R.lower),
                          torch.where(use, both.upper, R.upper))


def _abs_sum(I: Interval) -> float:
    """The sum of ``|bound|`` over ``I`` (one host read; NaN where a bound is NaN)."""
    if isinstance(I, Stacked):
        return float(_nograd(I.both).abs().sum())
    return float(_nograd(I.lower).abs().sum() + _nograd(I.upper).abs().sum())


def _abs_max(I: Interval) -> Tensor:
    """``max |x|`` over an interval array (inf-safe, detached)."""
    if isinstance(I, Stacked):  # bounds stacked [2, ...]: no views of each
        m = _nograd(I.both).abs().amax(0)
    else:
        m = _nograd(torch.maximum(I.lower.abs(), I.upper.abs()))
    return torch.nan_to_num(m, nan=0.0, posinf=0.0)
