"""Linear system, linear output: each filter equals its classical linear counterpart,
checked against independent numpy references at every step.

System: ``x+ = A x + w``, ``|w_i| <= W_i`` (box), ``y = C x + v``, ``|v_j| <= SIGMA_j``, two
states, two outputs (the strips are intersected one by one, output 0 first).

* HSNSMF = Chisci et al. 1996: prediction zonotope ``[A T, diag(W)]``, minimal-volume outer
  parallelotope over all generator bases ``T = B diag(sum_j |(B^-1 G)_ij|)``, then each strip
  by Wang et al. 2022, eq. 30-41 (Vicino-Zappa / Chisci parallelotope cap strip).
* MSZM = Alamo et al. 2005 with the volume rule: ``Z(lam) = (c + lam (y - p c),
  [(I - lam p') G, sigma lam])`` with ``lam`` minimising the exact volume (Gover-Krikorian sum
  over generator pairs, evaluated here by brute force). In 2-D the volume is convex piecewise
  linear in ``lam`` with its minimum at ``0`` or at a ``g_j / (p g_j)`` (the vertices of the
  line arrangement), so the reference minimises over those candidates exactly. No reduction
  (``order=60`` leaves room for every generator). The F-radius rule is checked in
  ``tests/test_noise_sets.py``.
* CDSMF = the ellipsoidal filter: ``E+ = A E (+) cover(box W)`` with the cover
  ``diag(n W_i^2)`` and the trace rule ``p = sqrt(tr S1 / tr S2)`` (default: the same after
  normalising by ``diag(S1 + S2)``, ``"scaled-trace"``) in
  ``S = (1 + 1/p) S1 + (1 + p) S2``; strip update by the minimal-volume member (Fogel-Huang) of
  ``(1 - rho) (x-c)' P^-1 (x-c) + rho (a x - o)^2 / h^2 <= 1`` after tightening the strip to
  E's extent along ``a``. The reference builds the combined quadratic directly (explicit
  inverses; fine in a test) and finds rho as a root of the analytic derivative of
  ``log det`` (brentq), independent of the filter's closed-form quadratic.

Tolerance: 1e-9 relative + 1e-9 absolute on the interval hulls (``res.lower``/``res.upper``)
at every step. The filters add documented outward margins (float padding): rounding margins
of 1e-12 (absolute, scaled by 1 + magnitudes) on remainders and strip half-widths, and for the
ellipsoids relative inflations of the shape matrix (``INFLATE = 1e-10`` per Minkowski sum and
per strip update, ``SHAPE_MARGIN = 1e-10`` per prediction). Without them the ellipsoid
reference differs by 1.1e-10 absolute (~1e-9 relative to the hull half-widths of ~0.1), at
the edge of the tolerance, so it applies the same documented factors (and only those); with
them the largest difference is 1.6e-11. The parallelotope and zonotope references apply no
margin (largest differences 2.3e-11 and 3.3e-12). Each test also checks that it can fail:
the reference perturbed by 1e-6 must fail the same comparison.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.optimize import brentq

import diffsmf as ds

F64 = torch.float64
A = np.array([[0.9, 0.2], [-0.1, 0.95]])
C = np.array([[1.0, 0.5], [0.0, 1.0]])
W = np.array([0.02, 0.01])
SIGMA = np.array([0.05, 0.08])
X0_C, X0_R = np.array([0.5, -0.3]), np.array([0.2, 0.2])
STEPS, BATCH = 16, 3
RTOL = ATOL = 1e-9


def _system() -> ds.System:
    At, Ct = torch.tensor(A, dtype=F64), torch.tensor(C, dtype=F64)

    def f(x, u=None, theta=None):
        return x @ At.T

    def h(x):
        return x @ Ct.T

    c0, r0 = torch.tensor(X0_C, dtype=F64), torch.tensor(X0_R, dtype=F64)
    Wt, Vt = torch.tensor(W, dtype=F64), torch.tensor(SIGMA, dtype=F64)
    return ds.System(f, h, ds.Interval(c0 - r0, c0 + r0), ds.Interval(-Wt, Wt),
                     ds.Interval(-Vt, Vt), name="linear2")


@pytest.fixture(scope="module")
def data():
    s = _system()
    tr = s.simulate(steps=STEPS, batch=BATCH, seed=7, noise="uniform")
    return s, tr


def _compare(res, refs, perturb_must_fail=True):
    """Compare res.lower/upper [B, T+1, n] with refs (list of [T+1, 2n] = lower|upper)."""
    lo, hi = res.lower.detach().numpy(), res.upper.detach().numpy()
    worst = 0.0
    for b, ref in enumerate(refs):
        got = np.concatenate([lo[b], hi[b]], -1)
        np.testing.assert_allclose(got, ref, rtol=RTOL, atol=ATOL)
        worst = max(worst, float((np.abs(got - ref) / (ATOL + RTOL * np.abs(ref))).max()))
        if perturb_must_fail:  # the comparison is sharp enough to catch a 1e-6 change
            bad = ref.copy()
            bad[STEPS // 2, 0] += 1e-6
            with pytest.raises(AssertionError):
                np.testing.assert_allclose(got, bad, rtol=RTOL, atol=ATOL)
    return worst


# ------------------------------------------------------------------ HSNSMF = Chisci 1996
def _chisci(G: np.ndarray) -> np.ndarray:
    """Minimal-volume outer parallelotope over generator bases (Chisci 1996) -> T."""
    n, m = G.shape
    best, bestT = np.inf, None
    for idx in itertools.combinations(range(m), n):
        B = G[:, idx]
        if abs(np.linalg.det(B)) < 1e-14:
            continue
        T = B * np.abs(np.linalg.solve(B, G)).sum(1)
        v = abs(np.linalg.det(T))
        if v < best:
            best, bestT = v, T
    return bestT


def _par_strip(xc, T, p, cs, tie=1e-9, rule=False):
    """Wang et al. 2022, eq. 30-41: parallelotope (xc, T) cap {|p x - cs| <= 1} -> list of (xc, T).

    Eq. 38-39 pick ``i* = argmax_j p_bar t_bar_j`` (j = n + 1: keep P_bar, value 1). The
    argmax is often an exact tie: a column clipped by eq. 37 on one side only has
    ``p_bar t_bar_j = (1 - eps0-) / 2`` (or ``(1 + eps0+) / 2``) whatever ``j``, and a column
    clipped on both sides gives exactly 1 (= keeping P_bar). Every tied choice has the same
    volume (eq. 38) but a different shape, so the method is not unique; all choices within
    ``tie`` (relative) are returned. With ``rule=True`` only the choice of the filter's
    documented tie rule (``Parallelotope.intersect_strip``: of the tied ones, the least sum of
    hull half-widths ``sum |T|``, then P_bar, then the lowest index) is returned.
    """
    pt = p @ T
    e_p = p @ xc - cs + np.abs(pt).sum()  # eq. 31
    e_m = p @ xc - cs - np.abs(pt).sum()  # eq. 32
    assert not (e_p < -1 or e_m > 1), "empty intersection in the reference"
    T = T * np.where(pt < 0, -1.0, 1.0)
    pt = np.abs(pt)
    rp, rm = min(1, e_p), min(1, -e_m)  # eq. 33-36
    pb = 2 / (rp + rm) * p
    cb = 2 / (rp + rm) * (cs + (rp - rm) / 2)
    xb, Tb = xc.copy(), T.copy()
    for i in range(T.shape[1]):  # eq. 37
        if pt[i] != 0:
            ri_p = min(1, (1 - e_m) / pt[i] - 1)
            ri_m = min(1, (1 + e_p) / pt[i] - 1)
            Tb[:, i] = (ri_p + ri_m) / 2 * T[:, i]
            xb = xb + (ri_p - ri_m) / 2 * T[:, i]
    pbt = pb @ Tb
    vals = np.append(pbt, 1.0)
    out = []
    for i_star in np.nonzero(vals >= vals.max() * (1 - tie))[0]:  # eq. 38-39 (all ties)
        if i_star == T.shape[1]:
            out.append((xb, Tb))  # eq. 40
            continue
        Ts = Tb - np.outer(Tb[:, i_star], pbt / pbt[i_star])  # eq. 41
        Ts[:, i_star] = Tb[:, i_star] / pbt[i_star]
        xs = xb + Tb[:, i_star] * (cb - pb @ xb) / pbt[i_star]
        out.append((xs, Ts))
    if rule:  # the documented tie rule: least sum |T| (1e-12), then P_bar, then lowest index
        h = np.array([np.abs(b[1]).sum() for b in out])
        least = [b for b, hb in zip(out, h) if hb <= h.min() * (1 + tie)]
        out = [b for b in least if b[1] is Tb] or least[:1]
    return out


def _hull(c, T):
    r = np.abs(T).sum(1)
    return np.concatenate([c - r, c + r])


def _hsnsmf_numpy(y: np.ndarray, follow: np.ndarray | None = None, rule: bool = False):
    """Reference hulls ``[T+1, 4]`` and the number of steps with a tied choice.

    Where eq. 38-39 tie (see `_par_strip`), the reference continues with the tied
    branch whose hull is nearest to ``follow[k]`` (the filter's hull; without ``follow``,
    the first branch). The filter is thus checked to make *one of* the tied Chisci choices
    at every step, and to be exact (1e-9) otherwise. ``rule=True``: every tie is resolved by
    the documented tie rule with its tolerance 1e-12 (one branch, no ``follow``)."""
    c, T = X0_C.copy(), np.diag(X0_R)
    out, ties = [_hull(c, T)], 0
    for k in range(y.shape[0]):
        c, T = A @ c, _chisci(np.hstack([A @ T, np.diag(W)]))
        c_pred, T_pred = c, T
        branches = [(c, T)]
        for j in range(C.shape[0]):
            branches = [b for cj, Tj in branches
                        for b in _par_strip(cj, Tj, C[j] / SIGMA[j], y[k, j] / SIGMA[j])]
        ties += len(branches) > 1
        if rule:
            c, T = c_pred, T_pred
            for j in range(C.shape[0]):
                (c, T), = _par_strip(c, T, C[j] / SIGMA[j], y[k, j] / SIGMA[j], 1e-12, True)
            out.append(_hull(c, T))
            continue
        if follow is None:
            c, T = branches[0]
        else:
            c, T = min(branches, key=lambda b: np.abs(_hull(*b) - follow[k + 1]).max())
        out.append(_hull(c, T))
    return np.stack(out), ties


def test_hsnsmf_equals_chisci_parallelotopes(data):
    s, tr = data
    with torch.no_grad():
        res = ds.filters.HSNSMF(s)(tr.y)
    assert res.consistent.all()
    got = torch.cat([res.lower, res.upper], -1).numpy()
    refs, ties = [], 0
    for b in range(BATCH):
        ref, t = _hsnsmf_numpy(tr.y[b].numpy(), follow=got[b])
        refs.append(ref)
        ties += t
    assert ties > 0  # the tie branch is exercised on this data
    _compare(res, refs)


def test_hsnsmf_tie_rule_equals_deterministic_chisci(data):
    """With the documented tie rule of eq. 38-39 (of the candidates within 1e-12 of the least
    volume, the least ``sum |T|`` within 1e-12, then P_bar, then the lowest index) the Chisci
    reference is one deterministic recursion, and the filter equals it to 1e-9 at every step
    without following the filter's branch."""
    s, tr = data
    with torch.no_grad():
        res = ds.filters.HSNSMF(s)(tr.y)
    refs, ties = [], 0
    for b in range(BATCH):
        ref, t = _hsnsmf_numpy(tr.y[b].numpy(), rule=True)
        refs.append(ref)
        ties += t
    assert ties > 0  # ties occur on this data, and the rule decides them
    worst = _compare(res, refs)
    assert worst < 1


# ------------------------------------------------------------------ MSZM = Alamo 2005 (volume)
def _zono_volume(G: np.ndarray) -> float:
    """2-D zonotope volume 4 sum_{i<j} |det [g_i g_j]| (Gover-Krikorian), brute force."""
    d = G[0][:, None] * G[1][None, :] - G[1][:, None] * G[0][None, :]
    return 2.0 * np.abs(d).sum()  # = 4 * sum over i < j (each pair counted twice)


def _alamo_volume_strip(c, G, p, y, sig):
    """Alamo 2005 Property 2 with the volume-minimal lambda (2-D: exact over candidates)."""
    pG = p @ G
    rad = np.abs(pG).sum()
    if abs(p @ c - y) + rad <= sig:  # the strip contains Z: lambda = 0
        return c, np.hstack([G, np.zeros((2, 1))])

    def member(lam):
        return c + lam * (y - p @ c), np.hstack([G - np.outer(lam, pG), sig * lam[:, None]])

    cands = [np.zeros(2)] + [G[:, j] / pG[j] for j in range(G.shape[1]) if pG[j] != 0]
    vols = [_zono_volume(member(lam)[1]) for lam in cands]
    vols[0] *= 1 - 1e-9  # ties: keep Z (as the filter does)
    return member(cands[int(np.argmin(vols))])


def _mszm_volume_numpy(y: np.ndarray) -> np.ndarray:
    c, G = X0_C.copy(), np.diag(X0_R)
    out = []

    def rec():
        r = np.abs(G).sum(1)
        out.append(np.concatenate([c - r, c + r]))

    rec()
    for k in range(y.shape[0]):
        c, G = A @ c, np.hstack([A @ G, np.diag(W)])
        for j in range(C.shape[0]):
            c, G = _alamo_volume_strip(c, G, C[j], y[k, j], SIGMA[j])
        rec()
    return np.stack(out)


def test_mszm_volume_rule_equals_alamo_2005(data):
    s, tr = data
    with torch.no_grad():
        res = ds.filters.MSZM(s, order=60, strip_method="volume")(tr.y)
        fr = ds.filters.MSZM(s, order=60, strip_method="fradius")(tr.y)
    assert res.consistent.all()
    refs = [_mszm_volume_numpy(tr.y[b].numpy()) for b in range(BATCH)]
    _compare(res, refs)
    # the two rules differ (the test would see a wrong rule)
    assert (res.upper - res.lower - (fr.upper - fr.lower)).abs().max() > 1e-4


# ------------------------------------------------------------------ CDSMF = ellipsoidal filter
INFLATE = 1e-10  # diffsmf.sets.ellipsoid.INFLATE (Minkowski sum, strip update)
SHAPE_MARGIN = 1e-10  # diffsmf.filters.cdsmf.SHAPE_MARGIN (per prediction)


def _fh_rho(g, r, e, n):
    """Minimal log det over rho in [0, 1): log det P+ = n log(1 - rho(1-rho) e^2 / D) - log D
    - (n-1) log(1-rho) + const, D = rho g + (1-rho) r; roots of the analytic derivative."""

    def f(rho):
        D = rho * g + (1 - rho) * r
        return n * np.log(1 - rho * (1 - rho) * e * e / D) - np.log(D) - (n - 1) * np.log1p(-rho)

    def df(rho):
        D = rho * g + (1 - rho) * r
        N = D - rho * (1 - rho) * e * e
        return (n * ((g - r) - e * e * (1 - 2 * rho)) / N - (n + 1) * (g - r) / D
                + (n - 1) / (1 - rho))

    grid = np.linspace(0.0, 1 - 1e-9, 4001)
    vals = np.array([df(t) for t in grid])
    cands = [0.0]
    for i in np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0]:
        cands.append(brentq(df, grid[i], grid[i + 1], xtol=1e-15, rtol=1e-15))
    return min(cands, key=f)


def _ell_strip(c, P, a, o, h):
    n = c.size
    g = a @ P @ a
    mid, sg = a @ c, np.sqrt(g)
    lo, hi = max(o - h, mid - sg), min(o + h, mid + sg)  # tighten to E's extent
    o2, h2 = (lo + hi) / 2, (hi - lo) / 2
    if h2 >= sg * (1 - 1e-12):
        return c, P  # the strip contains E
    r, e = h2 * h2, o2 - mid
    rho = _fh_rho(g, r, e, n)
    if rho == 0.0:
        return c, P
    Qinv = (1 - rho) * np.linalg.inv(P) + rho * np.outer(a, a) / r
    Q = np.linalg.inv(Qinv)
    c2 = Q @ ((1 - rho) * np.linalg.solve(P, c) + rho * a * o2 / r)
    k = (1 - rho) * (c - c2) @ np.linalg.solve(P, c - c2) + rho * (a @ c2 - o2) ** 2 / r
    P2 = (1 - k) * Q * (1 + INFLATE)
    if np.linalg.slogdet(P2)[1] >= np.linalg.slogdet(P)[1]:
        return c, P
    return c2, P2


def _cdsmf_numpy(y: np.ndarray, rule: str = "scaled-trace") -> np.ndarray:
    n = 2
    c, P = X0_C.copy(), np.diag(n * X0_R**2)
    out = []

    def rec():
        r = np.sqrt(np.diag(P))
        out.append(np.concatenate([c - r, c + r]))

    rec()
    for k in range(y.shape[0]):
        S1, S2 = A @ P @ A.T, np.diag(n * W**2)  # cover of the box W
        if rule == "trace":
            p = np.sqrt(np.trace(S1) / np.trace(S2))  # trace rule
        else:  # the trace rule in coordinates normalised by diag(S1 + S2)
            d = np.diag(S1) + np.diag(S2)
            p = np.sqrt((np.diag(S1) / d).sum() / (np.diag(S2) / d).sum())
        c, P = A @ c, ((1 + 1 / p) * S1 + (1 + p) * S2) * (1 + INFLATE) * (1 + SHAPE_MARGIN)
        for j in range(C.shape[0]):
            c, P = _ell_strip(c, P, C[j], y[k, j], SIGMA[j])
        rec()
    return np.stack(out)


@pytest.mark.parametrize("rule", ["scaled-trace", "trace"])
def test_cdsmf_equals_ellipsoidal_filter(data, rule):
    s, tr = data
    with torch.no_grad():
        res = ds.filters.CDSMF(s, sum_method=rule)(tr.y)
    assert res.consistent.all()
    refs = [_cdsmf_numpy(tr.y[b].numpy(), rule) for b in range(BATCH)]
    _compare(res, refs)
