r"""Iterative-learning estimation of intermittent actuator faults in uncertain repeated systems.

the iterative-learning fault-estimation abstract (the body is another paper); we follow the line of
Shi, He, Zhou (2016), "Iterative learning based estimation of periodically occurring faults".

Repeated system, trial k = 0, 1, ..., time t = 0..N-1 (every trial repeats the same task)::

    x_k(t+1) = (A + D Sigma(t) E) x_k(t) + B u(t) + F f(t),   y_k(t) = C x_k(t),
    |Sigma(t)|_2 <= 1 (time-varying parameter uncertainty),  f(t): intermittent fault (pulses).

Estimator (observer + learning law driven by the PREVIOUS trial's residual)::

    x̂_k(t+1) = A x̂_k(t) + B u(t) + F f̂_k(t) + L (y_k(t) - C x̂_k(t)),   x̂_k(0) = x0
    r_k(t+1) = y_k(t+1) - C x̂_k(t+1)
    f̂_{k+1}(t) = f̂_k(t) + K r_k(t+1)

(measurements may carry bounded noise, y_k(t) = C x_k(t) + v_k(t), fresh on every trial).
With e = x - x̂, Δf = f - f̂, w_k(t) = D Sigma(t) E x_k(t) and the disturbance vector
d_k(t) = [w_k(t); v_k(t); v_k(t+1)] this is a 2-D Roesser model (horizontal state e along t,
vertical state Δf along the trial index k)::

    [e_k(t+1); Δf_{k+1}(t)] = Φ [e_k(t); Δf_k(t)] + B_w d_k(t),
    Φ = [[A - L C, F], [-K C (A - L C), I - K C F]],   B_w = [[I, -L, 0], [-K C, K C L, -K]].

Design (two LMIs, documented in docs/observers.md):

1. L: the discrete robust observer LMI of `diffsmf.observers.lmi` (gamma = 0).
2. K with L fixed: the 2-D bounded-real lemma for Roesser models (Du & Xie) with
   P = diag(P1, P2) > 0, W = P2 K, minimising g = gamma_w^2::

       [[-P, 0, (PΦ)', C_z'], [0, -g I, (P B_w)', 0], [PΦ, P B_w, -P, 0], [C_z, 0, 0, -I]] < 0,
       PΦ = [[P1 (A - L C), P1 F], [-W C (A - L C), P2 - W C F]],  C_z = [0 I],
       P B_w = [[P1, -P1 L, 0], [-W C, W C L, -W]],
   and -P in the top-left block replaced by -rho^2 P (guaranteed contraction rho per step of
   the 2-D Lyapunov function V = e'P1 e + Δf'P2 Δf); rho is found by bisection.

   With w = 0 and e_k(0) = 0, summing the Lyapunov decrease over a trial telescopes the
   horizontal part, so ||Δf_{k+1}||_{P2} < ||Δf_k||_{P2} (weighted l2 over the trial): robust
   monotone convergence over trials; with w != 0 the error converges to a ball of size
   proportional to gamma_w |w|. A joint design of (L, K) is bilinear; the two-step split is our
   simplification. The learning operator of one trial (lifted matrix T with Δf_{k+1} = T Δf_k +
   ...) is also returned so that its norms can be checked numerically.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cvxpy as cp
import numpy as np
import torch
from torch import nn

from diffsmf.observers.lmi import design_lipschitz_observer

__all__ = [
    "ILCDesign",
    "ILCFaultEstimator",
    "RepeatedSystem",
    "design_ilc",
    "intermittent_fault_example",
]


@dataclass
class ILCDesign:
    """Gains and verified numbers: L [n, l], K [q, l], P1 [n, n], P2 [q, q], gamma_w (l2 gain
    from the uncertainty signal w to the fault error), status, message, lmi_max_eig (numpy),
    contraction = c with V(Φ z) <= c^2 V(z), V = diag(P1, P2) (numpy generalized eigenvalue);
    rho = the contraction imposed in the LMI (c <= rho).
    """

    status: str
    message: str
    L: np.ndarray | None = None
    K: np.ndarray | None = None
    P1: np.ndarray | None = None
    P2: np.ndarray | None = None
    gamma_w: float = float("inf")
    lmi_max_eig: float = float("nan")
    contraction: float = float("nan")
    rho: float = float("nan")

    @property
    def feasible(self) -> bool:
        return self.status == "verified"


def _roesser_blocks(A, C, F, L, K, P1, P2, g, rho2):
    """The 2-D bounded-real LMI matrix (docstring, step 2) in numpy, for verification."""
    n, q, l = A.shape[0], F.shape[1], C.shape[0]
    AL = A - L @ C
    W = P2 @ K
    PPhi = np.block([[P1 @ AL, P1 @ F], [-W @ C @ AL, P2 - W @ C @ F]])
    PBw = np.block([[P1, -P1 @ L, np.zeros((n, l))], [-W @ C, W @ C @ L, -W]])
    P = np.block([[P1, np.zeros((n, q))], [np.zeros((q, n)), P2]])
    Cz = np.hstack([np.zeros((q, n)), np.eye(q)])
    k, m = n + q, n + 2 * l
    M = np.block(
        [
            [-rho2 * P, np.zeros((k, m)), PPhi.T, Cz.T],
            [np.zeros((m, k)), -g * np.eye(m), PBw.T, np.zeros((m, q))],
            [PPhi, PBw, -P, np.zeros((k, q))],
            [Cz, np.zeros((q, m)), np.zeros((q, k)), -np.eye(q)],
        ]
    )
    return 0.5 * (M + M.T)


def _learning_problem(A, C, F, L, margin):
    """Step-2 SDP (docstring) with the contraction rho^2 as a Parameter:
    min |W|_F + 1e-4 g  s.t.  [[-rho^2 P, 0, (PΦ)', C_z'], [0, -g I, (P B_w)', 0],
    [PΦ, P B_w, -P, 0], [C_z, 0, 0, -I]] < 0,  P1 >= I, P2 >= I.
    The smallest learning gain meeting the contraction averages measurement noise over trials.
    """
    n, l, q = A.shape[0], C.shape[0], F.shape[1]
    P1 = cp.Variable((n, n), symmetric=True)
    P2 = cp.Variable((q, q), symmetric=True)
    W = cp.Variable((q, l))
    g = cp.Variable(nonneg=True)
    rho2 = cp.Parameter(nonneg=True)
    AL = A - L @ C
    k, m = n + q, n + 2 * l
    PPhi = cp.bmat([[P1 @ AL, P1 @ F], [-W @ C @ AL, P2 - W @ C @ F]])
    PBw = cp.bmat([[P1, -P1 @ L, np.zeros((n, l))], [-W @ C, W @ C @ L, -W]])
    P = cp.bmat([[P1, np.zeros((n, q))], [np.zeros((q, n)), P2]])
    Cz = np.hstack([np.zeros((q, n)), np.eye(q)])
    M = cp.bmat(
        [
            [-rho2 * P, np.zeros((k, m)), PPhi.T, Cz.T],
            [np.zeros((m, k)), -g * np.eye(m), PBw.T, np.zeros((m, q))],
            [PPhi, PBw, -P, np.zeros((k, q))],
            [Cz, np.zeros((q, m)), np.zeros((q, k)), -np.eye(q)],
        ]
    )
    Ms = 0.5 * (M + M.T)
    cons = [P1 >> np.eye(n), P2 >> np.eye(q), Ms << -margin * np.eye(M.shape[0])]
    objective = cp.Minimize(cp.norm(W, "fro") + 1e-4 * g)
    return cp.Problem(objective, cons), rho2, (P1, P2, W, g)


def _solve_quiet(prob, solver) -> str:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prob.solve(solver=solver)
    except Exception as exc:  # noqa: BLE001 - report, never leak solver exceptions
        return f"solver_error: {exc}"
    return str(prob.status)


def _bisect_rho(prob, rho2, solver, iters, rho=None):
    """Bisection for the smallest feasible trial contraction rho_min in (0, 1], then solve at
    the requested rho (default (1 + rho_min) / 2: fast AND robust). None on success, else
    (status, message)."""
    rho2.value = 1.0
    st = _solve_quiet(prob, solver)
    if st not in ("optimal", "optimal_inaccurate"):
        kind = "error" if st.startswith("solver_error") else "infeasible"
        return kind, f"2-D learning LMI not feasible even with rho = 1 (status {st})"
    lo, hi = 0.0, 1.0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        rho2.value = mid**2
        ok = _solve_quiet(prob, solver) in ("optimal", "optimal_inaccurate")
        lo, hi = (lo, mid) if ok else (mid, hi)
    if rho is not None and rho < hi:
        return "infeasible", f"requested contraction rho={rho:g} below the feasible {hi:.4g}"
    rho2.value = (0.5 * (1 + hi) if rho is None else rho) ** 2
    st = _solve_quiet(prob, solver)
    if st not in ("optimal", "optimal_inaccurate"):
        return "error", f"2-D learning LMI failed at the chosen rho (status {st})"
    return None


def design_ilc(
    A,
    C,
    F,
    *,
    rho: float | None = None,
    solver: str = "CLARABEL",
    margin: float = 1e-7,
    iters: int = 12,
) -> ILCDesign:
    """Observer gain L and learning gain K from the two LMIs of the module docstring.

    A [n, n], C [l, n], F [n, q] (fault input). Requires C F of full column rank (the fault must
    show in the next output). rho in (0, 1]: the guaranteed per-trial contraction of the 2-D
    Lyapunov function (default halfway between the fastest feasible and 1); among gains with
    that contraction the smallest (|P2 K|_F) is chosen; gamma_w is the certified l2 gain from
    the disturbances [w; v(t); v(t+1)] to the fault error.
    Returns an `ILCDesign`; infeasible -> status "infeasible".
    """
    A, C, F = (np.atleast_2d(np.asarray(M, float)) for M in (A, C, F))
    n, q = A.shape[0], F.shape[1]
    if A.shape != (n, n) or C.shape[1] != n or F.shape[0] != n:
        raise ValueError(f"shapes of A {A.shape}, C {C.shape}, F {F.shape} do not match")
    if np.linalg.matrix_rank(C @ F) < q:
        raise ValueError("C @ F must have full column rank (the fault must reach the output)")
    obs = design_lipschitz_observer(A, C, 0.0, 1.0, time="discrete")  # step 1: L
    if not obs.feasible:
        return ILCDesign(status=obs.status, message="observer LMI: " + obs.message)
    L = obs.L
    AL = A - L @ C
    prob, rho2, vs = _learning_problem(A, C, F, L, margin)
    if rho is not None and not 0 < rho <= 1:
        raise ValueError(f"rho must be in (0, 1], got {rho}")
    status = _bisect_rho(prob, rho2, solver, iters, rho)
    if status is not None:
        return ILCDesign(status=status[0], message=status[1], L=L)
    P1, P2, W, g = vs
    P1v, P2v = 0.5 * (P1.value + P1.value.T), 0.5 * (P2.value + P2.value.T)
    K = np.linalg.solve(P2v, W.value)
    gv = float(g.value)
    Mv = _roesser_blocks(A, C, F, L, K, P1v, P2v, gv, float(rho2.value))
    lmi_max = float(np.linalg.eigvalsh(Mv).max())
    Phi = np.block([[AL, F], [-K @ C @ AL, np.eye(q) - K @ C @ F]])
    Pd = np.block([[P1v, np.zeros((n, q))], [np.zeros((q, n)), P2v]])
    # contraction of the 2-D Lyapunov function: V(Φ z) <= rho^2 V(z) (w = 0), numpy check
    rho = float(np.sqrt(np.linalg.eigvals(np.linalg.solve(Pd, Phi.T @ Pd @ Phi)).real.max()))
    ok = lmi_max < 0 and np.linalg.eigvalsh(P1v).min() > 0 and np.linalg.eigvalsh(P2v).min() > 0
    return ILCDesign(
        status="verified" if ok else "unverified",
        message="verified: 2-D LMI negative definite (numpy)" if ok else
        f"numpy check failed (LMI max eig {lmi_max:.3g})",
        L=L, K=K, P1=P1v, P2=P2v, gamma_w=float(np.sqrt(gv)), lmi_max_eig=lmi_max, contraction=rho,
        rho=float(np.sqrt(rho2.value)),
    )


@dataclass
class RepeatedSystem:
    """x(t+1) = (A + D sigma(t) E) x(t) + B u(t) + F f(t), y = C x; one trial of N steps.

    sigma [N] values in [-1, 1] (scalar uncertainty, time-varying); fault [N, q]; u [N, m];
    x0 [n]. ``uncertainty="repeat"``: same sigma every trial; "random": fresh per trial.
    noise: bound of the uniform measurement noise (fresh on every trial, seeded by the trial).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    F: np.ndarray
    D: np.ndarray
    E: np.ndarray
    sigma: np.ndarray
    fault: np.ndarray
    u: np.ndarray
    x0: np.ndarray
    uncertainty: str = "repeat"
    noise: float = 0.0

    def simulate(self, trial: int = 0, batch: int = 1) -> torch.Tensor:
        """Outputs of one trial, y [batch, N+1, l] (float64; batch copies share the system)."""
        sigma = self.sigma
        rng = np.random.default_rng(1000 + trial)
        if self.uncertainty == "random":
            sigma = rng.uniform(-1, 1, size=self.sigma.shape)
        N = self.u.shape[0]
        x = np.broadcast_to(self.x0, (batch, self.A.shape[0])).copy()
        ys = [x @ self.C.T]
        for t in range(N):  # time loop only
            At = self.A + sigma[t] * self.D @ self.E
            x = x @ At.T + self.u[t] @ self.B.T + self.fault[t] @ self.F.T
            ys.append(x @ self.C.T)
        y = np.stack(ys, axis=1)
        y = y + rng.uniform(-self.noise, self.noise, size=y.shape) if self.noise > 0 else y
        return torch.as_tensor(y)


def intermittent_fault_example(
    N: int = 120, uncertainty: str = "repeat", noise: float = 0.0
) -> RepeatedSystem:
    """Built-in example: 3-state repeated system, 2 outputs, an actuator fault F = B made of three
    on/off pulses of different shapes (rectangle, triangle, half-sine), the coupling A[0, 1]
    uncertain by +-20 % (time-varying sigma(t) = sin(0.3 t))."""
    A = np.array([[1.0, 0.1, 0.0], [-0.2, 0.9, 0.1], [0.0, -0.1, 0.8]])
    B = np.array([[0.0], [0.1], [0.05]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    D = np.array([[0.02], [0.0], [0.0]])  # coupling A[0, 1] = 0.1 +- 0.02 (20 %), time-varying
    E = np.array([[0.0, 1.0, 0.0]])
    t = np.arange(N)
    f = np.zeros(N)
    f[(t >= 15) & (t < 30)] = 1.0  # rectangular pulse
    tri = (t >= 45) & (t < 65)
    f[tri] = 0.8 * (1 - np.abs(t[tri] - 55) / 10.0)  # triangular pulse
    hs = (t >= 80) & (t < 100)
    f[hs] = 0.6 * np.sin(np.pi * (t[hs] - 80) / 20.0)  # half-sine pulse
    sigma = np.sin(0.3 * t)
    u = np.sin(0.1 * t)[:, None]
    return RepeatedSystem(A=A, B=B, C=C, F=B.copy(), D=D, E=E, sigma=sigma, fault=f[:, None],
                          u=u, x0=np.zeros(3), uncertainty=uncertainty, noise=noise)


class ILCFaultEstimator(nn.Module):
    """State observer + iterative-learning fault update (module docstring), batched in torch.

    Buffers: A [n, n], B [n, m], C [l, n], F [n, q], L [n, l], K [q, l] (float64).
    """

    def __init__(self, A, B, C, F, L=None, K=None, design: ILCDesign | None = None):
        super().__init__()
        if L is None or K is None:
            design = design_ilc(A, C, F) if design is None else design
            if not design.feasible:
                raise ValueError(f"ILC design failed: {design.message}")
            L, K = design.L, design.K
        self.design = design
        for name, M in dict(A=A, B=B, C=C, F=F, L=L, K=K).items():
            self.register_buffer(name, torch.as_tensor(np.asarray(M, float)))

    def trial(self, y: torch.Tensor, u: torch.Tensor, fhat: torch.Tensor, x0: torch.Tensor):
        """One trial. y [..., N+1, l], u [..., N, m], fhat [..., N, q] (this trial's estimate),
        x0 [..., n]. Returns (xhat [..., N+1, n], residual [..., N+1, l], next fhat [..., N, q])."""
        N = u.shape[-2]
        if y.shape[-2] != N + 1 or fhat.shape[-2] != N:
            raise ValueError(f"y must have N+1={N + 1} and fhat N={N} time steps")
        xh = x0.expand(*y.shape[:-2], x0.shape[-1])
        xs, rs = [xh], [y[..., 0, :] - xh @ self.C.T]
        for t in range(N):  # observer, time loop only
            innov = y[..., t, :] - xh @ self.C.T
            xh = (
                xh @ self.A.T + u[..., t, :] @ self.B.T + fhat[..., t, :] @ self.F.T
                + innov @ self.L.T
            )
            xs.append(xh)
            rs.append(y[..., t + 1, :] - xh @ self.C.T)
        xhat, r = torch.stack(xs, -2), torch.stack(rs, -2)
        # learning law f̂_{k+1}(t) = f̂_k(t) + K r_k(t+1)  (Shi-He-Zhou style, P-type)
        return xhat, r, fhat + r[..., 1:, :] @ self.K.T

    def run(self, system: RepeatedSystem, trials: int, batch: int = 1):
        """Run ``trials`` trials on a `RepeatedSystem`. Returns fhat [trials, batch, N, q]
        (the estimate used in each trial) and max_err [trials, batch] (max_t |f - f̂_k(t)|)."""
        N = system.u.shape[0]
        u = torch.as_tensor(system.u).expand(batch, N, -1)
        fhat = torch.zeros(batch, N, self.F.shape[1], dtype=torch.float64)
        x0 = torch.as_tensor(system.x0, dtype=torch.float64)
        f = torch.as_tensor(system.fault)
        out = []
        for k in range(trials):  # trial loop (the iteration axis of ILC)
            y = system.simulate(trial=k, batch=batch)
            out.append(fhat)
            _, _, fhat = self.trial(y, u, fhat, x0)
        fh = torch.stack(out)
        err = (fh - f).abs().amax(dim=(-2, -1))
        return fh, err
