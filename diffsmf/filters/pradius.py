"""The P-radius gain of CORA's PRad-A and PRad-B observers (Le et al. 2013): an offline gain
``L`` for the zonotope observer ``c + L (y - C c)``, ``[(I - L C) G, L F]`` (Alamo et al. 2005,
Property 1 with a gain matrix) that minimises a bound on the set's P-radius.

Le et al. 2013, eq. 17 (as CORA writes it): for ``beta in (0, 1)``, find ``P > 0``, ``Y`` and the
largest ``tau >= 0`` with

    [[beta P,   0,    0,    A'P - A'C'Y'],
     [0,        E'E,  0,    E'P - E'C'Y'],
     [0,        0,    F'F,  F'Y'        ],
     [.,        .,    .,    P           ]]  >= 0,      (1 - beta) P / eps >= tau I,

with ``eps = max ||w||_2 + ||phi||_2^2`` (``phi`` the measurement noise half-widths), and
``L = P^-1 Y``. ``beta`` is bisected in (0, 1) to 0.01 as CORA does: upwards while the LMI is
feasible, downwards where it is not, and the gain is that of the last feasible ``beta`` (on
CORA's 2-D example 0.992; see the errata page). The third row
block is ``F'Y'`` (the paper's and CORA's ``F Y'`` only type-checks for a square F). PRad-A
designs one output at a time (``per_output=True``: the gain's column i from output i alone),
PRad-B all at once.

Any gain gives a guaranteed set (the observer is `MSZM` with ``strip_method="pradius-a"`` /
``"pradius-b"``); the design only decides the tightness. The LMI of the returned design is
rebuilt in numpy and checked (smallest eigenvalue >= ``-1e-7`` relative), independent of the
solver.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

__all__ = ["PRadiusGain", "pradius_gain"]


@dataclass
class PRadiusGain:
    """The result of `pradius_gain`.

    gain: ``L [n, m]``; P: ``[n, n]`` (of the last output designed, for PRad-A); beta: the
    ``beta`` of the design (the largest of the outputs', for PRad-A); status: ``"verified"``
    (the LMI holds in numpy),
    ``"unverified"`` (the solver's point fails the numpy check) or ``"infeasible"`` (no
    ``beta < 1`` is feasible; ``gain`` is then 0, the observer ignores the measurements);
    message: why.
    """

    gain: np.ndarray
    P: np.ndarray
    beta: float
    status: str
    message: str = ""


def _lmi(A, C, E, F, P, Y, beta) -> np.ndarray:
    """The block matrix of Le et al. 2013, eq. 17 (numpy or cvxpy expressions)."""
    n, q, r = A.shape[0], E.shape[1], F.shape[1]
    Z = np.zeros
    top = A.T @ P - A.T @ C.T @ Y.T
    mid = E.T @ P - E.T @ C.T @ Y.T
    low = F.T @ Y.T
    blocks = [[beta * P, Z((n, q)), Z((n, r)), top],
              [Z((q, n)), E.T @ E, Z((q, r)), mid],
              [Z((r, n)), Z((r, q)), F.T @ F, low],
              [top.T, mid.T, low.T, P]]
    return cp.bmat(blocks) if isinstance(P, cp.Expression) else np.block(blocks)


def _solve(A, C, E, F, eps, beta, solver) -> tuple[str, np.ndarray | None, np.ndarray | None]:
    n, m = A.shape[0], C.shape[0]
    P = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((n, m))
    tau = cp.Variable()
    M = _lmi(A, C, E, F, P, Y, beta)
    cons = [P >> 0, 0.5 * (M + M.T) >> 0, (1 - beta) * P / eps >> tau * np.eye(n), tau >= 0]
    prob = cp.Problem(cp.Maximize(tau), cons)
    try:
        with warnings.catch_warnings():  # "may be inaccurate": the design is checked in numpy
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=solver)
    except cp.error.SolverError as exc:
        return f"solver_error: {exc}", None, None
    return prob.status, P.value, Y.value


def _design(A, C, E, F, eps, solver, tol) -> tuple[np.ndarray, np.ndarray, float, str]:
    """CORA's bisection on beta -> (L, P, beta, message) of the last feasible beta (L = 0,
    beta = 1 where none is feasible)."""
    n, m = A.shape[0], C.shape[0]
    lo, hi, best = 0.0, 1.0, None
    while hi - lo > tol:
        beta = 0.5 * (lo + hi)
        status, P, Y = _solve(A, C, E, F, eps, beta, solver)
        if status in ("optimal", "optimal_inaccurate") and P is not None:
            lo, best = beta, (P, Y, beta)
        else:
            hi = beta
    if best is None:
        return np.zeros((n, m)), np.eye(n), 1.0, "no beta < 1 is feasible"
    P, Y, beta = best
    return np.linalg.solve(P, Y), P, beta, ""


def _verified(A, C, E, F, L, P, beta) -> bool:
    M = _lmi(A, C, E, F, P, P @ L, beta)
    M = 0.5 * (M + M.T)
    scale = max(1.0, float(np.abs(M).max()))
    return bool(np.linalg.eigvalsh(M).min() >= -1e-7 * scale
                and np.linalg.eigvalsh(0.5 * (P + P.T)).min() > 0)


def pradius_gain(A, C, E, F, *, per_output: bool = False, solver: str = "CLARABEL",
                 tol: float = 0.01) -> PRadiusGain:
    """P-radius gain (Le et al. 2013, eq. 17) -> `PRadiusGain`.

    Args:
        A: ``[n, n]`` state matrix (for a nonlinear model: its Jacobian at a working point).
        C: ``[m, n]`` output matrix.
        E: ``[n, q]`` process noise generators (``w = E d``, ``|d| <= 1``).
        F: ``[m, r]`` measurement noise generators.
        per_output: design each output's column alone (PRad-A) or all at once (PRad-B).
        solver: a cvxpy SDP solver (default Clarabel).
        tol: the bisection's tolerance on beta.

    Raises:
        ValueError: naming the argument whose shape does not fit.
    """
    A, C, E, F = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (A, C, E, F))
    n, m = A.shape[0], C.shape[0]
    for name, M, rows in (("A", A, n), ("C", C, m), ("E", E, n), ("F", F, m)):
        if M.shape[0] != rows or (name in ("A", "C") and M.shape[1] != n):
            raise ValueError(f"{name}: expected {rows} rows (and {n} columns for A and C), got "
                             f"{M.shape}")
        if not np.isfinite(M).all():
            raise ValueError(f"{name}: has a NaN or an infinite entry")
    eps = _max_norm(E)  # CORA: norm(W), the largest 2-norm of a disturbance
    phi = np.abs(F).sum(1)
    if not per_output:
        L, P, beta, msg = _design(A, C, E, F, eps + float(phi @ phi), solver, tol)
        ok = msg == "" and _verified(A, C, E, F, L, P, beta)
    else:
        cols, ok, msg, beta, P = [], True, "", 0.0, np.eye(n)
        for i in range(m):
            Fi = np.abs(F[i:i + 1]).sum(1, keepdims=True)  # the i-th output's noise box
            Li, P, b, mi = _design(A, C[i:i + 1], E, Fi, eps + float(Fi[0, 0] ** 2), solver, tol)
            ok = ok and mi == "" and _verified(A, C[i:i + 1], E, Fi, Li, P, b)
            cols.append(Li)
            beta, msg = max(beta, b), msg or mi
        L = np.hstack(cols)
    if msg:
        return PRadiusGain(L, P, beta, "infeasible", msg)
    return PRadiusGain(L, P, beta, "verified" if ok else "unverified",
                       "" if ok else "the solver's point fails the LMI in numpy")


def _max_norm(E: np.ndarray) -> float:
    """``max ||E d||_2`` over the cube ``|d| <= 1``: exact over the vertices up to 16
    generators, else the bound ``sum_j ||e_j||_2``."""
    q = E.shape[1]
    if q > 16:
        return float(np.linalg.norm(E, axis=0).sum())
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * q)).reshape(q, -1)
    return float(np.linalg.norm(E @ signs, axis=0).max())
