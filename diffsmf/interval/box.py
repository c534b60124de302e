"""The axis-aligned box set ``{x : lower <= x <= upper}`` (Song et al. 2017, sec. 3).

An `Interval` holds ``lower`` and ``upper`` tensors of one shape. It plays two roles:

* an *array of intervals* of any shape (scalars, vectors, interval matrices ``[..., k, n]``)
  with tensor-like indexing/reshaping; its operators, methods and ``__torch_function__`` hook
  delegate to the outward-rounded Moore arithmetic of `diffsmf.interval.arith`, so that a plain
  torch function evaluated on Intervals returns its natural interval extension
  (`interval_eval`);
* the *box set* ``{x : lower <= x <= upper}`` in R^n (last dim ``n``, leading batch dims) with
  every method of `ConvexSet`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, as_tensor, as_vector, check_count, family, strip_fields
from diffsmf.interval import arith
from diffsmf.interval.arith import IntervalArray, Stacked, as_interval, is_number
from diffsmf.interval.rounding import down, eps, up
from diffsmf.interval.torch_hooks import TORCH_IMPL, wrap_out
from diffsmf.utils import checking

__all__ = ["Interval", "interval_eval"]


# ---------------------------------------------------------------------------- the class
class Interval(ConvexSet, IntervalArray):
    """Interval array / axis-aligned box ``{x : lower <= x <= upper}``.

    Args:
        lower: ``[...]`` lower bounds (as a set: ``[..., n]``).
        upper: ``[...]`` upper bounds, broadcastable with ``lower``; ``None`` = point interval.

    Raises ``ValueError`` naming the argument on NaN, non-broadcastable shapes or
    ``lower > upper``. Infinite bounds are allowed.
    """

    _fields: ClassVar[tuple[str, ...]] = ("lower", "upper")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 1)
    lower: Tensor
    upper: Tensor

    def __init__(self, lower: Any, upper: Any = None) -> None:
        lo = as_tensor("lower", lower, field=True)
        hi = lo if upper is None else as_tensor("upper", upper, like=lo, field=True)
        try:
            lo, hi = torch.broadcast_tensors(lo, hi)
        except RuntimeError as exc:
            raise ValueError(
                f"upper: shape {tuple(hi.shape)} does not broadcast with lower {tuple(lo.shape)}"
            ) from exc
        if checking() and (lo.detach() > hi.detach()).any():
            raise ValueError("lower: must be <= upper elementwise")
        self._set(lower=lo, upper=hi)

    @classmethod
    def _pair(cls, both: Tensor) -> Interval:
        """An Interval from its bounds stacked as ``both [2, ...]`` (internal: the engine's
        arithmetic then treats both bounds in one op; see `diffsmf.interval.arith.Stacked`)."""
        return _StackedInterval._new(both)

    @classmethod
    def from_center_radius(cls, center: Any, radius: Any) -> Interval:
        """Box ``[c - r, c + r]`` (bounds rounded outward); ``radius >= 0`` elementwise."""
        c = as_tensor("center", center, field=True)
        r = as_tensor("radius", radius, like=c, field=True)
        if checking() and (r.detach() < 0).any():
            raise ValueError("radius: must be >= 0")
        return cls._make(down(c - r), up(c + r))

    @classmethod
    def point(cls, x: Any) -> Interval:
        """Degenerate interval ``[x, x]``."""
        t = as_tensor("x", x, field=True)
        return cls._make(t, t)

    # ------------------------------------------------------------------ tensor-like structure
    @property
    def batch_shape(self) -> torch.Size:
        """Leading dims (from the shapes alone: no midpoint is computed)."""
        return torch.broadcast_shapes(self.lower.shape, self.upper.shape)[:-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.lower.dtype

    @property
    def center(self) -> Tensor:
        """Midpoint ``(lower + upper) / 2``, shape of the interval."""
        return 0.5 * (self.lower + self.upper)

    @property
    def radius(self) -> Tensor:
        """Half-width ``(upper - lower) / 2``."""
        return 0.5 * (self.upper - self.lower)

    @property
    def width(self) -> Tensor:
        return self.upper - self.lower

    def mid_rad(self) -> tuple[Tensor, Tensor]:
        """Guaranteed midpoint-radius form: ``[c - r, c + r]`` contains the interval (reals)."""
        return arith.mid_rad(self)

    @property
    def shape(self) -> torch.Size:
        return self.lower.shape

    @property
    def ndim(self) -> int:
        return self.lower.dim()

    def numel(self) -> int:
        return self.lower.numel()

    def size(self, d: int | None = None) -> Any:
        return self.lower.size() if d is None else self.lower.size(d)

    def __len__(self) -> int:
        return len(self.lower)

    def __repr__(self) -> str:
        if self.lower.numel() <= 8:
            return f"Interval(lower={self.lower.tolist()}, upper={self.upper.tolist()})"
        return f"Interval(shape={tuple(self.shape)})"

    def __getitem__(self, idx: Any) -> Interval:
        """Index like a tensor over ALL dims (``x[..., 0]``, ``A[:, 1:]``)."""
        return Interval._make(self.lower[idx], self.upper[idx])

    def _map(self, fn: Callable[[Tensor], Tensor]) -> Interval:
        return Interval._make(fn(self.lower), fn(self.upper))

    def reshape(self, *shape: Any) -> Interval:
        return self._map(lambda t: t.reshape(*shape))

    view = reshape

    def unsqueeze(self, d: int) -> Interval:
        return self._map(lambda t: t.unsqueeze(d))

    def squeeze(self, *d: int) -> Interval:
        return self._map(lambda t: t.squeeze(*d))

    def transpose(self, d0: int, d1: int) -> Interval:
        return self._map(lambda t: t.transpose(d0, d1))

    def permute(self, *dims: Any) -> Interval:
        return self._map(lambda t: t.permute(*dims))

    def movedim(self, src: Any, dst: Any) -> Interval:
        return self._map(lambda t: t.movedim(src, dst))

    def flatten(self, start_dim: int = 0, end_dim: int = -1) -> Interval:
        return self._map(lambda t: t.flatten(start_dim, end_dim))

    def broadcast_to(self, shape: Sequence[int]) -> Interval:
        return self._map(lambda t: t.broadcast_to(shape))

    def clone(self) -> Interval:
        return self._map(torch.clone)

    @property
    def T(self) -> Interval:  # noqa: N802 - tensor naming
        return self._map(lambda t: t.T)

    @property
    def mT(self) -> Interval:  # noqa: N802 - tensor naming
        return self._map(lambda t: t.mT)

    # ------------------------------------------------------------------ arithmetic
    # (diffsmf.interval.arith: Moore arithmetic with outward rounding)
    def __neg__(self) -> Interval:
        return arith.neg(self)

    def __pos__(self) -> Interval:
        return self

    def __add__(self, other: Any) -> Interval:
        if is_number(other):
            return arith.shift(self, float(other))
        return arith.add(self, as_interval(other, self))

    def __radd__(self, other: Any) -> Interval:
        if is_number(other):
            return arith.shift(self, float(other))
        return arith.add(as_interval(other, self), self)

    def __sub__(self, other: Any) -> Interval:
        if is_number(other):
            return arith.shift(self, -float(other))
        return arith.add(self, -as_interval(other, self))

    def __rsub__(self, other: Any) -> Interval:
        if is_number(other):
            return arith.shift(-self, float(other))
        return arith.add(as_interval(other, self), -self)

    def __mul__(self, other: Any) -> Interval:
        if is_number(other):
            return arith.scale(self, float(other))
        return arith.mul(self, as_interval(other, self))

    def __rmul__(self, other: Any) -> Interval:
        if is_number(other):
            return arith.scale(self, float(other))
        return arith.mul(as_interval(other, self), self)

    def __truediv__(self, other: Any) -> Interval:
        return arith.div(self, as_interval(other, self))

    def __rtruediv__(self, other: Any) -> Interval:
        return arith.div(as_interval(other, self), self)

    def __pow__(self, p: Any) -> Interval:
        return arith.power(self, p)

    def __rpow__(self, base: Any) -> Interval:
        return arith.rpow(base, self)

    def __matmul__(self, other: Any) -> Interval:
        return arith.matmul(self, other)

    def __rmatmul__(self, other: Any) -> Interval:
        return arith.matmul(other, self)

    def __abs__(self) -> Interval:
        return self.abs()

    def reciprocal(self) -> Interval:
        """``1 / x``; see `diffsmf.interval.arith.div` for intervals containing 0."""
        return arith.reciprocal(self)

    def abs(self) -> Interval:
        """Exact range of ``|x|``."""
        return arith.absolute(self)

    def square(self) -> Interval:
        """Exact-range square: the four products, lower bound clamped at 0."""
        return arith.square(self)

    def sqrt(self) -> Interval:
        arith.check_domain(self, "sqrt", strict=False)
        return arith.monotone(self, torch.sqrt, 1, clamp_min=0.0)

    def exp(self) -> Interval:
        return arith.monotone(self, torch.exp, 2, clamp_min=0.0)

    def log(self) -> Interval:
        arith.check_domain(self, "log", strict=False)
        return arith.monotone(self, torch.log, 2)

    def tanh(self) -> Interval:
        return arith.monotone(self, torch.tanh, 2, clamp_min=-1.0, clamp_max=1.0)

    def sigmoid(self) -> Interval:
        return arith.monotone(self, torch.sigmoid, 2, clamp_min=0.0, clamp_max=1.0)

    def atan(self) -> Interval:
        return arith.monotone(self, torch.atan, 2)

    def softplus(self) -> Interval:
        return arith.monotone(self, torch.nn.functional.softplus, 2, clamp_min=0.0)

    def log1p(self) -> Interval:
        if checking() and bool((self.lower.detach() < -1).any()):  # else NaN, flagged
            low = float(self.lower.detach().min())
            raise ValueError(f"x: log1p needs lower >= -1, its argument reaches {low:.6g} "
                             "(interval leaves the domain)")
        return arith.monotone(self, torch.log1p, 2)

    def expm1(self) -> Interval:
        return arith.monotone(self, torch.expm1, 2, clamp_min=-1.0)

    def sinh(self) -> Interval:
        return arith.monotone(self, torch.sinh, 2)

    def erf(self) -> Interval:
        return arith.monotone(self, torch.erf, 2, clamp_min=-1.0, clamp_max=1.0)

    def cosh(self) -> Interval:
        """Exact range of ``cosh`` (even; minimum 1 at 0)."""
        return arith.monotone(self.abs(), torch.cosh, 2, clamp_min=1.0)

    def relu(self) -> Interval:
        return arith.relu(self)

    def clamp(self, min: Any = None, max: Any = None) -> Interval:  # noqa: A002
        return arith.clamp(self, min, max)

    def sin(self) -> Interval:
        """Exact range of ``sin`` (extrema inside the interval detected, batched)."""
        return arith.trig(self, torch.sin, phase_max=0.5 * math.pi, phase_min=-0.5 * math.pi)

    def cos(self) -> Interval:
        """Exact range of ``cos``."""
        return arith.trig(self, torch.cos, phase_max=0.0, phase_min=math.pi)

    def sum(self, dim: Any = None, keepdim: bool = False) -> Interval:
        """Sum over ``dim`` (all dims if ``None``) with a rounding-error margin."""
        return arith.total(self, dim, keepdim)

    def mean(self, dim: Any = None, keepdim: bool = False) -> Interval:
        n = self.numel() if dim is None else arith.count(self.shape, dim)
        return arith.total(self, dim, keepdim) / float(n)

    # ------------------------------------------------------------------ set API (box)
    def volume(self) -> Tensor:
        """Product of widths over the last dim, shape ``batch_shape``."""
        return self.width.prod(-1)

    def log_volume(self) -> Tensor:
        return torch.log(self.width).sum(-1)

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """``lower - atol <= x <= upper + atol`` for all components -> bool ``[...]``."""
        x = as_vector("x", x, self.lower, self.dim)
        return ((x >= self.lower - atol) & (x <= self.upper + atol)).all(-1)

    def support(self, d: Tensor) -> Tensor:
        """h(d) = sum_i max(d_i lower_i, d_i upper_i) (= d.c + |d|.r) -> ``[...]``."""
        d = as_vector("d", d, self.lower, self.dim)
        return torch.maximum(d * self.lower, d * self.upper).sum(-1)

    def interval_hull(self) -> Interval:
        return self

    def to_interval(self) -> Interval:
        return self

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> ConvexSet:
        """Exact image ``{A x + b}`` as a Zonotope(A c + b, A diag(r)); ``A [..., k, n]``."""
        A = as_tensor("A", A, like=self.lower, min_dim=2)
        if A.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., k, {self.dim}], got {tuple(A.shape)}")
        c, r = self.mid_rad()
        center = (A @ c.unsqueeze(-1)).squeeze(-1)
        if b is not None:
            center = center + as_tensor("b", b, like=self.lower)
        return family("Zonotope")(center, A * r.unsqueeze(-2))

    def translate(self, b: Tensor) -> Interval:
        b = as_tensor("b", b, like=self.lower)
        return Interval._make(down(self.lower + b), up(self.upper + b))

    def minkowski_sum(self, other: Any) -> ConvexSet:
        """Interval + Interval -> Interval (exact up to rounding); other sets delegate."""
        if isinstance(other, Interval):
            return arith.add(self, other)
        if isinstance(other, Tensor):
            return self.translate(other)
        return other.minkowski_sum(self)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` uniform points in the box -> ``[*batch_shape, k, n]``."""
        k = check_count("k", k)
        lo, hi = self.lower.unsqueeze(-2), self.upper.unsqueeze(-2)
        shape = (*self.batch_shape, k, self.dim)
        u = torch.rand(shape, generator=generator, dtype=self.dtype, device=self.device)
        return torch.minimum(torch.maximum(lo + u * (hi - lo), lo), hi)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` random corners of the box -> ``[*batch_shape, k, n]``."""
        k = check_count("k", k)
        lo, hi = self.lower.unsqueeze(-2), self.upper.unsqueeze(-2)
        shape = (*self.batch_shape, k, self.dim)
        u = torch.rand(shape, generator=generator, dtype=self.dtype, device=self.device)
        return torch.where(u < 0.5, lo, hi)

    def vertices(self) -> Tensor:
        """All ``2^n`` corners -> ``[*batch_shape, 2^n, n]`` (small n only)."""
        n = self.dim
        bits = torch.tensor(
            [[(i >> j) & 1 for j in range(n)] for i in range(2**n)], dtype=torch.bool
        ).to(self.device)
        return torch.where(bits, self.upper.unsqueeze(-2), self.lower.unsqueeze(-2))

    def _floored_radius(self, min_radius: float) -> tuple[Tensor, Tensor]:
        c, r = self.mid_rad()
        return c, torch.clamp(r, min=min_radius)

    def to_zonotope(self) -> ConvexSet:
        """Zonotope(c, diag(r)) (exact)."""
        c, r = self.mid_rad()
        return family("Zonotope")(c, torch.diag_embed(r))

    def to_parallelotope(self, min_radius: float = 1e-12) -> ConvexSet:
        """Parallelotope(c, diag(r)); radii below ``min_radius`` are floored (outer bound)."""
        c, r = self._floored_radius(min_radius)
        return family("Parallelotope")(c, torch.diag_embed(r))

    def to_ellipsoid(self, min_radius: float = 1e-12) -> ConvexSet:
        """Covering ellipsoid diag(n r_i^2) (Song et al. 2017, eq. 23/29 with the n-D erratum).

        Radii below ``min_radius`` are floored (the shape must be positive definite); the
        shape is inflated by ``4 eps`` relative so the corners are inside despite rounding.
        """
        c, r = self._floored_radius(min_radius)
        n = self.dim
        q = up(n * r * r * (1.0 + 4.0 * eps(r)))
        return family("Ellipsoid")(c, torch.diag_embed(q))

    def intersect(self, other: Interval) -> Interval:
        """Elementwise intersection; may be empty (check `is_empty`), not validated."""
        other = as_interval(other, self)
        return Interval._make(
            torch.maximum(self.lower, other.lower), torch.minimum(self.upper, other.upper)
        )

    def intersect_strip(self, strip: Any) -> Interval:
        """Interval hull of the box and ``strip`` ``{x : |a.x - y| <= w}`` (``normal``,
        ``offset``, ``halfwidth``), exact up to an outward rounding margin: for each ``j``
        with ``a_j != 0``, ``x_j`` lies in ``(y +- w - sum_{k != j} a_k x_k) / a_j``, the
        projection of the box cut by the strip (the revise step of interval constraint
        propagation, Jaulin et al. 2001). Infinite bounds are handled (an unbounded
        component leaves the others' bounds unbounded, never NaN). An empty intersection
        returns the box unchanged; `intersects_strip` flags it.
        """
        a, y, w = strip_fields(strip, self)  # a ValueError naming strip on a wrong dim
        y, w = y.unsqueeze(-1), w.unsqueeze(-1)
        lo, hi = self.lower, self.upper
        zero = a == 0
        t1, t2 = a * lo, a * hi
        t_lo = torch.minimum(t1, t2).masked_fill(zero, 0.0)  # a_j x_j over the box [..., n]
        t_hi = torch.maximum(t1, t2).masked_fill(zero, 0.0)
        other_lo, other_hi = _sum_of_others(t_lo), _sum_of_others(t_hi)
        num_lo, num_hi = y - w - other_hi, y + w - other_lo  # range of a_j x_j [..., n]
        a_safe = a.masked_fill(zero, 1.0)
        q1, q2 = num_lo / a_safe, num_hi / a_safe
        mag = (t_lo.abs() + t_hi.abs()).nan_to_num(posinf=0.0).sum(-1, keepdim=True)
        pad = 8 * (a.shape[-1] + 2) * eps(lo) * (y.abs() + w + mag) / a_safe.abs()
        new_lo = torch.where(zero, lo, torch.maximum(lo, torch.minimum(q1, q2) - pad))
        new_hi = torch.where(zero, hi, torch.minimum(hi, torch.maximum(q1, q2) + pad))
        empty = (new_lo > new_hi).any(-1, keepdim=True)
        return Interval._make(torch.where(empty, lo, new_lo), torch.where(empty, hi, new_hi))

    def is_empty(self) -> Tensor:
        """True where some component has ``lower > upper`` -> bool ``batch_shape``."""
        return (self.lower > self.upper).any(-1)

    def hull(self, other: Interval) -> Interval:
        """Smallest interval containing both (elementwise)."""
        other = as_interval(other, self)
        return Interval._make(
            torch.minimum(self.lower, other.lower), torch.maximum(self.upper, other.upper)
        )

    def subset_of(self, other: Interval) -> Tensor:
        other = as_interval(other, self)
        return ((self.lower >= other.lower) & (self.upper <= other.upper)).all(-1)

    # ------------------------------------------------------------------ torch integration
    @classmethod
    def __torch_function__(
        cls, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None
    ) -> Any:
        kwargs = kwargs or {}
        if getattr(func, "__name__", None) == "__rmatmul__":  # by name: see fix_dynamo_matmul
            impl = TORCH_IMPL[torch.Tensor.__rmatmul__]
        else:
            impl = TORCH_IMPL.get(func)
        if impl is None:
            return NotImplemented
        return impl(*args, **kwargs)



def _sum_of_others(t: Tensor) -> Tensor:
    """``sum_{k != j} t_k`` for every ``j`` ``[..., n]``, where ``t`` may hold ``inf`` terms of
    one sign: infinite where another term is, never ``inf - inf``."""
    inf = torch.isinf(t)
    finite = t.masked_fill(inf, 0.0)
    total = finite.sum(-1, keepdim=True)
    others_inf = inf.sum(-1, keepdim=True) - inf.to(torch.int64) > 0
    sign = torch.where(inf, t, torch.zeros_like(t)).sum(-1, keepdim=True).sign()
    return torch.where(others_inf, sign * torch.inf, total - finite)

class _StackedInterval(Stacked, Interval):
    """An Interval stored as one tensor ``both [2, ...]``; ``lower``/``upper`` are views."""

    @classmethod
    def _make(cls, lower: Tensor, upper: Tensor) -> Interval:
        return Interval._make(lower, upper)

    @classmethod
    def _from_tensors(cls, tensors: Sequence[Tensor]) -> ConvexSet:
        return Interval._from_tensors(tensors)


def interval_eval(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Natural interval extension: evaluate a plain torch function on Interval arguments.

    ``fn`` is written for tensors (``lambda x: torch.stack([x[..., 0] ** 2 * x[..., 1],
    torch.sin(x[..., 1])], -1)``); each Interval argument is propagated with the outward-correct
    Moore arithmetic of `diffsmf.interval.arith`, so the result encloses ``fn`` over the boxes.
    Tensor outputs (parts of ``fn`` independent of the Interval args) become point intervals;
    tuples are mapped.
    """
    return wrap_out(fn(*args, **kwargs), Interval)
