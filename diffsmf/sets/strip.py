"""Strips ``{x : |normal . x - offset| <= halfwidth}`` (measurement sets, Wang et al. 2022, eq.
23-29).

A strip is unbounded (for n >= 2): ``volume()`` returns ``inf``, ``sample`` raises, and the
support function is ``inf`` except along +-normal. It subclasses
`ConvexSet` for the batch utilities (indexing, ``expand``, ``stack``,
``where``, ``to``, ``detach``).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, as_tensor, as_vector, strip_batch, strip_fields
from diffsmf.utils import broadcast_shapes, checking

__all__ = ["Strip", "strip_batch", "strip_fields"]  # the two helpers live in convex


class Strip(ConvexSet):
    """Batched strip ``{x in R^n : |normal . x - offset| <= halfwidth}``.

    Args:
        normal: ``[..., n]`` (need not be unit; must be non-zero).
        offset: ``[...]``.
        halfwidth: ``[...]``, ``>= 0``.
    Batch dims of the three arguments broadcast.
    """

    _fields: ClassVar[tuple[str, ...]] = ("normal", "offset", "halfwidth")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 0, 0)
    normal: Tensor
    offset: Tensor
    halfwidth: Tensor

    def __init__(self, normal: Any, offset: Any, halfwidth: Any) -> None:
        a = as_tensor("normal", normal, min_dim=1, field=True)
        o = as_tensor("offset", offset, like=a, field=True)
        h = as_tensor("halfwidth", halfwidth, like=a, field=True)
        if checking():
            if (h.detach() < 0).any():
                raise ValueError("halfwidth: must be >= 0")
            if not torch.isfinite(a.detach()).all():
                raise ValueError("normal: contains inf")
            if (a.detach().abs().amax(-1) == 0).any():
                raise ValueError("normal: must be non-zero")
        try:
            batch = torch.broadcast_shapes(a.shape[:-1], o.shape, h.shape)
        except RuntimeError as exc:
            raise ValueError(
                f"offset/halfwidth: batch shapes {tuple(o.shape)}, {tuple(h.shape)} do not "
                f"broadcast with normal {tuple(a.shape)}"
            ) from exc
        self._set(
            normal=a.expand(*batch, a.shape[-1]), offset=o.expand(batch), halfwidth=h.expand(batch)
        )

    @classmethod
    def _make(cls, normal: Tensor, offset: Tensor, halfwidth: Tensor) -> Strip:
        """Internal constructor without validation (broadcasts the batch dims; no call where
        they agree already)."""
        batch = broadcast_shapes(normal.shape[:-1], offset.shape, halfwidth.shape)
        n = normal.shape[-1]
        obj = object.__new__(cls)
        object.__setattr__(obj, "normal", normal if normal.shape[:-1] == batch
                           else normal.expand(*batch, n))
        object.__setattr__(obj, "offset", offset if offset.shape == batch
                           else offset.expand(batch))
        object.__setattr__(obj, "halfwidth", halfwidth if halfwidth.shape == batch
                           else halfwidth.expand(batch))
        return obj

    @classmethod
    def from_bounds(cls, normal: Any, lower: Any, upper: Any) -> Strip:
        """Strip ``{x : lower <= normal . x <= upper}``."""
        lo = as_tensor("lower", lower, field=True)
        hi = as_tensor("upper", upper, like=lo, field=True)
        if (lo.detach() > hi.detach()).any():
            raise ValueError("lower: must be <= upper")
        return cls(normal, 0.5 * (lo + hi), 0.5 * (hi - lo))

    @classmethod
    def from_measurement(cls, C: Any, y: Any, noise_bound: Any) -> Strip:
        """Strips of a linear(ised) measurement ``y = C x + v``, ``|v_i| <= noise_bound_i``.

        ``C [..., m, n]``, ``y [..., m]``, ``noise_bound [..., m]`` -> Strip batch ``[..., m]``
        (one strip per output row, Wang et al. 2022, eq. 23-29).
        """
        return cls(C, y, noise_bound)

    # ------------------------------------------------------------------ structure
    @property
    def center(self) -> Tensor:
        """Point of the mid-plane closest to the origin: ``normal offset / |normal|^2``."""
        a = self.normal
        return a * (self.offset / (a * a).sum(-1)).unsqueeze(-1)

    @property
    def lower(self) -> Tensor:
        """``offset - halfwidth``: lower bound of ``normal . x``."""
        return self.offset - self.halfwidth

    @property
    def upper(self) -> Tensor:
        return self.offset + self.halfwidth

    def normalized(self) -> Strip:
        """Same strip with a unit normal."""
        s = self.normal.norm(dim=-1)
        return self._rebuild([self.normal / s.unsqueeze(-1), self.offset / s, self.halfwidth / s])

    # ------------------------------------------------------------------ set API
    def volume(self) -> Tensor:
        """``inf`` (a strip in n >= 2 dims is unbounded); ``2 halfwidth / |a|`` for n = 1."""
        if self.dim == 1:
            return 2.0 * self.halfwidth / self.normal.abs().squeeze(-1)
        return torch.full_like(self.offset, float("inf"))

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """``|normal . x - offset| <= halfwidth + atol`` -> bool ``[...]``."""
        x = as_vector("x", x, self.normal, self.dim)
        return ((self.normal * x).sum(-1) - self.offset).abs() <= self.halfwidth + atol

    def residual(self, x: Tensor) -> Tensor:
        """Signed distance in measurement units ``normal . x - offset`` -> ``[...]``."""
        return (self.normal * x).sum(-1) - self.offset

    def support(self, d: Tensor) -> Tensor:
        """``t offset + |t| halfwidth`` if ``d = t normal`` (to 1e-12 relative), else ``inf``."""
        d = as_vector("d", d, self.normal, self.dim)
        a = self.normal
        aa = (a * a).sum(-1)
        t = (d * a).sum(-1) / aa
        resid = (d - t.unsqueeze(-1) * a).norm(dim=-1)
        parallel = resid <= 1e-12 * d.norm(dim=-1).clamp(min=1e-300)
        h = t * self.offset + t.abs() * self.halfwidth
        return torch.where(parallel, h, torch.full_like(h, float("inf")))

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> Strip:
        """Image under invertible square ``A``: normal' = A^-T normal, offset' = o + normal'.b."""
        A = as_tensor("A", A, like=self.normal, min_dim=2)
        n = self.dim
        if A.shape[-2:] != (n, n):
            raise ValueError(f"A: strip maps need square invertible [..., {n}, {n}]")
        a2 = torch.linalg.solve(A.mT, self.normal.unsqueeze(-1)).squeeze(-1)
        s = Strip(a2, self.offset, self.halfwidth)
        return s if b is None else s.translate(b)

    def translate(self, b: Tensor) -> Strip:
        b = as_tensor("b", b, like=self.normal)
        off = self.offset + (self.normal * b).sum(-1)
        return Strip(self.normal, off, self.halfwidth)

    def minkowski_sum(self, other: Any) -> Strip:
        """Exact ``strip + S`` for a bounded set S: widen by S's extent along the normal."""
        if isinstance(other, Tensor):
            return self.translate(other)
        hp = other.support(self.normal)
        hm = other.support(-self.normal)
        return Strip(self.normal, self.offset + 0.5 * (hp - hm), self.halfwidth + 0.5 * (hp + hm))

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        raise ValueError("Strip: unbounded set, cannot sample uniformly (intersect it first)")

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        raise ValueError("Strip: unbounded set, no extreme points")

    def intersects_strip(self, strip: Any, atol: float = 0.0) -> Tensor:
        raise ValueError("Strip.intersects_strip: two strips with different normals always meet")
