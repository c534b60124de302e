"""Second-order forward-mode interval "jets": guaranteed Jacobian / Hessian enclosures over a box.

A :class:`Jet` carries, for every entry of a tensor-valued intermediate quantity ``q(x)`` of a
user function, three :class:`~diffsmf.sets.Interval` arrays enclosing, over all ``x`` in the
input box, its value ``q [...]``, its gradient ``dq/dx [..., n]`` and its Hessian
``d2q/dx2 [..., n, n]``. The propagation rules are the ordinary first/second-order chain, sum
and product rules, evaluated in the outward-rounded Moore arithmetic of ``Interval``
(Song et al. 2017, sec. 3 interval extensions, used here for the interval Hessian of Song et al.
2017, eq. 26-28 and for the DC parameter of Wang et al. 2022, eq. 15-16, erratum). For a unary
``phi``::

    grad phi(q) = phi'(Q) grad q,   hess phi(q) = phi'(Q) hess q + phi''(Q) grad q grad q'

with ``Q`` the value enclosure, so ``phi'`` and ``phi''`` are bounded over everything the
argument can take. Supported: ``+ - * /``, powers, ``exp log sqrt sin cos tanh sigmoid atan
square reciprocal abs atan2`` (abs only away from 0 for Hessians, atan2 away from its cut),
indexing, ``torch.stack/cat``,
``sum``, ``@`` / ``F.linear`` with constant matrices, mixing with constant tensors, numbers.
Anything else raises :class:`JetError` (a ``NotImplementedError`` and a ``ValueError``) naming
the operation: an unsupported torch function, a tensor method or attribute jets do not have
(``.detach()``, ``.numpy()``, ``.float()``, in-place ``.mul_()``), or a comparison of
state-dependent values (``x > 0``: a branch, which the remainder bounds cannot follow).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from diffsmf.sets.interval import Interval
from diffsmf.utils import checking

__all__ = ["Jet", "JetError", "interval_hessian", "interval_jacobian", "jet_eval"]

#: What a model function may use, said in every :class:`JetError`.
SUPPORTED = (
    "supported: + - * / **, exp log sqrt sin cos tanh sigmoid atan atan2 square reciprocal abs, "
    "indexing, stack, cat, sum, matmul / linear with constant matrices"
)


class JetError(NotImplementedError, ValueError):
    """A model function (``f`` or ``h``) uses something interval jets cannot enclose.

    The guaranteed remainders evaluate ``f`` and ``h`` over a whole box in interval-jet
    arithmetic (value, gradient and Hessian enclosures), so they must be smooth compositions of
    the supported operations. A ``ValueError`` (a user error: the CLI prints one line) and a
    ``NotImplementedError`` (what unsupported operations raised before).
    """


class _JetAttributeError(JetError, AttributeError):
    """A tensor method or attribute a :class:`Jet` does not have (keeps ``hasattr`` working)."""


def _model_hint(what: str) -> str:
    return (
        f"interval jets: {what}. The guaranteed remainders evaluate the model (f, h) over the "
        f"whole set in interval-jet arithmetic, so it must be a smooth composition of torch "
        f"operations on its argument ({SUPPORTED}; no numpy, .detach(), dtype casts, in-place "
        f"operations or branches on the state)"
    )

Const = Tensor | Interval | float | int


def _point(t: Any, like: Tensor) -> Interval:
    t = torch.as_tensor(t, dtype=like.dtype, device=like.device)
    return Interval(t, t)


def _unsq(c: Any, k: int) -> Any:
    """Append ``k`` singleton dims to a tensor / Interval (numbers unchanged)."""
    if isinstance(c, Interval):
        idx = (..., *([None] * k))
        return Interval._make(c.lower[idx], c.upper[idx])
    if isinstance(c, Tensor):
        return c[(..., *([None] * k))]
    return c


def _outer(a: Interval, b: Interval) -> Interval:
    """``a_i b_j`` -> ``[..., n, n]``."""
    return a.unsqueeze(-1) * b.unsqueeze(-2)


def _outer_sym(g: Interval) -> Interval:
    """``g_i g_j`` with the exact squares on the diagonal (tighter than products).

    The product enclosure of ``g_i g_i`` has the square's upper bound; its lower bound is the
    square's once clamped at 0 (the only product below the square's range is ``lo * hi < 0``).
    """
    o = _outer(g, g)
    n = g.shape[-1]
    eye = torch.eye(n, dtype=torch.bool, device=g.lower.device)
    return Interval._make(torch.where(eye, o.lower.clamp_min(0.0), o.lower), o.upper)


def _hadd(*hs: Interval | None) -> Interval | None:
    """Sum of Hessian enclosures where ``None`` is the structural zero."""
    out = None
    for h in hs:
        if h is not None:
            out = h if out is None else out + h
    return out


def _hmul(h: Interval | None, c: Any) -> Interval | None:
    """``h * c`` with ``None`` the structural zero (``c`` already broadcast to ``[..., 1, 1]``)."""
    return None if h is None else h * c


class Jet:
    """Interval enclosures of a value ``[...]``, gradient ``[..., n]`` and Hessian ``[..., n, n]``.

    ``hess`` is ``None`` in first-order mode (interval Jacobians only). In second-order mode
    the Hessian is stored as ``None`` while it is *structurally* zero (inputs, constants and
    affine expressions of them), so affine parts cost no Hessian arithmetic and an affine
    function is recognised exactly (:attr:`hess_is_zero`); :attr:`hess` materialises zeros.
    """

    __slots__ = ("_h", "grad", "order", "val")

    def __init__(
        self, val: Interval, grad: Interval, hess: Interval | None, order: int | None = None
    ) -> None:
        self.val = val
        shape = val.shape
        n = grad.shape[-1]
        self.grad = grad if grad.shape[:-1] == shape else grad.broadcast_to((*shape, n))
        if hess is not None and hess.shape[:-2] != shape:
            hess = hess.broadcast_to((*shape, n, n))
        self._h = hess
        self.order = order if order is not None else (1 if hess is None else 2)

    @property
    def hess(self) -> Interval | None:
        """Hessian enclosure ``[..., n, n]`` (``None`` in first-order mode)."""
        if self.order == 1:
            return None
        if self._h is None:
            lo = self.val.lower
            z = torch.zeros((*self.shape, self.n, self.n), dtype=lo.dtype, device=lo.device)
            return Interval._make(z, z)
        return self._h

    @property
    def hess_is_zero(self) -> bool:
        """True when the Hessian is structurally zero (the function is affine on R^n)."""
        return self.order == 2 and self._h is None

    # ---------------------------------------------------------------- structure
    @property
    def shape(self) -> torch.Size:
        return self.val.shape

    @property
    def ndim(self) -> int:
        return self.val.ndim

    def dim(self) -> int:
        return self.val.ndim

    def size(self, d: int | None = None) -> Any:
        return self.shape if d is None else self.shape[d]

    @property
    def n(self) -> int:
        return self.grad.shape[-1]

    def __repr__(self) -> str:
        return f"Jet(shape={tuple(self.shape)}, n={self.n}, order={self.order})"

    def __getattr__(self, name: str) -> Any:
        """Only called for names a Jet lacks: a tensor method the model used on its argument."""
        if name.startswith("__"):
            raise AttributeError(name)
        raise _JetAttributeError(_model_hint(f"the tensor method or attribute {name!r} is not "
                                             "supported"))

    def _compare(self, other: Any) -> Any:
        raise JetError(_model_hint("a comparison of state-dependent values (a branch such as "
                                   "x > 0, torch.where, clamp) is not supported"))

    __lt__ = __le__ = __gt__ = __ge__ = _compare

    def __bool__(self) -> bool:
        raise JetError(_model_hint("the truth value of a state-dependent value (if x: ...) is "
                                   "not defined"))

    def _const(self, c: Const) -> Jet:
        """Lift a constant (tensor, number or Interval) to a jet with zero derivatives."""
        like = self.val.lower
        v = c if isinstance(c, Interval) else _point(c, like)
        z = torch.zeros((*v.shape, self.n), dtype=like.dtype, device=like.device)
        return Jet(v, Interval._make(z, z), None, self.order)

    def _new(self, val: Interval, grad: Interval, hess: Interval | None) -> Jet:
        """A jet of the same order (``hess=None``: structural zero in second-order mode)."""
        return Jet(val, grad, hess, self.order)

    def __getitem__(self, idx: Any) -> Jet:
        if not isinstance(idx, tuple):
            idx = (idx,)
        s = slice(None)
        hess = None if self._h is None else self._h[idx + (s, s)]
        return self._new(self.val[idx], self.grad[idx + (s,)], hess)

    # ---------------------------------------------------------------- arithmetic
    def __neg__(self) -> Jet:
        return self._new(-self.val, -self.grad, None if self._h is None else -self._h)

    def __pos__(self) -> Jet:
        return self

    def __add__(self, other: Any) -> Jet:
        if isinstance(other, Jet):
            hess = _hadd(self._h, other._h)
            return self._new(self.val + other.val, self.grad + other.grad, hess)
        return self._new(self.val + other, self.grad, self._h)

    __radd__ = __add__

    def __sub__(self, other: Any) -> Jet:
        return self + (-other)

    def __rsub__(self, other: Any) -> Jet:
        return (-self) + other

    def __mul__(self, other: Any) -> Jet:
        if isinstance(other, Jet):
            return _mul(self, other)
        hess = _hmul(self._h, _unsq(other, 2))
        return self._new(self.val * other, self.grad * _unsq(other, 1), hess)

    __rmul__ = __mul__

    def __truediv__(self, other: Any) -> Jet:
        if isinstance(other, Jet):
            return self * other.reciprocal()
        hess = None if self._h is None else self._h / _unsq(other, 2)
        return self._new(self.val / other, self.grad / _unsq(other, 1), hess)

    def __rtruediv__(self, other: Any) -> Jet:
        return self.reciprocal() * other

    def __pow__(self, p: Any) -> Jet:
        if isinstance(p, Jet) or (isinstance(p, (Tensor, Interval)) and p.numel() != 1):
            return (self.log() * p).exp()
        pv = float(p.item() if isinstance(p, Tensor) else p)
        if pv == 0:
            return self._const(torch.ones(self.shape, dtype=self.val.lower.dtype))
        if pv == 1:
            return self
        if pv == 2:
            return _mul(self, self)
        x = self.val
        d2 = x ** (pv - 2) * (pv * (pv - 1)) if self.order == 2 else None
        return _chain(self, x**pv, x ** (pv - 1) * pv, d2)

    def __rpow__(self, base: Any) -> Jet:
        return (self * torch.log(torch.as_tensor(base, dtype=self.val.lower.dtype))).exp()

    def __matmul__(self, A: Any) -> Jet:
        return _matmul(self, A)

    def __rmatmul__(self, A: Any) -> Jet:
        return _rmatmul(A, self)

    # ---------------------------------------------------------------- elementary functions
    def square(self) -> Jet:
        return _mul(self, self)

    def exp(self) -> Jet:
        v = self.val.exp()
        return _chain(self, v, v, v)

    def log(self) -> Jet:
        r = self.val.reciprocal()
        return _chain(self, self.val.log(), r, -r.square())

    def sqrt(self) -> Jet:
        v = self.val.sqrt()
        d1 = v.reciprocal() * 0.5
        return _chain(self, v, d1, -(d1 * self.val.reciprocal()) * 0.5)

    def sin(self) -> Jet:
        v = self.val.sin()
        return _chain(self, v, self.val.cos(), -v)

    def cos(self) -> Jet:
        v = self.val.cos()
        return _chain(self, v, -self.val.sin(), -v)

    def tanh(self) -> Jet:
        v = self.val.tanh()
        d1 = 1.0 - v.square()
        return _chain(self, v, d1, v * d1 * (-2.0))

    def sigmoid(self) -> Jet:
        v = self.val.sigmoid()
        d1 = v * (1.0 - v)
        return _chain(self, v, d1, d1 * (1.0 - v * 2.0))

    def atan(self) -> Jet:
        d1 = (self.val.square() + 1.0).reciprocal()
        return _chain(self, self.val.atan(), d1, self.val * d1.square() * (-2.0))

    def reciprocal(self) -> Jet:
        v = self.val.reciprocal()
        return _chain(self, v, -v.square(), (v**3) * 2.0)

    def abs(self) -> Jet:
        lo, hi = self.val.lower, self.val.upper
        straddle = (lo < 0) & (hi > 0)
        if self.order == 2 and bool(straddle.detach().any()):
            raise JetError(
                "abs: interval Hessian of |q| is undefined where q's range contains 0 (the "
                "model is not smooth over the set)"
            )
        one = torch.ones_like(lo)
        d1 = Interval(torch.where(lo >= 0, one, -one), torch.where(hi <= 0, -one, one))
        zero = Interval(torch.zeros_like(lo), torch.zeros_like(lo))
        return _chain(self, self.val.abs(), d1, zero)

    def sum(self, dim: Any = None, keepdim: bool = False) -> Jet:
        nd = self.ndim
        dims = tuple(range(nd)) if dim is None else (dim,) if isinstance(dim, int) else dim
        dims = tuple(d % nd for d in dims)
        hess = None if self._h is None else self._h.sum(dims, keepdim)
        return self._new(self.val.sum(dims, keepdim), self.grad.sum(dims, keepdim), hess)

    # ---------------------------------------------------------------- torch hook
    @classmethod
    def __torch_function__(
        cls, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None
    ) -> Any:
        if getattr(func, "__name__", None) == "__rmatmul__":  # by name: see fix_dynamo_matmul
            impl = _TABLE[torch.Tensor.__rmatmul__]
        else:
            impl = _TABLE.get(func)
        if impl is None:
            name = getattr(func, "__name__", repr(func))
            raise JetError(_model_hint(f"torch operation {name!r} is not supported"))
        return impl(*args, **(kwargs or {}))


# -------------------------------------------------------------------- rules
def _mul(a: Jet, b: Jet) -> Jet:
    """Product rule, first and second order (``a is b`` uses exact squares)."""
    if a is b:
        grad = a.grad * _unsq(a.val, 1) * 2.0
        hess = None
        if a.order == 2:
            hess = _hadd(_hmul(a._h, _unsq(a.val, 2)), _outer_sym(a.grad)) * 2.0
        return a._new(a.val.square(), grad, hess)
    grad = a.grad * _unsq(b.val, 1) + b.grad * _unsq(a.val, 1)
    hess = None
    if a.order == 2:
        o = _outer(a.grad, b.grad)
        hess = _hadd(_hmul(a._h, _unsq(b.val, 2)), _hmul(b._h, _unsq(a.val, 2)), o + o.mT)
    return a._new(a.val * b.val, grad, hess)


def _chain(a: Jet, v: Interval, d1: Interval, d2: Interval | None) -> Jet:
    """``phi(a)`` from enclosures of ``phi``, ``phi'``, ``phi''`` over ``a.val``."""
    grad = a.grad * _unsq(d1, 1)
    hess = None
    if a.order == 2:
        hess = _hadd(_hmul(a._h, _unsq(d1, 2)), _outer_sym(a.grad) * _unsq(d2, 2))
    return a._new(v, grad, hess)


def _as_matrix(A: Any, like: Tensor) -> Tensor:
    if isinstance(A, (Jet, Interval)):
        raise JetError("interval jets: matmul supports constant (tensor) matrices only")
    return torch.as_tensor(A, dtype=like.dtype, device=like.device)


def _matmul(x: Jet, A: Any) -> Jet:
    """``x @ A`` with ``x [..., m]`` and a constant ``A [m, k]`` or ``[m]``."""
    A = _as_matrix(A, x.val.lower)
    if A.dim() > 2:
        raise JetError("interval jets: x @ A needs a 1-D or 2-D constant A")
    At = A.mT if A.dim() == 2 else A  # [k, m] or [m]
    n = x.n
    grad = At @ x.grad  # [..., k, n]
    hess = None
    if x._h is not None:
        Hf = x._h.reshape(*x._h.shape[:-2], n * n)  # [..., m, n*n]
        hess = At @ Hf
        hess = hess.reshape(*hess.shape[:-1], n, n)
    return x._new(x.val @ A, grad, hess)


def _rmatmul(A: Any, x: Jet) -> Jet:
    """``A @ x`` with a constant ``A [k, m]`` and an unbatched jet ``x [m]``."""
    A = _as_matrix(A, x.val.lower)
    if x.ndim != 1:
        raise JetError("interval jets: A @ x needs a 1-D x; write x @ A.T instead")
    return _matmul(x, A.mT if A.dim() == 2 else A)


def _linear(x: Jet, weight: Tensor, bias: Tensor | None = None) -> Jet:
    out = _matmul(x, weight.mT)
    return out if bias is None else out + bias


def _lift_all(items: Sequence[Any]) -> list[Jet]:
    ref = next(t for t in items if isinstance(t, Jet))
    jets = [t if isinstance(t, Jet) else ref._const(t) for t in items]
    shape = torch.broadcast_shapes(*[j.shape for j in jets])
    return [j if j.shape == shape else j + ref._const(torch.zeros(shape)) for j in jets]


def _stack(items: Sequence[Any], dim: int = 0, *, out: Any = None) -> Jet:
    jets = _lift_all(items)
    d = dim % (jets[0].ndim + 1)
    hess = None
    if any(j._h is not None for j in jets):
        hess = torch.stack([j.hess for j in jets], d)
    return jets[0]._new(
        torch.stack([j.val for j in jets], d), torch.stack([j.grad for j in jets], d), hess
    )


def _cat(items: Sequence[Any], dim: int = 0, *, out: Any = None) -> Jet:
    jets = [t if isinstance(t, Jet) else None for t in items]
    ref = next(j for j in jets if j is not None)
    jets = [t if isinstance(t, Jet) else ref._const(t) for t in items]
    d = dim % jets[0].ndim
    hess = None
    if any(j._h is not None for j in jets):
        hess = torch.cat([j.hess for j in jets], d)
    val, grad = torch.cat([j.val for j in jets], d), torch.cat([j.grad for j in jets], d)
    return jets[0]._new(val, grad, hess)


def _where(cond: Tensor, a: Jet, b: Jet) -> Jet:
    """Elementwise select between two jets of one shape (``cond`` over the value dims)."""
    hess = None
    if a._h is not None or b._h is not None:
        hess = torch.where(cond[..., None, None], a.hess, b.hess)
    val, grad = torch.where(cond, a.val, b.val), torch.where(cond[..., None], a.grad, b.grad)
    return a._new(val, grad, hess)


def _atan2(y: Any, x: Any) -> Jet:
    """``atan2(y, x)`` away from its branch cut: ``atan(y/x)`` where ``x > 0`` on the box,
    ``+-pi/2 - atan(x/y)`` where ``y > 0`` / ``y < 0``; boxes meeting the cut (x <= 0, y
    straddling 0) raise (the function is discontinuous there), except inside a filter step
    or while traced (`diffsmf.utils.checking` False), where those elements get NaN bounds
    (the filter flags them: ``FilterEvent.DOMAIN``) and the others are unaffected."""
    y, x = _lift_all([y, x])
    xpos = x.val.lower > 0
    ypos = y.val.lower > 0
    yneg = y.val.upper < 0
    cut = ~(xpos | ypos | yneg)
    if checking():
        if bool(cut.any()):
            raise JetError("atan2: the box meets the branch cut (x <= 0, y = 0)")
        return _atan2_off_cut(y, x, xpos, ypos)
    out = _atan2_off_cut(y, x, xpos, ypos)
    return _where(cut, _nan_jet(out), out)


def _nan_jet(j: Jet) -> Jet:
    """A jet like ``j`` whose every bound is NaN (a domain exit, flagged by the filters)."""
    def nan(iv: Interval) -> Interval:
        t = torch.full_like(iv.lower, math.nan)
        return Interval._make(t, t)

    return j._new(nan(j.val), nan(j.grad), None if j._h is None else nan(j._h))


def _atan2_off_cut(y: Jet, x: Jet, xpos: Tensor, ypos: Tensor) -> Jet:
    """``atan2(y, x)`` of `_atan2` on boxes that do not meet the branch cut."""
    lo = y.val.lower
    h = math.pi / 2
    inf = torch.full_like(lo, math.inf)
    half_pi = Interval(torch.nextafter(torch.full_like(lo, h), -inf),
                       torch.nextafter(torch.full_like(lo, h), inf))
    right = (y / x).atan()
    side = -((x / y).atan())
    upper = side + half_pi
    lower = side - half_pi
    return _where(xpos, right, _where(ypos, upper, lower))


def _dispatch(name: str, rname: str) -> Callable[[Any, Any], Any]:
    """``x <op> y`` calling the Jet's own (reflected) method, never back into torch."""

    def op(x: Any, y: Any) -> Any:
        return getattr(x, name)(y) if isinstance(x, Jet) else getattr(y, rname)(x)

    return op


def _binary(name: str, rname: str, swap: bool = False) -> Callable[..., Any]:
    op = _dispatch(name, rname)

    def f(x: Any, y: Any, *args: Any, **kwargs: Any) -> Any:
        if args or kwargs:
            raise JetError(f"interval jets: extra arguments {args} {kwargs}")
        return op(y, x) if swap else op(x, y)

    return f


def _unary(name: str) -> Callable[..., Jet]:
    def f(x: Jet, *args: Any, **kwargs: Any) -> Jet:
        return getattr(x, name)(*args, **kwargs)

    return f


def _build_table() -> dict[Any, Callable[..., Any]]:
    T = torch.Tensor
    table: dict[Any, Callable[..., Any]] = {}
    groups: list[tuple[tuple[Any, ...], Callable[..., Any]]] = [
        ((torch.add, T.add, T.__add__, T.__radd__), _binary("__add__", "__radd__")),
        ((torch.sub, torch.subtract, T.sub, T.__sub__), _binary("__sub__", "__rsub__")),
        ((T.__rsub__, torch.rsub), _binary("__sub__", "__rsub__", swap=True)),
        ((torch.mul, torch.multiply, T.mul, T.__mul__, T.__rmul__), _binary("__mul__", "__rmul__")),
        ((torch.div, torch.divide, torch.true_divide, T.div, T.__truediv__),
         _binary("__truediv__", "__rtruediv__")),
        ((T.__rtruediv__,), _binary("__truediv__", "__rtruediv__", swap=True)),
        ((torch.matmul, T.matmul, T.__matmul__), _binary("__matmul__", "__rmatmul__")),
        ((T.__rmatmul__,), _binary("__matmul__", "__rmatmul__", swap=True)),
        ((torch.pow, T.pow, T.__pow__), _binary("__pow__", "__rpow__")),
        ((T.__rpow__,), _binary("__pow__", "__rpow__", swap=True)),
        ((torch.neg, torch.negative, T.neg, T.__neg__), lambda x: -x),
        ((torch.stack,), _stack),
        ((torch.cat, torch.concat), _cat),
        ((torch.sum, T.sum), _unary("sum")),
        ((F.linear,), _linear),
        ((torch.atan2, torch.arctan2, T.atan2), _atan2),
    ]
    for fns, impl in groups:
        for fn in fns:
            table[fn] = impl
    for name in ("sin", "cos", "exp", "log", "sqrt", "tanh", "sigmoid", "atan", "square",
                 "reciprocal", "abs"):
        table[getattr(torch, name)] = _unary(name)
        table[getattr(T, name)] = _unary(name)
    table[torch.arctan] = _unary("atan")
    table[torch.absolute] = _unary("abs")
    table[T.__abs__] = _unary("abs")
    return table


_TABLE = _build_table()


# -------------------------------------------------------------------- entry points
def _seed(box: Interval, order: int) -> Jet:
    """The identity jet of the input box ``[..., n]``: grad = I, hess = 0."""
    lo = box.lower
    n = box.shape[-1]
    eye = torch.eye(n, dtype=lo.dtype, device=lo.device).expand(*box.shape, n)
    return Jet(box, Interval._make(eye, eye), None, order)  # Hessian: structural zero


def jet_eval(fn: Callable[[Any], Any], box: Interval, order: int = 2) -> Jet:
    """Evaluate ``fn`` on the box ``[..., n]`` in jet arithmetic -> Jet of shape ``[..., k]``.

    ``out.val`` encloses ``fn`` over the box, ``out.grad`` its Jacobian ``[..., k, n]`` and
    (order 2) ``out.hess`` the Hessians ``[..., k, n, n]``.
    """
    if not isinstance(box, Interval) or box.ndim < 1:
        raise ValueError("box: expected an Interval of shape [..., n]")
    if order not in (1, 2):
        raise ValueError(f"order: expected 1 or 2, got {order}")
    x = _seed(box, order)
    out = fn(x)
    if not isinstance(out, Jet):  # fn does not depend on x
        out = x._const(out)
    if out.ndim < 1:
        raise ValueError("fn: must return shape [..., k]")
    return out


def interval_jacobian(fn: Callable[[Any], Any], box: Interval) -> Interval:
    """Guaranteed enclosure of the Jacobian of ``fn`` over ``box [..., n]`` -> ``[..., k, n]``.

    Interval extension (Song et al. 2017, sec. 3.2) of the derivative; used for the mean-value form
    of the parameter deviation (Song et al. 2017, eq. 18-21).
    """
    return jet_eval(fn, box, order=1).grad


def interval_hessian(fn: Callable[[Any], Any], box: Interval) -> Interval:
    """Guaranteed enclosure of the Hessians of ``fn`` over ``box`` -> ``[..., k, n, n]``.

    Interval Hessian of Song et al. 2017, eq. 26-28 (there written for the Lagrange remainder).
    """
    out = jet_eval(fn, box, order=2)
    assert out.hess is not None
    return out.hess
