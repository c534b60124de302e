"""design_lipschitz_observer: the reduced LMI and the few-solve alpha search
against an independent 3-block cvxpy problem and a scipy search over alpha; honest statuses;
bad input named in the error."""

import re
import warnings

import cvxpy as cp
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from diffsmf.observers import analyze_observer_gain, design_lipschitz_observer, lmi_matrix
from diffsmf.observers import lmi as lmi_mod

A_VDP = np.array([[0.0, 1.0], [-1.0, 1.0]])  # Wang et al. 2009, eq. 23
C_VDP = np.array([[1.0, 0.0]])
ST_VDP = (np.array([[0.0], [1.0]]), np.eye(2))


def _three_block_mu(A, C, gamma, alpha, structure=None, kappa=None, time="continuous"):
    """Reference: min mu of the documented 3-block LMI (docs/observers.md) at fixed alpha,
    written here from scratch with constant data (not lmi.lmi_problem)."""
    n, l = A.shape[0], C.shape[0]
    Bf, H = (np.eye(n), np.eye(n)) if structure is None else structure
    nf = Bf.shape[1]
    P = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((n, l))
    lam, mu = cp.Variable(nonneg=True), cp.Variable(nonneg=True)
    PAL, PB, G = P @ A - Y @ C, P @ Bf, gamma**2 * H.T @ H
    If, Zf, Zn = np.eye(nf), np.zeros((nf, nf)), np.zeros((n, nf))
    if time == "continuous":
        M = cp.bmat([[PAL + PAL.T + alpha * P + lam * G, PB, PB],
                     [PB.T, -lam * If, Zf], [PB.T, Zf, -mu * If]])
    else:
        M = cp.bmat([[-(1 - alpha) * P + lam * G, Zn, Zn, PAL.T], [Zn.T, -lam * If, Zf, PB.T],
                     [Zn.T, Zf, -mu * If, PB.T], [PAL, PB, PB, -P]])
    cons = [P >> np.eye(n), 0.5 * (M + M.T) << -1e-6 * np.eye(M.shape[0])]
    if kappa is not None:
        cons.append(cp.bmat([[kappa * np.eye(l), Y.T], [Y, kappa * np.eye(n)]]) >> 0)
    prob = cp.Problem(cp.Minimize(mu), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob.solve(solver="CLARABEL")
    return float(mu.value) if prob.status in ("optimal", "optimal_inaccurate") else np.inf


def _reduced_mu(A, C, gamma, alpha, structure=None, kappa=None, time="continuous"):
    n, l = A.shape[0], C.shape[0]
    Bf, H = (np.eye(n), np.eye(n)) if structure is None else structure
    prob, par, var, con = lmi_mod.lmi_problem(n, l, time, False, kappa is not None,
                                              *lmi_mod.structure_keys(Bf, H))
    par["margin"].value, par["A"].value, par["C"].value, par["g2"].value = 1e-6, A, C, gamma**2
    if kappa is not None:
        par["kappa"].value = kappa
    return lmi_mod._Search(prob, par, var, con, "CLARABEL", n)(alpha)


def _cases():
    rng = np.random.default_rng(11)
    out = [("vdp", A_VDP, C_VDP, 1.0, ST_VDP, 300.0, "continuous")]
    for k in range(3):
        n, l = 3 + k, 2
        A = rng.standard_normal((n, n)) * 0.5 - 0.6 * np.eye(n)
        out.append((f"random{k}", A, rng.standard_normal((l, n)),
                    0.1, None, 1e3, "continuous"))
    out.append(("discrete", np.eye(2) + 0.1 * A_VDP, C_VDP, 0.3, ST_VDP, None, "discrete"))
    return out


@pytest.mark.parametrize("case", _cases(), ids=lambda c: c[0])
def test_reduced_lmi_same_optimum_as_three_block(case):
    """Two disturbance blocks through the same B_f merged into one (module docstring): same
    min mu at fixed alpha as the 3-block LMI, and the dual gives d mu*/d alpha."""
    _, A, C, gamma, st, kappa, time = case
    d = design_lipschitz_observer(A, C, gamma, 1.0, structure=st, max_gain=kappa, time=time)
    assert d.feasible, d.message
    for alpha in (0.5 * d.decay, d.decay):
        ref = _three_block_mu(A, C, gamma, alpha, st, kappa, time)
        pt = _reduced_mu(A, C, gamma, alpha, st, kappa, time)
        assert pt.ok and pt.mu == pytest.approx(ref, rel=1e-4)  # solver tolerance
        h = 2e-2 * alpha  # sensitivity from the dual vs a central difference of the reference
        fd = (_three_block_mu(A, C, gamma, alpha + h, st, kappa, time)
              - _three_block_mu(A, C, gamma, alpha - h, st, kappa, time)) / (2 * h)
        assert pt.dmu == pytest.approx(fd, rel=2e-2)


@pytest.mark.parametrize("case", _cases(), ids=lambda c: c[0])
def test_alpha_search_matches_scipy_reference_in_few_solves(case):
    """The design's bound equals the optimum over alpha found by scipy's bounded Brent search on
    the independent 3-block problem, with at most 6 SDP solves (was 19-53)."""
    _, A, C, gamma, st, kappa, time = case
    d = design_lipschitz_observer(A, C, gamma, 1.0, structure=st, max_gain=kappa, time=time)
    assert d.feasible, d.message
    amax = 100.0 if time == "continuous" else 1.0

    def J(s):
        mu = _three_block_mu(A, C, gamma, float(np.exp(s)), st, kappa, time)
        return np.log(mu / np.exp(s)) if np.isfinite(mu) else 1e3

    s_d = np.log(d.decay)
    ref = minimize_scalar(J, bounds=(s_d - 1.5, min(s_d + 1.5, np.log(amax))), method="bounded",
                          options=dict(xatol=1e-4))
    j_ref = float(np.exp(ref.fun))
    assert d.gain**2 == pytest.approx(j_ref, rel=1e-3)  # gain^2 = mu/alpha (lambda_min(P) = 1)
    assert d.gain**2 <= j_ref * (1 + 3e-4)
    assert d.solves <= 6


def test_infeasible_verdict_agrees_with_three_block_reference():
    rng = np.random.default_rng(11)
    A, C = rng.standard_normal((3, 3)) * 0.5, rng.standard_normal((1, 3))
    d = design_lipschitz_observer(A, C, 0.1, 1.0, max_gain=1e3)
    assert d.status == "infeasible" and d.solves == 1 and d.bound == np.inf
    assert _three_block_mu(A, C, 0.1, 1e-4, kappa=1e3) == np.inf


def test_numpy_check_rebuilds_three_block_lmi():
    d = design_lipschitz_observer(A_VDP, C_VDP, 1.0, 3.0, structure=ST_VDP, max_gain=1000)
    assert d.feasible and d.solver_status == "optimal"
    M = lmi_matrix(A_VDP, C_VDP, d.L, d.P, d.lam, d.mu, d.decay, 1.0, ST_VDP)
    assert M.shape == (4, 4) and np.linalg.eigvalsh(M).max() < 0
    # mu is the smallest this (P, L, lambda, alpha) certify, times 1 + 1e-6: 1 % less fails
    M_less = lmi_matrix(A_VDP, C_VDP, d.L, d.P, d.lam, 0.99 * d.mu, d.decay, 1.0, ST_VDP)
    assert np.linalg.eigvalsh(M_less).max() > 0
    assert d.mu == pytest.approx(d.margins["mu_solver"], rel=1e-4)


def test_unverified_design_claims_no_bound():
    """A point failing the numpy check is 'unverified' with bound = gain = inf."""
    d = design_lipschitz_observer(A_VDP, C_VDP, 1.0, 3.0, structure=ST_VDP, max_gain=1000)
    base = dict(time="continuous", lipschitz=1.0, approx_error=3.0, structured=True)
    bad = lmi_mod._verify(A_VDP, C_VDP, -d.L, d.P, d.lam, d.mu, d.decay, 1.0, 3.0, ST_VDP, base,
                          "optimal_inaccurate")
    assert bad.status == "unverified" and not bad.feasible
    assert bad.bound == np.inf and bad.gain == np.inf and bad.component_bounds is None
    assert "optimal_inaccurate" in bad.message and "no bound" in bad.message


@pytest.mark.parametrize("status,expected", [("user_limit", "error"),
                                             ("infeasible_inaccurate", "infeasible"),
                                             ("unbounded", "error"),
                                             ("solver_error: boom", "error")])
def test_solver_statuses_reported_not_turned_into_numbers(monkeypatch, status, expected):
    def fake_solve(prob, solver, rows=0):
        return status

    monkeypatch.setattr(lmi_mod, "_solve", fake_solve)
    d = design_lipschitz_observer(A_VDP, C_VDP, 0.1, 1.0)
    assert d.status == expected and d.bound == np.inf and d.L is None
    assert d.solver_status == status and status.split(":")[0] in d.message


def test_solver_status_optimal_inaccurate_is_reported(monkeypatch):
    orig = lmi_mod._solve

    def inaccurate(prob, solver, rows=0):
        st = orig(prob, solver, rows)
        return "optimal_inaccurate" if st == "optimal" else st

    monkeypatch.setattr(lmi_mod, "_solve", inaccurate)
    d = design_lipschitz_observer(A_VDP, C_VDP, 1.0, 3.0, structure=ST_VDP, max_gain=1000)
    assert d.feasible and d.solver_status == "optimal_inaccurate"
    assert "optimal_inaccurate" in d.message  # certified by the numpy check, and says so


def test_zero_lipschitz_and_zero_error_accepted():
    """gamma = 0 (linear error dynamics) and eps = 0 (exact model: bound 0, asymptotic
    convergence) are meaningful and accepted; only negative or non-finite values raise."""
    d = design_lipschitz_observer(A_VDP, C_VDP, 0.0, 0.0, max_gain=100)
    assert d.feasible and d.bound == 0.0 and np.isfinite(d.gain)


_BAD = [
    (dict(A=np.ones((2, 3))), "A"),
    (dict(A=np.array([[0.0, np.nan], [1.0, 0.0]])), "A"),
    (dict(A="not a matrix"), "A"),
    (dict(A=np.zeros((0, 0))), "A"),
    (dict(C=np.ones((1, 3))), "C"),
    (dict(C=np.array([[np.inf, 0.0]])), "C"),
    (dict(C=np.zeros((0, 2))), "C"),
    (dict(lipschitz=-1.0), "lipschitz"),
    (dict(lipschitz=float("nan")), "lipschitz"),
    (dict(lipschitz=float("inf")), "lipschitz"),
    (dict(lipschitz="big"), "lipschitz"),
    (dict(approx_error=-0.1), "approx_error"),
    (dict(approx_error=float("nan")), "approx_error"),
    (dict(structure=(np.ones((3, 1)), np.eye(2))), "structure"),
    (dict(structure=(np.ones((2, 1)), np.eye(3))), "structure"),
    (dict(structure=np.eye(2)), "structure"),
    (dict(time="hybrid"), "time"),
    (dict(objective="fast"), "objective"),
    (dict(solver="NOSUCHSOLVER"), "solver"),
    (dict(alpha_max=0.0), "alpha_max"),
    (dict(alpha_max=-1.0), "alpha_max"),
    (dict(time="discrete", alpha_max=2.0), "alpha_max"),
    (dict(max_gain=0.0), "max_gain"),
    (dict(max_gain=float("nan")), "max_gain"),
    (dict(margin=0.0), "margin"),
    (dict(iters=1), "iters"),
    (dict(iters=2.5), "iters"),
]


@pytest.mark.parametrize("kw,name", _BAD, ids=[f"{n}-{i}" for i, (_, n) in enumerate(_BAD)])
def test_bad_input_raises_value_error_naming_argument(kw, name):
    args = dict(A=A_VDP, C=C_VDP, lipschitz=0.1, approx_error=1.0)
    args.update(kw)
    A, C, g, e = (args.pop(k) for k in ("A", "C", "lipschitz", "approx_error"))
    with pytest.raises(ValueError, match=rf"^{re.escape(name)}\b"):
        design_lipschitz_observer(A, C, g, e, **args)


@pytest.mark.parametrize("L,name", [(np.ones((3, 1)), "L"), (np.array([[np.nan], [1.0]]), "L"),
                                    (None, "L")])
def test_analyze_bad_gain_named(L, name):
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        analyze_observer_gain(A_VDP, C_VDP, L, 0.1, 1.0)
