"""The weight of an ellipsoid's measurement update (Song et al. 2017, eq. 36-39; Fogel and Huang
1982): the family of updated ellipsoids in the weight rho, its volume, and the search for the
rho that minimises it (bracketing, zoom and Newton steps on the log-volume).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.utils import tracing

__all__ = ["ZOOM_POINTS", "ZOOM_STAGES"]

class _MeasFamily:
    """The rho-family of outer ellipsoids of ``E(c, P) ∩ {(y - Hx)' R^-1 (y - Hx) <= 1}``.

    For the (non-differentiable) search over rho the family is reduced to scalars by the
    simultaneous diagonalisation of ``G = H P H'`` and ``R``: with ``R = L L'``,
    ``L^-1 G L^-T = V diag(gamma) V'``, ``e~ = V' L^-1 e``, ``u_i = |P H' L^-T v_i|^2``,
    ``D_i = rho gamma_i + 1 - rho``:
    ``xi = 1 - rho (1 - rho) sum e~_i^2 / D_i``,
    ``log det P+ = n log xi - (n - m) log(1 - rho) - sum log D_i + const``,
    ``tr P+ = xi / (1 - rho) (tr P - rho sum u_i / D_i)``.
    """

    def __init__(self, P: Tensor, H: Tensor, G: Tensor, R: Tensor, e: Tensor) -> None:
        self.P, self.H, self.G, self.R, self.e = P, H, G, R, e
        self.PH = P @ H.mT  # [..., n, m]
        self.batch = torch.broadcast_shapes(
            P.shape[:-2], H.shape[:-2], G.shape[:-2], R.shape[:-2], e.shape[:-1]
        )
        self.n, self.m = P.shape[-1], G.shape[-1]
        self._reduced = False

    def _reduce(self) -> None:
        """Reduced scalar quantities for the search (computed lazily, no gradient)."""
        if self._reduced:
            return
        self._reduced = True
        P, G, R, e = self.P, self.G, self.R, self.e
        with torch.no_grad():  # a non-PD R (a diverged element): NaN there, flagged later
            L = linalg.lapack_cholesky(R)
            X = torch.linalg.solve_triangular(L, G, upper=False)
            Gt = linalg.sym(torch.linalg.solve_triangular(L, X.mT, upper=False))
            bad, Gt = linalg.finite_or_eye(Gt)
            gam, V = torch.linalg.eigh(Gt)
            gam = torch.where(bad.unsqueeze(-1), torch.nan, gam)
            et = V.mT @ torch.linalg.solve_triangular(L, e.unsqueeze(-1), upper=False)
            U = torch.linalg.solve_triangular(L, self.PH.mT, upper=False)  # L^-1 H P
            U = V.mT @ U
            bs = self.batch
            self.gam = gam.clamp(min=0.0).expand(*bs, self.m)
            self.e2 = (et.squeeze(-1) ** 2).expand(*bs, self.m)
            self.u = (U * U).sum(-1).expand(*bs, self.m)
            self.trP = torch.diagonal(P, dim1=-2, dim2=-1).sum(-1).expand(bs)

    @property
    def requires_grad(self) -> bool:
        return any(t.requires_grad for t in (self.P, self.H, self.G, self.R, self.e))

    # ---------------------------------------------------------------- reduced (search only)
    def _Di(self, rho: Tensor) -> Tensor:
        self._reduce()
        r = rho.unsqueeze(-1)
        return r * self.gam.unsqueeze(-2) + (1 - r)  # rho [..., K] -> [..., K, m]

    def _xi_r(self, rho: Tensor, Di: Tensor) -> Tensor:
        return 1.0 - rho * (1 - rho) * (self.e2.unsqueeze(-2) / Di).sum(-1)

    def red_log_volume(self, rho: Tensor) -> Tensor:
        Di = self._Di(rho)
        xi = self._xi_r(rho, Di).clamp(min=1e-300)
        return (
            self.n * torch.log(xi) - (self.n - self.m) * torch.log1p(-rho) - torch.log(Di).sum(-1)
        )

    def red_trace(self, rho: Tensor) -> Tensor:
        Di = self._Di(rho)
        xi = self._xi_r(rho, Di).clamp(min=1e-300)
        tr = self.trP.unsqueeze(-1) - rho * (self.u.unsqueeze(-2) / Di).sum(-1)
        return xi / (1 - rho) * tr

    def empty(self) -> Tensor:
        """True where the intersection is empty: ``max_rho rho(1-rho) e'D^-1 e > 1``
        (the maximand is concave in rho: a minimum over x of functions affine in rho)."""

        def phi(rho: Tensor) -> Tensor:
            return 1.0 - self._xi_r(rho, self._Di(rho))

        best = _zoom(phi, self.batch, self.P, maximize=True)
        return phi(best.unsqueeze(-1)).squeeze(-1) > 1.0

    # ---------------------------------------------------------------- full (differentiable)
    def _D(self, rho: Tensor) -> Tensor:
        rr = rho[..., None, None]
        return linalg.sym(rr * self.G + (1 - rr) * self.R)

    def _xi(self, rho: Tensor, L: Tensor) -> Tensor:
        ee = self.e.unsqueeze(-1).expand(*L.shape[:-1], 1)
        z = linalg.solve_lower(L, ee)
        return 1.0 - rho * (1 - rho) * (z * z).sum((-2, -1))

    def evaluate(self, rho: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
        """Center and shape for ``rho [...]`` (eq. 36-39 in the rho-safe form)."""
        D = self._D(rho)
        L = linalg.cholesky(D)
        xi = self._xi(rho, L).clamp(min=1e-12)
        ee = self.e.unsqueeze(-1).expand(*L.shape[:-1], 1)
        De = linalg.cholesky_solve(ee, L)
        rr = rho[..., None, None]
        c2 = c + (rr * self.PH @ De).squeeze(-1)
        PHt = self.PH.mT.expand(*L.shape[:-2], *self.PH.mT.shape[-2:])
        W = linalg.cholesky_solve(PHt, L)  # D^-1 H P
        KHP = rr * self.PH @ W
        core = self.P - KHP
        # guarantee floor: as rho -> 1 with H P H' >> R the difference cancels (e.g. 6e4 -
        # 6e4 -> 3e-8); its rounding error in entry (i, j) is below 16 (n + m) eps a_i a_j with
        # a_i = sqrt(P_ii) + sqrt(|KHP_ii|) (|M_ij| <= sqrt(M_ii M_jj) for these PSD terms), a
        # matrix that n eps' diag(a^2) dominates (Gershgorin after scaling by a). Per
        # coordinate, so that it does not depend on the units of the states (a multiple of I
        # sized by ||P||_F added a state's variance to every other one).
        eps = torch.finfo(core.dtype).eps
        n = self.P.shape[-1]
        err = 16 * (n + self.H.shape[-2]) * eps * n
        dP = torch.diagonal(self.P, dim1=-2, dim2=-1).clamp(min=0)
        dK = torch.diagonal(KHP, dim1=-2, dim2=-1).abs()
        a = (dP.sqrt() + dK.sqrt()).detach()
        core = core + torch.diag_embed(err * a * a)
        P2 = (xi / (1 - rho))[..., None, None] * core
        return c2, linalg.sym(P2)

    def log_volume(self, rho: Tensor) -> Tensor:
        """``log det P+`` up to a constant (differentiable, Cholesky based)."""
        L = linalg.cholesky(self._D(rho))
        xi = self._xi(rho, L).clamp(min=1e-300)
        logdetD = 2 * torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)
        return self.n * torch.log(xi) - (self.n - self.m) * torch.log1p(-rho) - logdetD

    def trace(self, rho: Tensor) -> Tensor:
        L = linalg.cholesky(self._D(rho))
        xi = self._xi(rho, L).clamp(min=1e-300)
        PHt = self.PH.mT.expand(*L.shape[:-2], *self.PH.mT.shape[-2:])
        W = linalg.cholesky_solve(PHt, L)
        trP = torch.diagonal(self.P, dim1=-2, dim2=-1).sum(-1)
        return xi / (1 - rho) * (trP - rho * (self.PH * W.mT).sum((-2, -1)))


#: Points per stage and stages of the bracketing search `_zoom`: each stage keeps 2 of
#: ZOOM_POINTS - 1 intervals (a factor 1/4), 13 stages narrow the bracket to 4^-13 = 1.5e-8 of
#: its width, below the 36-step golden-section search it replaced (0.618^36 = 2.9e-8), in 13
#: vectorised evaluations instead of 36 sequential ones (a third of the graph under
#: torch.compile).
ZOOM_POINTS = 9


ZOOM_STAGES = 13


def _zoom(
    fun: Any,
    batch: torch.Size,
    like: Tensor,
    maximize: bool = False,
    lo: Tensor | None = None,
    hi: Tensor | None = None,
    top: float = 1.0 - 1e-9,
    points: int = ZOOM_POINTS,
    stages: int = ZOOM_STAGES,
) -> Tensor:
    """Batched bracketing search of a unimodal ``fun(rho [..., K]) -> [..., K]`` on ``[lo, hi]``
    (default ``[0, top]``) -> the midpoint of the final bracket ``[...]`` (no gradient).

    Each stage evaluates ``points`` equispaced points of the bracket at once and keeps the two
    intervals around the best one, which contain the optimum of a unimodal function. Branch-free
    (compile-ready); the same result in eager mode and under ``torch.compile``.
    """
    with torch.no_grad():
        a = torch.zeros(batch, dtype=like.dtype, device=like.device) if lo is None else lo
        b = torch.full(batch, top, dtype=like.dtype, device=like.device) if hi is None else hi
        a, b = a.expand(batch), b.expand(batch)
        sign = -1.0 if maximize else 1.0
        t = torch.linspace(0.0, 1.0, points, dtype=like.dtype, device=like.device)
        last = points - 1
        for _ in range(stages):
            x = a.unsqueeze(-1) + (b - a).unsqueeze(-1) * t  # [..., K]
            i = (sign * fun(x)).argmin(-1, keepdim=True)
            a_new = torch.gather(x, -1, (i - 1).clamp(min=0)).squeeze(-1)
            b = torch.gather(x, -1, (i + 1).clamp(max=last)).squeeze(-1)
            a = a_new
        return 0.5 * (a + b)


def _minimize_rho(
    red_obj: Any,
    full_obj: Any,
    batch: torch.Size,
    like: Tensor,
    needs_grad: bool,
    top: float = 1.0 - 1e-9,
    grid: int = 33,
) -> Tensor:
    """Minimise the family objective over ``rho in [0, 1)``: coarse grid and bracketing refinement
    on the reduced (scalar) objective without gradient, then one differentiable Newton step on
    the full objective (autograd derivatives; implicit function theorem)."""
    with torch.no_grad():
        pts = torch.linspace(0.0, top, grid, dtype=like.dtype, device=like.device)
        vals = red_obj(pts.expand(*batch, grid))
        i = vals.argmin(-1)
        lo = pts[(i - 1).clamp(min=0)]
        hi = pts[(i + 1).clamp(max=grid - 1)]
        rho0 = _zoom(red_obj, batch, like, lo=lo, hi=hi, top=top).clamp(0.0, top)
        at_edge = (rho0 <= 1e-7) | (rho0 >= top - 1e-7)
        rho0 = torch.where(rho0 <= 1e-7, torch.zeros_like(rho0), rho0)
    if not (torch.is_grad_enabled() and needs_grad):
        return rho0
    if tracing():  # torch.compile cannot trace autograd.grad: forward mode, same derivatives
        g, h = _rho_derivatives(full_obj, rho0.detach())
    else:
        with torch.enable_grad():
            r = rho0.detach().clone().requires_grad_(True)
            f = full_obj(r)
            (g,) = torch.autograd.grad(f.sum(), r, create_graph=True)
            (h,) = torch.autograd.grad(g.sum(), r, create_graph=True)
    ok = (~at_edge) & (h.detach() > 0)
    step = torch.where(ok, g / torch.where(ok, h, torch.ones_like(h)), torch.zeros_like(g))
    # value: the Newton-polished root; derivative: -d(obj')/d(theta) / obj'' (r is constant)
    return (rho0 - step).detach().clamp(0.0, top) - (step - step.detach())


def _rho_derivatives(obj: Any, r: Tensor) -> tuple[Tensor, Tensor]:
    """First and second derivatives of the elementwise objective ``obj(r) [...]`` at ``r``
    in forward-over-reverse mode (``torch.func.jvp`` of ``torch.func.grad`` of the sum, unit
    tangent: each element's objective depends on its own ``r`` only), differentiable w.r.t.
    what ``obj`` closes over.
    The traceable twin of `_minimize_rho`'s two ``autograd.grad`` calls (equal up to
    rounding)."""
    from torch.func import grad, jvp

    def total(x: Tensor) -> Tensor:
        return obj(x).sum()

    g, h = jvp(grad(total), (r,), (torch.ones_like(r),))
    return g, h
