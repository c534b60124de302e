"""Breiman's hinging-hyperplane model (Breiman 1993), Wang et al. 2009's "model 3" baseline.

``f(x) = sum_k h_k(x)`` with each hinge ``h_k(x) = max(b1 . [x;1], b2 . [x;1])`` or ``min(...)``.
Fitting (Breiman 1993, sec. III; Pucar and Sjoberg 1998): hinges are added one at a time, each
found by the hinge-finding algorithm on the current residual (split the samples by the hinge
hyperplane, fit one affine function on each side by least squares, move the hyperplane to where
the two fits cross, repeat until the split no longer changes), from several random starts and
both max/min types; after each addition all hinges are refitted by backfitting, then jointly
(all hinge sides fixed, one least squares over every coefficient, repeat while it improves).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.pwl._threads import single_thread
from diffsmf.pwl.fit import as_xy

__all__ = ["HingingHyperplanes"]

_F64 = torch.float64


def _lstsq(Xa: Tensor, r: Tensor, mask: Tensor) -> Tensor:
    """Ridge-stabilised least squares of r [N] on the rows of Xa [N, n+1] selected by mask."""
    A = Xa[mask]
    G = A.T @ A
    G = G + 1e-10 * (G.diagonal().sum() + 1) * torch.eye(G.shape[0], dtype=_F64)
    return torch.linalg.solve(G, A.T @ r[mask])


def _hinge_eval(Xa: Tensor, beta: Tensor, sign: Tensor) -> Tensor:
    """Hinges at Xa [N, n+1]: beta [K, 2, n+1], sign [K] (+1 max, -1 min) -> [N, K]."""
    v = torch.einsum("nd,kjd->nkj", Xa, beta)
    return sign * torch.maximum(sign * v[..., 0], sign * v[..., 1])


class HingingHyperplanes(nn.Module):
    """Sum of K hinge functions (Breiman 1993); one output. ``forward(x [..., n]) -> [..., 1]``.

    Args:
        n_hinges: K.
        n_starts: random starting hyperplanes per hinge (the best is kept).
        max_iter: hinge-finding iterations per start.
        backfit_passes: passes of backfitting after each new hinge.
        seed: seed of the random starts.
    """

    def __init__(self, n_hinges: int = 10, n_starts: int = 8, max_iter: int = 30,
                 backfit_passes: int = 2, seed: int = 0):
        super().__init__()
        if n_hinges < 1:
            raise ValueError(f"n_hinges: must be >= 1, got {n_hinges}")
        self.n_hinges = n_hinges
        self.n_starts = n_starts
        self.max_iter = max_iter
        self.backfit_passes = backfit_passes
        self.seed = seed
        self.register_buffer("beta", torch.zeros(0, 2, 1, dtype=_F64))
        self.register_buffer("sign", torch.zeros(0, dtype=_F64))

    # ------------------------------------------------------------------ fitting
    def _find_hinge(self, Xa: Tensor, r: Tensor, gen: torch.Generator
                    ) -> tuple[Tensor, float, float]:
        """Hinge-finding algorithm on residual r [N] -> (beta [2, n+1], sign, sse)."""
        N, d = Xa.shape
        best = (torch.zeros(2, d, dtype=_F64), 1.0, float((r**2).sum()))
        for _ in range(self.n_starts):
            normal = torch.randn(d - 1, generator=gen, dtype=_F64)
            c = Xa[int(torch.randint(N, (1,), generator=gen)), :-1]
            delta = torch.cat([normal, -(normal @ c)[None]])
            for sign in (1.0, -1.0):
                beta = self._iterate_split(Xa, r, sign * (Xa @ delta) >= 0, sign)
                if beta is None:
                    continue
                s = torch.tensor(sign, dtype=_F64)
                sse = float(((r - _hinge_eval(Xa, beta[None], s[None])[:, 0]) ** 2).sum())
                if sse < best[2]:
                    best = (beta, sign, sse)
        return best

    def fit(self, X: Any, y: Any) -> HingingHyperplanes:
        """Fit to X [N, n], y [N] (or [N, 1]); returns self."""
        with single_thread():
            return self._fit(X, y)

    def _fit(self, X: Any, y: Any) -> HingingHyperplanes:
        X, Y = as_xy(X, y)
        if Y.shape[1] != 1:
            raise ValueError(f"y: HingingHyperplanes fits one output, got {Y.shape[1]}")
        if X.shape[0] < 2 * (X.shape[1] + 1):
            raise ValueError(f"X: need at least {2 * (X.shape[1] + 1)} samples for one hinge")
        r_all = Y[:, 0]
        Xa = torch.cat([X, torch.ones(X.shape[0], 1, dtype=_F64)], 1)
        gen = torch.Generator().manual_seed(self.seed)
        betas: list[Tensor] = []
        signs: list[float] = []
        for _ in range(self.n_hinges):
            fitted = self._sum(Xa, betas, signs)
            b, s, _ = self._find_hinge(Xa, r_all - fitted, gen)
            betas.append(b)
            signs.append(s)
            for _ in range(self.backfit_passes):  # backfitting
                for k in range(len(betas)):
                    rest = self._sum(Xa, betas[:k] + betas[k + 1:], signs[:k] + signs[k + 1:])
                    b, s, _ = self._refit(Xa, r_all - rest, betas[k], signs[k])
                    betas[k], signs[k] = b, s
            betas = self._joint_refit(Xa, r_all, betas, signs)
        self.beta = torch.stack(betas)
        self.sign = torch.tensor(signs, dtype=_F64)
        return self

    def _iterate_split(self, Xa: Tensor, r: Tensor, mask: Tensor, sign: float) -> Tensor | None:
        """Breiman's hinge-finding iterations from the split ``mask [N]``: fit one affine map
        per side by least squares, re-split where they cross, until the split is stable.
        Returns ``beta [2, d]`` or ``None`` when a side has fewer than d samples at once."""
        d = Xa.shape[1]
        beta = None
        for _ in range(self.max_iter):
            if int(mask.sum()) < d or int((~mask).sum()) < d:
                break
            b1, b2 = _lstsq(Xa, r, mask), _lstsq(Xa, r, ~mask)
            beta = torch.stack([b1, b2])
            new = sign * (Xa @ (b1 - b2)) >= 0
            if bool((new == mask).all()):
                break
            mask = new
        return beta

    def _refit(self, Xa: Tensor, r: Tensor, beta: Tensor, sign: float
               ) -> tuple[Tensor, float, float]:
        """Hinge-finding iterations started from the current hinge (backfitting step)."""
        found = self._iterate_split(Xa, r, sign * (Xa @ (beta[0] - beta[1])) >= 0, sign)
        beta = beta if found is None else found
        s = torch.tensor(sign, dtype=_F64)
        return beta, sign, float(((r - _hinge_eval(Xa, beta[None], s[None])[:, 0]) ** 2).sum())

    def _joint_refit(self, Xa: Tensor, y: Tensor, betas: list[Tensor], signs: list[float]
                     ) -> list[Tensor]:
        """All hinges at once (Pucar and Sjoberg 1998): with the hinge sides fixed the model is
        linear in every beta; least squares, update the sides, repeat while the error drops."""
        sg = torch.tensor(signs, dtype=_F64)
        beta = torch.stack(betas)
        sse = float(((y - _hinge_eval(Xa, beta, sg).sum(-1)) ** 2).sum())
        for _ in range(self.max_iter):
            m = (sg * (Xa @ (beta[:, 0] - beta[:, 1]).T) >= 0).to(_F64)  # [N, K]
            D = torch.cat([m[:, :, None] * Xa[:, None], (1 - m)[:, :, None] * Xa[:, None]], 2)
            D = D.reshape(Xa.shape[0], -1)  # [N, K * 2 (n+1)], per hinge: side 1 then side 2
            sol = _lstsq(D, y, torch.ones(Xa.shape[0], dtype=torch.bool))
            new = sol.reshape(len(betas), 2, Xa.shape[1])
            new_sse = float(((y - _hinge_eval(Xa, new, sg).sum(-1)) ** 2).sum())
            if new_sse >= sse * (1 - 1e-12):
                break
            beta, sse = new, new_sse
        return list(beta.unbind(0))

    @staticmethod
    def _sum(Xa: Tensor, betas: list[Tensor], signs: list[float]) -> Tensor:
        if not betas:
            return torch.zeros(Xa.shape[0], dtype=_F64)
        return _hinge_eval(Xa, torch.stack(betas), torch.tensor(signs, dtype=_F64)).sum(-1)

    # ------------------------------------------------------------------ evaluation
    def forward(self, x: Tensor) -> Tensor:
        """x [..., n] -> [..., 1] (differentiable in x)."""
        if self.beta.shape[0] == 0:
            raise ValueError("HingingHyperplanes: call fit first")
        x = torch.as_tensor(x, dtype=_F64)
        xa = torch.cat([x, torch.ones_like(x[..., :1])], -1)
        v = torch.einsum("...d,kjd->...kj", xa, self.beta)
        h = self.sign * torch.maximum(self.sign * v[..., 0], self.sign * v[..., 1])
        return h.sum(-1, keepdim=True)

    def n_parameters(self) -> int:
        return self.beta.numel()

    def n_regions(self, x: Tensor) -> int:
        """Number of distinct linear regions met by the points x [N, n] (hinge activation
        patterns; on a dense grid this counts the model's pieces in the domain)."""
        x = torch.as_tensor(x, dtype=_F64)
        xa = torch.cat([x, torch.ones_like(x[..., :1])], -1)
        v = torch.einsum("nd,kjd->nkj", xa, self.beta)
        pattern = (v[..., 0] >= v[..., 1]).long()
        return int(torch.unique(pattern, dim=0).shape[0])
