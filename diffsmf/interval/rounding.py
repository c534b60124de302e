"""Outward rounding of float bounds: the guarantee of every interval operation.

After an operation whose exact real result lies within ``k`` units in the last place of the
computed float (``k = 1`` for the correctly rounded IEEE ``+ - * / sqrt``, ``k = 2`` for library
transcendental functions), `down` / `up` move a lower / upper bound outward:

* ``k = 1``: to the neighbouring float (``torch.nextafter``, one op). A correctly rounded
  result is within half a spacing of the exact one on either side, so the neighbour bounds it;
  an overflowed bound (a lower bound of +inf) becomes the largest finite float, 0 the smallest
  subnormal;
* ``k = 1`` for a sum (``absolute=False``): by ``eps |x|`` (at least one spacing: ``ulp(x) <=
  eps |x|`` for normal ``x``; and nothing below the normal range, where a sum of floats is
  exact, so a zero sum stays exact);
* ``k >= 2``: to the neighbouring float, then by the relative offset ``2 (k - 1) eps |x|``
  (``ulp(x) <= eps |x|`` for normal ``x``; the factor 2 absorbs the rounding of the offset's
  own addition), plus the smallest subnormal when ``absolute`` (results in the subnormal range
  or underflowed to 0).

While traced (``torch.compile``, the captured online step), `down` / `up` take one additive
step instead (`_traced_step`): ``x -+ (2k - 1) eps max(|x|, floor / eps)``, with ``floor =
2^-511`` in float64 (`traced_floor`). That is at least ``k`` ulps for every ``x``, in four
elementwise ops that the compiler fuses, and it never makes a subnormal number: a bound near 0
moves out to at least ``+-floor``, so products of two bounds stay in the normal range.
Arithmetic on subnormal numbers takes a slow path on x86 CPUs (a compiled HSNSMF step at
B = 10,000 ran 1.75x slower with them). The price is an absolute looseness of at most
``floor`` (1.5e-154) per rounding, near 0 only.

`outward` rounds bounds stacked as one tensor ``[2, ...]`` (lower, upper) in the same ops.
Gradients of the bounds flow unchanged (``nextafter`` passes the gradient of its first
argument; offsets are computed on detached values and added).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

from diffsmf.utils import materialize, tracing

__all__ = ["down", "eps", "finite_inner", "nan_to_zero", "outward", "pair_const", "pair_signs",
           "subnormal", "tiny", "traced_floor", "traced_program", "up"]


def eps(t: Tensor) -> float:
    """Machine epsilon of ``t``'s dtype."""
    return torch.finfo(t.dtype).eps


def tiny(t: Tensor) -> float:
    """Smallest positive normal number of ``t``'s dtype."""
    return torch.finfo(t.dtype).tiny


def subnormal(t: Tensor) -> float:
    """Smallest positive subnormal number of ``t``'s dtype."""
    fi = torch.finfo(t.dtype)
    return fi.tiny * fi.eps


def nan_to_zero(t: Tensor) -> Tensor:
    """``0 * inf := 0`` (the interval convention for products of a zero and an infinite bound)."""
    return torch.where(torch.isnan(t), torch.zeros_like(t), t)


def _step(x: Tensor, k: int, direction: float, absolute: bool) -> Tensor:
    """Move ``x`` outward by at least ``k`` ulps towards ``direction`` (+-inf): one
    ``nextafter`` (an overflowed bound, a lower bound of +inf, becomes the largest finite
    float), then for ``k >= 2`` the relative offset ``2 (k - 1) eps |x|`` (+ the smallest
    subnormal when ``absolute``); a sum (``absolute=False``, ``k = 1``) by ``eps |x|``; while
    traced, every other rounding by `_traced_step`."""
    if k <= 0:
        return x
    if k == 1 and not absolute:  # a sum: eps |x| (one ulp or more; 0 below the normal range,
        big = torch.finfo(x.dtype).max  # where a sum of floats is exact)
        x = x.clamp(max=big) if direction < 0 else x.clamp(min=-big)
        return torch.add(x, _nograd(x).abs(), alpha=eps(x) if direction > 0 else -eps(x))
    if tracing():
        return _traced_step(x, k, direction)
    t = _TARGETS.get((direction, x.dtype, x.device))
    if t is None:
        t = torch.tensor(direction, dtype=x.dtype, device=x.device)
        _TARGETS[(direction, x.dtype, x.device)] = t
    out = torch.nextafter(x, t)
    if k == 1:
        return out
    # then k - 1 ulps more, relatively (the first step made an overflowed bound finite)
    pad = _nograd(out).abs() * (2.0 * (k - 1) * eps(x))
    if absolute:
        pad = pad + subnormal(x)
    return out + pad if direction > 0 else out - pad


def traced_floor(dtype: torch.dtype) -> float:
    """The least move of a traced rounding step: ``2^floor(e / 2)`` for the least normal
    exponent ``e`` of ``dtype`` (float64: ``2^-511``, float32: ``2^-63``), so that the
    product of two such numbers is still normal."""
    return 2.0 ** math.floor(math.log2(torch.finfo(dtype).tiny) / 2)


def _traced_step(x: Tensor, k: int, direction: float) -> Tensor:
    """``x`` moved by at least ``k`` ulps towards ``direction`` (+-inf), while traced:
    ``x + (2k - 1) eps max(|x|, floor / eps)`` (`traced_floor`), an overflowed bound made the
    largest finite float first; NaN stays NaN, an infinity in ``direction`` stays.

    Why it is enough: for normal ``x``, ``ulp(x) <= eps |x|``, and the ``k``-th neighbour is
    at most ``(2k - 1) ulp(x)`` away (a crossing into the next binade doubles the spacing
    after the first step only where ``|x|`` is near the binade's top, where ``eps |x|`` is
    near ``2 ulp(x)``). The factor ``(2k - 1) eps`` is exact, and for ``k >= 2`` its product
    with ``|x|`` keeps a margin over its own rounding. Near 0 the move is at least
    ``floor``, far above the ``k`` subnormal spacings needed there. The sum is then rounded to
    nearest, which cannot fall below the float it exceeds. Gradients pass through ``x``."""
    fi = torch.finfo(x.dtype)
    x = x.clamp(min=-fi.max) if direction > 0 else x.clamp(max=fi.max)
    step = (2 * k - 1) * fi.eps
    return torch.add(x, _traced_magnitude(x), alpha=step if direction > 0 else -step)


def _traced_magnitude(x: Tensor) -> Tensor:
    """``max(|x|, floor / eps)`` without gradient: what `_traced_step` scales by
    ``(2k - 1) eps``."""
    return _nograd(x).abs().clamp_min(traced_floor(x.dtype) / torch.finfo(x.dtype).eps)


#: the 0-dim ``+-inf`` targets of ``nextafter`` per dtype and device (made once, eagerly)
_TARGETS: dict = {}


def _nograd(x: Tensor) -> Tensor:
    """``x`` detached where it records a gradient (``detach`` is an op of its own)."""
    return x.detach() if x.requires_grad else x


def down(x: Tensor, k: int = 1, absolute: bool = True) -> Tensor:
    """A lower bound ``x`` moved down by ``k`` ulps (see the module docstring)."""
    return _step(x, k, -math.inf, absolute)


def up(x: Tensor, k: int = 1, absolute: bool = True) -> Tensor:
    """An upper bound ``x`` moved up by ``k`` ulps (see the module docstring)."""
    return _step(x, k, math.inf, absolute)


def _target(x: Tensor, rank: int) -> Tensor:
    """``[-inf, inf]`` shaped ``[2, 1, ..., 1]`` (``rank`` dims) in ``x``'s dtype and device."""
    return _pair_const(x, rank, -math.inf, math.inf)


def _pair_const(x: Tensor, rank: int, lo: float, hi: float) -> Tensor:
    """``[lo, hi]`` shaped ``[2, 1, ..., 1]`` (``rank`` dims) like ``x`` (cached eagerly, and
    within a `traced_program` block while traced)."""
    key = (lo, hi, rank, x.dtype, x.device)
    memo = _MEMO.consts if tracing() else _TARGETS
    t = None if memo is None else memo.get(key)
    if t is None:
        t = torch.tensor([lo, hi], dtype=x.dtype, device=x.device).reshape(2, *([1] * (rank - 1)))
        if memo is not None:
            memo[key] = t
    return t


class _Memo(threading.local):
    def __init__(self) -> None:  # (an instance attribute from the start: Dynamo guards on it)
        self.consts: dict | None = None  # a dict inside a `traced_program` block, else None


_MEMO = _Memo()


@contextmanager
def traced_program() -> Iterator[None]:
    """While traced, the block of one program run of the engine. Within it, each per-bound
    constant (`pair_const`) is made once and reused (one graph constant instead of one per
    rounding; the memo is dropped at the block's end, so no traced tensor outlives the trace),
    and each result of `outward` is realised into a buffer (`utils.materialize`)."""
    prev = _MEMO.consts
    _MEMO.consts = {}
    try:
        yield
    finally:
        _MEMO.consts = prev


def _in_traced_program() -> bool:
    return _MEMO.consts is not None


def pair_const(x: Tensor, rank: int, lo: float, hi: float) -> Tensor:
    """``[lo, hi]`` shaped ``[2, 1, ..., 1]`` (``rank`` dims) like ``x`` (cached eagerly):
    a per-bound constant of stacked bounds."""
    return _pair_const(x, rank, lo, hi)


def pair_signs(x: Tensor, rank: int) -> Tensor:
    """``[-1, 1]`` shaped ``[2, 1, ..., 1]`` (``rank`` dims): the outward direction of stacked
    bounds."""
    return _pair_const(x, rank, -1.0, 1.0)


def finite_inner(both: Tensor) -> Tensor:
    """Stacked bounds ``[2, ...]`` whose lower bound overflowed to +inf (or upper to -inf) made
    the largest finite float, like ``nextafter``; other bounds unchanged (one op)."""
    big = torch.finfo(both.dtype).max
    return torch.clamp(both, min=_pair_const(both, both.dim(), -math.inf, -big),
                       max=_pair_const(both, both.dim(), big, math.inf))


def outward(both: Tensor, k: int = 1, absolute: bool = True, point: bool = False) -> Tensor:
    """Bounds stacked as ``both [2, ...]`` (lower, upper) moved outward like `down` / `up`, in
    one op for ``k = 1``; ``point``: ``both`` is one tensor ``[...]`` (a point, the computed
    value of both bounds) and the result is ``[2, ...]``."""
    rank = both.dim() + 1 if point else both.dim()
    if not absolute and k == 1:  # a sum: see _step
        if point:
            big = torch.finfo(both.dtype).max
            t = both.clamp(-big, big)
        else:
            t = finite_inner(both)
        e = eps(both)
        return torch.addcmul(t, _pair_const(both, rank, -e, e), _nograd(t).abs())
    if tracing():  # _traced_step on both bounds: [-1, 1] (2k - 1) eps max(|x|, floor / eps)
        x = finite_inner(torch.stack([both, both]) if point else both)
        e = (2 * k - 1) * eps(x)
        out = torch.addcmul(x, _pair_const(x, rank, -e, e), _traced_magnitude(x))
        # in a program run, each rounded result is computed once into a buffer: Inductor would
        # otherwise inline the chains of stacked ops into every consumer, which lengthens
        # the cold compiles by a fifth or more
        return materialize(out) if _in_traced_program() else out
    out = torch.nextafter(both, _target(both, rank))
    if k > 1:  # then k - 1 ulps more, relatively (see _step); the first step made inf finite
        pad = _nograd(out).abs() * (2.0 * (k - 1) * eps(both))
        if absolute:
            pad = pad + subnormal(both)
        out = torch.addcmul(out, pair_signs(both, rank), pad)
    return out
