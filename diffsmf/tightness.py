"""How far a filter's set is from the best possible: inner estimates of the feasible set.

The exact feasible set at step k is ``X_k = {x_k : x_0 in X0, w_j in W, theta_j in Theta,
|y_j - h(x_j) - cV| <= rV, j = 1..k}`` (the model, the filter's noise bounds and the data).
Every guaranteed filter returns an outer bound of X_k. For a direction d, any feasible
trajectory gives a point of X_k, so ``[min d.x_k, max d.x_k]`` over the feasible trajectories
found by optimisation is an *inner* estimate of the projection of X_k on d. The report gives,
per direction, ``outer width / inner width`` (>= 1; 1 = the filter is as tight as possible
along d) and every feasible state found outside the filter's set (a containment failure).

Optimisation: scipy SLSQP over ``(x0 parameters, w_0..w_{k-1}[, theta_0..theta_{k-1}])``,
bounds for the boxes, two inequality constraints per measurement component, gradients and
constraint Jacobians by torch autograd; several starts (the true trajectory when known,
which is feasible by construction, then random points of the boxes).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from scipy.optimize import minimize
from torch import Tensor

from diffsmf.filters.base import check_filter
from diffsmf.sets import Ellipsoid, Interval, Parallelotope, Zonotope
from diffsmf.systems.system import Trajectory, check_system

__all__ = ["InnerBounds", "TightnessReport", "inner_bounds", "tightness"]


@dataclass
class InnerBounds:
    """Inner estimates: ``lo``/``hi [S, D]`` of ``d.x_k`` over feasible trajectories found,
    the feasible end states ``points[s]`` (list of ``[n]`` arrays) and solver statistics."""

    steps: list[int]
    directions: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    points: list[list[np.ndarray]]
    solves: int = 0
    feasible_solves: int = 0


@dataclass
class TightnessReport:
    """Per (step, direction): outer/inner widths and their ratio; containment failures."""

    filter: str
    rows: list[dict[str, Any]] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def table(self) -> str:
        lines = [f"{'step':>5} {'direction':>16} {'outer':>11} {'inner':>11} {'ratio':>8}"]
        for r in self.rows:
            d = "[" + ", ".join(f"{v:.2g}" for v in r["direction"]) + "]"
            lines.append(
                f"{r['step']:>5} {d:>16} {r['outer_width']:>11.4g} {r['inner_width']:>11.4g} "
                f"{r['ratio']:>8.3f}"
            )
        lines.append(f"containment failures: {len(self.failures)}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------- the model
class _Problem:
    """Decision vector z = [xi0 (p), w (k n), theta (k q)] for one trajectory and step k."""

    def __init__(self, filt: Any, system: Any, y: Tensor, u: Tensor | None, k: int) -> None:
        self.system, self.k, self.n = system, k, system.n
        self.y, self.u = y[:k], None if u is None else u[:k]
        X0 = system.x0_set
        c0 = X0.center.detach()
        self.ellipsoid = False
        if isinstance(X0, Interval):
            G = torch.diag(((X0.upper - X0.lower) / 2).detach())
            c0 = ((X0.upper + X0.lower) / 2).detach()
        elif isinstance(X0, Parallelotope):  # c + T xi, |xi|_inf <= 1
            G = X0.T.detach()
        elif isinstance(X0, Zonotope):  # c + G xi, |xi|_inf <= 1
            G = X0.generators.detach()
        elif isinstance(X0, Ellipsoid):  # c + L xi, |xi|_2 <= 1
            G = torch.linalg.cholesky(X0.shape.detach())
            self.ellipsoid = True
        else:
            raise ValueError(f"system: unsupported initial set {type(X0).__name__}")
        self.c0, self.G = c0, G
        self.p = G.shape[-1]
        wc, wr = filt.process_noise_center.detach(), filt.process_half_widths.detach()
        self.vc, self.vr = (filt.measurement_noise_center.detach(),
                            filt.measurement_half_widths.detach())
        P = system.parameters
        self.q = 0 if P is None else P.dim
        lo = [-np.ones(self.p)] + [(wc - wr).numpy()] * k
        hi = [np.ones(self.p)] + [(wc + wr).numpy()] * k
        if self.q:
            lo += [P.lower.detach().numpy()] * k
            hi += [P.upper.detach().numpy()] * k
        self.lb, self.ub = np.concatenate(lo), np.concatenate(hi)

    def split(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        p, n, k, q = self.p, self.n, self.k, self.q
        xi, w = z[:p], z[p : p + k * n].reshape(k, n)
        th = z[p + k * n :].reshape(k, q) if q else None
        return xi, w, th

    def rollout(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """End state ``x_k [n]`` and measurement residuals ``[k, m]`` (model eq. of System)."""
        xi, w, th = self.split(z)
        x = self.c0 + self.G @ xi
        res = []
        for j in range(self.k):
            uj = None if self.u is None else self.u[j]
            tj = th[j] if th is not None else self.system.theta_nominal
            x = self.system.f(x, uj, tj) + w[j]
            res.append(self.system.innovation(self.y[j], self.system.h(x)) - self.vc)
        return x, torch.stack(res)

    def constraints(self, z: Tensor) -> Tensor:
        """``>= 0`` when feasible: ``rV -+ residual`` (and ``1 - |xi|^2`` for an ellipsoid)."""
        _, r = self.rollout(z)
        g = torch.cat([(self.vr - r).reshape(-1), (self.vr + r).reshape(-1)])
        if self.ellipsoid:
            g = torch.cat([g, (1 - (z[: self.p] ** 2).sum()).reshape(1)])
        return g

    def start_from_truth(self, x: Tensor, theta: Tensor | None) -> np.ndarray:
        """z reproducing a known trajectory ``x [k+1, n]`` (feasible by construction)."""
        xi = torch.linalg.lstsq(self.G, (x[0] - self.c0).unsqueeze(-1)).solution.squeeze(-1)
        ws = []
        for j in range(self.k):
            uj = None if self.u is None else self.u[j]
            tj = theta[j] if theta is not None else self.system.theta_nominal
            ws.append(x[j + 1] - self.system.f(x[j], uj, tj))
        parts = [xi, torch.stack(ws).reshape(-1)]
        if self.q:
            th = theta[: self.k] if theta is not None else None
            th = self.system.theta_nominal.expand(self.k, -1) if th is None else th
            parts.append(th.reshape(-1))
        return np.clip(torch.cat(parts).detach().numpy(), self.lb, self.ub)


def _solve(
    prob: _Problem, d: Tensor, sign: float, z0: np.ndarray, maxiter: int
) -> tuple[np.ndarray, float]:
    """Maximise ``sign * d.x_k`` from ``z0``; returns (z, max constraint violation)."""

    def t(z: np.ndarray) -> Tensor:
        return torch.as_tensor(z, dtype=torch.float64)

    def obj(z: np.ndarray) -> tuple[float, np.ndarray]:
        zt = t(z).requires_grad_(True)
        val = -sign * (d * prob.rollout(zt)[0]).sum()
        (g,) = torch.autograd.grad(val, zt)
        return float(val.detach()), g.numpy()

    def cons(z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return prob.constraints(t(z)).numpy()

    def cjac(z: np.ndarray) -> np.ndarray:
        return torch.func.jacrev(prob.constraints)(t(z)).numpy()

    r = minimize(
        obj,
        z0,
        jac=True,
        method="SLSQP",
        bounds=list(zip(prob.lb, prob.ub)),
        constraints=[{"type": "ineq", "fun": cons, "jac": cjac}],
        options={"maxiter": maxiter, "ftol": 1e-12},
    )
    z = np.clip(r.x, prob.lb, prob.ub)
    return z, float(max(0.0, -cons(z).min()))


def _check_args(filt: Any, system: Any, traj: Any) -> None:
    """The filter, the system and the trajectory of `inner_bounds` / `tightness`,
    each checked with a ``ValueError`` naming the argument (swapped arguments included)."""
    check_filter("filt", filt, check_system("system", system))
    if not isinstance(traj, Trajectory):
        raise ValueError(
            "traj: must be a diffsmf Trajectory (system.simulate(...), or Trajectory(x, y, u, "
            f"theta) for logged data), got {type(traj).__name__}"
        )


def inner_bounds(
    filt: Any,
    system: Any,
    traj: Any,
    steps: Sequence[int],
    *,
    directions: Tensor | None = None,
    starts: int = 3,
    index: int = 0,
    seed: int = 0,
    maxiter: int = 200,
    feas_tol: float = 1e-10,
) -> InnerBounds:
    """Inner estimates of ``d.x_k`` over feasible trajectories for trajectory ``index``.

    ``directions [D, n]`` (default: the state axes); ``starts`` optimiser starts per
    (step, direction, sign): the true trajectory when ``traj.x`` is known, then uniform random
    points of the boxes. A solution counts only if every constraint holds to ``feas_tol``
    (absolute, in measurement units).
    """
    _check_args(filt, system, traj)
    n = system.n
    D = torch.eye(n, dtype=torch.float64) if directions is None else torch.as_tensor(directions)
    if D.dim() != 2 or D.shape[-1] != n:
        raise ValueError(f"directions: expected [D, {n}], got {tuple(D.shape)}")
    T = traj.y.shape[1]
    if any(not 1 <= k <= T for k in steps):
        raise ValueError(f"steps: each must be in 1..{T}, got {list(steps)}")
    y = traj.y[index].detach()
    u = None if traj.u is None else traj.u[index].detach()
    x_true = None if getattr(traj, "x", None) is None else traj.x[index].detach()
    th_true = None if getattr(traj, "theta", None) is None else traj.theta[index].detach()
    rng = np.random.default_rng(seed)
    lo = np.full((len(steps), D.shape[0]), np.inf)
    hi = np.full((len(steps), D.shape[0]), -np.inf)
    points: list[list[np.ndarray]] = []
    out = InnerBounds(list(steps), D.numpy(), lo, hi, points)
    for si, k in enumerate(steps):
        prob = _Problem(filt, system, y, u, k)
        z_starts = []
        if x_true is not None:
            z_starts.append(prob.start_from_truth(x_true[: k + 1], th_true))
        while len(z_starts) < starts:
            z_starts.append(rng.uniform(prob.lb, prob.ub))
        pts = []
        if x_true is not None:
            pts.append(x_true[k].numpy())
        for di in range(D.shape[0]):
            for sign in (1.0, -1.0):
                for z0 in z_starts:
                    z, viol = _solve(prob, D[di], sign, z0, maxiter)
                    out.solves += 1
                    if viol > feas_tol:
                        continue
                    out.feasible_solves += 1
                    with torch.no_grad():
                        xk = prob.rollout(torch.as_tensor(z))[0].numpy()
                    pts.append(xk)
        P = np.stack(pts) if pts else np.zeros((0, n))
        if len(P):
            proj = P @ D.numpy().T  # [N, D]
            lo[si], hi[si] = proj.min(0), proj.max(0)
        points.append(list(P))
    return out


def tightness(
    filt: Any,
    system: Any,
    traj: Any,
    steps: Sequence[int],
    *,
    directions: Tensor | None = None,
    starts: int = 3,
    index: int = 0,
    seed: int = 0,
    inner: InnerBounds | None = None,
    atol: float = 1e-9,
) -> TightnessReport:
    """Tightness of ``filt`` on trajectory ``index`` of ``traj`` at ``steps`` (1-based k).

    Runs the filter on that trajectory, computes (or takes) `inner_bounds`, and reports
    per step and direction: ``outer_width = h(d) + h(-d)`` of the filter's set, the inner
    width, ``ratio = outer / inner`` and every feasible state outside the set
    (``contains(atol)`` false: a containment failure). ``inner`` may be shared between filters
    with the same noise bounds (the feasible set does not depend on the filter).
    """
    _check_args(filt, system, traj)
    if inner is None:
        inner = inner_bounds(
            filt, system, traj, steps, directions=directions, starts=starts, index=index, seed=seed
        )
    with torch.no_grad():
        u = None if traj.u is None else traj.u[index : index + 1]
        res = filt(traj.y[index : index + 1], u=u)
    rep = TightnessReport(filter=type(filt).__name__)
    D = torch.as_tensor(inner.directions)
    for si, k in enumerate(inner.steps):
        S = res.sets[0, k]
        with torch.no_grad():
            hp, hm = S.support(D), S.support(-D)
        for di in range(D.shape[0]):
            iw = float(inner.hi[si, di] - inner.lo[si, di])
            ow = float(hp[di] + hm[di])
            rep.rows.append(
                {
                    "step": k,
                    "direction": D[di].tolist(),
                    "outer_width": ow,
                    "inner_width": iw,
                    "ratio": ow / iw if iw > 0 else float("inf"),
                    "outer": [float(-hm[di]), float(hp[di])],
                    "inner": [float(inner.lo[si, di]), float(inner.hi[si, di])],
                }
            )
        for x in inner.points[si]:
            xt = torch.as_tensor(x)
            if not bool(S.contains(xt, atol=atol)):
                rep.failures.append({"step": k, "state": x.tolist()})
    return rep
