"""Ellipsoid: exact quantities, outer bounds contain sampled points, optimal weights."""

import math

import numpy as np
import pytest
import scipy.optimize
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import diffsmf as ds
from diffsmf.sets.ellipsoid import Ellipsoid, _lambdas, minkowski_weight

SETTINGS = settings(max_examples=12, deadline=None)


def _spd(n, batch=(), seed=0, cond=10.0):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(*batch, n, n, generator=g)
    return A @ A.mT / n + torch.eye(n) / cond


def _ell(n, batch=(), seed=0):
    g = torch.Generator().manual_seed(seed + 1000)
    return Ellipsoid(torch.randn(*batch, n, generator=g), _spd(n, batch, seed))


def _pts(E, k, seed):
    """Uniform + boundary points -> [k, *batch, n] (for contains broadcasting)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.cat([E.sample(k, g), E.sample_extreme(k, g)], -2)
    return x.movedim(-2, 0)


# ---------------------------------------------------------------------------- exact quantities
def test_volume_formula():
    S = torch.tensor([[4.0, 1.0], [1.0, 2.0]])
    E = Ellipsoid(torch.zeros(2), S)
    assert E.volume().item() == pytest.approx(math.pi * math.sqrt(7.0), rel=1e-12)
    S3 = _spd(3, seed=3)
    E3 = Ellipsoid(torch.ones(3), S3)
    ref = 4.0 / 3.0 * math.pi * math.sqrt(float(np.linalg.det(S3.numpy())))
    assert E3.volume().item() == pytest.approx(ref, rel=1e-12)
    S5 = _spd(5, seed=4)
    ref5 = 8.0 * math.pi**2 / 15.0 * math.sqrt(float(np.linalg.det(S5.numpy())))
    assert Ellipsoid(torch.zeros(5), S5).volume().item() == pytest.approx(ref5, rel=1e-12)


def test_contains_support_hull_against_numpy():
    E = _ell(3, (4,), seed=2)
    g = torch.Generator().manual_seed(0)
    x = 2 * torch.randn(500, 4, 3, generator=g) + E.center
    Sinv = np.linalg.inv(E.shape.numpy())
    d = (x - E.center).numpy()
    q = np.einsum("kbi,bij,kbj->kb", d, Sinv, d)
    assert (E.contains(x).numpy() == (q <= 1 + 1e-9)).all()
    dirs = torch.randn(4, 3, generator=g)
    bnd = E.sample_extreme(4000, g)  # [4, k, 3]
    h = E.support(dirs)
    hs = (bnd @ dirs.unsqueeze(-1)).squeeze(-1).amax(-1)
    assert (hs <= h + 1e-9).all() and (h - hs < 0.05 * h.abs().clamp(min=1)).all()
    hull = E.interval_hull()
    assert hull.contains(bnd.movedim(-2, 0)).all()
    assert torch.allclose(hull.radius, E.shape.diagonal(dim1=-2, dim2=-1).sqrt())


@SETTINGS
@given(st.integers(0, 10_000), st.integers(2, 5), st.integers(1, 6))
def test_linear_map_contains_images(seed, n, k):
    E = _ell(n, (3,), seed)
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(3, k, n, generator=g)
    b = torch.randn(3, k, generator=g)
    F = E.linear_map(A, b)
    x = _pts(E, 300, seed)  # [k, 3, n]
    y = (A @ x.unsqueeze(-1)).squeeze(-1) + b
    assert F.contains(y, atol=1e-7).all()
    if k == n:
        assert torch.allclose(F.volume(), E.volume() * torch.linalg.det(A).abs())


def test_translate_and_sample_inside():
    E = _ell(3, (2,), seed=9)
    T = E.translate(torch.tensor([1.0, 2.0, 3.0]))
    x = _pts(E, 200, 1)
    assert T.contains(x + torch.tensor([1.0, 2.0, 3.0])).all()
    assert E.sample(10).shape == (2, 10, 3)


# ---------------------------------------------------------------------------- Minkowski sum
@SETTINGS
@given(st.integers(0, 10_000), st.integers(2, 5), st.sampled_from(["trace", "volume"]))
def test_minkowski_sum_contains_sums(seed, n, method):
    E1, E2 = _ell(n, (3,), seed), _ell(n, (3,), seed + 1)
    E = E1.minkowski_sum(E2, method=method)
    x = _pts(E1, 300, seed) + _pts(E2, 300, seed + 5)
    assert E.contains(x, atol=0.0).all()


@SETTINGS
@given(st.integers(0, 10_000), st.integers(2, 5))
def test_minkowski_weights_against_brute_force(seed, n):
    S1, S2 = _spd(n, seed=seed), _spd(n, seed=seed + 1) * (0.1 + seed % 5)

    def logdet(lp):
        p = math.exp(lp)
        return float(torch.logdet((1 + 1 / p) * S1 + (1 + p) * S2))

    def trace(lp):
        p = math.exp(lp)
        return float(torch.trace((1 + 1 / p) * S1 + (1 + p) * S2))

    for method, fn in (("volume", logdet), ("trace", trace)):
        p = minkowski_weight(S1, S2, method).item()
        res = scipy.optimize.minimize_scalar(
            fn, bounds=(-12, 12), method="bounded", options={"xatol": 1e-10}
        )
        assert math.log(p) == pytest.approx(res.x, abs=1e-4)
        assert fn(math.log(p)) <= res.fun + 1e-9
    # the erratum equation of Jiang et al. 2016, eq. 35: sum 1/(lambda + 1/p) = n p^2/(p + 1)
    p = minkowski_weight(S1, S2, "volume")
    lam = _lambdas(S1, S2)
    lhs = (1.0 / (lam + 1.0 / p)).sum(-1)
    assert lhs.item() == pytest.approx((n * p**2 / (p + 1)).item(), rel=1e-9)


def test_minkowski_weight_equal_shapes_is_one():
    S = _spd(4, (3,), seed=5)
    assert torch.allclose(minkowski_weight(S, S, "volume"), torch.ones(3), atol=1e-12)
    assert torch.allclose(minkowski_weight(S, S, "trace"), torch.ones(3))
    assert minkowski_weight(S, 4 * S, "trace")[0].item() == pytest.approx(0.5)


def test_minkowski_with_box_and_zonotope():
    E = _ell(3, seed=3)
    B = ds.Interval(-torch.ones(3) * 0.5, torch.ones(3))
    Z = ds.Zonotope(torch.zeros(3), torch.randn(3, 5, generator=torch.Generator().manual_seed(0)))
    for other in (B, Z):
        F = E.minkowski_sum(other, method="volume")
        g = torch.Generator().manual_seed(1)
        x = E.sample_extreme(500, g) + other.sample_extreme(500, g)
        assert F.contains(x, atol=0.0).all()


def test_batched_equals_per_element():
    E1, E2 = _ell(3, (4,), 1), _ell(3, (4,), 2)
    S = ds.Strip(
        torch.randn(4, 3, generator=torch.Generator().manual_seed(0)),
        E1.center[:, 0] + 0.3,
        torch.full((4,), 0.4),
    )
    for op in (
        lambda a, b, s: a.minkowski_sum(b, method="volume"),
        lambda a, b, s: a.intersect_strip(s),
        lambda a, b, s: a.intersect_strip(s, method="trace"),
        lambda a, b, s: a.intersect_ellipsoid(b),
    ):
        full = op(E1, E2, S)
        for i in range(4):
            one = op(E1[i], E2[i], S[i])
            assert torch.allclose(one.shape, full.shape[i], rtol=1e-7, atol=1e-10)
            assert torch.allclose(one.center, full.center[i], rtol=1e-7, atol=1e-10)


# ---------------------------------------------------------------------------- intersections
@SETTINGS
@given(st.integers(0, 10_000), st.integers(2, 5), st.sampled_from(["volume", "trace", "fixed"]))
def test_intersect_strip_contains_feasible_points(seed, n, method):
    E = _ell(n, (4,), seed)
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(4, n, generator=g)
    mid = (a * E.center).sum(-1)
    S = ds.Strip(a, mid + torch.randn(4, generator=g), 0.05 + torch.rand(4, generator=g))
    F = E.intersect_strip(S, method=method)
    x = _pts(E, 1500, seed)
    inside = S.contains(x, atol=0.0)
    # per batch element: feasible points lie in F
    ok = F.contains(x, atol=0.0)
    assert (ok | ~inside).all()
    assert torch.isfinite(F.shape).all()
    assert (F.volume() <= E.volume() * (1 + 1e-9)).all()


def test_intersect_strip_volume_rho_is_minimal():
    E = _ell(3, (5,), seed=21)
    g = torch.Generator().manual_seed(2)
    a = torch.randn(5, 3, generator=g)
    mid = (a * E.center).sum(-1)
    S = ds.Strip(a, mid + 0.5 * torch.randn(5, generator=g), 0.1 + 0.3 * torch.rand(5, generator=g))
    best = E.intersect_strip(S, method="volume").volume()
    trace = E.intersect_strip(S, method="trace").volume()
    rho = torch.linspace(0.0, 0.999, 2000).unsqueeze(-1)  # [K, 1] against batch [5]
    brute = E.expand(2000, 5).intersect_strip(S.expand(2000, 5), rho=rho).volume().amin(0)
    assert (best <= brute * (1 + 1e-6)).all()
    assert (best <= trace * (1 + 1e-9)).all()


def test_strip_containing_set_returns_same_set():
    E = _ell(3, (2,), seed=4)
    a = torch.tensor([[1.0, 0.0, 0.5], [0.0, 2.0, 1.0]])
    h = E.support(a) - (a * E.center).sum(-1)
    S = ds.Strip(a, (a * E.center).sum(-1), h * 1.5)
    for method in ("volume", "trace", "fixed"):
        F = E.intersect_strip(S, method=method)
        assert torch.equal(F.shape, E.shape) and torch.equal(F.center, E.center)


def test_empty_intersection_returns_input_without_nan():
    E = _ell(2, (3,), seed=5)
    a = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    far = E.support(a) + 10.0
    S = ds.Strip(a, far, torch.full((3,), 0.5))
    assert not E.intersects_strip(S).any()
    F = E.intersect_strip(S)
    assert torch.equal(F.shape, E.shape) and torch.isfinite(F.shape).all()
    E2 = Ellipsoid(E.center + 100.0, E.shape)
    G = E.intersect_ellipsoid(E2)
    assert torch.equal(G.shape, E.shape)


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 4), st.sampled_from(["volume", "trace", "fixed"]))
def test_intersect_ellipsoid_contains_common_points(seed, n, method):
    E1 = _ell(n, (3,), seed)
    E2 = Ellipsoid(
        E1.center + 0.5 * torch.randn(3, n, generator=torch.Generator().manual_seed(seed)),
        _spd(n, (3,), seed + 3),
    )
    F = E1.intersect_ellipsoid(E2, method=method)
    x = torch.cat([_pts(E1, 1500, seed), _pts(E2, 1500, seed + 1)])
    both = E1.contains(x, atol=0.0) & E2.contains(x, atol=0.0)
    assert (F.contains(x, atol=0.0) | ~both).all()
    meet = both.any(0)  # certainly non-empty: never larger than either input
    vmin = torch.minimum(E1.volume(), E2.volume())
    assert (F.volume()[meet] <= vmin[meet] * (1 + 1e-9)).all()


@pytest.mark.parametrize("m", [2, 3])
def test_intersect_measurement_contains_feasible_points(m):
    E = _ell(3, (2,), seed=8)
    g = torch.Generator().manual_seed(8)
    H = torch.randn(2, m, 3, generator=g)
    R = _spd(m, (2,), seed=9) * 0.3
    y = (H @ E.center.unsqueeze(-1)).squeeze(-1) + 0.2
    F = E.intersect_measurement(H, y, R)
    x = _pts(E, 3000, 3)
    r = y - (H @ x.unsqueeze(-1)).squeeze(-1)
    feas = torch.einsum("kbi,bij,kbj->kb", r, torch.linalg.inv(R), r) <= 1
    assert feas.any() and (F.contains(x, atol=0.0) | ~feas).all()


def test_intersect_measurement_one_output_is_the_minimal_family_member():
    """m = 1, method "volume": the closed-form (Fogel-Huang) member contains every feasible
    sample and is the smallest member of the eq. 36-39 family on a fine rho grid (evaluated
    independently here, in numpy), to 1e-6 in log-volume."""
    E = _ell(3, (4,), seed=21)
    g = torch.Generator().manual_seed(21)
    H = torch.randn(4, 1, 3, generator=g)
    R = torch.rand(4, 1, 1, generator=g) * 0.2 + 0.01
    y = (H @ E.center.unsqueeze(-1)).squeeze(-1) + torch.tensor([[0.3], [-0.1], [0.0], [0.5]])
    F = E.intersect_measurement(H, y, R)
    x = _pts(E, 4000, 21)
    r = y - (H @ x.unsqueeze(-1)).squeeze(-1)
    feas = (r[..., 0] ** 2 <= R[..., 0, 0])
    assert feas.any() and (F.contains(x, atol=0.0) | ~feas).all()
    P = E.shape.numpy()
    for b in range(4):
        h, e = H[b, 0].numpy(), float(y[b, 0] - H[b, 0] @ E.center[b])
        best = np.inf
        for rho in np.linspace(1e-4, 1 - 1e-4, 4001):
            D = rho * h @ P[b] @ h + (1 - rho) * float(R[b, 0, 0])
            xi = 1 - rho * (1 - rho) * e * e / D
            K = rho * P[b] @ h / D
            S = xi / (1 - rho) * (P[b] - np.outer(K, h @ P[b]))
            best = min(best, np.linalg.slogdet(S)[1])
        assert best - 1e-6 <= float(torch.logdet(F.shape[b])) <= best + 1e-6
    # a fixed member of the same family (rho = 0.5) is no smaller
    G = E.intersect_measurement(H, y, R, rho=0.5)
    assert (F.volume() <= G.volume() * (1 + 1e-9)).all()


def test_intersect_measurement_one_output_zero_h_keeps_the_set():
    """A zero measurement row carries no information: the set comes back unchanged (no
    exception, no NaN)."""
    E = _ell(2, (2,), seed=3)
    F = E.intersect_measurement(torch.zeros(2, 1, 2), torch.tensor([[0.05], [0.0]]),
                                torch.full((2, 1, 1), 0.01))
    torch.testing.assert_close(F.shape, E.shape)
    torch.testing.assert_close(F.center, E.center)


# ---------------------------------------------------------------------------- covers
def test_from_box_and_from_zonotope_cover():
    g = torch.Generator().manual_seed(0)
    B = ds.Interval(-torch.rand(2, 4, generator=g), torch.rand(2, 4, generator=g))
    E = Ellipsoid.from_box(B)
    assert E.contains(B.vertices().movedim(-2, 0), atol=0.0).all()
    Z = ds.Zonotope(torch.randn(2, 3, generator=g), torch.randn(2, 3, 6, generator=g))
    for method in ("auto", "generators", "hull"):
        F = Ellipsoid.from_zonotope(Z, method=method)
        x = Z.sample_extreme(3000, g).movedim(-2, 0)
        assert F.contains(x, atol=0.0).all()
    flat = ds.Zonotope(torch.zeros(3), torch.tensor([[1.0], [1.0], [0.0]]))
    with pytest.raises(ValueError, match="Z"):
        Ellipsoid.from_zonotope(flat, method="generators")
    assert Ellipsoid.from_zonotope(flat).contains(torch.tensor([1.0, 1.0, 0.0]), atol=0.0)


# ---------------------------------------------------------------------------- gradients
def test_gradcheck_minkowski_sum():
    S1, S2 = _spd(3, seed=1), _spd(3, seed=2)
    L1 = torch.linalg.cholesky(S1).requires_grad_(True)
    L2 = torch.linalg.cholesky(S2).requires_grad_(True)

    def fn(L1, L2, method):
        E1 = Ellipsoid(torch.zeros(3), L1 @ L1.mT)
        E2 = Ellipsoid(torch.ones(3), L2 @ L2.mT)
        return E1.minkowski_sum(E2, method=method).shape

    for method in ("trace", "volume"):
        assert torch.autograd.gradcheck(
            lambda a, b, method=method: fn(a, b, method), (L1, L2), fast_mode=True
        )


def test_gradcheck_intersect_strip():
    S = _spd(3, seed=6)
    L = torch.linalg.cholesky(S).requires_grad_(True)
    c = torch.tensor([0.1, -0.2, 0.3], requires_grad=True)
    a = torch.tensor([1.0, 0.5, -0.3], requires_grad=True)
    hw = torch.tensor(0.2, requires_grad=True)

    def fn(L, c, a, hw, method):
        E = Ellipsoid(c, L @ L.mT)
        F = E.intersect_strip(ds.Strip(a, (a * c).sum() + 0.1, hw), method=method)
        return F.center, F.shape

    for method in ("volume", "trace"):
        assert torch.autograd.gradcheck(
            lambda *t, method=method: fn(*t, method), (L, c, a, hw), fast_mode=True
        )


def test_gradcheck_intersect_ellipsoid_and_measurement():
    L1 = torch.linalg.cholesky(_spd(2, seed=11)).requires_grad_(True)
    L2 = torch.linalg.cholesky(_spd(2, seed=12))
    c2 = torch.tensor([0.3, -0.2], requires_grad=True)

    def both(L1, c2):
        E1 = Ellipsoid(torch.zeros(2), L1 @ L1.mT)
        F = E1.intersect_ellipsoid(Ellipsoid(c2, L2 @ L2.mT), method="volume")
        return F.center, F.shape

    def meas(L1, c2):
        E1 = Ellipsoid(torch.zeros(2), L1 @ L1.mT)
        H = c2.unsqueeze(0) + torch.tensor([[1.0, 0.0]])
        F = E1.intersect_measurement(H, torch.tensor([0.2]), (L2[:1, :1] ** 2), method="trace")
        return F.center, F.shape

    def meas_volume(L1, c2):  # m = 1, "volume": the Fogel-Huang closed form
        E1 = Ellipsoid(torch.zeros(2), L1 @ L1.mT)
        H = c2.unsqueeze(0) + torch.tensor([[1.0, 0.0]])
        F = E1.intersect_measurement(H, torch.tensor([0.2]), (L2[:1, :1] ** 2))
        return F.center, F.shape

    for fn in (both, meas, meas_volume):
        assert torch.autograd.gradcheck(fn, (L1, c2), fast_mode=True)


def test_validation_names_argument():
    with pytest.raises(ValueError, match="shape"):
        Ellipsoid(torch.zeros(2), torch.tensor([[1.0, 0.0], [0.0, -1.0]]))
    with pytest.raises(ValueError, match="shape"):
        Ellipsoid(torch.zeros(2), torch.tensor([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="shape"):
        Ellipsoid(torch.zeros(3), torch.eye(2))
    with pytest.raises(ValueError, match="center"):
        Ellipsoid(torch.tensor([float("nan"), 0.0]), torch.eye(2))
    with pytest.raises(ValueError, match="p"):
        _ell(2).minkowski_sum(_ell(2), p=-1.0)
    with pytest.raises(ValueError, match="method"):
        _ell(2).minkowski_sum(_ell(2), method="foo")
    with pytest.raises(ValueError, match="R"):
        _ell(2).intersect_measurement(torch.eye(2), torch.zeros(2), -torch.eye(2))


def test_intersect_measurement_square_h_element_by_element():
    """Square ``H``: the two-sided update wherever ``H`` is invertible, the one-sided family
    where it is singular, decided per batch element (so a singular element does not change
    its neighbours' sets, and eager equals the branch-free traced code)."""
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    E = ds.Ellipsoid(t([[0.0, 0.0], [0.1, 0.0]]), t([[[1.0, 0.2], [0.2, 0.5]]] * 2))
    H = t([[[1.0, 0.3], [0.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]]])  # second one singular
    y = t([[0.5, 0.2], [0.3, 0.3]])
    R = t([[[0.04, 0.0], [0.0, 0.09]]] * 2)
    both = E.intersect_measurement(H, y, R)
    for i in range(2):
        Ei = ds.Ellipsoid(E.center[i], E.shape[i])
        one = Ei.intersect_measurement(H[i], y[i], R[i])
        torch.testing.assert_close(both.center[i], one.center, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(both.shape[i], one.shape, rtol=1e-12, atol=1e-15)
    # the invertible element took the two-sided form: the intersection with E(H^-1 y, ...)
    Hi = torch.linalg.inv(H[0])
    E2 = ds.Ellipsoid(Hi @ y[0], Hi @ R[0] @ Hi.mT)
    ref = ds.Ellipsoid(E.center[0], E.shape[0]).intersect_ellipsoid(E2)
    torch.testing.assert_close(both.shape[0], ref.shape, rtol=1e-9, atol=1e-14)


def test_intersect_measurement_square_h_singular_element_gradients():
    """A singular ``H`` in the batch does not put NaN into the gradients (its two-sided
    branch is computed on the identity and discarded)."""
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    H = t([[[1.0, 0.3], [0.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]]]).requires_grad_(True)
    R = t([[[0.04, 0.0], [0.0, 0.09]]] * 2).requires_grad_(True)
    E = ds.Ellipsoid(t([[0.0, 0.0], [0.1, 0.0]]), t([[[1.0, 0.2], [0.2, 0.5]]] * 2))
    out = E.intersect_measurement(H, t([[0.5, 0.2], [0.3, 0.3]]), R)
    torch.logdet(out.shape).sum().backward()
    assert torch.isfinite(H.grad).all() and torch.isfinite(R.grad).all()
    assert (H.grad[0] != 0).any()  # the regular element's two-sided update depends on H


def test_contains_degenerate_shape_matches_least_squares():
    """A singular PSD shape (a flat ellipsoid) used to raise from Cholesky; now a point is in
    it iff d = x - c = L u with |u| <= 1 (min-norm u by numpy lstsq), up to ~1e-9 off-plane."""
    g = torch.Generator().manual_seed(2)
    L = torch.randn(3, 2, generator=g, dtype=torch.float64)
    c = torch.randn(3, generator=g, dtype=torch.float64)
    E = Ellipsoid._make(c, L @ L.T)
    u = 1.3 * torch.randn(200, 2, generator=g, dtype=torch.float64)
    off = torch.randn(200, 3, generator=g, dtype=torch.float64)
    off[:100] = 0.0  # on the plane
    off[100:] *= 1e-3
    x = c + u @ L.T + off
    got = E.contains(x).numpy()
    d = (x - c).numpy()
    sol, *_ = np.linalg.lstsq(L.numpy(), d.T, rcond=None)
    resid = np.linalg.norm(L.numpy() @ sol - d.T, axis=0)
    ref = (np.linalg.norm(sol, axis=0) <= 1 + 1e-9) & (resid <= 1e-12)
    np.testing.assert_array_equal(got, ref)
    assert 20 < ref.sum() < 100  # both answers occur


@pytest.mark.parametrize("n", [1, 2, 3])
def test_volume_closed_form_matches_cholesky_and_rejects_non_pd(n):
    """Up to n = 2 ``volume`` is ``V_n sqrt(det S)`` from the closed-form determinant: equal
    to the Cholesky form ``V_n exp(sum log diag L)`` to rounding on a batch with a nearly
    singular shape, differentiable (gradcheck); a shape that is not positive definite still
    raises eagerly (the Cholesky path) and gives NaN while traced."""
    from diffsmf.sets.ellipsoid import unit_ball_volume

    g = torch.Generator().manual_seed(n)
    A = torch.randn(40, n, n, dtype=torch.float64, generator=g)
    S = A @ A.mT + 1e-3 * torch.eye(n, dtype=torch.float64)
    S[0] = torch.diag(torch.tensor([1.0] + [1e-10] * (n - 1), dtype=torch.float64))
    E = Ellipsoid(torch.zeros(40, n, dtype=torch.float64), S)
    ref = unit_ball_volume(n) * torch.exp(E.log_det_half())
    torch.testing.assert_close(E.volume(), ref, rtol=1e-12, atol=0.0)
    c = torch.zeros(2, n, dtype=torch.float64)

    def vol(s):
        return Ellipsoid._make(c, s).volume()

    Sg = S[1:3].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda s: vol(0.5 * (s + s.mT)), (Sg,))
    with pytest.raises(RuntimeError):
        vol(-S[1:3])
    if n <= 2:
        traced = torch.compile(vol, backend="eager", fullgraph=True)
        assert torch.isnan(traced(-S[1:3])).all()
        torch.testing.assert_close(traced(S[1:3]), ref[1:3], rtol=1e-12, atol=0.0)
