r"""LMI design of robust observers for Lipschitz systems with a bounded model error (seed 004).

System (seed 004 eq. 1) and observer (eq. 3, our sign convention)::

    x' = A x + f(x) + B u,    y = C x
    x̂' = A x̂ + f̂(x̂) + B u + L (y - C x̂)

With e = x - x̂ and ``f(x) - f̂(x̂) = [f̂(x) - f̂(x̂)] + [f(x) - f̂(x)]`` the error obeys
(eq. 5-8, rewritten)::

    e' = (A - L C) e + B_phi dphi + B_d d,   |dphi| <= gamma |H e|,   |d| <= eps

General case: ``B_phi = B_d = H = I`` and gamma the Lipschitz constant of f̂ (eq. 2).
Structured case ``structure=(B_f, H)``: f = B_f phi(H x), so ``B_phi = B_d = B_f``.

Derivation (replaces the garbled Theorem 1 / eq. 17-22, see docs/observers.md). Take
V = e' P e, P >= I (fixed scale). If, for some alpha > 0, lambda >= 0, mu >= 0,

    V' + alpha V - mu |d|^2 + lambda (gamma^2 |H e|^2 - |dphi|^2) <= 0   for all e, dphi, d

(an S-procedure: the lambda term is >= 0 on every admissible dphi), then along every trajectory
V' <= -alpha V + mu eps^2, hence (comparison lemma)

    V(t) <= exp(-alpha t) V(0) + (1 - exp(-alpha t)) mu eps^2 / alpha,

and |e(t)| <= sqrt(V(t) / lambda_min(P)) -> eps sqrt(mu / (alpha lambda_min(P))) =: bound.
With Y = P L the condition is the LMI (continuous time)

    [[He(P A - Y C) + alpha P + lambda gamma^2 H'H,  P B_phi,     P B_d ],
     [B_phi' P,                                     -lambda I,    0     ],
     [B_d' P,                                        0,          -mu I  ]]  <  0

and, in discrete time (e+ = (A - L C) e + B_phi dphi + B_d d, V+ <= (1 - alpha) V + mu eps^2),
after a Schur complement,

    [[-(1-alpha) P + lambda gamma^2 H'H, 0, 0, (P A - Y C)'],
     [0, -lambda I, 0, B_phi' P], [0, 0, -mu I, B_d' P],
     [P A - Y C, P B_phi, P B_d, -P]]  <  0.

For fixed alpha this is an SDP in (P, Y, lambda, mu); we minimise mu and search alpha (golden
section in log alpha) for the smallest ``bound / eps = sqrt(mu / alpha)``. The gain is
L = P^-1 Y (seed 004 eq. 22). Rajamani (1998) is the special case eps = 0.

Every design is verified without the solver: the LMI matrix is rebuilt in numpy from the returned
P and L (not from the solver's Y) and its eigenvalues checked, as are the eigenvalues of P and of
A - L C; :func:`simulate_error_check` checks the envelope above on simulated error trajectories.
"""

from __future__ import annotations

import time as _time
import warnings
from dataclasses import dataclass, field
from functools import lru_cache

import cvxpy as cp
import numpy as np

__all__ = [
    "ObserverDesign",
    "analyze_observer_gain",
    "design_lipschitz_observer",
    "error_envelope",
    "lmi_matrix",
    "simulate_error_check",
]

_STATUS_OK = ("optimal", "optimal_inaccurate")


@dataclass
class ObserverDesign:
    """Result of :func:`design_lipschitz_observer` / :func:`analyze_observer_gain`.

    status: "verified" (solved and checked in numpy), "infeasible", "unverified" (the solver
    returned a point that fails the numpy check) or "error" (solver failure); ``message`` says why.
    L [n, l] gain, P [n, n], closed_loop = A - L C [n, n], bound = guaranteed limsup |e| (2-norm),
    gain = bound / eps (peak gain from the model error to the estimation error, the paper's
    "gamma"), component_bounds [n] = limsup |e_i|, decay = alpha, margins = verified numbers.
    """

    status: str
    message: str
    time: str
    lipschitz: float
    approx_error: float
    L: np.ndarray | None = None
    P: np.ndarray | None = None
    closed_loop: np.ndarray | None = None
    bound: float = float("inf")
    gain: float = float("inf")
    component_bounds: np.ndarray | None = None
    decay: float = 0.0
    lam: float = 0.0
    mu: float = 0.0
    structured: bool = False
    B_f: np.ndarray | None = None
    H: np.ndarray | None = None
    margins: dict = field(default_factory=dict)
    solves: int = 0
    seconds: float = 0.0

    @property
    def feasible(self) -> bool:
        return self.status == "verified"

    def __repr__(self) -> str:
        return (
            f"ObserverDesign(status={self.status!r}, bound={self.bound:.4g}, gain={self.gain:.4g},"
            f" decay={self.decay:.4g}, L={None if self.L is None else self.L.round(4).tolist()})"
        )


# ----------------------------------------------------------------------------- input checking
def _as_matrix(M, name: str, rows: int | None = None, cols: int | None = None) -> np.ndarray:
    try:
        M = np.asarray(M, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric matrix") from exc
    if M.ndim == 1:
        M = M[None, :] if name == "C" else M[:, None]
    if M.ndim != 2 or not np.all(np.isfinite(M)):
        raise ValueError(f"{name} must be a finite 2-D matrix, got shape {M.shape}")
    if rows is not None and M.shape[0] != rows:
        raise ValueError(f"{name} must have {rows} rows, got shape {M.shape}")
    if cols is not None and M.shape[1] != cols:
        raise ValueError(f"{name} must have {cols} columns, got shape {M.shape}")
    return M


def _check_inputs(A, C, lipschitz, approx_error, time, structure):
    A = _as_matrix(A, "A")
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A must be square, got shape {A.shape}")
    C = _as_matrix(C, "C", cols=n)
    if time not in ("continuous", "discrete"):
        raise ValueError(f"time must be 'continuous' or 'discrete', got {time!r}")
    if not np.isfinite(lipschitz) or lipschitz < 0:
        raise ValueError(f"lipschitz must be finite and >= 0, got {lipschitz}")
    if not np.isfinite(approx_error) or approx_error < 0:
        raise ValueError(f"approx_error must be finite and >= 0, got {approx_error}")
    if structure is None:
        Bf, H = np.eye(n), np.eye(n)
    else:
        if len(structure) != 2:
            raise ValueError("structure must be a pair (B_f, H)")
        Bf = _as_matrix(structure[0], "structure B_f", rows=n)
        H = _as_matrix(structure[1], "structure H", cols=n)
    return A, C, float(lipschitz), float(approx_error), Bf, H


# ----------------------------------------------------------------------------- the LMI (numpy)
def lmi_matrix(A, C, L, P, lam, mu, alpha, lipschitz, structure=None, time="continuous"):
    """The design LMI matrix (must be negative definite) rebuilt in numpy from P and L.

    Continuous: seed 004 Theorem 1 as re-derived in the module docstring; discrete: its Schur
    form. Returns the symmetric matrix [k, k]; used to verify solver output independently.
    """
    n = A.shape[0]
    Bf, H = (np.eye(n), np.eye(n)) if structure is None else structure
    Bf, H = np.asarray(Bf, float), np.asarray(H, float)
    nf = Bf.shape[1]
    G = lipschitz**2 * H.T @ H
    PAL = P @ (A - L @ C)
    PB = P @ Bf
    Z = np.zeros((nf, nf))
    if time == "continuous":
        M = np.block(
            [
                [PAL + PAL.T + alpha * P + lam * G, PB, PB],
                [PB.T, -lam * np.eye(nf), Z],
                [PB.T, Z, -mu * np.eye(nf)],
            ]
        )
    else:
        Zn = np.zeros((n, nf))
        M = np.block(
            [
                [-(1 - alpha) * P + lam * G, Zn, Zn, PAL.T],
                [Zn.T, -lam * np.eye(nf), Z, PB.T],
                [Zn.T, Z, -mu * np.eye(nf), PB.T],
                [PAL, PB, PB, -P],
            ]
        )
    return 0.5 * (M + M.T)


# ----------------------------------------------------------------------------- cvxpy problems
@lru_cache(maxsize=32)
def _problem(n: int, l: int, nf: int, time: str, fixed_gain: bool, capped: bool):
    """Build ONCE (cached per shape) the SDP min mu s.t. LMI(alpha) < -margin I, P >= I.

    capped: add |Y|_2 <= kappa (Parameter), which with P >= I gives |L|_2 = |P^-1 Y|_2 <= kappa.
    """
    A = cp.Parameter((n, n), name="A")
    C = cp.Parameter((l, n), name="C")
    G = cp.Parameter((n, n), name="G", PSD=True)  # gamma^2 H'H
    Bf = cp.Parameter((n, nf), name="Bf")
    alpha = cp.Parameter(nonneg=True, name="alpha")
    margin = cp.Parameter(nonneg=True, name="margin")  # strictness, raised on a failed check
    P = cp.Variable((n, n), symmetric=True, name="P")
    lam = cp.Variable(nonneg=True, name="lam")
    mu = cp.Variable(nonneg=True, name="mu")
    if fixed_gain:  # analysis of a given L: A holds A - L C, C unused (zeros)
        Lpar = cp.Parameter((n, l), name="L")
        PAL = P @ A
        Y = None
    else:
        Lpar = None
        Y = cp.Variable((n, l), name="Y")
        PAL = P @ A - Y @ C
    PB = P @ Bf
    In, If, Zf = np.eye(n), np.eye(nf), np.zeros((nf, nf))
    if time == "continuous":
        M = cp.bmat(
            [
                [PAL + PAL.T + alpha * P + lam * G, PB, PB],
                [PB.T, -lam * If, Zf],
                [PB.T, Zf, -mu * If],
            ]
        )
    else:
        Zn = np.zeros((n, nf))
        M = cp.bmat(
            [
                [-P + alpha * P + lam * G, Zn, Zn, PAL.T],
                [Zn.T, -lam * If, Zf, PB.T],
                [Zn.T, Zf, -mu * If, PB.T],
                [PAL, PB, PB, -P],
            ]
        )
    k = M.shape[0]
    Ms = 0.5 * (M + M.T)  # symmetric by construction; makes cvxpy's symmetry check exact
    cons = [P >> In, Ms << -margin * np.eye(k)]  # matrix margin, not a scalar >>
    kappa2 = None
    if capped and Y is not None:
        kappa2 = cp.Parameter(nonneg=True, name="kappa2")
        cons.append(cp.bmat([[kappa2 * np.eye(l), Y.T], [Y, In]]) >> 0)
    prob = cp.Problem(cp.Minimize(mu), cons)
    params = dict(A=A, C=C, G=G, Bf=Bf, alpha=alpha, L=Lpar, kappa2=kappa2, margin=margin)
    return prob, params, dict(P=P, Y=Y, lam=lam, mu=mu)


def _solve(prob, solver: str) -> str:
    """Solve; map solver exceptions to a status string (no exception leaks)."""
    try:
        with warnings.catch_warnings():  # "inaccurate" warnings: the numpy check decides
            warnings.simplefilter("ignore")
            prob.solve(solver=solver)
    except cp.error.SolverError as exc:  # numerical failure inside the solver
        return f"solver_error: {exc}"
    except Exception as exc:  # noqa: BLE001 - a design must report, not raise
        return f"solver_error: {type(exc).__name__}: {exc}"
    return str(prob.status)


class _Search:
    """Solve the fixed-alpha SDP for many alphas on one cached cvxpy problem."""

    def __init__(self, prob, params, vars_, solver):
        self.prob, self.params, self.vars, self.solver = prob, params, vars_, solver
        self.solves, self.cache = 0, {}

    def __call__(self, alpha: float):
        if alpha in self.cache:
            return self.cache[alpha]
        self.params["alpha"].value = alpha
        status = _solve(self.prob, self.solver)
        self.solves += 1
        out = None
        if status in _STATUS_OK and self.vars["mu"].value is not None:
            vals = {k: (None if v is None else np.array(v.value)) for k, v in self.vars.items()}
            out = (float(self.vars["mu"].value) / alpha, vals, status)
        else:
            out = (float("inf"), None, status)
        self.cache[alpha] = out
        return out


def _alpha_search(search: _Search, alpha_max: float, objective: str, iters: int):
    """Find alpha: largest feasible (bisection), then golden section on log alpha for mu/alpha."""
    lo, hi = alpha_max * 1e-6, alpha_max
    if search(lo)[1] is None:  # try the smallest decay: if infeasible, the design is infeasible
        return None, search(lo)[2]
    if search(hi)[1] is None:
        a, b = np.log(lo), np.log(hi)
        for _ in range(iters):  # bisection for the largest feasible alpha
            m = 0.5 * (a + b)
            a, b = (m, b) if search(float(np.exp(m)))[1] is not None else (a, m)
        hi = float(np.exp(a))
    if objective == "decay":
        return 0.9 * hi if search(0.9 * hi)[1] is not None else hi, "optimal"
    a, b = np.log(lo), np.log(hi)
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    for _ in range(iters):  # golden section on J(alpha) = mu*(alpha) / alpha
        if search(float(np.exp(c)))[0] < search(float(np.exp(d)))[0]:
            b, d = d, c
            c = b - g * (b - a)
        else:
            a, c = c, d
            d = a + g * (b - a)
    best = min(search.cache.items(), key=lambda kv: kv[1][0])
    return best[0], "optimal"


# ----------------------------------------------------------------------------- public API
def design_lipschitz_observer(
    A,
    C,
    lipschitz: float,
    approx_error: float,
    *,
    time: str = "continuous",
    objective: str = "bound",
    structure=None,
    solver: str = "CLARABEL",
    alpha_max: float | None = None,
    max_gain: float | None = None,
    margin: float = 1e-6,
    iters: int = 25,
) -> ObserverDesign:
    """Observer gain L minimising the guaranteed error bound (seed 004 eq. 20-22, re-derived).

    A [n, n], C [l, n]; lipschitz = gamma (of f̂, or of phi under ``structure=(B_f, H)``);
    approx_error = eps >= sup |f - f̂| on the domain. objective: "bound" (min limsup |e|) or
    "decay" (about the fastest guaranteed decay: 0.9 x the largest feasible alpha).
    alpha_max caps the searched decay (default 100 continuous, 1 discrete); max_gain caps the
    spectral norm of L (high-gain designs otherwise drive |L| to the alpha cap).
    Returns an :class:`ObserverDesign` (never raises for infeasible or failed solves).
    """
    A, C, gamma, eps, Bf, H = _check_inputs(A, C, lipschitz, approx_error, time, structure)
    if objective not in ("bound", "decay"):
        raise ValueError(f"objective must be 'bound' or 'decay', got {objective!r}")
    n, l, nf = A.shape[0], C.shape[0], Bf.shape[1]
    alpha_max = (100.0 if time == "continuous" else 1.0) if alpha_max is None else alpha_max
    if alpha_max <= 0 or (time == "discrete" and alpha_max > 1):
        raise ValueError(f"alpha_max must be in (0, inf) (continuous) or (0, 1], got {alpha_max}")
    t0 = _time.perf_counter()
    if max_gain is not None and not max_gain > 0:
        raise ValueError(f"max_gain must be positive, got {max_gain}")
    prob, par, var = _problem(n, l, nf, time, False, max_gain is not None)
    par["margin"].value = float(margin)
    par["A"].value, par["C"].value, par["Bf"].value = A, C, Bf
    if max_gain is not None:
        par["kappa2"].value = float(max_gain) ** 2
    G = gamma**2 * H.T @ H
    par["G"].value = 0.5 * (G + G.T)
    search = _Search(prob, par, var, solver)
    alpha, status = _alpha_search(search, alpha_max, objective, iters)
    base = dict(time=time, lipschitz=gamma, approx_error=eps, structured=structure is not None)
    if alpha is None:
        return _failed(status, base, search, t0, gamma)
    res = _first_verified(search, alpha, A, C, None, gamma, eps, (Bf, H), base)
    res.solves, res.seconds = search.solves, _time.perf_counter() - t0
    return res


def analyze_observer_gain(
    A,
    C,
    L,
    lipschitz: float,
    approx_error: float,
    *,
    time: str = "continuous",
    structure=None,
    solver: str = "CLARABEL",
    alpha_max: float | None = None,
    margin: float = 1e-6,
    iters: int = 25,
) -> ObserverDesign:
    """Same LMI with a GIVEN gain L [n, l] (variables P, lambda, mu): is L certified, and how well.

    Used to check gains from other tools (python-control ``place``/``lqe``) against our LMI.
    """
    A, C, gamma, eps, Bf, H = _check_inputs(A, C, lipschitz, approx_error, time, structure)
    L = _as_matrix(L, "L", rows=A.shape[0], cols=C.shape[0])
    n, l, nf = A.shape[0], C.shape[0], Bf.shape[1]
    alpha_max = (100.0 if time == "continuous" else 1.0) if alpha_max is None else alpha_max
    t0 = _time.perf_counter()
    prob, par, var = _problem(n, l, nf, time, True, False)
    par["margin"].value = float(margin)
    par["A"].value, par["C"].value, par["Bf"].value = A - L @ C, np.zeros((l, n)), Bf
    par["L"].value = L
    G = gamma**2 * H.T @ H
    par["G"].value = 0.5 * (G + G.T)
    search = _Search(prob, par, var, solver)
    alpha, status = _alpha_search(search, alpha_max, "bound", iters)
    base = dict(time=time, lipschitz=gamma, approx_error=eps, structured=structure is not None)
    if alpha is None:
        return _failed(status, base, search, t0, gamma)
    res = _first_verified(search, alpha, A, C, L, gamma, eps, (Bf, H), base)
    res.solves, res.seconds = search.solves, _time.perf_counter() - t0
    return res


def _first_verified(search, alpha, A, C, L_fixed, gamma, eps, structure, base, tries=8):
    """Verify the best alpha's point in numpy; if the solver's point fails the check (solver
    tolerance near the boundary), fall back to the next-best solved alphas."""
    order = [alpha] + [a for a, v in sorted(search.cache.items(), key=lambda kv: kv[1][0])
                       if a != alpha and v[1] is not None]
    first = None

    def check(vals, a):
        P = vals["P"]
        L = np.linalg.solve(P, vals["Y"]) if L_fixed is None else L_fixed  # eq. 22: L = P^-1 R
        return _verify(A, C, L, P, vals["lam"], vals["mu"], a, gamma, eps, structure, base)

    for a in order[:tries]:
        res = check(search(a)[1], a)
        if res.feasible:
            return res
        first = first or res
    # solver tolerance is relative to the size of P: raise the matrix margin and re-solve
    m0 = float(search.params["margin"].value)
    scale = max(1.0, float(np.abs(first.P).max()) if first.P is not None else 1.0)
    for m in (1e2 * m0 * scale, 1e4 * m0 * scale):
        search.params["margin"].value = m
        search.cache.pop(alpha, None)
        vals = search(alpha)[1]
        if vals is not None:
            res = check(vals, alpha)
            if res.feasible:
                search.params["margin"].value = m0
                return res
    search.params["margin"].value = m0
    return first


def _failed(status: str, base: dict, search: _Search, t0: float, gamma: float) -> ObserverDesign:
    if status.startswith("solver_error"):
        st, msg = "error", f"the SDP solver failed: {status}"
    else:
        st = "infeasible"
        msg = (
            f"LMI infeasible (solver status {status!r}): no observer gain with P >= I certifies "
            f"robust stability for lipschitz={gamma:g} with this (A, C)"
            + (" and structure" if base["structured"] else "")
            + "; check detectability of (A, C), lower the Lipschitz constant or use structure="
        )
    out = ObserverDesign(status=st, message=msg, **base)
    out.solves, out.seconds = search.solves, _time.perf_counter() - t0
    return out


def _verify(A, C, L, P, lam, mu, alpha, gamma, eps, structure, base) -> ObserverDesign:
    """Independent check: eigenvalues of the rebuilt LMI, of P, and of A - L C (numpy only)."""
    lam, mu, alpha = float(lam), float(mu), float(alpha)
    P = 0.5 * (P + P.T)
    M = lmi_matrix(A, C, L, P, lam, mu, alpha, gamma, structure, base["time"])
    lmi_max = float(np.linalg.eigvalsh(M).max())
    p_min = float(np.linalg.eigvalsh(P).min())
    AL = A - L @ C
    ev = np.linalg.eigvals(AL)
    stab = float(ev.real.max()) if base["time"] == "continuous" else float(np.abs(ev).max())
    stable = stab < 0 if base["time"] == "continuous" else stab < 1
    gain = float(np.sqrt(mu / (alpha * p_min))) if p_min > 0 else float("inf")
    Pinv = np.linalg.inv(P)
    comp = eps * np.sqrt(mu / alpha * np.clip(np.diag(Pinv), 0, None))
    ok = lmi_max < 0 and p_min > 0 and stable
    margins = dict(lmi_max_eig=lmi_max, P_min_eig=p_min, closed_loop_eigs=ev,
                   closed_loop_abscissa=stab)
    msg = (
        "verified: LMI matrix negative definite, P > 0 and A - L C stable (numpy eigenvalues)"
        if ok
        else f"solver point fails the numpy check (LMI max eig {lmi_max:.3g}, P min eig "
        f"{p_min:.3g}, closed-loop {stab:.3g})"
    )
    return ObserverDesign(
        status="verified" if ok else "unverified", message=msg, L=L, P=P, closed_loop=AL,
        B_f=structure[0], H=structure[1],
        bound=gain * eps, gain=gain, component_bounds=comp, decay=alpha, lam=lam, mu=mu,
        margins=margins, **base,
    )


def error_envelope(design: ObserverDesign, e0, t) -> np.ndarray:
    """Guaranteed |e(t)| bound from e(0) (module docstring): sqrt(V(t) / lambda_min(P)).

    e0 [..., n], t [T] (times, continuous; step indices, discrete) -> [..., T].
    """
    P, a = design.P, design.decay
    e0 = np.asarray(e0, float)
    V0 = np.einsum("...i,ij,...j->...", e0, P, e0)[..., None]
    t = np.asarray(t, float)
    decay = np.exp(-a * t) if design.time == "continuous" else (1 - a) ** t
    Vinf = design.mu * design.approx_error**2 / a
    V = decay * V0 + (1 - decay) * Vinf
    return np.sqrt(V / design.margins["P_min_eig"])


def simulate_error_check(
    design: ObserverDesign, steps: int = 2000, dt: float = 1e-3, batch: int = 64, seed: int = 0
) -> dict:
    """Simulate the error system with adversarial-ish admissible dphi and d; compare to envelope.

    dphi = gamma |H e| s(t) (unit s, random switching signs), d = eps on a random unit direction
    switched piecewise-constantly. Continuous time uses RK4 with the disturbances held per step.
    Returns {"max_ratio": max_t |e(t)| / envelope(t), "ok": max_ratio <= 1 + 1e-6}.
    """
    rng = np.random.default_rng(seed)
    if not design.feasible:
        raise ValueError("design must be feasible (status 'verified') to simulate")
    n = design.P.shape[0]
    A_L = design.closed_loop
    Bf, H = design.B_f, design.H
    nf = Bf.shape[1]
    e = rng.standard_normal((batch, n))
    e0 = e.copy()
    g, eps = design.lipschitz, design.approx_error
    ratio = 0.0
    hold = max(1, steps // 20)
    for k in range(steps):
        if k % hold == 0:
            s = rng.standard_normal((batch, nf))
            s /= np.linalg.norm(s, axis=-1, keepdims=True)
            dd = rng.standard_normal((batch, nf))
            dd *= eps / np.linalg.norm(dd, axis=-1, keepdims=True)

        def rhs(x, s=s, dd=dd):
            dphi = g * np.linalg.norm(x @ H.T, axis=-1, keepdims=True) * s
            return x @ A_L.T + (dphi + dd) @ Bf.T

        if design.time == "continuous":
            k1 = rhs(e)
            k2 = rhs(e + 0.5 * dt * k1)
            k3 = rhs(e + 0.5 * dt * k2)
            k4 = rhs(e + dt * k3)
            e = e + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            t = (k + 1) * dt
        else:
            e = rhs(e)
            t = k + 1
        env = error_envelope(design, e0, np.array([t]))[..., 0]
        ratio = max(ratio, float((np.linalg.norm(e, axis=-1) / env).max()))
    return {"max_ratio": ratio, "ok": ratio <= 1 + 1e-6}
