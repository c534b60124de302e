"""Derivative enclosures: interval jets with the tangent dimensions in front.

A `Jet` encloses, over every ``x`` in an input box, a tensor-valued intermediate quantity
``q(x)`` of a model program: its value ``val [*E, *s]``, its gradient ``grad [n, *E, *s]`` and
its Hessian ``hess [n, n, *E, *s]``, each an `Interval` array (``*E`` are
the caller's batch dims, ``*s`` the quantity's own shape as captured, ``n`` the number of
differentiation variables). With the tangent dimensions *leading*, every operation that only
moves values, and every linear one, applies to the value, the gradient and the Hessian
unchanged: the program's shape arguments refer to the trailing ``*s`` dims only.

``grad is None`` is a structurally zero gradient (a quantity that does not depend on ``x``,
e.g. an interval parameter); ``hess is None`` is a structurally zero Hessian (``q`` affine in
``x`` so far), so affine parts cost no Hessian arithmetic and an affine model is recognised
exactly. An entry of ``[-inf, inf]`` in ``grad`` or ``hess`` says that the derivative does not
exist there (a discontinuity, or a kink for the Hessian): the remainder bounds then fall back
to a bound of lower order for the outputs concerned.

The calculus (Song et al. 2017, sec. 3, interval extensions): for a unary ``phi`` with
enclosures ``phi(Q)``, ``phi'(Q)``, ``phi''(Q)`` over the value enclosure ``Q``::

    grad phi(q) = phi'(Q) grad q,   hess phi(q) = phi'(Q) hess q + phi''(Q) grad q grad q'

and the product rule for ``a * b``. A non-smooth ``phi`` passes the hull of its one-sided
derivatives (its Clarke generalised derivative), for which the mean-value inclusion still
holds (Lebourg's theorem), and ``[-inf, inf]`` as ``phi''`` where a kink lies in ``Q``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from diffsmf.interval import arith
from diffsmf.interval.arith import Stacked
from diffsmf.interval.box import Interval
from diffsmf.utils import tracing

__all__ = ["Jet", "chain", "hadd", "hull", "move", "mul", "nonsmooth", "point", "register_seed",
           "scaled"]


class Jet:
    """Interval enclosures of a value and its first two derivatives (tangent dims leading).

    Args:
        val: value enclosure ``[*E, *s]``.
        grad: gradient enclosure ``[n, *E, *s]`` or ``None`` (structurally zero).
        hess: Hessian enclosure ``[n, n, *E, *s]`` or ``None`` (structurally zero).
        order: 0 (values only), 1 (values and gradients) or 2.
        n: number of differentiation variables.
    """

    __slots__ = ("grad", "hess", "n", "order", "val")

    def __init__(
        self, val: Interval, grad: Interval | None, hess: Interval | None, order: int, n: int
    ) -> None:
        self.val = val
        self.grad = grad if order >= 1 else None
        self.hess = hess if order >= 2 else None
        self.order = order
        self.n = n

    def like(self, val: Interval, grad: Interval | None, hess: Interval | None) -> Jet:
        """A jet of the same order and variables."""
        return Jet(val, grad, hess, self.order, self.n)

    @property
    def shape(self) -> torch.Size:
        return arith.shape_of(self.val)

    def __repr__(self) -> str:
        return f"Jet(shape={tuple(self.shape)}, n={self.n}, order={self.order})"


def point(t: Tensor) -> Interval:
    """The degenerate interval ``[t, t]``."""
    return Interval._make(t, t)


def move(x: Any, fn: Callable[[Tensor], Tensor]) -> Any:
    """Apply a value-moving op to both bounds of an Interval (once for a point or for stacked
    bounds: ``fn`` must then act on trailing dims only, or on dims counted from the end; or to a
    tensor / None)."""
    if x is None:
        return None
    if isinstance(x, Stacked):
        return x._pair(fn(x.both))
    if isinstance(x, Interval):
        if x.lower is x.upper:
            t = fn(x.lower)
            return Interval._make(t, t)
        return Interval._make(fn(x.lower), fn(x.upper))
    return fn(x)


def hull(a: Interval, b: Interval) -> Interval:
    """Elementwise interval hull of two enclosures (broadcast)."""
    return Interval._make(torch.minimum(a.lower, b.lower), torch.maximum(a.upper, b.upper))


def lead(x: Interval, fn: Callable[[Tensor, int], Tensor]) -> Interval:
    """Apply ``fn(t, k)`` to the bounds of ``x``, where the tangent dims start at dim ``k``
    (1 for stacked bounds, else 0)."""
    if isinstance(x, Stacked):
        return x._pair(fn(x.both, 1))
    return move(x, lambda t: fn(t, 0))


def _outer(a: Interval, b: Interval) -> Interval:
    """``a_i b_j`` over the leading tangent dim -> ``[n, n, ...]``."""
    return arith.mul(lead(a, lambda t, k: t.unsqueeze(k + 1)),
                     lead(b, lambda t, k: t.unsqueeze(k)))


def _outer_sym(g: Interval, g2: Interval | None = None) -> Interval:
    """``g_i g_j`` (or ``g2_i g_j`` for ``g2 = c g``, ``c >= 0``) with exact squares on the
    diagonal (tighter than products)."""
    o = _outer(g if g2 is None else g2, g)
    if isinstance(o, Stacked):  # [2, n, n, ...]: the upper bounds of squares are >= 0 anyway
        t = o.both
        return o._pair(torch.where(_eye(t.shape[1], t.dim() - 3, t.device), t.clamp_min(0.0), t))
    n = g.lower.shape[0]
    eye = torch.eye(n, dtype=torch.bool, device=g.lower.device)
    eye = eye.reshape(n, n, *([1] * (g.lower.dim() - 1)))
    return Interval._make(torch.where(eye, o.lower.clamp_min(0.0), o.lower), o.upper)


#: Derivative sums keep an exact zero sum exact (True: two ops more a sum). False: every sum is
#: moved to its neighbouring floats (`diffsmf.interval.rounding.outward`, one op; a zero sum
#: becomes the smallest subnormals, like a product); value sums stay exact either way
EXACT_SUMS = False


def _eye(n: int, trailing: int, device: torch.device) -> Tensor:
    """Boolean identity ``[n, n, 1, ..., 1]`` (``trailing`` ones; cached eagerly)."""
    key = (n, trailing, device)
    e = _EYES.get(key)
    if e is None:
        e = torch.eye(n, dtype=torch.bool, device=device).reshape(n, n, *([1] * trailing))
        if not tracing():
            _EYES[key] = e
    return e


_EYES: dict = {}


def hadd(*hs: Interval | None) -> Interval | None:
    """Sum of enclosures where ``None`` is the structural zero (a zero sum rounded outward
    like any other: one op a bound)."""
    out = None
    for h in hs:
        if h is not None:
            out = h if out is None else arith.add(out, h, exact_zero=EXACT_SUMS)
    return out


def register_seed(g: Tensor) -> None:
    """Declare ``g [n, 1.., d]`` (a cached constant, eagerly) the gradient of an input box: a
    0 / 1 matrix with one 1 per column (column j is the variable of input element j). `chain`
    then forms ``phi'`` times it, and ``phi''`` times its outer product, by selection."""
    if tracing():
        return
    mask = g != 0
    both = mask.unsqueeze(1) & mask.unsqueeze(0)  # [n, n, 1.., d]: g_i g_j != 0
    _SEED_MASKS[id(g)] = (g, mask, both)


#: id of a seed gradient -> (the gradient, its non-zero mask, that of its outer product)
_SEED_MASKS: dict[int, tuple[Tensor, Tensor, Tensor]] = {}


def _select(mask: Tensor, d: Interval) -> Interval:
    """``g d`` for a 0 / 1 array ``g`` (``mask`` its non-zeros, tangent dims leading) and an
    enclosure ``d [*E, *s]``: ``d`` where ``g`` is 1, 0 elsewhere (``0 * inf := 0``, as
    `arith.mul` defines it), exactly: no product, no rounding."""
    if isinstance(d, Stacked):
        sd = d.both
        k = mask.dim() - (sd.dim() - 1)  # the tangent dims in front of d's
        lifted = sd.reshape(2, *([1] * k), *sd.shape[1:])
        return d._pair(torch.where(mask, lifted, 0.0))
    return Interval._make(torch.where(mask, d.lower, 0.0), torch.where(mask, d.upper, 0.0))


def chain(a: Jet, v: Interval, d1: Interval | None, d2: Interval | None) -> Jet:
    """``phi(a)`` from enclosures of ``phi``, ``phi'``, ``phi''`` over ``a.val`` (the factors
    ``[*E, *s]`` broadcast against the leading tangent dims). On an input box itself
    (`register_seed`: gradient 0 / 1, Hessian 0) the derivatives are selected, not
    multiplied."""
    if a.grad is None or d1 is None:
        return a.like(v, None, None)
    seed = _SEED_MASKS.get(id(a.grad.lower)) if a.hess is None and _SEED_MASKS else None
    if seed is not None and seed[0] is a.grad.lower and a.grad.upper is a.grad.lower:
        hess = _select(seed[2], d2) if a.order >= 2 and d2 is not None else None
        return a.like(v, _select(seed[1], d1), hess)
    grad = arith.mul(a.grad, d1)
    hess = None
    if a.order >= 2:
        h1 = None if a.hess is None else arith.mul(a.hess, d1)
        h2 = None if d2 is None else arith.mul(_outer_sym(a.grad), d2)
        hess = hadd(h1, h2)
    return a.like(v, grad, hess)


def scaled(a: Jet, s: float) -> Jet:
    """``s * a`` for a Python number ``s`` (two products per enclosure, not four)."""
    def f(t: Interval | None) -> Interval | None:
        return None if t is None else arith.scale(t, s)

    return a.like(f(a.val), f(a.grad), f(a.hess))


def mul(a: Jet | Tensor, b: Jet | Tensor) -> Jet:
    """Product rule, first and second order (``a is b`` uses exact squares)."""
    if not isinstance(a, Jet):
        a, b = b, a
    if isinstance(b, (int, float)) and not isinstance(b, bool):  # two products, not four
        return scaled(a, float(b))
    if not isinstance(b, Jet):  # jet times a constant tensor
        c = point(torch.as_tensor(b, dtype=a.val.lower.dtype, device=a.val.lower.device))
        return a.like(arith.mul(a.val, c), _scaled(a.grad, c, 1), _scaled(a.hess, c, 2))
    if a is b:
        return a.like(arith.square(a.val), *_square_derivs(a))
    grad = _mul_sum(a.grad, b.val, b.grad, a.val)
    hess = None
    if a.order >= 2:
        cross = None
        if a.grad is not None and b.grad is not None:
            o = _outer(a.grad, b.grad)
            cross = arith.add(o, lead(o, lambda t, k: t.transpose(k, k + 1)),
                              exact_zero=EXACT_SUMS)
        hess = hadd(_scaled(a.hess, b.val, 2), _scaled(b.hess, a.val, 2), cross)
    return a.like(arith.mul(a.val, b.val), grad, hess)


def _mul_sum(x1: Interval | None, y1: Interval, x2: Interval | None, y2: Interval
             ) -> Interval | None:
    """``x1 y1 + x2 y2`` for derivatives ``x1``, ``x2`` (None: structurally zero), the two
    products in one where `arith.mul_sum` applies (the same bounds)."""
    if x1 is not None and x2 is not None and not EXACT_SUMS:
        out = arith.mul_sum(x1, y1, x2, y2)
        if out is not None:
            return out
    return hadd(_scaled(x1, y1, 1), _scaled(x2, y2, 1))


def _square_derivs(a: Jet) -> tuple[Interval | None, Interval | None]:
    """``d(a^2) = 2 a da``, ``dd(a^2) = 2 (a dda + da da')`` (the factor 2 is exact)."""
    if a.grad is None:
        return None, None
    g = a.grad
    if g.lower is g.upper:  # a point gradient: 2 g is exact
        g2 = point(g.lower * 2.0)
        grad = arith.mul(g2, a.val)
        hess = None
        if a.order >= 2:
            hess = hadd(arith.scale(_scaled(a.hess, a.val, 2), 2.0) if a.hess is not None
                        else None, _outer_sym(g, g2))
        return grad, hess
    grad = arith.mul(g, arith.scale(a.val, 2.0))
    hess = None
    if a.order >= 2:
        hess = arith.scale(hadd(_scaled(a.hess, a.val, 2), _outer_sym(g)), 2.0)
    return grad, hess


def _scaled(t: Interval | None, c: Interval, k: int) -> Interval | None:
    """``t * c`` for a derivative ``t [n]*k + [*E, *s]`` and a factor ``c [*E, *s]`` (tensors
    broadcast from the right, and the ``k`` tangent dims lead: no reshaping)."""
    return None if t is None else arith.mul(t, c)


def nonsmooth(like: Interval) -> Interval:
    """``[-inf, inf]`` shaped like ``like``: a derivative that does not exist."""
    inf = torch.full_like(like.lower, torch.inf)
    return Interval._make(-inf, inf)
