"""Rules of the smooth elementwise functions (exp, log, sqrt, trigonometric, hyperbolic,
activations, atan2): each encloses the value and applies the chain rule with enclosed
derivatives, clamped to its domain.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval import arith
from diffsmf.interval.box import Interval
from diffsmf.interval.jet import Jet, chain, mul, point
from diffsmf.interval.rounding import down, up
from diffsmf.interval.rules.arithmetic import _linear_combo, _pow_scalar, _recip_jet
from diffsmf.interval.rules.base import (
    Ctx,
    _common,
    _is_jet,
    _lift,
    _nan_where,
    _ref,
    _select,
    aten,
    register,
)

__all__ = []

@register(aten.pow, category="elementwise")
def _pow(ctx: Ctx, a: Any, p: Any) -> Any:
    if not _is_jet(a) and not _is_jet(p):
        return torch.pow(a, p)
    if _is_jet(p) or (isinstance(p, Tensor) and p.numel() != 1):
        if not _is_jet(a):  # base ** jet = exp(jet * log(base))
            base = torch.as_tensor(a, dtype=p.val.lower.dtype)
            return _exp(ctx, mul(p, torch.log(base)))
        return _exp(ctx, mul(p if _is_jet(p) else p, _log(ctx, a)))
    pv = float(p.item() if isinstance(p, Tensor) else p)
    return _pow_scalar(a, pv)


# ----------------------------------------------------------------------------- elementwise
def _unary(fn: Callable[[Jet], Jet], torch_fn: Callable[..., Tensor]) -> Callable:
    def rule(ctx: Ctx, a: Any, *args: Any, **kwargs: Any) -> Any:
        if not _is_jet(a):
            return torch_fn(a, *args, **kwargs)
        return fn(a, *args, **kwargs)

    return rule


def _o(a: Jet, k: int) -> bool:
    return a.order >= k


def _exp_j(a: Jet) -> Jet:
    v = a.val.exp()
    return chain(a, v, v, v)


def _domain(a: Jet, low: float, strict: bool) -> tuple[Interval, Tensor]:
    """The argument clamped into ``[low, inf)`` and the mask of elements that left it.

    Clamping is sound: the true states are in the model's domain (the model is evaluated on
    them), so only the part of the set inside it must be enclosed; the function is enclosed by
    its continuous extension ``phi(max(x, low))``, whose derivative enclosure is unbounded where
    ``phi'`` is at ``low`` (sqrt, asin), and the filters then use a bound of lower order."""
    lo = a.val.lower
    bad = (lo <= low) if strict else (lo < low)
    cl = Interval._make(lo.clamp_min(low), a.val.upper.clamp_min(low))
    return cl, bad


# The derivatives of log, sqrt and rsqrt are quotients of non-negative numbers on the clamped
# domain (`_domain`), enclosed by `arith.quotient_nonneg` (the range from the end points)
# instead of the general interval reciprocal, which also covers intervals that cross 0.
def _log_j(a: Jet) -> Jet:
    x, bad = _domain(a, 0.0, strict=False)
    r = arith.quotient_nonneg(1.0, x)
    return chain(a, x.log(), r, -r.square())


def _log1p_j(a: Jet) -> Jet:
    x, bad = _domain(a, -1.0, strict=False)
    # x + 1 >= 0 for x >= -1; the clamp keeps a sum rounded below 0 out of the quotient
    r = arith.quotient_nonneg(1.0, arith.clamp(x + 1.0, min=0.0))
    return chain(a, x.log1p(), r, -r.square())


def _sqrt_j(a: Jet) -> Jet:
    x, bad = _domain(a, 0.0, strict=False)
    v = arith.monotone(x, torch.sqrt, 1, clamp_min=0.0)  # x >= 0: `Interval.sqrt` unchecked
    # sqrt' = 1 / (2 sqrt x), sqrt'' = -1 / (4 sqrt x) / x: falling magnitudes on x >= 0
    d1 = arith.quotient_nonneg(0.5, v) if _o(a, 1) else None
    d2 = -arith.quotient_nonneg(arith.quotient_nonneg(0.25, v), x) if _o(a, 2) else None
    return chain(a, v, d1, d2)


def _rsqrt_j(a: Jet) -> Jet:
    x, bad = _domain(a, 0.0, strict=False)
    v = arith.quotient_nonneg(1.0, arith.monotone(x, torch.sqrt, 1, clamp_min=0.0))
    r = arith.quotient_nonneg(1.0, x)
    d1 = v * r * (-0.5) if _o(a, 1) else None
    d2 = v * r.square() * 0.75 if _o(a, 2) else None
    return chain(a, v, d1, d2)


def _expm1_j(a: Jet) -> Jet:
    e = a.val.exp()
    return chain(a, a.val.expm1(), e, e)


def _sin_j(a: Jet) -> Jet:
    v = a.val.sin()
    return chain(a, v, a.val.cos() if _o(a, 1) else None, -v)


def _cos_j(a: Jet) -> Jet:
    v = a.val.cos()
    return chain(a, v, -a.val.sin() if _o(a, 1) else None, -v)


def _tan_j(a: Jet) -> Jet:
    # tan is continuous between its poles; a box meeting a pole is a domain exit (NaN)
    lo, hi = a.val.lower, a.val.upper
    k_lo = torch.floor((lo.detach() + math.pi / 2) / math.pi)
    k_hi = torch.floor((hi.detach() + math.pi / 2) / math.pi)
    near = (hi - lo).detach() >= math.pi - 1e-12
    bad = (k_lo != k_hi) | near
    v = Interval._make(down(torch.tan(lo), 4), up(torch.tan(hi), 4))
    v = Interval._make(torch.where(bad, lo, v.lower), torch.where(bad, hi, v.upper))
    s = v.square() + 1.0  # tan' = 1 + tan^2, tan'' = 2 tan (1 + tan^2)
    return _nan_where(chain(a, v, s, v * s * 2.0), bad)


def _asin_like(a: Jet, fn: Callable[[Tensor], Tensor], sign: float) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    (lo < -1.0) | (hi > 1.0)
    x = Interval._make(lo.clamp(-1.0, 1.0), hi.clamp(-1.0, 1.0))
    f_lo, f_hi = fn(x.lower), fn(x.upper)
    v = Interval._make(down(torch.minimum(f_lo, f_hi), 4), up(torch.maximum(f_lo, f_hi), 4))
    q = (1.0 - x.square())  # 1 - x^2 >= 0
    q = Interval._make(q.lower.clamp_min(0.0), q.upper.clamp_min(0.0))
    r = q.sqrt().reciprocal()  # 1 / sqrt(1 - x^2), inf at +-1
    d1 = r * sign if _o(a, 1) else None
    d2 = x * r * q.reciprocal() * sign if _o(a, 2) else None
    return chain(a, v, d1, d2)


def _atan_j(a: Jet) -> Jet:
    d1 = (a.val.square() + 1.0).reciprocal()
    return chain(a, a.val.atan(), d1, a.val * d1.square() * (-2.0) if _o(a, 2) else None)


def _sinh_j(a: Jet) -> Jet:
    v = a.val.sinh()
    return chain(a, v, a.val.cosh(), v)


def _cosh_j(a: Jet) -> Jet:
    v = a.val.cosh()
    return chain(a, v, a.val.sinh(), v)


def _tanh_j(a: Jet) -> Jet:
    v = a.val.tanh()
    d1 = 1.0 - v.square()
    return chain(a, v, d1, v * d1 * (-2.0) if _o(a, 2) else None)


def _sigmoid_j(a: Jet) -> Jet:
    v = a.val.sigmoid()
    d1 = v * (1.0 - v)
    return chain(a, v, d1, d1 * (1.0 - v * 2.0) if _o(a, 2) else None)


def _softplus_j(a: Jet, beta: float = 1.0, threshold: float = 20.0) -> Jet:
    # beta * softplus is the smooth log(1 + exp(beta x)); torch's threshold switches to x only
    # where it agrees with it to rounding (documented), so the smooth function is enclosed
    x = a.val * beta if beta != 1 else a.val
    v = x.softplus()
    s = x.sigmoid()
    if beta != 1:
        v = v / beta
    d2 = s * (1.0 - s) * beta if _o(a, 2) else None
    pad = math.exp(-threshold) if threshold * beta < 40 else 0.0
    v = Interval._make(v.lower - pad, v.upper + pad)
    return chain(a, v, s, d2)


def _erf_j(a: Jet) -> Jet:
    c = 2.0 / math.sqrt(math.pi)
    g = (-a.val.square()).exp() * c
    return chain(a, a.val.erf(), g, a.val * g * (-2.0) if _o(a, 2) else None)


def _gelu_j(a: Jet, approximate: str = "none") -> Jet:
    x = a.val
    if approximate != "none":  # tanh form: 0.5 x (1 + tanh(k (x + 0.044715 x^3)))
        k = math.sqrt(2.0 / math.pi)
        inner = _linear_combo(a, _pow_scalar(a, 3.0), k, k * 0.044715)
        t = _tanh_j(inner)
        return mul(mul(a, 0.5), _linear_combo(t, 1.0, 1, 1))
    phi = (-(x.square()) * 0.5).exp() * (1.0 / math.sqrt(2.0 * math.pi))
    cdf = ((x * (1.0 / math.sqrt(2.0))).erf() + 1.0) * 0.5
    # value: gelu is decreasing below its minimum point xm and increasing above
    xm = -0.7517916243457
    f_lo = torch.nn.functional.gelu(x.lower)
    f_hi = torch.nn.functional.gelu(x.upper)
    fmin = torch.nn.functional.gelu(torch.full_like(x.lower, xm))
    inside = (x.lower < xm) & (x.upper > xm)
    low = torch.where(inside, fmin, torch.minimum(f_lo, f_hi))
    v = Interval._make(down(low, 8), up(torch.maximum(f_lo, f_hi), 8))
    d1 = cdf + x * phi if _o(a, 1) else None
    d2 = phi * (2.0 - x.square()) if _o(a, 2) else None
    return chain(a, v, d1, d2)


for _op, _rule, _fn in (
    (aten.exp, _exp_j, torch.exp), (aten.log, _log_j, torch.log),
    (aten.log1p, _log1p_j, torch.log1p), (aten.expm1, _expm1_j, torch.expm1),
    (aten.sqrt, _sqrt_j, torch.sqrt), (aten.rsqrt, _rsqrt_j, torch.rsqrt),
    (aten.sin, _sin_j, torch.sin), (aten.cos, _cos_j, torch.cos), (aten.tan, _tan_j, torch.tan),
    (aten.asin, lambda a: _asin_like(a, torch.asin, 1.0), torch.asin),
    (aten.acos, lambda a: _asin_like(a, torch.acos, -1.0), torch.acos),
    (aten.atan, _atan_j, torch.atan), (aten.sinh, _sinh_j, torch.sinh),
    (aten.cosh, _cosh_j, torch.cosh), (aten.tanh, _tanh_j, torch.tanh),
    (aten.sigmoid, _sigmoid_j, torch.sigmoid), (aten.erf, _erf_j, torch.erf),
):
    register(_op, category="elementwise")(_unary(_rule, _fn))
register(aten.softplus, category="activation")(
    _unary(_softplus_j, torch.nn.functional.softplus))
register(aten.gelu, category="activation")(
    _unary(_gelu_j, lambda x, approximate="none": torch.nn.functional.gelu(
        x, approximate=approximate)))


def _exp(ctx: Ctx, a: Any) -> Any:
    return _exp_j(a) if _is_jet(a) else torch.exp(a)


def _log(ctx: Ctx, a: Any) -> Any:
    return _log_j(a) if _is_jet(a) else torch.log(a)


# ----------------------------------------------------------------------------- angles
@register(aten.atan2, category="elementwise")
def _atan2(ctx: Ctx, y: Any, x: Any) -> Any:
    """``atan2(y, x)``: on the right half-plane ``atan(y/x)``, above/below the x axis
    ``+-pi/2 - atan(x/y)``; a box meeting the branch cut (``x <= 0``, ``y = 0``) gets the hull
    ``[-pi, pi]`` and no derivative (the function jumps by ``2 pi`` there)."""
    if not _is_jet(y) and not _is_jet(x):
        return torch.atan2(y, x)
    ref = _ref([y, x])
    Y, X = _common([_lift(y, ref), _lift(x, ref)])
    xpos = X.val.lower > 0
    ypos = Y.val.lower > 0
    yneg = Y.val.upper < 0
    ok = xpos | ypos | yneg
    one = point(torch.ones_like(X.val.lower))
    safe_x = _select(xpos, X, one)
    safe_y = _select(ypos | yneg, Y, one)
    right = _atan_j(mul(Y, _recip_jet(safe_x)))
    side = _atan_j(mul(X, _recip_jet(safe_y)))
    half = math.pi / 2
    hp = Interval._make(torch.full_like(X.val.lower, math.nextafter(half, 0)),
                        torch.full_like(X.val.lower, math.nextafter(half, 4)))
    upper = _linear_combo(ref.like(hp, None, None), side, 1, -1)
    lower = _linear_combo(ref.like(-hp, None, None), side, 1, -1)
    out = _select(xpos, right, _select(ypos, upper, lower))
    pi = math.nextafter(math.pi, 4)
    cut = ref.like(Interval._make(torch.full_like(X.val.lower, -pi),
                                  torch.full_like(X.val.lower, pi)), None, None)
    return _select(ok, out, cut, undefined_derivative=True)
