"""Combined Kalman + set-membership filter (Jiang et al. 2016) and statistical linearisation.

References: filterpy's KalmanFilter (Gaussian part), a hand-written numpy ellipsoidal
set-membership recursion (bounded part), scipy root finding / minimisation (Minkowski weights),
numpy weighted least squares (statistical linearisation), worst-case (vertex) simulations
(containment).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import eigh as sp_eigh
from scipy.optimize import brentq, minimize_scalar

import diffsmf as ds
from diffsmf.filters.combined import CombinedFilter
from diffsmf.linearize import axis_points, statistical_linearization
from diffsmf.sets import Ellipsoid
from diffsmf.sets.ellipsoid import outer_sum_shape
from diffsmf.systems import System

torch.set_default_dtype(torch.float64)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """These tests use many tiny matrices; extra intra-op threads only add contention."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _spd(n: int, gen: torch.Generator, scale: float = 1.0) -> torch.Tensor:
    L = torch.randn(n, n, generator=gen)
    return scale * (L @ L.T + 0.5 * torch.eye(n))


def _linear_system(n=4, m=2, seed=0, bounded=True, gaussian=True):
    """Random stable linear system with ellipsoidal bounded parts and Gaussian parts."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(n, n, generator=g)
    A = 0.95 * A / torch.linalg.eigvals(A).abs().max()
    H = torch.randn(m, n, generator=g)
    mats = dict(A=A, H=H, D=_spd(n, g, 0.05), E=_spd(m, g, 0.1), Q=_spd(n, g, 0.02),
                R=_spd(m, g, 0.05), S0=_spd(n, g, 0.5), P0=_spd(n, g, 0.3),
                x0=torch.randn(n, generator=g))
    sys = System(
        lambda x, u, th: x @ A.T,
        lambda x: x @ H.T,
        Ellipsoid(mats["x0"], mats["S0"]),
        Ellipsoid(torch.zeros(n), mats["D"]) if bounded else None,
        Ellipsoid(torch.zeros(m), mats["E"]) if bounded else None,
        process_cov=mats["Q"] if gaussian else None,
        measurement_cov=mats["R"] if gaussian else None,
    )
    return sys, mats


def _run(filt, y):
    with torch.no_grad():
        return filt(y)


# ---------------------------------------------------------------- statistical linearisation
def test_axis_points_are_4n_plus_1_on_the_axes():
    g = torch.Generator().manual_seed(1)
    c, S = torch.randn(3, generator=g), _spd(3, g)
    pts, z, M = axis_points(c, S)
    assert pts.shape == (13, 3)
    d = pts - c
    r2 = (d * torch.linalg.solve(S, d.T).T).sum(-1)  # Mahalanobis radius^2
    expected = torch.tensor([0.0] + [0.25, 0.25, 1.0, 1.0] * 3)
    torch.testing.assert_close(r2, expected, rtol=0, atol=1e-12)
    evecs = np.linalg.eigh(S.numpy())[1]
    for i in range(3):  # each group of 4 points lies on one principal axis (up to sign)
        dirs = d[1 + 4 * i : 5 + 4 * i].numpy()
        cos = np.abs(dirs @ evecs) / np.linalg.norm(dirs, axis=1, keepdims=True)
        assert np.isclose(cos.max(1), 1.0, atol=1e-10).all()


@pytest.mark.parametrize("axes", ["principal", "symmetric"])
def test_statistical_linearization_matches_numpy_wls(axes):
    g = torch.Generator().manual_seed(2)
    c, S = torch.randn(2, 3, generator=g), torch.stack([_spd(3, g), _spd(3, g)])
    w = torch.tensor([3.0, 1.0, 0.5])  # centre, level 0.5, level 1

    def fn(x):
        return torch.stack([torch.sin(x[..., 0]) * x[..., 1], x[..., 2] ** 3, x.exp().sum(-1)], -1)

    A, b = statistical_linearization(fn, c, S, weights=w, axes=axes)
    pts, _, _ = axis_points(c, S, axes=axes)
    lw = np.array([3.0] + [1.0, 1.0, 0.5, 0.5] * 3)
    for i in range(2):  # independent reference: numpy lstsq on sqrt-weighted rows
        X = np.c_[pts[:, i].numpy(), np.ones(13)]
        Y = fn(pts[:, i]).numpy()
        coef = np.linalg.lstsq(np.sqrt(lw)[:, None] * X, np.sqrt(lw)[:, None] * Y, rcond=None)[0]
        np.testing.assert_allclose(A[i].numpy(), coef[:3].T, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(b[i].numpy(), coef[3], rtol=1e-9, atol=1e-10)


def test_statistical_linearization_exact_for_affine_and_point_count():
    g = torch.Generator().manual_seed(3)
    A0, b0 = torch.randn(2, 4, generator=g), torch.randn(2, generator=g)
    c, S = torch.randn(4, generator=g), _spd(4, g, 100.0)
    A, b = statistical_linearization(lambda x: x @ A0.T + b0, c, S, levels=(1.0,))
    torch.testing.assert_close(A, A0, rtol=0, atol=1e-12)
    torch.testing.assert_close(b, b0, rtol=0, atol=1e-12)
    assert axis_points(c, S, levels=(1 / 3, 2 / 3, 1.0))[0].shape == (25, 4)


@pytest.mark.parametrize("axes", ["principal", "symmetric"])
def test_statistical_linearization_gradients(axes):
    g = torch.Generator().manual_seed(13)
    c, S = torch.randn(3, generator=g), _spd(3, g).requires_grad_()

    def fit(S):
        return statistical_linearization(torch.sin, c, 0.5 * (S + S.mT), axes=axes)

    assert torch.autograd.gradcheck(fit, (S,))
    # repeated eigenvalues (x/y-symmetric ellipsoid): no NaN (principal: basis held fixed)
    S2 = torch.diag(torch.tensor([2.0, 2.0, 0.5])).requires_grad_()
    A, b = fit(S2)
    (A.sum() + b.sum()).backward()
    assert torch.isfinite(S2.grad).all()


@pytest.mark.parametrize("axes", ["principal", "symmetric"])
def test_statistical_linearization_degenerate_shape(axes):
    """A collapsed direction (rank-deficient or zero shape) gives a finite fit, exact on the
    ellipsoid's range; without the axis floor it would be 0 / 0 = NaN."""
    g = torch.Generator().manual_seed(5)
    A0, b0, c = torch.randn(2, 3, generator=g), torch.randn(2, generator=g), torch.randn(3)
    L = torch.randn(3, 2, generator=g)
    S = L @ L.T  # rank 2
    A, b = statistical_linearization(lambda x: x @ A0.T + b0, c, S, axes=axes)
    assert torch.isfinite(A).all() and torch.isfinite(b).all()
    torch.testing.assert_close(A @ L, A0 @ L, rtol=0, atol=1e-9)  # exact on range(S)
    torch.testing.assert_close(A @ c + b, A0 @ c + b0, rtol=0, atol=1e-9)
    torch.testing.assert_close(A, A0, rtol=0, atol=1e-3)  # the floored axis: finite slope
    A, b = statistical_linearization(torch.sin, c, torch.zeros(3, 3), axes=axes)
    assert torch.isfinite(A).all()
    torch.testing.assert_close(A @ c + b, torch.sin(c), rtol=0, atol=1e-12)


def test_noise_free_collapse_stays_finite_and_consistent():
    """No noise of either kind: the mean set collapses onto the true state (observable
    system). Before, the gain became 0 / 0 and the filter raised 'center: contains NaN'."""
    sys, M = _linear_system(bounded=False, gaussian=False, seed=4)
    traj = sys.simulate(12, batch=3, seed=1)
    res = _run(CombinedFilter(sys, initial_cov=M["P0"]), traj.y)
    assert torch.isfinite(res.center).all() and torch.isfinite(res.sets.shape).all()
    assert res.bounded.all() and res.consistent.all()
    torch.testing.assert_close(res.center[:, -1], traj.x[:, -1], rtol=0, atol=1e-8)
    assert ((res.lower - 1e-8 <= traj.x) & (traj.x <= res.upper + 1e-8)).all()
    assert (res.upper - res.lower)[:, -1].max() < 1e-8  # collapsed onto the true state
    assert res.sets.contains(traj.x).all()  # flat ellipsoids: Cholesky with a rounding ridge


def test_guard_flags_a_nan_ellipsoid_instead_of_raising():
    sys, M = _linear_system(gaussian=False, seed=3)
    filt = CombinedFilter(sys, initial_cov=M["P0"])
    st = filt.initial_state(2)
    c = st.set.center.clone()
    c[1, 0] = float("nan")
    out = filt.guard(st.replace(set=Ellipsoid._make(c, st.set.shape)))
    assert out.bounded.tolist() == [True, False]
    assert torch.isfinite(out.set.center).all()


def test_statistical_linearization_bad_input():
    c, S = torch.zeros(2), torch.eye(2)
    with pytest.raises(ValueError, match="levels"):
        statistical_linearization(torch.sin, c, S, levels=())
    with pytest.raises(ValueError, match="axes"):
        statistical_linearization(torch.sin, c, S, axes="cholesky")
    with pytest.raises(ValueError, match="weights"):
        statistical_linearization(torch.sin, c, S, weights=[1.0, 2.0])
    with pytest.raises(ValueError, match="weights"):
        statistical_linearization(torch.sin, c, S, weights=[1.0, 0.0, 0.0])


# ---------------------------------------------------------------- Minkowski weights
def _S_of_p(S1, S2, p):
    return (1 + 1 / p) * S1 + (1 + p) * S2


def test_outer_sum_weights_against_scipy():
    g = torch.Generator().manual_seed(4)
    S1, S2 = _spd(3, g), _spd(3, g, 0.3)
    a1, a2 = S1.numpy(), S2.numpy()
    St = outer_sum_shape(S1, S2, "trace").numpy()
    pt = minimize_scalar(lambda p: np.trace(_S_of_p(a1, a2, p)), bounds=(1e-6, 1e6),
                         method="bounded", options={"xatol": 1e-12}).x
    np.testing.assert_allclose(St, _S_of_p(a1, a2, pt), rtol=1e-6)
    lam = sp_eigh(a2, a1, eigvals_only=True)  # eigenvalues of S1^-1 S2

    def eq35(p):  # erratum: sum 1 / (lam + 1/p) = n p^2 / (p + 1)
        return (1 / (lam + 1 / p)).sum() - 3 * p * p / (p + 1)

    pv = brentq(eq35, 1e-8, 1e8, xtol=1e-15)
    Sv = outer_sum_shape(S1, S2, "volume").numpy()
    np.testing.assert_allclose(Sv, _S_of_p(a1, a2, pv), rtol=1e-9)
    pm = minimize_scalar(lambda p: np.linalg.slogdet(_S_of_p(a1, a2, p))[1], bounds=(1e-6, 1e6),
                         method="bounded", options={"xatol": 1e-12}).x
    assert abs(pm - pv) < 1e-4 * pv
    same = outer_sum_shape(S1, S1, "volume")  # erratum check: S1 = S2 gives p = 1
    torch.testing.assert_close(same, 4 * S1)
    torch.testing.assert_close(outer_sum_shape(S1, 0 * S1, "volume"), S1)
    torch.testing.assert_close(outer_sum_shape(S1, 0 * S1, "trace"), S1)


@pytest.mark.parametrize("weight", ["trace", "volume"])
def test_outer_sum_contains_minkowski_sum_of_boundary_points(weight):
    g = torch.Generator().manual_seed(5)
    S1, S2 = _spd(3, g), _spd(3, g, 0.2)
    S2[:, 2] = 0.0  # degenerate (rank-2) second operand
    S2[2, :] = 0.0
    S = outer_sum_shape(S1, S2, weight)
    x1 = Ellipsoid(torch.zeros(3), S1).sample_extreme(4000, g)
    u = torch.randn(4000, 2, generator=g)
    u = u / u.norm(dim=-1, keepdim=True)
    x2 = torch.nn.functional.pad(u @ torch.linalg.cholesky(S2[:2, :2]).T, (0, 1))
    assert Ellipsoid(torch.zeros(3), S).contains(x1 + x2).all()


# ---------------------------------------------------------------- filter vs references
def test_gaussian_only_equals_filterpy_kalman():
    from filterpy.kalman import KalmanFilter

    sys, M = _linear_system(bounded=False, seed=6)
    traj = sys.simulate(15, batch=3, seed=1)
    res = _run(CombinedFilter(sys, initial_cov=M["P0"]), traj.y)
    for b in range(3):
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.F, kf.H, kf.Q, kf.R = (M[k].numpy() for k in ("A", "H", "Q", "R"))
        kf.x, kf.P = M["x0"].numpy().copy(), M["P0"].numpy().copy()
        for k in range(15):
            kf.predict()
            kf.update(traj.y[b, k].numpy())
            np.testing.assert_allclose(res.center[b, k + 1].numpy(), kf.x, rtol=0, atol=1e-10)
            np.testing.assert_allclose(res.covariance[b, k + 1].numpy(), kf.P, rtol=0,
                                       atol=1e-10)
    # with no bounded noise the mean set is only transported: S_k = M_k ... S_0 ... M_k'
    assert (res.volume[:, -1] < res.volume[:, 0]).all()


def test_gaussian_only_nonlinear_matches_filterpy_ekf():
    """No bounded noise and a tiny initial mean set: the fit over F(a, S + 1e-6 P) is a
    small-step central difference, so the combined filter is the EKF (filterpy, exact
    range/bearing Jacobian) up to the O(step^2) difference of the slopes (measured: 4e-12
    relative on the centre, 1e-10 on P)."""
    from filterpy.kalman import ExtendedKalmanFilter

    from diffsmf.systems.radar import radar_initial_cov, radar_matrices

    sys = ds.systems.get("radar", bounded=False, initial_shape=1e-10 * torch.eye(4))
    traj = sys.simulate(25, batch=2, seed=9)
    P0 = radar_initial_cov()
    res = _run(CombinedFilter(sys, initial_cov=P0), traj.y)
    A, _ = radar_matrices()

    def HJ(x):
        r2 = x[0] ** 2 + x[2] ** 2
        r = np.sqrt(r2)
        return np.array([[x[0] / r, 0, x[2] / r, 0], [-x[2] / r2, 0, x[0] / r2, 0]])

    def Hx(x):
        return np.array([np.hypot(x[0], x[2]), np.arctan2(x[2], x[0])])

    for b in range(2):
        ekf = ExtendedKalmanFilter(dim_x=4, dim_z=2)
        ekf.F, ekf.Q, ekf.R = A.numpy(), sys.process_cov.numpy(), sys.measurement_cov.numpy()
        ekf.x, ekf.P = sys.x0_set.center.numpy().copy(), P0.numpy().copy()
        for k in range(25):
            ekf.predict()
            ekf.update(traj.y[b, k].numpy(), HJ, Hx)
            np.testing.assert_allclose(res.center[b, k + 1].numpy(), ekf.x, rtol=1e-9)
            np.testing.assert_allclose(res.covariance[b, k + 1].numpy(), ekf.P, rtol=1e-7,
                                       atol=1e-9)


def test_gaussian_only_gradients_finite_after_mean_set_collapse():
    """No bounded noise: the mean set collapses (S -> 0); tuning Q, R must still get finite
    gradients (the degenerate Minkowski branches are masked, not differentiated through)."""
    sys, M = _linear_system(bounded=False, seed=12)
    traj = sys.simulate(8, batch=4, seed=10)
    filt = CombinedFilter(sys, initial_cov=M["P0"], weight="volume")
    res = filt(traj.y)
    loss = (res.center - traj.x).pow(2).sum() + res.covariance.diagonal(dim1=-2, dim2=-1).sum()
    loss.backward()
    for p in (filt.raw_process_std, filt.raw_measurement_std):
        assert torch.isfinite(p.grad).all() and (p.grad != 0).any()


def _reference_smf(M, y, weight):
    """Pure ellipsoidal SMF (numpy): S(p) sums for prediction and update, gain S H'(HSH'+E)^-1.

    Each sum carries diffsmf's rounding margin ``1 + 1e-10`` (``diffsmf.sets.ellipsoid.INFLATE``).
    """

    def osum(S1, S2):
        if weight == "trace":
            p = np.sqrt(np.trace(S1) / np.trace(S2))
        else:
            lam = sp_eigh(S2, S1, eigvals_only=True)
            n = len(lam)
            p = brentq(lambda p: (1 / (lam + 1 / p)).sum() - n * p * p / (p + 1), 1e-9, 1e9,
                       xtol=1e-14)
        return ((1 + 1 / p) * S1 + (1 + p) * S2) * (1 + 1e-10)

    A, H, D, E = (M[k].numpy() for k in ("A", "H", "D", "E"))
    a, S = M["x0"].numpy().copy(), M["S0"].numpy().copy()
    out = [(a, S)]
    for yk in y:
        a, S = A @ a, osum(A @ S @ A.T, D)
        K = S @ H.T @ np.linalg.inv(H @ S @ H.T + E)
        a = a + K @ (yk - H @ a)
        IKH = np.eye(len(a)) - K @ H
        S = osum(IKH @ S @ IKH.T, K @ E @ K.T)
        out.append((a, S))
    return out


@pytest.mark.parametrize("weight", ["trace", "volume"])
def test_bounded_only_equals_reference_ellipsoidal_smf(weight):
    sys, M = _linear_system(gaussian=False, seed=7)
    traj = sys.simulate(12, batch=2, seed=2, noise="vertex")
    filt = CombinedFilter(sys, initial_cov=M["P0"], weight=weight)
    assert filt.gain == "set"  # no Gaussian part: pure set-membership gain
    res = _run(filt, traj.y)
    for b in range(2):
        ref = _reference_smf(M, traj.y[b].numpy(), weight)
        for k, (a, S) in enumerate(ref):
            np.testing.assert_allclose(res.center[b, k].numpy(), a, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(res.sets.shape[b, k].numpy(), S, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("gain", ["set", "kalman"])
def test_mean_set_contains_true_state_vertex_noise(gain):
    sys, M = _linear_system(gaussian=False, seed=8)
    traj = sys.simulate(20, batch=1000, seed=3, noise="vertex")
    # gain "kalman": the filter assumes Gaussian parts the truth does not have; any gain keeps
    # the guarantee on the mean set when the true Gaussian noise is zero
    kw = {"measurement_cov": M["R"], "process_cov": M["Q"]} if gain == "kalman" else {}
    res = _run(CombinedFilter(sys, initial_cov=M["P0"], gain=gain, **kw), traj.y)
    assert res.sets.contains(traj.x, atol=1e-9).all()
    assert res.consistent.all()  # every measurement is consistent with the true bounds


@settings(max_examples=12, deadline=None)
@given(
    n=st.integers(1, 4),
    m_frac=st.floats(0.0, 1.0),
    seed=st.integers(0, 10_000),
    weight=st.sampled_from(["trace", "volume"]),
)
def test_containment_property_random_linear_systems(n, m_frac, seed, weight):
    """Any dims, any weight rule: zero Gaussian noise, vertex noise, state in the mean set."""
    m = 1 + int(m_frac * (n - 1))
    sys, M = _linear_system(n=n, m=m, seed=seed, gaussian=False)
    traj = sys.simulate(10, batch=50, seed=seed, noise="vertex")
    res = _run(CombinedFilter(sys, initial_cov=M["P0"], weight=weight), traj.y)
    assert res.sets.contains(traj.x, atol=1e-9).all()


def test_gradcheck_noise_bounds_and_covariances():
    sys, M = _linear_system(n=2, m=1, seed=9)
    traj = sys.simulate(3, batch=2, seed=4)
    names = ["raw_process_noise", "raw_measurement_noise", "raw_process_std",
             "raw_measurement_std"]
    for weight in ("trace", "volume"):
        filt = CombinedFilter(sys, initial_cov=M["P0"], weight=weight)
        params = tuple(getattr(filt, k).detach().clone().requires_grad_() for k in names)

        def run(*p, filt=filt):
            r = torch.func.functional_call(filt, dict(zip(names, p)), (traj.y,))
            return r.center, r.sets.shape, r.covariance

        assert torch.autograd.gradcheck(run, params, fast_mode=True)
        assert torch.autograd.gradcheck(lambda *p: run(*p)[0][:, -1], params)  # full Jacobian


def test_gradcheck_nonlinear_symmetric_axes():
    sys = ds.systems.get("radar")
    traj = sys.simulate(3, batch=1, seed=5)
    from diffsmf.systems.radar import radar_initial_cov

    filt = CombinedFilter(sys, initial_cov=radar_initial_cov(), axes="symmetric")
    names = ["raw_process_noise", "raw_measurement_noise", "raw_measurement_std"]
    params = tuple(getattr(filt, k).detach().clone().requires_grad_() for k in names)

    def run(*p):
        r = torch.func.functional_call(filt, dict(zip(names, p)), (traj.y,))
        return r.center[..., -1, :], r.sets.log_volume()[..., -1]

    assert torch.autograd.gradcheck(run, params, atol=1e-6, rtol=1e-4, fast_mode=True)


# ---------------------------------------------------------------- radar, region, errors
def test_radar_system_and_filter_runs():
    sys = ds.systems.get("radar")
    assert "radar" in ds.systems.names()
    y = sys.h(torch.tensor([200.0, 12.0, 200.0, 10.0]))
    torch.testing.assert_close(y, torch.tensor([200.0 * 2**0.5, torch.pi / 4]))
    G = torch.tensor([[0.5, 0.0], [1.0, 0.0], [0.0, 0.5], [0.0, 1.0]])
    torch.testing.assert_close(sys.process_cov, G @ G.T * 0.25)
    torch.testing.assert_close(sys.process_noise.shape, G @ G.T * 0.64 + 1e-9 * torch.eye(4))
    from diffsmf.systems.radar import radar_initial_cov

    traj = sys.simulate(30, batch=20, seed=6)
    res = _run(CombinedFilter(sys, initial_cov=radar_initial_cov()), traj.y)
    pos_err = (res.center[:, 1:, [0, 2]] - traj.x[:, 1:, [0, 2]]).norm(dim=-1)
    assert pos_err.mean() < 30.0  # range noise alone is ~20 m (Gaussian) + 30 m (bounded)
    assert torch.isfinite(res.volume).all()


def test_confidence_region_contains_mean_set_and_sigma_ellipsoid():
    sys, M = _linear_system(seed=10)
    traj = sys.simulate(5, batch=2, seed=7)
    res = CombinedFilter(sys, initial_cov=M["P0"])(traj.y)
    reg = res.confidence_region(k=2.0)
    g = torch.Generator().manual_seed(0)
    mean_pts = res.sets.sample_extreme(200, g)
    sig = Ellipsoid(torch.zeros(4), 4.0 * res.covariance).sample_extreme(200, g)
    assert reg.contains((mean_pts + sig).movedim(-2, 0)).all()
    with pytest.raises(ValueError, match="k"):
        res.confidence_region(k=0.0)


def test_nan_skip_and_bad_input():
    sys, M = _linear_system(seed=11)
    traj = sys.simulate(4, batch=2, seed=8)
    y = traj.y.clone()
    y[0, 2] = float("nan")
    filt = CombinedFilter(sys, initial_cov=M["P0"], skip_nan=True)
    st = filt.initial_state(2)
    for k in range(3):
        st = filt.predict(st)
        pred = st
        st = filt.update(st, y[:, k])
    torch.testing.assert_close(st.set.shape[0], pred.set.shape[0])  # element 0 skipped at k=2
    torch.testing.assert_close(st.extras["covariance"][0], pred.extras["covariance"][0])
    assert not torch.allclose(st.set.shape[1], pred.set.shape[1])
    with pytest.raises(ValueError, match="initial_cov"):
        CombinedFilter(sys, initial_cov=torch.eye(3))
    default = ds.filters.by_name("combined")(sys)  # P0 = covariance of uniform on x0_set
    pts = sys.x0_set.sample(20000, torch.Generator().manual_seed(0))
    torch.testing.assert_close(default.initial_cov, torch.cov(pts.T), rtol=0.1, atol=0.01)
    with pytest.raises(ValueError, match="weight"):
        CombinedFilter(sys, initial_cov=M["P0"], weight="det")
    with pytest.raises(ValueError, match="axes"):
        CombinedFilter(sys, axes="cholesky")
    with pytest.raises(ValueError, match="levels"):
        CombinedFilter(sys, levels=(0.0,))
    sys0, _ = _linear_system(seed=11, gaussian=False)
    with pytest.raises(ValueError, match="measurement_cov"):
        CombinedFilter(sys0, initial_cov=M["P0"], gain="kalman")
