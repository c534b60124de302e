"""Intervals: Moore interval arithmetic (Song et al. 2017, sec. 3) and the axis-aligned box set.

An `Interval` holds ``lower`` and ``upper`` tensors of one shape. It plays two roles:

* an *array of intervals* of any shape (scalars, vectors, interval matrices ``[..., k, n]``)
  with outward-correct Moore arithmetic, tensor-like indexing/reshaping and a
  ``__torch_function__`` hook, so that a plain torch function evaluated on Intervals returns its
  natural interval extension (`interval_eval`);
* the *box set* ``{x : lower <= x <= upper}`` in R^n (last dim ``n``, leading batch dims) with
  every method of `ConvexSet`.

Outward rounding (guarantee): after every arithmetic operation the lower bound is moved down and
the upper bound up by at least ``k`` units in the last place, by the relative offset
``2 k eps |x|`` (plus the smallest subnormal for all but sums; see `_step`) -- a few
elementwise ops, cheaper than ``torch.nextafter`` with inf guards (``k = 1`` for correctly
rounded IEEE operations ``+ - * / sqrt``, ``k = 2`` for library transcendental functions
``exp log sin cos tanh atan sigmoid``, ``k = |p| + 1`` for ``x ** p`` computed by
``torch.pow``). Sums and matrix products add the classical a-priori bound
``gamma_k * sum |terms|`` (``gamma_k = (k + 4) eps``) before rounding. The rounding offsets are
computed on detached values and added, so gradients of ``lower``/``upper`` flow unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from diffsmf.interval.rounding import down, eps, nan_to_zero, subnormal, tiny, up
from diffsmf.sets.base import ConvexSet, as_tensor, as_vector, check_count, family
from diffsmf.utils import checking, tracing

__all__ = ["Interval", "interval_eval"]

_TWO_PI = 2.0 * math.pi


# ---------------------------------------------------------------------------- rounding helpers
# one home: diffsmf.interval.rounding (aliases keep this module's names)
_down = down
_up = up
_eps = eps
_tiny = tiny
_subnormal = subnormal
_nan0 = nan_to_zero


# ---------------------------------------------------------------------------- the class
class Interval(ConvexSet):
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
        lo = as_tensor("lower", lower)
        hi = lo if upper is None else as_tensor("upper", upper, like=lo)
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
    def _make(cls, lower: Tensor, upper: Tensor) -> Interval:
        """Fast constructor without validation (internal)."""
        obj = object.__new__(cls)
        object.__setattr__(obj, "lower", lower)
        object.__setattr__(obj, "upper", upper)
        return obj

    @classmethod
    def from_center_radius(cls, center: Any, radius: Any) -> Interval:
        """Box ``[c - r, c + r]`` (bounds rounded outward); ``radius >= 0`` elementwise."""
        c = as_tensor("center", center)
        r = as_tensor("radius", radius, like=c)
        if checking() and (r.detach() < 0).any():
            raise ValueError("radius: must be >= 0")
        return cls._make(_down(c - r), _up(c + r))

    @classmethod
    def point(cls, x: Any) -> Interval:
        """Degenerate interval ``[x, x]``."""
        t = as_tensor("x", x)
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
        c = self.center
        r = _up(torch.maximum(self.upper - c, c - self.lower))
        return c, r

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
    def __neg__(self) -> Interval:
        return Interval._make(-self.upper, -self.lower)

    def __pos__(self) -> Interval:
        return self

    def __add__(self, other: Any) -> Interval:
        if _number(other):
            return _shift(self, float(other))
        return _add(self, _as_interval(other, self))

    def __radd__(self, other: Any) -> Interval:
        if _number(other):
            return _shift(self, float(other))
        return _add(_as_interval(other, self), self)

    def __sub__(self, other: Any) -> Interval:
        if _number(other):
            return _shift(self, -float(other))
        return _add(self, -_as_interval(other, self))

    def __rsub__(self, other: Any) -> Interval:
        if _number(other):
            return _shift(-self, float(other))
        return _add(_as_interval(other, self), -self)

    def __mul__(self, other: Any) -> Interval:
        if _number(other):
            return _scale(self, float(other))
        return _mul(self, _as_interval(other, self))

    def __rmul__(self, other: Any) -> Interval:
        if _number(other):
            return _scale(self, float(other))
        return _mul(_as_interval(other, self), self)

    def __truediv__(self, other: Any) -> Interval:
        return _div(self, _as_interval(other, self))

    def __rtruediv__(self, other: Any) -> Interval:
        return _div(_as_interval(other, self), self)

    def __pow__(self, p: Any) -> Interval:
        return _pow(self, p)

    def __rpow__(self, base: Any) -> Interval:
        b = as_tensor("base", base, like=self.lower)
        if (b.detach() <= 0).any():
            raise ValueError("base: must be > 0 for base ** Interval")
        return (self * torch.log(b)).exp()

    def __matmul__(self, other: Any) -> Interval:
        return _matmul(self, other)

    def __rmatmul__(self, other: Any) -> Interval:
        return _matmul(other, self)

    def __abs__(self) -> Interval:
        return self.abs()

    def reciprocal(self) -> Interval:
        """``1 / x``; see `_div` for intervals containing 0."""
        return _recip(self)

    def abs(self) -> Interval:
        """Exact range of ``|x|``."""
        lo, hi = self.lower, self.upper
        mag = torch.maximum(-lo, hi)
        low = torch.where(lo >= 0, lo, torch.where(hi <= 0, -hi, torch.zeros_like(lo)))
        return Interval._make(low, mag)

    def square(self) -> Interval:
        """Exact-range square: the four products, lower bound clamped at 0."""
        p = _mul(self, self)
        return Interval._make(p.lower.clamp_min(0.0), p.upper)

    def sqrt(self) -> Interval:
        _check_domain(self, "sqrt", strict=False)
        return _monotone(self, torch.sqrt, 1, clamp_min=0.0)

    def exp(self) -> Interval:
        return _monotone(self, torch.exp, 2, clamp_min=0.0)

    def log(self) -> Interval:
        _check_domain(self, "log", strict=False)
        return _monotone(self, torch.log, 2)

    def tanh(self) -> Interval:
        return _monotone(self, torch.tanh, 2, clamp_min=-1.0, clamp_max=1.0)

    def sigmoid(self) -> Interval:
        return _monotone(self, torch.sigmoid, 2, clamp_min=0.0, clamp_max=1.0)

    def atan(self) -> Interval:
        return _monotone(self, torch.atan, 2)

    def softplus(self) -> Interval:
        return _monotone(self, torch.nn.functional.softplus, 2, clamp_min=0.0)

    def log1p(self) -> Interval:
        if checking() and bool((self.lower.detach() < -1).any()):  # else NaN, flagged
            low = float(self.lower.detach().min())
            raise ValueError(f"x: log1p needs lower >= -1, its argument reaches {low:.6g} "
                             "(interval leaves the domain)")
        return _monotone(self, torch.log1p, 2)

    def expm1(self) -> Interval:
        return _monotone(self, torch.expm1, 2, clamp_min=-1.0)

    def sinh(self) -> Interval:
        return _monotone(self, torch.sinh, 2)

    def erf(self) -> Interval:
        return _monotone(self, torch.erf, 2, clamp_min=-1.0, clamp_max=1.0)

    def cosh(self) -> Interval:
        """Exact range of ``cosh`` (even; minimum 1 at 0)."""
        return _monotone(self.abs(), torch.cosh, 2, clamp_min=1.0)

    def relu(self) -> Interval:
        return Interval._make(torch.relu(self.lower), torch.relu(self.upper))

    def clamp(self, min: Any = None, max: Any = None) -> Interval:  # noqa: A002
        lo, hi = self.lower, self.upper
        lo = torch.clamp(lo, min=min, max=max)
        hi = torch.clamp(hi, min=min, max=max)
        return Interval._make(lo, hi)

    def sin(self) -> Interval:
        """Exact range of ``sin`` (extrema inside the interval detected, batched)."""
        return _trig(self, torch.sin, phase_max=0.5 * math.pi, phase_min=-0.5 * math.pi)

    def cos(self) -> Interval:
        """Exact range of ``cos``."""
        return _trig(self, torch.cos, phase_max=0.0, phase_min=math.pi)

    def sum(self, dim: Any = None, keepdim: bool = False) -> Interval:
        """Sum over ``dim`` (all dims if ``None``) with a rounding-error margin."""
        return _sum(self, dim, keepdim)

    def mean(self, dim: Any = None, keepdim: bool = False) -> Interval:
        n = self.numel() if dim is None else _count(self.shape, dim)
        return _sum(self, dim, keepdim) / float(n)

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
        return Interval._make(_down(self.lower + b), _up(self.upper + b))

    def minkowski_sum(self, other: Any) -> ConvexSet:
        """Interval + Interval -> Interval (exact up to rounding); other sets delegate."""
        if isinstance(other, Interval):
            return _add(self, other)
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
        q = _up(n * r * r * (1.0 + 4.0 * _eps(r)))
        return family("Ellipsoid")(c, torch.diag_embed(q))

    def intersect(self, other: Interval) -> Interval:
        """Elementwise intersection; may be empty (check `is_empty`), not validated."""
        other = _as_interval(other, self)
        return Interval._make(
            torch.maximum(self.lower, other.lower), torch.minimum(self.upper, other.upper)
        )

    def is_empty(self) -> Tensor:
        """True where some component has ``lower > upper`` -> bool ``batch_shape``."""
        return (self.lower > self.upper).any(-1)

    def hull(self, other: Interval) -> Interval:
        """Smallest interval containing both (elementwise)."""
        other = _as_interval(other, self)
        return Interval._make(
            torch.minimum(self.lower, other.lower), torch.maximum(self.upper, other.upper)
        )

    def subset_of(self, other: Interval) -> Tensor:
        other = _as_interval(other, self)
        return ((self.lower >= other.lower) & (self.upper <= other.upper)).all(-1)

    # ------------------------------------------------------------------ torch integration
    @classmethod
    def __torch_function__(
        cls, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None
    ) -> Any:
        kwargs = kwargs or {}
        if getattr(func, "__name__", None) == "__rmatmul__":  # by name: see fix_dynamo_matmul
            impl = _TORCH_IMPL[torch.Tensor.__rmatmul__]
        else:
            impl = _TORCH_IMPL.get(func)
        if impl is None:
            return NotImplemented
        return impl(*args, **kwargs)


# ---------------------------------------------------------------------------- primitives
def _as_interval(x: Any, like: Interval | None = None) -> Interval:
    """Interval, tensor or number -> Interval (points become degenerate intervals)."""
    if isinstance(x, Interval):
        if like is not None and x.lower.dtype != like.lower.dtype:
            dt = torch.promote_types(x.lower.dtype, like.lower.dtype)
            return Interval._make(x.lower.to(dt), x.upper.to(dt))
        return x
    ref = like.lower if like is not None else None
    if isinstance(x, Tensor) and ref is not None and x.is_floating_point():
        dt = torch.promote_types(x.dtype, ref.dtype)
        t = x.to(dtype=dt, device=ref.device)
    else:
        t = as_tensor("operand", x, like=ref)
    return Interval._make(t, t)


def _add(a: Interval, b: Interval) -> Interval:
    # Song et al. 2017, sec. 3: [a] + [b] = [a_lo + b_lo, a_hi + b_hi]; a zero sum is exact
    lo, hi = a.lower + b.lower, a.upper + b.upper
    return Interval._make(_down(lo, absolute=False), _up(hi, absolute=False))


def _mul(a: Interval, b: Interval) -> Interval:
    # Song et al. 2017, sec. 3: [a] * [b] = [min, max] of the four endpoint products (0 * inf := 0)
    # a NaN operand (an enclosure outside its domain) stays NaN: only 0 * inf becomes 0
    al, au, bl, bu = torch.broadcast_tensors(a.lower, a.upper, b.lower, b.upper)
    p = torch.stack([al, au]).unsqueeze(1) * torch.stack([bl, bu]).unsqueeze(0)  # [2, 2, ...]
    p = torch.nan_to_num(p.flatten(0, 1), nan=0.0, posinf=math.inf, neginf=-math.inf)
    lo, hi = torch.aminmax(p, dim=0)
    nan = torch.isnan(al) | torch.isnan(au) | torch.isnan(bl) | torch.isnan(bu)
    return Interval._make(torch.where(nan, al + au + bl + bu, _down(lo)),
                          torch.where(nan, al + au + bl + bu, _up(hi)))


def _scale(a: Interval, s: float) -> Interval:
    """``[a] * s`` for a Python number ``s`` (two products instead of four)."""
    if s == 0:
        z = torch.zeros_like(a.lower)
        return Interval._make(z, z)
    lo, hi = (a.lower * s, a.upper * s) if s > 0 else (a.upper * s, a.lower * s)
    if s in (1.0, -1.0):
        return Interval._make(lo, hi)
    return Interval._make(_down(lo), _up(hi))


def _shift(a: Interval, s: float) -> Interval:
    """``[a] + s`` for a Python number ``s``."""
    if s == 0:
        return a
    return Interval._make(_down(a.lower + s, absolute=False), _up(a.upper + s, absolute=False))


def _number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _recip(b: Interval) -> Interval:
    """Extended reciprocal: [c,d] not containing 0 -> [1/d, 1/c]; [0,d] -> [1/d, inf];
    [c,0] -> [-inf, 1/c]; c < 0 < d (or [0,0]) -> [-inf, inf] (documented extended result)."""
    c, d = b.lower, b.upper
    inf = torch.full_like(c, math.inf)
    one = torch.ones_like(c)
    safe_c = torch.where(c == 0, one, c)
    safe_d = torch.where(d == 0, one, d)
    lo = _down(1.0 / safe_d)
    hi = _up(1.0 / safe_c)
    pos = c > 0
    neg = d < 0
    zero_left = (c == 0) & (d > 0)
    zero_right = (c < 0) & (d == 0)
    lo = torch.where(pos | neg | zero_left, lo, -inf)
    hi = torch.where(pos | neg | zero_right, hi, inf)
    return Interval._make(lo, hi)


def _div(a: Interval, b: Interval) -> Interval:
    # Song et al. 2017, sec. 3: [a] / [b] = [a] * [1/b_hi, 1/b_lo] for 0 not in [b]
    c, d = b.lower, b.upper
    nonzero = (c > 0) | (d < 0)
    one = torch.ones_like(c)
    sc = torch.where(nonzero, c, one)
    sd = torch.where(nonzero, d, one)
    q = torch.stack(torch.broadcast_tensors(a.lower / sc, a.lower / sd, a.upper / sc, a.upper / sd))
    direct = Interval._make(_down(q.amin(0)), _up(q.amax(0)))
    if not tracing() and bool(nonzero.all()):
        return direct
    ext = _mul(a, _recip(b))
    nz = torch.broadcast_to(nonzero, direct.shape)
    return Interval._make(
        torch.where(nz, direct.lower, ext.lower), torch.where(nz, direct.upper, ext.upper)
    )


def _pow(x: Interval, p: Any) -> Interval:
    """``x ** p``: integer p (even powers exact: [-2, 1]^2 = [0, 4]; negative p via 1/x^|p|),
    or real p for x >= 0 (monotone)."""
    if isinstance(p, Interval) or (isinstance(p, Tensor) and p.numel() != 1):
        return (_as_interval(p, x) * x.log()).exp()
    pv = float(p.item() if isinstance(p, Tensor) else p)
    if pv == int(pv):
        pi = int(pv)
        if pi == 0:
            one = torch.ones_like(x.lower)
            return Interval._make(one, one)
        if pi == 1:
            return x
        if pi < 0:
            return _recip(_pow(x, -pi))
        if pi == 2:
            return x.square()
        k = pi + 1
        lo_p, hi_p = torch.pow(x.lower, pi), torch.pow(x.upper, pi)
        if pi % 2 == 1:
            return Interval._make(_down(lo_p, k), _up(hi_p, k))
        lo, hi = x.lower, x.upper
        low = torch.where(lo >= 0, lo_p, torch.where(hi <= 0, hi_p, torch.zeros_like(lo_p)))
        high = torch.maximum(lo_p, hi_p)
        low = torch.where(low > 0, _down(low, k), low).clamp(min=0.0)
        return Interval._make(low, _up(high, k))
    _check_domain(x, f"power {pv}", strict=pv < 0)
    k = int(abs(pv)) + 2
    lo_p, hi_p = torch.pow(x.lower, pv), torch.pow(x.upper, pv)
    if pv > 0:
        return Interval._make(_down(lo_p, k).clamp(min=0.0), _up(hi_p, k))
    return Interval._make(_down(hi_p, k).clamp(min=0.0), _up(lo_p, k))


def _check_domain(x: Interval, name: str, strict: bool) -> None:
    if not checking():  # traced or in a filter step: out of the domain the bounds are NaN
        return  # (no host sync), and the filters flag those elements (FilterEvent.DOMAIN)
    bad = (x.lower <= 0) if strict else (x.lower < 0)
    if bool(bad.detach().any()):
        rel = ">" if strict else ">="
        low = float(x.lower.detach().min())
        raise ValueError(f"x: {name} needs lower {rel} 0, its argument reaches {low:.6g} "
                         "(interval leaves the domain)")


def _monotone(
    x: Interval,
    fn: Callable[[Tensor], Tensor],
    ulps: int,
    clamp_min: float | None = None,
    clamp_max: float | None = None,
) -> Interval:
    """Increasing function: [fn(lo), fn(hi)] rounded outward, clamped to fn's range."""
    lo = _down(fn(x.lower), ulps)
    hi = _up(fn(x.upper), ulps)
    if clamp_min is not None or clamp_max is not None:
        lo = torch.clamp(lo, min=clamp_min, max=clamp_max)
        hi = torch.clamp(hi, min=clamp_min, max=clamp_max)
    return Interval._make(lo, hi)


def _hits(a: Tensor, b: Tensor, phase: float) -> Tensor:
    """True where some ``phase + 2 pi k`` lies in ``[a, b]`` (generous: never misses one)."""
    a64, b64 = a.detach().double(), b.detach().double()
    slack = 1e-9 + 64 * _eps(a) * (1.0 + torch.maximum(a64.abs(), b64.abs()))
    k_lo = torch.ceil((a64 - phase) / _TWO_PI - slack)
    k_hi = torch.floor((b64 - phase) / _TWO_PI + slack)
    return k_lo <= k_hi


def _trig(
    x: Interval, fn: Callable[[Tensor], Tensor], phase_max: float, phase_min: float
) -> Interval:
    # Song et al. 2017, sec. 3 (simple interval extension): range of sin/cos = endpoint values,
    # widened to +-1 where a maximum/minimum lies inside the interval.
    fa, fb = fn(x.lower), fn(x.upper)
    lo = _down(torch.minimum(fa, fb), 2)
    hi = _up(torch.maximum(fa, fb), 2)
    wide = (x.upper - x.lower).detach() >= _TWO_PI
    has_max = wide | _hits(x.lower, x.upper, phase_max)
    has_min = wide | _hits(x.lower, x.upper, phase_min)
    one = torch.ones_like(lo)
    hi = torch.where(has_max, one, hi).clamp(max=1.0)
    lo = torch.where(has_min, -one, lo).clamp(min=-1.0)
    return Interval._make(lo, hi)


def _count(shape: torch.Size, dim: Any) -> int:
    dims = (dim,) if isinstance(dim, int) else tuple(dim)
    return math.prod([shape[d] for d in dims])  # a list: Dynamo traces it


def _sum(x: Interval, dim: Any = None, keepdim: bool = False) -> Interval:
    """Sum with the a-priori float error bound gamma_k sum|terms| added outward."""
    if dim is None:
        lo_t, hi_t = x.lower.reshape(-1), x.upper.reshape(-1)
        dim_, keep = 0, False
        k = lo_t.numel()
    else:
        lo_t, hi_t, dim_, keep = x.lower, x.upper, dim, keepdim
        k = _count(x.shape, dim)
    if k <= 1:
        return Interval._make(lo_t.sum(dim_, keepdim=keep), hi_t.sum(dim_, keepdim=keep))
    g = (k + 4) * _eps(lo_t)
    tiny = k * _tiny(lo_t)
    lo_s = lo_t.sum(dim_, keepdim=keep)
    hi_s = hi_t.sum(dim_, keepdim=keep)
    lo_err = g * _nan0(lo_t.detach().abs()).sum(dim_, keepdim=keep) + tiny
    hi_err = g * _nan0(hi_t.detach().abs()).sum(dim_, keepdim=keep) + tiny
    return Interval._make(_down(lo_s - lo_err), _up(hi_s + hi_err))


def _matmul(a: Any, b: Any) -> Interval:
    """``a @ b`` with an Interval on either side; tensor semantics of ``torch.matmul``."""
    if isinstance(a, Interval) and isinstance(b, Interval):
        return _matmul_ii(a, b)
    if isinstance(a, Interval):
        A = as_tensor("other", b, like=a.lower)
        c, r = a.mid_rad()
        k = A.shape[0] if A.dim() == 1 else A.shape[-2]
        return _mid_rad_out(c @ A, r @ A.abs(), c.abs() @ A.abs(), k)
    A = as_tensor("other", a, like=b.lower)
    c, r = b.mid_rad()
    k = A.shape[-1]
    return _mid_rad_out(A @ c, A.abs() @ r, A.abs() @ c.abs(), k)


def _mid_rad_out(mc: Tensor, mr: Tensor, mabs: Tensor, k: int) -> Interval:
    # point matrix x interval vector/matrix (midpoint-radius form, exact in real arithmetic)
    # plus the dot-product rounding bound gamma_k (|c||A| + r|A|).
    err = (k + 4) * _eps(mc) * (mabs + mr) + k * _tiny(mc)
    rad = mr + err
    return Interval._make(_down(mc - rad), _up(mc + rad))


def _matmul_ii(a: Interval, b: Interval) -> Interval:
    # interval matrix product: entrywise exact Moore products summed (Song et al. 2017, sec. 3)
    sq_a, sq_b = a.ndim == 1, b.ndim == 1
    if sq_a:
        a = a.unsqueeze(0)
    if sq_b:
        b = b.unsqueeze(-1)
    prod = _mul(a.unsqueeze(-1), b.unsqueeze(-3))  # [..., m, k, p]
    out = _sum(prod, -2)
    if sq_a:
        out = out.squeeze(-2)
    if sq_b:
        out = out.squeeze(-1)
    return out


# ---------------------------------------------------------------------------- torch hooks
def _is_iv(x: Any) -> bool:
    return isinstance(x, Interval)


def _binop(op: Callable[[Interval, Interval], Interval], swap: bool = False) -> Callable:
    def f(x: Any, y: Any, *args: Any, **kwargs: Any) -> Interval:
        if swap:
            x, y = y, x
        like = x if _is_iv(x) else y
        return op(_as_interval(x, like), _as_interval(y, like))

    return f


def _sub(a: Interval, b: Interval) -> Interval:
    return _add(a, -b)


def _unary(name: str) -> Callable:
    def f(x: Any, *args: Any, **kwargs: Any) -> Any:
        return getattr(_as_interval(x), name)(*args, **kwargs)

    return f


def _stack(tensors: Sequence[Any], dim: int = 0, *, out: Any = None) -> Interval:
    like = next(t for t in tensors if _is_iv(t))
    ivs = [_as_interval(t, like) for t in tensors]
    return Interval._make(
        torch.stack([i.lower for i in ivs], dim), torch.stack([i.upper for i in ivs], dim)
    )


def _cat(tensors: Sequence[Any], dim: int = 0, *, out: Any = None) -> Interval:
    like = next(t for t in tensors if _is_iv(t))
    ivs = [_as_interval(t, like) for t in tensors]
    return Interval._make(
        torch.cat([i.lower for i in ivs], dim), torch.cat([i.upper for i in ivs], dim)
    )


def _where(cond: Tensor, x: Any, y: Any) -> Interval:
    like = x if _is_iv(x) else y
    a, b = _as_interval(x, like), _as_interval(y, like)
    return Interval._make(torch.where(cond, a.lower, b.lower), torch.where(cond, a.upper, b.upper))


def _maximum(x: Any, y: Any) -> Interval:
    like = x if _is_iv(x) else y
    a, b = _as_interval(x, like), _as_interval(y, like)
    return Interval._make(torch.maximum(a.lower, b.lower), torch.maximum(a.upper, b.upper))


def _minimum(x: Any, y: Any) -> Interval:
    like = x if _is_iv(x) else y
    a, b = _as_interval(x, like), _as_interval(y, like)
    return Interval._make(torch.minimum(a.lower, b.lower), torch.minimum(a.upper, b.upper))


def _like(fn: Callable) -> Callable:
    def f(x: Interval, *args: Any, **kwargs: Any) -> Tensor:
        return fn(x.lower, *args, **kwargs)

    return f


def _pow_fn(x: Any, p: Any) -> Interval:
    if _is_iv(x):
        return _pow(x, p)
    return Interval.__rpow__(p, x)


def _softplus(x: Any, beta: float = 1.0) -> Interval:
    iv = _as_interval(x)
    if beta == 1.0:
        return iv.softplus()
    return (iv * beta).softplus() / beta


def _sum_fn(x: Interval, dim: Any = None, keepdim: bool = False, **kwargs: Any) -> Interval:
    return _sum(x, dim, keepdim)


def _build_table() -> dict[Any, Callable]:
    T = torch.Tensor
    F = torch.nn.functional
    table: dict[Any, Callable] = {}
    for fns, impl in [
        ((torch.add, T.add, T.__add__, T.__radd__), _binop(_add)),
        ((torch.sub, torch.subtract, T.sub, T.__sub__), _binop(_sub)),
        ((T.__rsub__, torch.rsub), _binop(_sub, swap=True)),
        ((torch.mul, torch.multiply, T.mul, T.__mul__, T.__rmul__), _binop(_mul)),
        ((torch.div, torch.divide, torch.true_divide, T.div, T.__truediv__), _binop(_div)),
        ((T.__rtruediv__,), _binop(_div, swap=True)),
        ((torch.matmul, torch.mm, torch.mv, T.matmul, T.__matmul__), _matmul),
        ((T.__rmatmul__,), lambda a, b: _matmul(b, a)),
        ((torch.pow, T.pow, T.__pow__), _pow_fn),
        ((T.__rpow__,), lambda a, b: _pow_fn(b, a)),
        ((torch.stack,), _stack),
        ((torch.cat, torch.concat), _cat),
        ((torch.where,), _where),
        ((torch.maximum,), _maximum),
        ((torch.minimum,), _minimum),
        ((torch.sum, T.sum), _sum_fn),
        ((torch.zeros_like,), _like(torch.zeros_like)),
        ((torch.ones_like,), _like(torch.ones_like)),
        ((torch.full_like,), _like(torch.full_like)),
        ((torch.neg, torch.negative, T.neg, T.__neg__), lambda x: -_as_interval(x)),
        ((F.relu,), lambda x, inplace=False: _as_interval(x).relu()),
        ((F.softplus,), lambda x, beta=1.0, threshold=20.0: _softplus(x, beta)),
    ]:
        for fn in fns:
            table[fn] = impl
    for name in [
        "sin",
        "cos",
        "exp",
        "log",
        "sqrt",
        "tanh",
        "abs",
        "square",
        "sigmoid",
        "atan",
        "relu",
        "clamp",
        "reciprocal",
        "mean",
        "log1p",
        "expm1",
        "sinh",
        "cosh",
        "erf",
        "reshape",
        "unsqueeze",
        "squeeze",
        "transpose",
        "permute",
        "movedim",
        "flatten",
        "clone",
    ]:
        if hasattr(torch, name):
            table[getattr(torch, name)] = _unary(name)
        if hasattr(T, name):
            table[getattr(T, name)] = _unary(name)
    table[torch.arctan] = _unary("atan")
    table[torch.clip] = _unary("clamp")
    table[torch.absolute] = _unary("abs")
    return table


_TORCH_IMPL = _build_table()


def interval_eval(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Natural interval extension: evaluate a plain torch function on Interval arguments.

    ``fn`` is written for tensors (``lambda x: torch.stack([x[..., 0] ** 2 * x[..., 1],
    torch.sin(x[..., 1])], -1)``); each Interval argument is propagated with the outward-correct
    Moore arithmetic above, so the result encloses ``fn`` over the boxes. Tensor outputs (parts
    of ``fn`` independent of the Interval args) become point intervals; tuples are mapped.
    """
    out = fn(*args, **kwargs)
    return _wrap_out(out)


def _wrap_out(out: Any) -> Any:
    if isinstance(out, Interval):
        return out
    if isinstance(out, Tensor):
        return Interval._make(out, out)
    if isinstance(out, (tuple, list)):
        return type(out)(_wrap_out(o) for o in out)
    return out
