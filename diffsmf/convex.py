"""`ConvexSet`, the base of every set family: the interval engine's box
(`diffsmf.interval.box.Interval`) and the families of `diffsmf.sets`. It lies below the
engine, so that the engine owns its value type and never imports `diffsmf.sets`.

A set is a small immutable object holding a few tensors whose leading dimensions are batch
dimensions (``batch_shape``) and whose trailing dimensions are fixed by the set type
(``center [..., n]``, ``generators [..., n, m]``, ...). Methods broadcast over the batch dims,
never loop over them, and are differentiable with respect to every continuous field.

Subclasses declare ``_fields`` (names of their tensor attributes, in constructor order) and
``_event_dims`` (how many trailing dims of each field are *not* batch dims). The generic
batch utilities below (indexing, ``expand``, ``to``, ``stack``, ``where``) are written once
here from that declaration.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar

import torch
from torch import Tensor

from diffsmf.utils import broadcast_shapes, checking, is_int, tracing, user_stacklevel

DEFAULT_DTYPE = torch.float64

_F = TypeVar("_F", bound=Callable[..., Any])

#: ``{(source class, target family name): conversion}``, filled by `register_conversion`
#: (all pairs in `diffsmf.sets.conversions`).
_CONVERSIONS: dict[tuple[type, str], Callable[..., Any]] = {}
#: ``{name: class}`` of the set families met by `register_conversion`.
_FAMILIES: dict[str, type] = {}


def register_conversion(src: type, dst: type) -> Callable[[_F], _F]:
    """Decorator registering ``fn(S, *args, **kw)`` as the conversion of a ``src`` set to the
    family ``dst``, as ``torch.distributions.kl.register_kl`` registers KL pairs. Every pair is
    registered in `diffsmf.sets.conversions`, the one module that imports all the families,
    so that the modules of the families do not import each other (`convert`, `family`)."""

    def deco(fn: _F) -> _F:
        _CONVERSIONS[(src, dst.__name__)] = fn
        _FAMILIES[src.__name__] = src
        _FAMILIES[dst.__name__] = dst
        return fn

    return deco


def convert(S: ConvexSet, dst: str, *args: Any, **kw: Any) -> ConvexSet:
    """``S`` converted to the set family named ``dst`` (e.g. ``"Zonotope"``) by the conversion
    registered for the first class of ``type(S).__mro__`` that has one (`register_conversion`);
    ``ValueError`` when there is none."""
    for cls in type(S).__mro__:
        fn = _CONVERSIONS.get((cls, dst))
        if fn is not None:
            return fn(S, *args, **kw)
    raise ValueError(f"S: no conversion of a {type(S).__name__} to a {dst}")


def family(name: str) -> type:
    """The set class named ``name`` (``"Interval"``, ``"Zonotope"``, ...), as registered by
    `register_conversion`: the constructor that a module lower in the import order uses
    without importing the family's module."""
    return _FAMILIES[name]


def as_tensor(
    name: str, value: Any, *, like: Tensor | None = None, min_dim: int = 0, field: bool = False
) -> Tensor:
    """Convert ``value`` to a float64 tensor (or to ``like``'s dtype and device).

    Floating tensors of lower precision are promoted to float64: the guaranteed (outward)
    rounding margins of the sets are float64 margins, so a float32 set would silently lose
    its guarantee. ``field=True`` marks a tensor that defines a set (its bounds, centre,
    generators): a lower-precision one whose values are not the decimals they print as is
    flagged by a warning (`warn_rounded`). Raises ``ValueError`` naming ``name`` on NaN, on
    non-numeric input or on too few dims.
    """
    if isinstance(value, Tensor):
        t = value
        if not t.is_floating_point() or torch.finfo(t.dtype).bits < 64:
            if field and t.is_floating_point():
                warn_rounded(name, t)
            t = t.to(like.dtype if like is not None else DEFAULT_DTYPE)
    else:
        try:
            t = torch.as_tensor(
                value,
                dtype=like.dtype if like is not None else DEFAULT_DTYPE,
                device=like.device if like is not None else None,
            )
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ValueError(f"{name}: cannot convert to a tensor ({exc})") from exc
    if like is not None and (t.dtype != like.dtype or t.device != like.device):
        t = t.to(dtype=like.dtype, device=like.device)
    if t.dim() < min_dim:
        raise ValueError(f"{name}: expected at least {min_dim} dims, got shape {tuple(t.shape)}")
    if checking() and torch.isnan(t.detach()).any():
        raise ValueError(f"{name}: contains NaN")
    return t


#: at most this many values of a lower-precision set field are compared with their decimals
_ROUNDED_CHECK = 4096


def warn_rounded(name: str, t: Tensor) -> None:
    """Warn when the lower-precision tensor ``t`` (float32, float16, bfloat16) that defines a
    set holds a value other than the decimal it prints as: ``torch.tensor(0.01)`` in float32
    is 0.009999999776482582, so a noise bound or an initial box written as 0.01 would be
    built on that number, up to half a float32 ulp inside (or outside) the bound the user
    wrote, and the set's guarantee would hold for the rounded bound only. Values that print
    exactly (0.5, 0.25, integers) pass silently. Host-side, on the first `_ROUNDED_CHECK`
    values; never while traced."""
    if tracing() or t.numel() == 0:
        return
    vals = t.detach().flatten()[:_ROUNDED_CHECK].cpu()
    if t.dtype != torch.float32:  # float16 / bfloat16: exact in float32, printed as such
        vals = vals.to(torch.float32)
    for v in vals.numpy():
        exact = float(v)
        if exact == exact and float(str(v)) != exact:  # (NaN is reported by as_tensor)
            warnings.warn(
                f"{name}: a {str(t.dtype).removeprefix('torch.')} tensor, in which {v!s} is "
                f"{exact!r}: the set is built on the rounded values, not on the decimals "
                "written; create set bounds in float64 (dtype=torch.float64, or "
                "torch.set_default_dtype(torch.float64) first)",
                UserWarning, stacklevel=user_stacklevel())
            return


def as_vector(name: str, value: Any, like: Tensor, dim: int) -> Tensor:
    """Vector(s) ``value [..., dim]`` (points, directions, offsets) as a tensor like ``like``;
    ``ValueError`` naming ``name`` for NaN or a last dimension other than ``dim``."""
    v = as_tensor(name, value, like=like, min_dim=1)
    if v.shape[-1] != dim:
        raise ValueError(f"{name}: expected [..., {dim}], got {tuple(v.shape)}")
    return v


def as_offset(b: Any, like: Tensor, dim: int) -> Tensor:
    """Offset vector ``b [..., dim]`` of a translation or affine map, validated against ``like``."""
    return as_vector("b", b, like, dim)


def check_count(name: str, k: Any) -> int:
    """``k`` as a count (an ``int`` >= 0, not a ``bool``), else ``ValueError`` naming ``name``."""
    if not is_int(k) or k < 0:
        raise ValueError(f"{name}: must be an integer >= 0, got {k!r}")
    return int(k)


def check_finite(name: str, t: Tensor) -> Tensor:
    """Raise ``ValueError`` naming ``name`` if ``t`` has NaN or inf; return ``t``."""
    if checking() and not torch.isfinite(t.detach()).all():
        raise ValueError(f"{name}: contains NaN or inf")
    return t


def check_nonempty(name: str, S: Any) -> None:
    """Raise ``ValueError`` naming ``name`` when the set ``S`` (or an element of its batch) is
    certified empty (``S.is_empty()``; eager only, one LP for a constrained zonotope).

    Only an `Interval` with ``lower > upper`` or a
    `ConstrainedZonotope` whose constraints ``A xi = b`` have no solution
    in the box can be empty; a filter started from, or driven by, an empty set has no state to
    bound and would report plausible-looking sets. Sets without ``is_empty`` pass."""
    is_empty = getattr(S, "is_empty", None)
    if is_empty is None or tracing():
        return
    if bool(is_empty().any()):
        raise ValueError(
            f"{name}: is empty (a {type(S).__name__} that holds no point"
            + (": its constraints A xi = b have no solution with |xi|_inf <= 1)"
               if hasattr(S, "num_constraints") else ")")
        )


class ConvexSet:
    """Abstract batched convex set in R^n.

    Every concrete set provides ``center [..., n]``, ``dim``, ``batch_shape``, ``volume()``,
    ``contains(x, atol)``, ``interval_hull()``, ``linear_map(A, b)``, ``minkowski_sum(other)``,
    ``support(d)``, ``sample(k)`` and ``sample_extreme(k)``.
    """

    _fields: ClassVar[tuple[str, ...]] = ()
    _event_dims: ClassVar[tuple[int, ...]] = ()

    def _rand(self, k: int, m: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` draws of ``m`` uniform numbers in ``[0, 1)`` per set -> ``[..., k, m]``."""
        return torch.rand((*self.batch_shape, k, m), dtype=self.dtype, device=self.device,
                          generator=generator)

    # ------------------------------------------------------------------ structure
    @property
    def center(self) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def dim(self) -> int:
        """State dimension n."""
        return self.center.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        return self.center.shape[:-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.center.dtype

    @property
    def device(self) -> torch.device:
        return getattr(self, self._fields[0]).device  # no op (``center`` may compute one)

    def _tensors(self) -> tuple[Tensor, ...]:
        return tuple(getattr(self, f) for f in self._fields)

    @classmethod
    def _from_tensors(cls, tensors: Sequence[Tensor]) -> ConvexSet:
        """A set of type ``cls`` from its field tensors (no re-validation)."""
        obj = object.__new__(cls)
        for name, t in zip(cls._fields, tensors):
            object.__setattr__(obj, name, t)
        return obj

    def _rebuild(self, tensors: Sequence[Tensor]) -> ConvexSet:
        """New set of the same type from field tensors (no re-validation)."""
        return type(self)._from_tensors(tensors)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"{type(self).__name__} is immutable")

    def _set(self, **fields: Tensor) -> None:
        """Used by constructors only: assign validated fields."""
        for name, t in fields.items():
            object.__setattr__(self, name, t)

    def __getitem__(self, idx: Any) -> ConvexSet:
        """Index the batch dimensions: ``S[0]``, ``S[:, 3]``, ``S[mask]``."""
        if not isinstance(idx, tuple):
            idx = (idx,)
        return self._rebuild(
            [t[idx + (slice(None),) * e] for t, e in zip(self._tensors(), self._event_dims)]
        )

    def expand(self, *batch_shape: int) -> ConvexSet:
        """Broadcast to ``batch_shape`` (views, no copy)."""
        if len(batch_shape) == 1 and isinstance(batch_shape[0], (tuple, list, torch.Size)):
            batch_shape = tuple(batch_shape[0])
        out = []
        for t, e in zip(self._tensors(), self._event_dims):
            ev = t.shape[t.dim() - e :]
            out.append(t.expand(*batch_shape, *ev))
        return self._rebuild(out)

    def to(self, *args: Any, **kwargs: Any) -> ConvexSet:
        """Like ``Tensor.to``: move every field to a device / dtype."""
        return self._rebuild([t.to(*args, **kwargs) for t in self._tensors()])

    def detach(self) -> ConvexSet:
        return self._rebuild([t.detach() for t in self._tensors()])

    def __repr__(self) -> str:
        return f"{type(self).__name__}(dim={self.dim}, batch_shape={tuple(self.batch_shape)})"

    # ------------------------------------------------------------------ set API
    def volume(self) -> Tensor:  # pragma: no cover - abstract
        """Lebesgue volume, shape ``batch_shape``."""
        raise NotImplementedError

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:  # pragma: no cover
        """Membership of points ``x [..., n]`` (broadcast against batch) -> bool ``[...]``."""
        raise NotImplementedError

    def support(self, d: Tensor) -> Tensor:  # pragma: no cover - abstract
        """Support function h(d) = max_{x in S} d.x for directions ``d [..., n]`` -> ``[...]``."""
        raise NotImplementedError

    def interval_hull(self) -> ConvexSet:
        """Smallest axis-aligned box (an `Interval`) containing the set (from the support
        function)."""
        eye = torch.eye(self.dim, dtype=self.dtype, device=self.device)
        c = self.center
        r = _support_axes(self, eye) - c  # radius along each axis, [..., n]
        return family("Interval")(c - r, c + r)

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> ConvexSet:  # pragma: no cover
        """Image ``{A x + b : x in S}`` with ``A [..., k, n]``, ``b [..., k]``."""
        raise NotImplementedError

    def translate(self, b: Tensor) -> ConvexSet:  # pragma: no cover
        """``{x + b}``; ``b [..., n]``."""
        raise NotImplementedError

    def minkowski_sum(self, other: ConvexSet) -> ConvexSet:  # pragma: no cover
        raise NotImplementedError

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:  # noqa: D102
        """``k`` points inside the set, shape ``[*batch_shape, k, n]``."""
        raise NotImplementedError

    def sample_extreme(
        self, k: int, generator: torch.Generator | None = None
    ) -> Tensor:  # pragma: no cover
        """``k`` worst-case points (vertices / boundary points), ``[*batch_shape, k, n]``.

        Used by ``System.simulate(noise="vertex")``.
        """
        raise NotImplementedError

    def intersects_strip(self, strip: Any, atol: float = 0.0) -> Tensor:
        """Exact test that the set meets ``strip`` (any convex set): bool ``[...]``.

        The projection of the set on the strip normal is the interval
        ``normal.c +- h(normal)``; the intersection is non-empty iff it meets
        ``[offset - halfwidth, offset + halfwidth]``.
        """
        a = strip.normal
        mid = (a * self.center).sum(-1)
        rad = self.support(a) - mid
        return (mid - strip.offset).abs() <= rad + strip.halfwidth + atol


def _support_axes(s: ConvexSet, eye: Tensor) -> Tensor:
    """Support of ``s`` along the n unit axes -> ``[..., n]``."""
    n = s.dim
    d = eye.reshape((n,) + (1,) * len(s.batch_shape) + (n,))  # [n, 1.., n]
    h = s.support(d)  # [n, ...]
    return h.movedim(0, -1)


def stack(sets: Sequence[ConvexSet], dim: int = 0) -> ConvexSet:
    """Stack sets of one type and equal field shapes into a new batch dim ``dim``.

    ``dim`` indexes the batch dims (``0`` = new leading dim).
    """
    if len(sets) == 0:
        raise ValueError("sets: need at least one set to stack")
    cls = type(sets[0])
    if any(type(s) is not cls for s in sets):
        raise ValueError("sets: all sets must have the same type to stack")
    nb = len(sets[0].batch_shape)
    if dim < 0:
        dim += nb + 1
    fields = []
    for i, _name in enumerate(cls._fields):
        fields.append(torch.stack([s._tensors()[i] for s in sets], dim=dim))
    return sets[0]._rebuild(fields)


def align(sets: Sequence[ConvexSet], count: int | None = None) -> list[ConvexSet]:
    """The same sets with equal field shapes where a set type allows it: zonotopes are padded
    with zero generators to the largest generator count (or to ``count``), constrained
    zonotopes also with trivial constraints ``0 xi = 0`` to the largest constraint count;
    other types are returned unchanged. Use before `stack` / `cat` / `where`
    of sets of one type."""
    sets = list(sets)
    if sets and hasattr(sets[0], "pad_generators"):
        m = max(s.generators.shape[-1] for s in sets)
        sets = [s.pad_generators(max(m, count or 0)) for s in sets]
    if sets and hasattr(sets[0], "pad_constraints"):
        k = max(s.num_constraints for s in sets)
        sets = [s.pad_constraints(k) for s in sets]
    return sets


def cat(sets: Sequence[ConvexSet]) -> ConvexSet:
    """Concatenate sets of one type along their leading batch dim (``[B_i, ...]`` ->
    ``[sum B_i, ...]``); zonotopes are first `align`-ed."""
    if len(sets) == 0:
        raise ValueError("sets: need at least one set to concatenate")
    cls = type(sets[0])
    if any(type(s) is not cls for s in sets):
        raise ValueError("sets: all sets must have the same type to concatenate")
    sets = align(sets)
    fields = [torch.cat([s._tensors()[i] for s in sets], 0) for i in range(len(cls._fields))]
    return sets[0]._rebuild(fields)


def where(cond: Tensor, a: ConvexSet, b: ConvexSet) -> ConvexSet:
    """Batched select: ``a`` where ``cond [...]`` is True, else ``b`` (same type; zonotopes
    and constrained zonotopes of different sizes are first `align`-ed, so the result
    has the larger generator and constraint counts)."""
    if type(a) is not type(b):
        raise ValueError(f"where: sets differ in type ({type(a).__name__}, {type(b).__name__})")
    if any(ta.shape[ta.dim() - e :] != tb.shape[tb.dim() - e :]
           for ta, tb, e in zip(a._tensors(), b._tensors(), a._event_dims)):
        a, b = align([a, b])
    out = []
    for ta, tb, e in zip(a._tensors(), b._tensors(), a._event_dims):
        c = cond.reshape(cond.shape + (1,) * e)
        out.append(torch.where(c, ta, tb))
    return a._rebuild(out)


def strip_fields(strip: Any, ref: ConvexSet) -> tuple[Tensor, Tensor, Tensor]:
    """(normal [..., n], offset [...], halfwidth [...]) of a strip (any object with those
    fields, a `diffsmf.sets.Strip`), checked against the set ``ref``."""
    try:
        p, y, sig = strip.normal, strip.offset, strip.halfwidth
    except AttributeError as exc:
        raise ValueError("strip: expected a Strip (normal, offset, halfwidth)") from exc
    p = p.to(ref.center.dtype)
    if p.shape[-1] != ref.dim:
        raise ValueError(f"strip: normal has dim {p.shape[-1]}, set has dim {ref.dim}")
    return p, y.to(p.dtype), sig.to(p.dtype)


def strip_batch(batch: torch.Size, p: Tensor, y: Tensor, sig: Tensor) -> torch.Size:
    """Common batch shape of a set and a strip; ``ValueError`` naming ``strip`` otherwise."""
    try:
        return broadcast_shapes(batch, p.shape[:-1], y.shape, sig.shape)
    except RuntimeError as exc:
        raise ValueError(
            f"strip: batch shape {tuple(y.shape)} does not broadcast with the set's "
            f"batch shape {tuple(batch)}"
        ) from exc
