"""Parallelotopes ``P = {c + T eta : ||eta||_inf <= 1}``, T square and invertible (seed 000).

``center [..., n]``, ``T [..., n, n]``. Batched and differentiable; linear solves, never
explicit inverses.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from diffsmf.sets.base import ConvexSet, as_tensor, check_finite

if TYPE_CHECKING:  # pragma: no cover
    from diffsmf.sets.ellipsoid import Ellipsoid
    from diffsmf.sets.interval import Interval
    from diffsmf.sets.strip import Strip
    from diffsmf.sets.zonotope import Zonotope

__all__ = ["Parallelotope"]

_EPS = torch.finfo(torch.float64).eps


class Parallelotope(ConvexSet):
    """Parallelotope ``{c + T eta : eta in [-1, 1]^n}`` (seed 000 "hyperparallel space").

    Args:
        center: ``[..., n]``.
        T: ``[..., n, n]``, invertible. Batch dims broadcast.

    Raises:
        ValueError: naming ``center`` or ``T`` on NaN/inf, a shape mismatch, or a singular
            ``T`` (smallest singular value <= 1e-13 x largest).
    """

    _fields: ClassVar[tuple[str, ...]] = ("_c", "T")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 2)

    def __init__(self, center: Any, T: Any) -> None:
        c = check_finite("center", as_tensor("center", center, min_dim=1))
        T = check_finite("T", as_tensor("T", T, like=c, min_dim=2))
        n = c.shape[-1]
        if T.shape[-1] != T.shape[-2]:
            raise ValueError(f"T: must be square, got shape {tuple(T.shape)}")
        if T.shape[-1] != n:
            raise ValueError(f"T: expected [..., {n}, {n}] to match center, got {tuple(T.shape)}")
        try:
            batch = torch.broadcast_shapes(c.shape[:-1], T.shape[:-2])
        except RuntimeError as exc:
            raise ValueError(
                f"T: batch shape {tuple(T.shape[:-2])} does not broadcast with center batch "
                f"shape {tuple(c.shape[:-1])}"
            ) from exc
        if T.numel() > 0:
            sv = torch.linalg.svdvals(T.detach())
            if (sv[..., -1] <= 1e-13 * sv[..., 0]).any() or (sv[..., 0] == 0).any():
                raise ValueError("T: singular (parallelotope must be full-dimensional)")
        self._set(_c=c.expand(*batch, n), T=T.expand(*batch, n, n))

    @classmethod
    def _make(cls, c: Tensor, T: Tensor) -> Parallelotope:
        """Internal constructor without validation (broadcasts the batch dims)."""
        batch = torch.broadcast_shapes(c.shape[:-1], T.shape[:-2])
        n = c.shape[-1]
        obj = object.__new__(cls)
        object.__setattr__(obj, "_c", c.expand(*batch, n))
        object.__setattr__(obj, "T", T.expand(*batch, n, n))
        return obj

    @property
    def center(self) -> Tensor:
        """``[..., n]``."""
        return self._c

    @property
    def generators(self) -> Tensor:
        """``T`` viewed as zonotope generators ``[..., n, n]``."""
        return self.T

    # ------------------------------------------------------------------ set API
    def volume(self) -> Tensor:
        """``2^n |det T|`` -> ``[...]`` (seed 000)."""
        return (2.0**self.dim) * torch.linalg.det(self.T).abs()

    def support(self, d: Tensor) -> Tensor:
        """h(d) = d.c + ||T' d||_1; ``d [..., n]`` -> ``[...]``."""
        d = as_tensor("d", d, like=self._c, min_dim=1)
        return (d * self._c).sum(-1) + (d.unsqueeze(-1) * self.T).sum(-2).abs().sum(-1)

    def interval_hull(self) -> Interval:
        """Box ``c +- sum_j |T_:,j|`` (exact)."""
        from diffsmf.sets.interval import Interval

        r = self.T.abs().sum(-1)
        return Interval(self._c - r, self._c + r)

    def to_interval(self) -> Interval:
        return self.interval_hull()

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """Exact membership: ``eta = T^-1 (x - c)`` by a solve; ``|eta_i| ||T_:,i|| <=
        ||T_:,i|| + atol`` (``atol`` in distance units along each edge) -> bool ``[...]``."""
        x = as_tensor("x", x, like=self._c, min_dim=1)
        if x.shape[-1] != self.dim:
            raise ValueError(f"x: expected [..., {self.dim}], got {tuple(x.shape)}")
        with torch.no_grad():
            r = (x - self._c).detach()
            batch = torch.broadcast_shapes(r.shape[:-1], self.batch_shape)
            T = self.T.detach().expand(*batch, self.dim, self.dim)
            eta = torch.linalg.solve(T, r.expand(*batch, self.dim).unsqueeze(-1)).squeeze(-1)
            cn = T.norm(dim=-2)
            tol = atol + 1e-10 * cn
            return ((eta.abs() - 1) * cn <= tol).all(-1)

    def vertices(self) -> Tensor:
        """All ``2^n`` vertices ``c + T s``, s in {-1, 1}^n -> ``[..., 2^n, n]``."""
        s = torch.tensor(
            list(itertools.product((-1.0, 1.0), repeat=self.dim)),
            dtype=self.dtype,
            device=self.device,
        )
        return self._c.unsqueeze(-2) + s @ self.T.transpose(-1, -2)

    def linear_map(self, A: Tensor, b: Tensor | None = None) -> Parallelotope | Zonotope:
        """``{A x + b}``: a Parallelotope ``(A c + b, A T)`` for square ``A [..., n, n]``
        (degenerate if A is singular), else a Zonotope."""
        A = as_tensor("A", A, like=self._c, min_dim=2)
        if A.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., k, {self.dim}], got {tuple(A.shape)}")
        if A.shape[-2] != self.dim:
            return self.to_zonotope().linear_map(A, b)
        c = (A @ self._c.unsqueeze(-1)).squeeze(-1)
        if b is not None:
            b = as_tensor("b", b, like=self._c, min_dim=1)
            if b.shape[-1] != self.dim:
                raise ValueError(f"b: expected [..., {self.dim}], got {tuple(b.shape)}")
            c = c + b
        return Parallelotope._make(c, A @ self.T)

    def translate(self, b: Tensor) -> Parallelotope:
        """``{x + b}``, ``b [..., n]``."""
        b = as_tensor("b", b, like=self._c, min_dim=1)
        if b.shape[-1] != self.dim:
            raise ValueError(f"b: expected [..., {self.dim}], got {tuple(b.shape)}")
        return Parallelotope._make(self._c + b, self.T)

    def minkowski_sum(self, other: ConvexSet | Tensor) -> Zonotope:
        """Exact Minkowski sum as a Zonotope (generators ``[T, G_other]``)."""
        return self.to_zonotope().minkowski_sum(other)

    def to_zonotope(self) -> Zonotope:
        """The same set as a Zonotope with generators ``T``."""
        from diffsmf.sets.zonotope import Zonotope

        return Zonotope._make(self._c, self.T)

    def to_parallelotope(self) -> Parallelotope:
        return self

    def to_ellipsoid(self) -> Ellipsoid:
        """Covering ellipsoid ``shape = n T T' (1 + 1e-12)`` (``||eta||^2 <= n``; guaranteed)."""
        from diffsmf.sets.ellipsoid import Ellipsoid

        n = self.dim
        Q = n * (self.T @ self.T.transpose(-1, -2)) * (1 + 1e-12)
        return Ellipsoid(self._c, (Q + Q.transpose(-1, -2)) / 2)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` points uniform in P -> ``[..., k, n]``."""
        u = torch.rand(
            (*self.batch_shape, k, self.dim),
            dtype=self.dtype,
            device=self.device,
            generator=generator,
        )
        return self._c.unsqueeze(-2) + (2 * u - 1) @ self.T.transpose(-1, -2)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` random vertices ``c + T s`` -> ``[..., k, n]``."""
        u = torch.rand(
            (*self.batch_shape, k, self.dim),
            dtype=self.dtype,
            device=self.device,
            generator=generator,
        )
        s = torch.where(u >= 0.5, 1.0, -1.0).to(self.dtype)
        return self._c.unsqueeze(-2) + s @ self.T.transpose(-1, -2)

    def intersect_strip(self, strip: Strip) -> Parallelotope:  # pragma: no cover - next commit
        raise NotImplementedError
