"""ESO: ellipsoidal strip observers, CORA's ESO-A (Gollamudi et al. 1996) and ESO-B (Liu et al.
2016), for nonlinear models through the linearisation and remainder of `CDSMF`.

The set after each update is the optimal-bounding-ellipsoid (OBE) family
``{x : (x - c)' Q^-1 (x - c) <= sigma^2}``, kept as the ellipsoid of shape ``sigma^2 Q``
(``state.set``) and ``sigma^2`` (``extras["sigma2"]``). One measurement update of weight
``lambda in (0, 1)`` combines the prior with the measurement's bound:

* ESO-A (``method="gollamudi"``): ``||y' - H x||_2 <= gamma``; ``Q+^-1 = (1 - lambda) Q^-1 +
  lambda H'H``, ``c+ = c + lambda Q+ H' delta``, ``sigma+^2 = (1 - lambda) sigma^2 + lambda
  gamma^2 - lambda (1 - lambda) delta' ((1 - lambda) I + lambda H Q H')^-1 delta``
  (Gollamudi et al. 1996, Theorem 1), ``lambda = min(alpha, nu)`` with their optimal ``nu``
  (Theorem 2);
* ESO-B (``method="liu"``): ``(y' - H x)' V^-1 (y' - H x) <= 1``; ``T = V / lambda + H Q H' /
  (1 - lambda)``, ``K = Q H' T^-1 / (1 - lambda)``, ``c+ = c + K delta``, ``Q+ = (I - K H) Q /
  (1 - lambda)``, ``sigma+^2 = (1 - lambda) sigma^2 + lambda - delta' T^-1 delta`` (Liu et al.
  2016, eq. 23-27 and Theorem 3 for lambda).

``y' - H x`` is the linearised measurement residual: ``H`` the Stirling slopes of ``h`` at the
centre, the remainder of ``h`` over the ellipsoid's hull and the noise box folded into
per-output half-widths ``w`` (`linearised_strips`); ``gamma = ||w||_2`` and ``V = diag(m w^2)``
(the covering ellipsoid of the box). Every ``lambda in (0, 1)`` gives an outer bound, so the
weight rules only decide the tightness; an element whose rule gives no such weight, or whose
data leave ``sigma+^2 <= 0`` (no state is consistent), keeps its prior (``consistent`` False
for the latter). The prediction is `CDSMF`'s with the trace rule (CORA's).

Deviations from CORA's ESO-A/B, which are not guaranteed as written: see the errata page.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf import linalg
from diffsmf.filters.base import FilterState
from diffsmf.filters.cdsmf import CDSMF
from diffsmf.filters.state import updated_state
from diffsmf.filters.strips import linearised_strips
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.systems.system import System

__all__ = ["ESO"]

#: the rules for the weight of a measurement update
METHODS = ("gollamudi", "liu")
SIGMA2 = "sigma2"


class ESO(CDSMF):
    """Ellipsoidal strip observer (ESO-A / ESO-B), guaranteed.

    Args:
        system: the system to filter.
        method: ``"gollamudi"`` (CORA's ESO-A) or ``"liu"`` (ESO-B).
        alpha: Gollamudi's upper bound on the weight, in (0, 1) (CORA: 1e-4; default 0.5).
        sum_method: the prediction's Minkowski rule (default ``"trace"``, CORA's).
        **kw: as `CDSMF` (``stirling_step``, ``remainder``, ``initial_set``, noise, ...).

    State set: ``Ellipsoid`` ``[B]`` of shape ``sigma^2 Q``; ``extras["sigma2"] [B]``.
    """

    def __init__(self, system: System, *, method: str = "gollamudi", alpha: float = 0.5,
                 sum_method: str = "trace", **kw) -> None:
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        if not (isinstance(alpha, (int, float)) and 0 < alpha < 1):
            raise ValueError(f"alpha: the largest weight must be in (0, 1), got {alpha!r}")
        super().__init__(system, sum_method=sum_method, **kw)
        self.method, self.alpha = method, float(alpha)

    def _initial_state(self, batch: int | None = None) -> FilterState:
        state = super()._initial_state(batch)
        one = torch.ones(state.set.batch_shape, dtype=state.set.dtype,
                         device=state.set.center.device)
        return state.replace(extras={**state.extras, SIGMA2: one})

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        new = super()._predict(state, u)  # the set sigma^2 Q itself (sigma^2 unchanged)
        return new.replace(extras={**new.extras, SIGMA2: state.extras[SIGMA2]})

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        E = state.set
        s2 = state.extras[SIGMA2]
        a, d, w, ev = linearised_strips(self, E, E.interval_hull(), y)
        usable = (torch.isfinite(w) & torch.isfinite(a).all(-1)).all(-1)
        w = torch.where(usable.unsqueeze(-1), w, torch.ones_like(w))
        a = torch.where(usable.unsqueeze(-1).unsqueeze(-1), a, torch.zeros_like(a))
        Q = E.shape / s2.unsqueeze(-1).unsqueeze(-1)
        delta = d - (a @ E.center.unsqueeze(-1)).squeeze(-1)  # y' - H c
        step = _gollamudi if self.method == "gollamudi" else _liu
        c2, Q2, s22, lam_ok = step(E.center, Q, s2, a, delta, w, self.alpha)
        keep = usable & lam_ok
        consistent = ~keep | (s22 > 0)
        take = keep & (s22 > 0)
        s22 = torch.where(take, s22, s2)
        shape = torch.where(take.unsqueeze(-1).unsqueeze(-1), linalg.sym(Q2) * s22[..., None, None],
                            E.shape)
        center = torch.where(take.unsqueeze(-1), c2, E.center)
        new = updated_state(state, Ellipsoid._make(center, shape), consistent,
                            torch.zeros_like(s2, dtype=torch.int64) if ev is None else ev)
        return new.replace(extras={**new.extras, SIGMA2: s22})


def _gollamudi(c: Tensor, Q: Tensor, s2: Tensor, H: Tensor, delta: Tensor, w: Tensor,
               alpha: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gollamudi et al. 1996, Theorems 1-2 -> (centre, Q, sigma^2, weight found)."""
    m = H.shape[-2]
    g2 = (w * w).sum(-1)  # gamma^2
    HQ = H @ Q
    G = HQ @ H.transpose(-1, -2)
    dd = (delta * delta).sum(-1)
    # the weight (Theorem 2), differentiable where it is chosen; any value in (0, 1) is an
    # outer bound, elsewhere the element keeps its prior
    nu, pos = _obe_weight(_largest_eigenvalue(G), (g2 - s2) / dd.clamp_min(1e-300))
    nu = torch.where(pos, nu, torch.full_like(nu, alpha))
    lam = torch.minimum(nu, torch.full_like(nu, alpha))
    with torch.no_grad():
        ok = (lam > 1e-12) & (lam < 1 - 1e-12) & torch.isfinite(lam) & (dd + s2 > g2)
    lam = torch.where(ok, lam, torch.full_like(lam, 0.5))
    lam_ = lam.unsqueeze(-1).unsqueeze(-1)
    eye = torch.eye(m, dtype=Q.dtype, device=Q.device)
    Gt = (1 - lam_) * eye + lam_ * G
    s22 = (1 - lam) * s2 + lam * g2 - lam * (1 - lam) * (
        delta.unsqueeze(-2) @ linalg.solve(Gt, delta.unsqueeze(-1))).squeeze(-1).squeeze(-1)
    # Q+ = ((1 - lam) Q^-1 + lam H'H)^-1 = (Q - Q H' (H Q H' + (1 - lam)/lam I)^-1 H Q)/(1 - lam)
    S = G + ((1 - lam) / lam).unsqueeze(-1).unsqueeze(-1) * eye
    Q2 = (Q - HQ.transpose(-1, -2) @ linalg.solve(S, HQ)) / (1 - lam_)
    c2 = c + lam.unsqueeze(-1) * (Q2 @ (H.transpose(-1, -2) @ delta.unsqueeze(-1))).squeeze(-1)
    return c2, Q2, s22, ok


def _liu(c: Tensor, Q: Tensor, s2: Tensor, H: Tensor, delta: Tensor, w: Tensor,
         alpha: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # noqa: ARG001 (one signature)
    """Liu et al. 2016, eq. 23-27 with Theorem 3's weight -> (centre, Q, sigma^2, found)."""
    m = H.shape[-2]
    V = torch.diag_embed(m * w * w)  # the covering ellipsoid of the box |v_i| <= w_i
    HQ = H @ Q
    G = HQ @ H.transpose(-1, -2)
    dd = (delta * delta / (m * w * w)).sum(-1)  # delta' V^-1 delta
    # the weight (Theorem 3), differentiable where it is chosen
    Vi = 1 / (m * w * w).sqrt()
    Gn = Vi.unsqueeze(-1) * G * Vi.unsqueeze(-2)  # bar V G bar V'
    lam, pos = _obe_weight(_largest_eigenvalue(Gn), (1 - s2) / dd.clamp_min(1e-300))
    with torch.no_grad():
        ok = (lam > 1e-12) & (lam < 1 - 1e-12) & torch.isfinite(lam) & pos & (s2 + dd > 1)
    lam = torch.where(ok, lam, torch.full_like(lam, 0.5))
    lam_ = lam.unsqueeze(-1).unsqueeze(-1)
    T = V / lam_ + G / (1 - lam_)
    Ti_HQ = linalg.solve(T, HQ)  # T^-1 H Q
    K = Ti_HQ.transpose(-1, -2) / (1 - lam_)  # Q H' T^-1 / (1 - lam)
    Ti_d = linalg.solve(T, delta.unsqueeze(-1))
    s22 = (1 - lam) * s2 + lam - (delta.unsqueeze(-2) @ Ti_d).squeeze(-1).squeeze(-1)
    Q2 = (Q - K @ HQ) / (1 - lam_)
    c2 = c + (K @ delta.unsqueeze(-1)).squeeze(-1)
    return c2, Q2, s22, ok


def _obe_weight(g: Tensor, beta: Tensor) -> tuple[Tensor, Tensor]:
    """The optimal-bounding-ellipsoid weight shared by both rules (Gollamudi et al. 1996,
    Theorem 2; Liu et al. 2016, Theorem 3): ``(1 - sqrt(g / omega)) / (1 - g)`` with ``omega =
    1 + beta (g - 1)``, ``(1 - beta) / 2`` at ``g = 1`` -> (weight, ``omega > 0`` [...]);
    the weight is meaningless where ``omega <= 0`` (the caller replaces or rejects it)."""
    omega = 1 + beta * (g - 1)
    with torch.no_grad():
        near1 = (g - 1).abs() < 1e-12
        pos = omega > 0
    w = torch.where(near1, (1 - beta) / 2,
                    (1 - torch.sqrt(g / torch.where(pos, omega, torch.ones_like(omega))))
                    / torch.where(near1, torch.ones_like(g), 1 - g))
    return w, pos


def _largest_eigenvalue(G: Tensor) -> Tensor:
    """``lambda_max`` of the symmetric ``G [..., m, m]``; NaN where G is not finite (a diverged
    element: its weight is then not found and it keeps its prior), never a batch error."""
    fin = torch.isfinite(G).all(-1).all(-1)
    eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
    safe = torch.where(fin.unsqueeze(-1).unsqueeze(-1), linalg.sym(G), eye)
    g = torch.linalg.eigvalsh(safe)[..., -1]
    return torch.where(fin, g, torch.full_like(g, torch.nan))
