"""Nonlinear filters (HSNSMF, MSZM, CDSMF, ESMF, EKF): structure, references, gradients, faults.

Containment on the built-in systems is in tests/test_filters_containment.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import diffsmf as ds
from diffsmf.filters import CDSMF, EKF, ESMF, HSNSMF, MSZM, by_name

GUARANTEED = [HSNSMF, MSZM, CDSMF, ESMF, ds.filters.IntervalFilter]
ALL = [*GUARANTEED, EKF]

A_LIN = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=torch.float64)
C_LIN = torch.tensor([[1.0, 0.5]], dtype=torch.float64)


def linear_system() -> ds.System:
    """x+ = A x + [u, 0] + w, y = C x + v; box noises (a linear ds.System)."""

    def f(x, u, theta):
        return x @ A_LIN.T + torch.cat([u, torch.zeros_like(u)], -1)

    def h(x):
        return x @ C_LIN.T

    return ds.System(
        f,
        h,
        x0_set=ds.Interval(torch.tensor([-0.5, 0.0]), torch.tensor([0.5, 1.0])),
        process_noise=ds.Interval(torch.full((2,), -0.01), torch.full((2,), 0.01)),
        measurement_noise=ds.Interval(torch.full((1,), -0.05), torch.full((1,), 0.05)),
        inputs=lambda k: torch.tensor([0.1 * np.sin(0.3 * k)]),
        name="linear",
    )


def quadratic_system() -> ds.System:
    """Wang et al. 2022, eq. 42 written here (independent of the library): 2-D, nonlinear f."""

    def f(x, u, theta):
        return torch.stack([0.5 * x[..., 0] * x[..., 1], 0.2 * x[..., 1] ** 2], -1) + u

    def h(x):
        return x[..., :1] + 0.1 * x[..., 1:] ** 2  # nonlinear h as well

    return ds.System(
        f,
        h,
        x0_set=ds.Interval(torch.tensor([-0.3, 0.2]), torch.tensor([-0.1, 0.4])),
        process_noise=ds.Interval(torch.full((2,), -1e-3), torch.full((2,), 1e-3)),
        measurement_noise=ds.Interval(torch.full((1,), -1e-3), torch.full((1,), 1e-3)),
        inputs=lambda k: torch.tensor([0.6, 0.6]),
        name="quadratic",
    )


# ---------------------------------------------------------------------- basics
def test_by_name_and_result_shapes():
    sys = quadratic_system()
    traj = sys.simulate(steps=5, batch=3, seed=1)
    for name in ["hsnsmf", "mszm", "cdsmf", "esmf", "ekf"]:
        res = by_name(name)(sys)(traj.y, u=traj.u)
        assert res.center.shape == (3, 6, 2)
        assert res.volume.shape == (3, 6) and res.consistent.shape == (3, 6)
        assert (res.lower <= res.upper).all()
    with pytest.raises(ValueError, match="name"):
        by_name("nope")
    with pytest.raises(ValueError, match="order"):
        MSZM(sys, order=0)
    with pytest.raises(ValueError, match="order"):
        MSZM(sys, order=True)  # a bool is not an order
    with pytest.raises(ValueError, match="stirling_step"):
        HSNSMF(sys, stirling_step=-1.0)


def test_ekf_matches_filterpy_on_linear_system():
    from filterpy.kalman import KalmanFilter

    sys = linear_system()
    traj = sys.simulate(steps=20, batch=1, seed=3)
    ekf = EKF(sys)
    with torch.no_grad():
        res = ekf(traj.y, u=traj.u)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x = np.array([0.0, 0.5])
    kf.P = np.diag([0.5**2 / 3, 0.5**2 / 3])
    kf.F = A_LIN.numpy()
    kf.H = C_LIN.numpy()
    kf.Q = np.diag([0.01**2 / 3] * 2)
    kf.R = np.array([[0.05**2 / 3]])
    kf.B = np.array([[1.0], [0.0]])
    for k in range(20):
        kf.predict(u=traj.u[0, k].numpy())
        kf.update(traj.y[0, k].numpy())
        np.testing.assert_allclose(res.center[0, k + 1].numpy(), kf.x, atol=1e-10)
        np.testing.assert_allclose(res.covariance[0, k + 1].numpy(), kf.P, atol=1e-12)
    # the reported set is the 3-sigma ellipsoid
    torch.testing.assert_close(res.sets.shape, 9 * res.covariance)


# ---------------------------------------------------------------------- linear system
def test_linear_remainders_are_zero():
    from diffsmf.linearize import dc_remainder, lagrange_remainder, stirling_jacobian

    sys = linear_system()
    P = ds.Parallelotope(torch.tensor([[0.3, -0.2]]), torch.tensor([[[0.2, 0.05], [0.0, 0.1]]]))
    u = torch.tensor([[0.1]])

    def fn(x):
        return sys.f(x, u, None)

    c = P.center
    F = stirling_jacobian(fn, c, 0.1)
    torch.testing.assert_close(F[0], A_LIN, atol=1e-13, rtol=0)
    for R in (dc_remainder(fn, P, c, F), lagrange_remainder(fn, P.interval_hull(), c, F)):
        assert R.lower.abs().max() < 1e-12 and R.upper.abs().max() < 1e-12
    H = stirling_jacobian(sys.h, c, 0.1)
    R = dc_remainder(sys.h, P, c, H)
    assert R.lower.abs().max() < 1e-12 and R.upper.abs().max() < 1e-12


def _girard(G: np.ndarray, order: int) -> np.ndarray:
    """Girard 2005 reduction written independently (numpy), with the scores of the generators
    normalised by the interval hull's half-widths (unit-free, as ``Zonotope.reduce``)."""
    n, m = G.shape
    if m <= order * n:
        return G
    r = np.abs(G).sum(1)
    Gs = G / np.where(r > 0, r, 1.0)[:, None]
    score = np.abs(Gs).sum(0) - np.abs(Gs).max(0)
    idx = np.argsort(-score, kind="stable")
    keep = G[:, idx[: order * n - n]]
    rest = G[:, idx[order * n - n :]]
    return np.hstack([keep, np.diag(np.abs(rest).sum(1))])


def _alamo_reference(sys, y, u, order):
    """Direct Alamo 2005 zonotope filter for x+ = A x + B u + w, y = C x + v (numpy)."""
    c = np.array([0.0, 0.5])
    G = np.diag([0.5, 0.5])
    W = np.diag([0.01, 0.01])
    sig = 0.05
    p = C_LIN.numpy()[0]
    out = []
    for k in range(y.shape[0]):
        c = A_LIN.numpy() @ c + np.array([u[k, 0], 0.0])
        G = _girard(np.hstack([A_LIN.numpy() @ G, W]), order)
        pc, rad = p @ c, np.abs(p @ G).sum()
        if abs(pc - y[k, 0]) + rad <= sig:
            lam = np.zeros(2)
        else:
            lam = G @ G.T @ p / (p @ G @ G.T @ p + sig**2)
        c = c + lam * (y[k, 0] - pc)
        G = _girard(np.hstack([G - np.outer(lam, p @ G), sig * lam[:, None]]), order)
        out.append((c.copy(), np.abs(G).sum(1)))
    return out


def test_mszm_equals_direct_alamo_filter_on_linear_system():
    sys = linear_system()
    traj = sys.simulate(steps=15, batch=1, seed=4, noise="vertex")
    with torch.no_grad():
        res = MSZM(sys, order=3)(traj.y, u=traj.u)
    ref = _alamo_reference(sys, traj.y[0].numpy(), traj.u[0].numpy(), 3)
    for k, (c, r) in enumerate(ref):
        np.testing.assert_allclose(res.center[0, k + 1].numpy(), c, atol=1e-9)
        hull_r = (res.upper[0, k + 1] - res.lower[0, k + 1]).numpy() / 2
        np.testing.assert_allclose(hull_r, r, atol=1e-9)


# ---------------------------------------------------------------------- batching
@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_batch_equals_loop(cls):
    sys = quadratic_system()
    traj = sys.simulate(steps=6, batch=3, seed=5)
    filt = cls(sys)
    res = filt(traj.y, u=traj.u)
    for b in range(3):
        one = filt(traj.y[b : b + 1], u=traj.u[b : b + 1])
        torch.testing.assert_close(one.center[0], res.center[b], atol=1e-12, rtol=1e-10)
        torch.testing.assert_close(one.volume[0], res.volume[b], atol=1e-14, rtol=1e-9)


# ---------------------------------------------------------------------- gradients
@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_gradcheck_noise_bounds(cls):
    from conftest import gradcheck_noise_bounds

    sys = quadratic_system()
    traj = sys.simulate(steps=3, batch=2, seed=6)
    assert gradcheck_noise_bounds(cls(sys), traj)  # EKF: volume of the 3-sigma ellipsoid


def test_gradient_reaches_stirling_step():
    sys = quadratic_system()
    traj = sys.simulate(steps=3, batch=2, seed=6)
    filt = HSNSMF(sys)
    filt(traj.y, u=traj.u).volume[:, -1].sum().backward()
    assert filt.raw_stirling_step.grad is not None
    assert torch.isfinite(filt.raw_stirling_step.grad).all()


# ---------------------------------------------------------------------- faults
@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_nan_raises_and_skip_nan_skips(cls):
    sys = quadratic_system()
    traj = sys.simulate(steps=4, batch=2, seed=7)
    y = traj.y.clone()
    y[0, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        cls(sys)(y, u=traj.u)
    filt = cls(sys, skip_nan=True)
    res = filt(y, u=traj.u)
    # the skipped update leaves the predicted set of step 3 for element 0
    st = filt.initial_state(batch=2)
    for k in range(3):
        st = filt.predict(st, traj.u[:, k])
        if k < 2:
            st = filt.update(st, traj.y[:, k])
    torch.testing.assert_close(res.center[0, 3], st.set.center[0])
    torch.testing.assert_close(res.volume[0, 3], st.set.volume()[0])
    ref = cls(sys)(traj.y, u=traj.u)
    torch.testing.assert_close(res.center[1], ref.center[1])


@pytest.mark.parametrize(
    "name", ["hsnsmf", "mszm", "cdsmf", "esmf", "ekf", "czsmf", "combined", "interval"]
)
def test_eager_update_and_step_check_y(name):
    """``update`` / ``step`` (eager) refuse a measurement that would broadcast (``[1, m]``,
    ``[B]``, ``[B, 2m]``) or holds inf, naming ``y``; before, HSNSMF, MSZM, CDSMF and CZSMF
    returned a plausible set, ``consistent`` True, for each of these."""
    sys = quadratic_system()
    traj = sys.simulate(steps=2, batch=3, seed=1)
    filt = by_name(name)(sys)
    st = filt.predict(filt.initial_state(batch=3), traj.u[:, 0])
    y = traj.y[:, 0]  # [3, 1]
    bad = {
        "[1, m]": y[:1],
        "[B]": y[:, 0],
        "[B, 2m]": y.repeat(1, 2),
    }
    for yb in bad.values():
        with pytest.raises(ValueError, match=r"^y: expected shape \[3, 1\]"):
            filt.update(st, yb)
        with pytest.raises(ValueError, match=r"^y: expected shape \[3, 1\]"):
            filt.step(filt.initial_state(batch=3), traj.u[:, 0], yb)
    with pytest.raises(ValueError, match="^y: contains inf"):
        filt.update(st, torch.full_like(y, float("inf")))
    # a list or a float32 tensor of the right shape is converted to the system's float64
    for yc, yd in ((y.tolist(), y), (y.float(), y.float().double())):
        out, ref = filt.update(st, yc), filt.update(st, yd)
        torch.testing.assert_close(out.set.center, ref.set.center, rtol=0, atol=0)


@pytest.mark.parametrize(
    "name", ["hsnsmf", "mszm", "cdsmf", "esmf", "ekf", "czsmf", "combined", "interval"]
)
def test_initial_state_batch_checked(name):
    """``initial_state(batch=...)``: a count or None; -1, True, 2.5 raise naming ``batch``
    (before: raw expand errors, or ``True`` taken as 1)."""
    filt = by_name(name)(quadratic_system())
    for bad in (-1, True, 2.5, "2"):
        with pytest.raises(ValueError, match="^batch: must be an integer >= 0"):
            filt.initial_state(batch=bad)
    assert filt.initial_state(batch=np.int64(3)).consistent.shape == (3,)
    assert filt.initial_state().consistent.shape == (1,)


@pytest.mark.parametrize("cls", GUARANTEED, ids=lambda c: c.__name__)
def test_inconsistent_measurement_keeps_prediction(cls):
    sys = quadratic_system()
    traj = sys.simulate(steps=4, batch=2, seed=8)
    y = traj.y.clone()
    y[0, 2] = y[0, 2] + 10.0  # far outside the reachable measurement range
    filt = cls(sys)
    res = filt(y, u=traj.u)
    assert not res.consistent[0, 3] and res.consistent[1].all() and res.consistent[0, :3].all()
    st = filt.initial_state(batch=2)
    for k in range(3):
        st = filt.predict(st, traj.u[:, k])
        if k < 2:
            st = filt.update(st, y[:, k])
    torch.testing.assert_close(res.center[0, 3], st.set.center[0])
    torch.testing.assert_close(res.volume[0, 3], st.set.volume()[0])
    assert res.sets[0, 3].contains(traj.x[0, 3])


def test_missing_or_non_numeric_y_names_y():
    """``y=None`` or text gives a ValueError naming ``y`` (not torch's TypeError)."""
    sys = quadratic_system()
    filt = HSNSMF(sys)
    for bad in (None, "abc"):
        with pytest.raises(ValueError, match=r"^y: cannot convert"):
            filt(bad)
        with pytest.raises(ValueError, match=r"^y: cannot convert"):
            filt.step(filt.initial_state(batch=1), torch.zeros(1, sys.n_inputs), bad)


def test_mszm_stable_partition_equals_stable_sort():
    """MSZM's zero-column partition (one running sum) is the permutation of a stable sort
    of the zero flags, on random patterns including all-zero and all-non-zero rows."""
    from diffsmf.filters.mszm import _stable_partition

    g = torch.Generator().manual_seed(0)
    keep = torch.rand(200, 13, generator=g) < torch.rand(200, 1, generator=g)
    keep[0], keep[1] = False, True
    order = torch.sort((~keep).to(torch.int8), dim=-1, stable=True).indices
    dest = _stable_partition(keep, keep.sum(-1))
    inverse = torch.empty_like(order).scatter_(-1, dest, torch.arange(13).expand(200, 13))
    assert torch.equal(inverse, order)
