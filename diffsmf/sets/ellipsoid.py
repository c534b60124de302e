"""Ellipsoids ``{x : (x - c)' S^-1 (x - c) <= 1}`` (seed 001 eq. 10-17, seed 003 eq. 34-36)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from diffsmf.sets.base import ConvexSet, as_tensor, check_finite

if TYPE_CHECKING:  # pragma: no cover
    from diffsmf.sets.interval import Interval

__all__ = ["Ellipsoid"]


def _sym(S: Tensor) -> Tensor:
    return 0.5 * (S + S.mT)


def _chol(name: str, S: Tensor) -> Tensor:
    """Cholesky factor; ``ValueError`` naming ``name`` if not positive definite."""
    L, info = torch.linalg.cholesky_ex(S)
    if bool((info != 0).any()):
        raise ValueError(f"{name}: not symmetric positive definite")
    return L


def unit_ball_volume(n: int) -> float:
    """Volume of the unit n-ball ``pi^(n/2) / Gamma(n/2 + 1)``."""
    return math.exp(0.5 * n * math.log(math.pi) - math.lgamma(0.5 * n + 1.0))


class Ellipsoid(ConvexSet):
    """Batched ellipsoid ``{x : (x - c)' shape^-1 (x - c) <= 1}``.

    Args:
        center: ``[..., n]``.
        shape: ``[..., n, n]`` symmetric positive definite (checked by Cholesky; symmetrised).
    Batch dims broadcast.
    """

    _fields: ClassVar[tuple[str, ...]] = ("center_", "shape")
    _event_dims: ClassVar[tuple[int, ...]] = (1, 2)
    center_: Tensor
    shape: Tensor

    def __init__(self, center: Any, shape: Any) -> None:
        c = as_tensor("center", center, min_dim=1)
        S = as_tensor("shape", shape, like=c, min_dim=2)
        check_finite("center", c)
        check_finite("shape", S)
        n = c.shape[-1]
        if S.shape[-2:] != (n, n):
            raise ValueError(f"shape: expected [..., {n}, {n}], got {tuple(S.shape)}")
        Sd = S.detach()
        scale = Sd.abs().amax(dim=(-2, -1)).clamp(min=1e-300)
        if ((Sd - Sd.mT).abs().amax(dim=(-2, -1)) > 1e-8 * scale).any():
            raise ValueError("shape: not symmetric")
        try:
            batch = torch.broadcast_shapes(c.shape[:-1], S.shape[:-2])
        except RuntimeError as exc:
            raise ValueError(
                f"shape: batch shape {tuple(S.shape[:-2])} does not broadcast with center "
                f"{tuple(c.shape[:-1])}"
            ) from exc
        S = _sym(S)
        _chol("shape", S.detach())
        self._set(center_=c.expand(*batch, n), shape=S.expand(*batch, n, n))

    @classmethod
    def _make(cls, center: Tensor, shape: Tensor) -> Ellipsoid:
        """Construct without validation (internal; inputs known valid)."""
        obj = object.__new__(cls)
        batch = torch.broadcast_shapes(center.shape[:-1], shape.shape[:-2])
        n = center.shape[-1]
        object.__setattr__(obj, "center_", center.expand(*batch, n))
        object.__setattr__(obj, "shape", shape.expand(*batch, n, n))
        return obj

    @property
    def center(self) -> Tensor:
        return self.center_

    def cholesky(self) -> Tensor:
        """Lower Cholesky factor ``L`` of the shape, ``[..., n, n]``."""
        return torch.linalg.cholesky(self.shape)

    # ------------------------------------------------------------------ exact quantities
    def volume(self) -> Tensor:
        """``V_n sqrt(det S)`` with ``V_n`` the unit-ball volume -> ``batch_shape``."""
        return unit_ball_volume(self.dim) * torch.exp(self.log_det_half())

    def log_det_half(self) -> Tensor:
        """``0.5 log det S`` (via Cholesky)."""
        L = self.cholesky()
        return torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)

    def log_volume(self) -> Tensor:
        return math.log(unit_ball_volume(self.dim)) + self.log_det_half()

    def mahalanobis2(self, x: Tensor) -> Tensor:
        """``(x - c)' S^-1 (x - c)`` via a triangular solve -> ``[...]`` (x broadcasts)."""
        x = as_tensor("x", x, like=self.center_)
        d = (x - self.center_).unsqueeze(-1)
        L = self.cholesky()
        batch = torch.broadcast_shapes(d.shape[:-2], L.shape[:-2])
        n = self.dim
        z = torch.linalg.solve_triangular(
            L.expand(*batch, n, n), d.expand(*batch, n, 1), upper=False
        )
        return (z * z).sum((-2, -1))

    def contains(self, x: Tensor, atol: float = 1e-9) -> Tensor:
        """``(x - c)' S^-1 (x - c) <= 1 + atol`` -> bool ``[...]``."""
        return self.mahalanobis2(x) <= 1.0 + atol

    def support(self, d: Tensor) -> Tensor:
        """``h(d) = d.c + sqrt(d' S d)`` -> ``[...]``."""
        d = as_tensor("d", d, like=self.center_)
        q = (d.unsqueeze(-2) @ self.shape @ d.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        return (d * self.center_).sum(-1) + torch.sqrt(q.clamp(min=0.0))

    def interval_hull(self) -> Interval:
        """``c +- sqrt(diag S)`` (rounded outward)."""
        from diffsmf.sets.interval import Interval

        r = torch.sqrt(torch.diagonal(self.shape, dim1=-2, dim2=-1).clamp(min=0.0))
        return Interval.from_center_radius(self.center_, r)

    # ------------------------------------------------------------------ maps
    def linear_map(self, A: Tensor, b: Tensor | None = None, reg: float = 1e-12) -> Ellipsoid:
        """Image ``{A x + b}`` = Ellipsoid(A c + b, A S A'); ``A [..., k, n]`` any k.

        The image is exact when ``A S A'`` is positive definite (square invertible A, or k <= n
        with full row rank). Otherwise (k > n or rank-deficient A) the image is a degenerate
        ellipsoid; it is replaced by the outer bound ``A S A' + reg * (tr(A S A')/k + 1e-300) I``
        so that the shape stays positive definite (documented deviation).
        """
        A = as_tensor("A", A, like=self.center_, min_dim=2)
        if A.shape[-1] != self.dim:
            raise ValueError(f"A: expected [..., k, {self.dim}], got {tuple(A.shape)}")
        c = (A @ self.center_.unsqueeze(-1)).squeeze(-1)
        if b is not None:
            c = c + as_tensor("b", b, like=self.center_)
        S = _sym(A @ self.shape @ A.mT)
        k = A.shape[-2]
        _, info = torch.linalg.cholesky_ex(S.detach())
        if bool((info != 0).any()) or k > self.dim:
            eye = torch.eye(k, dtype=S.dtype, device=S.device)
            tr = torch.diagonal(S, dim1=-2, dim2=-1).sum(-1) / k
            jitter = (reg * (tr + 1e-300)).unsqueeze(-1).unsqueeze(-1) * eye
            bad = (info != 0).reshape(info.shape + (1, 1)) | (k > self.dim)
            S = torch.where(bad, S + jitter, S)
        return Ellipsoid._make(c, S)

    def translate(self, b: Tensor) -> Ellipsoid:
        b = as_tensor("b", b, like=self.center_)
        return Ellipsoid._make(self.center_ + b, self.shape)

    # ------------------------------------------------------------------ sampling
    def _unit_ball(self, k: int, generator: torch.Generator | None, boundary: bool) -> Tensor:
        n = self.dim
        shape = (*self.batch_shape, k, n)
        g = torch.randn(shape, generator=generator, dtype=self.dtype, device=self.device)
        u = g / g.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        if boundary:
            return u
        r = torch.rand(shape[:-1], generator=generator, dtype=self.dtype, device=self.device)
        return u * r.pow(1.0 / n).unsqueeze(-1)

    def sample(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` uniform points inside -> ``[*batch_shape, k, n]``."""
        u = self._unit_ball(k, generator, boundary=False)
        L = self.cholesky().unsqueeze(-3)
        return self.center_.unsqueeze(-2) + (L @ u.unsqueeze(-1)).squeeze(-1)

    def sample_extreme(self, k: int, generator: torch.Generator | None = None) -> Tensor:
        """``k`` random boundary points -> ``[*batch_shape, k, n]``."""
        u = self._unit_ball(k, generator, boundary=True)
        L = self.cholesky().unsqueeze(-3)
        return self.center_.unsqueeze(-2) + (L @ u.unsqueeze(-1)).squeeze(-1)
