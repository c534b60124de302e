"""Outward rounding of float bounds: the guarantee of every interval operation.

After an operation whose exact real result lies within ``k`` units in the last place of the
computed float (``k = 1`` for the correctly rounded IEEE ``+ - * / sqrt``, ``k = 2`` for library
transcendental functions), `down` / `up` move a lower / upper bound outward:

* ``k = 1``: to the neighbouring float (``torch.nextafter``, one op). A correctly rounded
  result is within half a spacing of the exact one on either side, so the neighbour bounds it;
  an overflowed bound (a lower bound of +inf) becomes the largest finite float, 0 becomes the
  smallest subnormal (unless ``absolute`` is False: a zero sum of floats is exact);
* ``k >= 2``: by the relative offset ``2 k eps |x|`` (``ulp(x) <= eps |x|`` for normal ``x``;
  the factor 2 absorbs the rounding of the offset's own addition), plus the smallest subnormal
  when ``absolute`` (results in the subnormal range or underflowed to 0).

Gradients of the bounds flow unchanged (``nextafter`` passes the gradient of its first
argument; the relative offset is computed on detached values and added).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffsmf.utils import tracing

__all__ = ["down", "eps", "nan_to_zero", "subnormal", "tiny", "up"]


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
    """Move ``x`` outward by at least ``k`` ulps towards ``direction`` (+-inf).

    An overflowed bound (a lower bound of +inf, an upper bound of -inf) first becomes the largest
    finite float, like ``nextafter``. On the CPU with autograd recording, a host check for
    infinities is cheaper than a clamp node on every call; elsewhere (no grad, tracing,
    accelerators: no host sync) the clamp is always applied.
    """
    if k <= 0:
        return x
    if k == 1:
        t = _TARGETS.get((direction, x.dtype, x.device))
        if t is None:
            t = torch.tensor(direction, dtype=x.dtype, device=x.device)
            if not tracing():
                _TARGETS[(direction, x.dtype, x.device)] = t
        out = torch.nextafter(x, t)
        return out if absolute else torch.where(x == 0, x, out)
    grad = x.requires_grad and torch.is_grad_enabled()
    if not grad or tracing() or x.device.type != "cpu" or bool(torch.isinf(x.detach()).any()):
        big = torch.finfo(x.dtype).max
        x = x.clamp(max=big) if direction < 0 else x.clamp(min=-big)
    pad = (x.detach() if grad else x).abs() * (2.0 * k * eps(x))
    if absolute:
        pad = pad + subnormal(x)
    return x + pad if direction > 0 else x - pad


#: the 0-dim ``+-inf`` targets of ``nextafter`` per dtype and device (made once, eagerly)
_TARGETS: dict = {}


def down(x: Tensor, k: int = 1, absolute: bool = True) -> Tensor:
    """A lower bound ``x`` moved down by ``k`` ulps (see the module docstring)."""
    return _step(x, k, -math.inf, absolute)


def up(x: Tensor, k: int = 1, absolute: bool = True) -> Tensor:
    """An upper bound ``x`` moved up by ``k`` ulps (see the module docstring)."""
    return _step(x, k, math.inf, absolute)
