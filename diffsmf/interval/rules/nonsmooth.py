"""Rules of the piecewise-smooth functions (relu, leaky relu, elu, clamp, abs, max, min): slopes
enclosed over the box, a Hessian of ``[-inf, inf]`` where a kink lies inside.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval.box import Interval
from diffsmf.interval.errors import EngineError
from diffsmf.interval.jet import Jet, chain, mul, point
from diffsmf.interval.rounding import down, up
from diffsmf.interval.rules.arithmetic import _linear_combo
from diffsmf.interval.rules.base import Ctx, _is_jet, aten, register
from diffsmf.interval.rules.elementwise import _unary

__all__ = []

# ----------------------------------------------------------------------------- non-smooth
def _piecewise(a: Jet, v: Interval, d1_lo: Tensor, d1_hi: Tensor, kink: Tensor,
               d2: Interval | None = None) -> Jet:
    """A continuous piecewise function: slope hull ``[d1_lo, d1_hi]`` (its Clarke derivative),
    second derivative ``d2`` (default 0) except ``[-inf, inf]`` where a kink lies in the box."""
    d1 = Interval._make(d1_lo, d1_hi)
    if a.order >= 2:
        base = d2 if d2 is not None else point(torch.zeros_like(v.lower))
        inf = torch.full_like(v.lower, torch.inf)
        d2 = Interval._make(torch.where(kink, -inf, base.lower), torch.where(kink, inf, base.upper))
    return chain(a, v, d1, d2)


def _slopes(lo: Tensor, hi: Tensor, x0: float, left: float, right: float) -> tuple[Tensor, ...]:
    """Slope hull of a function with slope ``left`` below ``x0`` and ``right`` above."""
    below = hi <= x0
    above = lo >= x0
    sl = torch.full_like(lo, left)
    sr = torch.full_like(lo, right)
    smin = torch.minimum(sl, sr)
    smax = torch.maximum(sl, sr)
    d_lo = torch.where(below, sl, torch.where(above, sr, smin))
    d_hi = torch.where(below, sl, torch.where(above, sr, smax))
    return d_lo, d_hi, (lo < x0) & (hi > x0)


def _relu_j(a: Jet) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    d_lo, d_hi, kink = _slopes(lo, hi, 0.0, 0.0, 1.0)
    return _piecewise(a, a.val.relu(), d_lo, d_hi, kink)


def _leaky_j(a: Jet, slope: float = 0.01) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    d_lo, d_hi, kink = _slopes(lo, hi, 0.0, slope, 1.0)
    f = lambda t: torch.where(t >= 0, t, t * slope)  # noqa: E731 - monotone for slope >= 0
    v = Interval._make(down(torch.minimum(f(lo), f(hi))), up(torch.maximum(f(lo), f(hi))))
    return _piecewise(a, v, d_lo, d_hi, kink)


def _elu_j(a: Jet, alpha: float = 1.0, scale: float = 1.0, input_scale: float = 1.0) -> Jet:
    """ELU, ``alpha >= 0``: ``x`` above 0, ``alpha (e^x - 1)`` below (increasing)."""
    if alpha < 0:
        raise EngineError("elu: alpha < 0 is not supported")
    if input_scale != 1.0:
        a = mul(a, input_scale)
    x = a.val
    lo, hi = x.lower, x.upper
    neg = x.expm1() * alpha
    v = Interval._make(torch.where(lo >= 0, lo, neg.lower), torch.where(hi >= 0, hi, neg.upper))
    en = Interval._make(lo.clamp_max(0.0), hi.clamp_max(0.0)).exp() * alpha  # slopes below 0
    one = torch.ones_like(lo)
    d_lo = torch.where(lo >= 0, one, torch.where(hi > 0, torch.minimum(en.lower, one), en.lower))
    d_hi = torch.where(lo >= 0, one, torch.where(hi > 0, torch.maximum(en.upper, one), en.upper))
    zero = torch.zeros_like(lo)
    d2 = Interval._make(torch.where(hi <= 0, en.lower, zero), torch.where(hi <= 0, en.upper, zero))
    out = _piecewise(a, v, d_lo, d_hi, (lo < 0) & (hi > 0), d2)
    return mul(out, scale) if scale != 1.0 else out


def _clamp_j(a: Jet, lo_b: Any = None, hi_b: Any = None) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    ones = torch.ones_like(lo)
    zeros = torch.zeros_like(lo)
    mn = -math.inf if lo_b is None else lo_b
    mx = math.inf if hi_b is None else hi_b
    mn_t = torch.as_tensor(mn, dtype=lo.dtype, device=lo.device)
    mx_t = torch.as_tensor(mx, dtype=lo.dtype, device=lo.device)
    v = Interval._make(torch.clamp(lo, mn_t, mx_t), torch.clamp(hi, mn_t, mx_t))
    inside = (lo >= mn_t) & (hi <= mx_t)
    outside = (hi <= mn_t) | (lo >= mx_t)
    d_lo = torch.where(inside, ones, zeros)
    d_hi = torch.where(outside, zeros, ones)
    kink = ((lo < mn_t) & (hi > mn_t)) | ((lo < mx_t) & (hi > mx_t))
    return _piecewise(a, v, d_lo, d_hi, kink)


def _abs_j(a: Jet) -> Jet:
    lo, hi = a.val.lower, a.val.upper
    d_lo, d_hi, kink = _slopes(lo, hi, 0.0, -1.0, 1.0)
    return _piecewise(a, a.val.abs(), d_lo, d_hi, kink)


register(aten.relu, category="non-smooth")(_unary(_relu_j, torch.relu))
register(aten.leaky_relu, category="non-smooth")(
    _unary(_leaky_j, torch.nn.functional.leaky_relu))
register(aten.elu, category="non-smooth")(_unary(
    _elu_j, lambda x, alpha=1.0, scale=1.0, input_scale=1.0: aten.elu(x, alpha, scale,
                                                                      input_scale)))
register(aten.abs, category="non-smooth")(_unary(_abs_j, torch.abs))
register(aten.clamp, category="non-smooth")(_unary(_clamp_j, torch.clamp))
register(aten.clamp_min, category="non-smooth")(
    _unary(lambda a, m: _clamp_j(a, m, None), torch.clamp_min))
register(aten.clamp_max, category="non-smooth")(
    _unary(lambda a, m: _clamp_j(a, None, m), torch.clamp_max))
register(aten.hardtanh, category="non-smooth")(
    _unary(lambda a, mn=-1.0, mx=1.0: _clamp_j(a, mn, mx), torch.nn.functional.hardtanh))


@register(aten.maximum, aten.minimum, aten.fmax, aten.fmin, category="non-smooth")
def _maxmin(ctx: Ctx, a: Any, b: Any) -> Any:
    is_max = "max" in ctx.name
    if not _is_jet(a) and not _is_jet(b):
        return torch.maximum(a, b) if is_max else torch.minimum(a, b)
    # max(a, b) = b + relu(a - b); min(a, b) = a - relu(a - b)
    d = _linear_combo(a, b, 1, -1)
    r = _relu_j(d)
    return _linear_combo(b, r, 1, 1) if is_max else _linear_combo(a, r, 1, -1)
