"""Parallelotope: validation, exact geometry vs scipy, strip intersection (Wang et al. 2022, eq.
30-41)."""

import itertools

import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull, Delaunay

import diffsmf as ds
from diffsmf.sets.parallelotope import Parallelotope


def rand_par(n, batch=(), seed=0):
    g = torch.Generator().manual_seed(seed)
    return Parallelotope(
        torch.randn(*batch, n, generator=g), torch.randn(*batch, n, n, generator=g)
    )


def corners(P):
    s = np.array(list(itertools.product((-1.0, 1.0), repeat=P.dim)))
    return P.center.detach().numpy() + s @ P.T.detach().numpy().T


def cut_vertices(P, a, y, h):
    """Vertices of P cap S: P's vertices inside S and P's edges crossing the boundary."""
    n = P.dim
    c, T = P.center.numpy(), P.T.numpy()
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))
    out = [c + T @ s for s in signs if abs(a @ (c + T @ s) - y) <= h]
    for s in signs:  # edges from vertex c + T s towards the vertex with coordinate i flipped
        v = c + T @ s
        for i in range(n):
            e = -2 * s[i] * T[:, i]
            ae = a @ e
            if abs(ae) < 1e-14:
                continue
            for level in (y - h, y + h):
                t = (level - a @ v) / ae
                if 0 <= t <= 1:
                    out.append(v + t * e)
    return np.array(out).reshape(-1, n)


def test_validation_names_argument():
    with pytest.raises(ValueError, match="T"):
        Parallelotope(torch.zeros(2), torch.ones(2, 3))
    with pytest.raises(ValueError, match="T"):
        Parallelotope(torch.zeros(2), torch.tensor([[1.0, 2.0], [2.0, 4.0]]))  # singular
    with pytest.raises(ValueError, match="T"):
        Parallelotope(torch.zeros(3), torch.eye(2))
    with pytest.raises(ValueError, match="center"):
        Parallelotope(torch.tensor([0.0, float("nan")]), torch.eye(2))
    with pytest.raises(ValueError, match="T"):
        Parallelotope(torch.zeros(2), torch.tensor([[float("inf"), 0.0], [0.0, 1.0]]))


@pytest.mark.parametrize("n,seed", [(2, 0), (3, 1)])
def test_volume_vertices_exact(n, seed):
    P = rand_par(n, seed=seed)
    V = P.vertices()
    assert V.shape == (2**n, n)
    hull = ConvexHull(V.numpy())
    assert P.volume().item() == pytest.approx(hull.volume, rel=1e-10)
    assert P.volume().item() == pytest.approx(2**n * abs(np.linalg.det(P.T.numpy())), rel=1e-12)
    box = P.interval_hull()
    assert np.allclose(box.lower.numpy(), V.numpy().min(0))
    assert np.allclose(box.upper.numpy(), V.numpy().max(0))
    d = torch.randn(7, n)
    assert torch.allclose(P.support(d), (d @ V.T).amax(-1))


def test_contains_matches_delaunay():
    P = rand_par(3, seed=2)
    g = torch.Generator().manual_seed(0)
    eta = 1.4 * (2 * torch.rand(300, 3, generator=g) - 1)
    x = P.center + eta @ P.T.T
    ref = Delaunay(corners(P)).find_simplex(x.numpy()) >= 0
    ours = P.contains(x).numpy()
    assert (ours == ref).all() and ours.any() and (~ours).any()
    assert P.contains(P.vertices()).all() and P.contains(P.sample_extreme(50)).all()


def test_linear_map_types_and_minkowski():
    P = rand_par(3, seed=3)
    A = torch.randn(3, 3)
    Q = P.linear_map(A, torch.ones(3))
    assert isinstance(Q, Parallelotope)
    assert Q.volume().item() == pytest.approx(P.volume().item() * abs(torch.det(A).item()))
    R = P.linear_map(torch.randn(2, 3))
    assert isinstance(R, ds.Zonotope) and R.dim == 2
    S = P.minkowski_sum(ds.Interval(-torch.ones(3), torch.ones(3)))
    assert isinstance(S, ds.Zonotope) and S.num_generators == 6
    VS = corners(P)[:, None] + np.array(list(itertools.product((-1, 1), repeat=3)))[None]
    assert S.volume().item() == pytest.approx(ConvexHull(VS.reshape(-1, 3)).volume, rel=1e-9)
    Z = P.to_zonotope()
    assert torch.equal(Z.generators, P.T) and torch.equal(Z.center, P.center)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_intersect_strip_is_outer_bound(n):
    B = 200
    P = rand_par(n, batch=(B,), seed=10 + n)
    g = torch.Generator().manual_seed(n)
    a = torch.randn(B, n, generator=g)
    y = (a * P.center).sum(-1) + torch.randn(B, generator=g)
    h = torch.rand(B, generator=g) + 0.05
    S = ds.Strip(a, y, h)
    Q = P.intersect_strip(S)
    assert torch.isfinite(Q.T).all() and torch.isfinite(Q.center).all()
    x = P.sample(500, generator=g).transpose(0, 1)  # [k, B, n]
    inside = S.contains(x)
    assert inside.any()
    assert Q.contains(x)[inside].all()
    meets = P.intersects_strip(S)
    assert (Q.volume()[meets] <= P.volume()[meets] * (1 + 1e-12)).all()
    for i in range(0, B, 20):  # worst case: exact vertices of P cap S
        if meets[i]:
            Vc = torch.as_tensor(cut_vertices(P[i], a[i].numpy(), y[i].item(), h[i].item()))
            assert Q[i].contains(Vc).all()


def test_intersect_strip_2d_near_exact_area():
    P = Parallelotope(torch.zeros(2), torch.tensor([[1.0, 0.3], [0.2, 1.0]]))
    a, y, h = np.array([1.0, 1.0]), 0.5, 0.3
    Q = P.intersect_strip(ds.Strip(torch.as_tensor(a), y, h))
    exact = ConvexHull(cut_vertices(P, a, y, h)).volume
    assert exact <= Q.volume().item() <= 2.5 * exact


def test_intersect_strip_containing_and_empty_return_input():
    P = rand_par(3, seed=5)
    a = torch.tensor([0.3, -1.0, 0.5])
    wide = ds.Strip(a, a @ P.center, 1e3)
    Q = P.intersect_strip(wide)
    assert torch.allclose(Q.T, P.T, rtol=1e-14) and torch.allclose(Q.center, P.center)
    far = ds.Strip(a, a @ P.center + 1e3, 1.0)
    E = P.intersect_strip(far)
    assert torch.equal(E.T, P.T) and torch.equal(E.center, P.center)
    assert not P.intersects_strip(far)


def test_intersect_strip_batched_equals_per_element():
    P = rand_par(3, batch=(5,), seed=6)
    a = torch.randn(5, 3)
    S = ds.Strip(a, (a * P.center).sum(-1) + 0.2, torch.rand(5) + 0.1)
    Q = P.intersect_strip(S)
    for i in range(5):
        Qi = P[i].intersect_strip(S[i])
        assert torch.allclose(Q.T[i], Qi.T, atol=1e-14)
        assert torch.allclose(Q.center[i], Qi.center, atol=1e-14)


def test_intersect_strip_sequential_measurements_zero_halfwidth_is_finite():
    P = rand_par(2, seed=7)
    S = ds.Strip(torch.tensor([[1.0, 0.0], [0.0, 1.0]]), P.center, torch.zeros(2))
    Q = P
    for i in range(2):
        Q = Q.intersect_strip(S[i])
    assert torch.isfinite(Q.T).all() and Q.contains(P.center)
    assert Q.volume() < 1e-10 * P.volume()


def test_gradcheck_intersect_strip_and_volume():
    g = torch.Generator().manual_seed(8)
    c = torch.randn(3, generator=g, requires_grad=True)
    T = torch.randn(3, 3, generator=g, requires_grad=True)
    a = torch.tensor([1.0, 0.4, -0.2])
    y = ((a @ c).detach() + 0.3).requires_grad_()
    h = torch.tensor(0.4, requires_grad=True)

    def f(c, T, y, h):
        Q = Parallelotope(c, T).intersect_strip(ds.Strip(a, y, h))
        return Q.center, Q.T, Q.volume()

    assert torch.autograd.gradcheck(f, (c, T, y, h))
    A = torch.randn(3, 3, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda T, A: Parallelotope(c, T).linear_map(A).volume(), (T, A))


def test_empty_strip_intersection_has_finite_gradients():
    """Regression: the unused branch of an empty intersection gave NaN gradients (0 * inf)."""


    for offset in (5.0, -5.0, 1.4):
        c = torch.zeros(2, dtype=torch.float64, requires_grad=True)
        T = torch.tensor([[1.0, 0.2], [0.1, 1.0]], dtype=torch.float64, requires_grad=True)
        strip = ds.Strip(torch.tensor([1.0, 0.0], dtype=torch.float64), offset, 0.1)
        P = ds.Parallelotope(c, T)
        R = P.intersect_strip(strip)
        gc, gT = torch.autograd.grad(R.volume(), (c, T))
        assert torch.isfinite(gc).all() and torch.isfinite(gT).all()
        assert not bool(P.intersects_strip(strip))
        assert torch.equal(R.T, P.T)


# ---------------------------------------------------------------- eq. 38-39 tie rule
def _ulp_variants(a: torch.Tensor) -> torch.Tensor:
    """``a`` and every copy of it with one component moved by +-1 ulp: ``[1 + 2 n, n]``."""
    out = [a]
    for i in range(a.shape[-1]):
        for to in (2.0 * a[i] + 1.0, torch.zeros(())):
            b = a.clone()
            b[i] = torch.nextafter(a[i], torch.as_tensor(to, dtype=a.dtype))
            out.append(b)
    return torch.stack(out)


@pytest.mark.parametrize("n", [2, 3])
def test_intersect_strip_exact_tie_takes_lowest_index_whatever_the_ulp(n):
    """Unit box, strip ``|1'x| <= 0.5``: by symmetry every ``p_bar t_bar_j = 2`` (eq. 38-39 tie
    n ways, all with volume ``2^n / 2``). The tie rule replaces the lowest index, so the result
    is the hand-computed Chisci parallelotope (eq. 41 with i* = 1: column 1 -> ``e_1 / 2``,
    column j -> ``e_j - e_1``) for the exact strip and for every 1-ulp perturbation of its
    normal. (Before the rule, ``torch.max`` took whichever value rounded highest.)"""
    a = _ulp_variants(torch.ones(n, dtype=torch.float64))
    B = a.shape[0]
    P = Parallelotope(torch.zeros(B, n), torch.eye(n).expand(B, n, n))
    Q = P.intersect_strip(ds.Strip(a, torch.zeros(B), torch.full((B,), 0.5)))
    want = torch.eye(n)
    want[0, 0], want[0, 1:] = 0.5, -1.0
    assert torch.allclose(Q.T, want.expand(B, n, n), rtol=0, atol=1e-12)
    assert torch.allclose(Q.center, torch.zeros(B, n), rtol=0, atol=1e-12)
    assert torch.allclose(Q.volume(), torch.full((B,), 2.0**n / 2), rtol=1e-12)
    for i in range(B):  # still an outer bound of P cap S
        Vc = torch.as_tensor(cut_vertices(P[i], a[i].numpy(), 0.0, 0.5))
        assert Q[i].contains(Vc).all()


def test_intersect_strip_tie_with_keeping_keeps_the_parallelotope():
    """``|x1 + x2| <= 1`` on the unit box: ``p_bar t_bar_j = 1`` for both j, the value of
    keeping P_bar (eq. 40), so all three candidates have the same volume and P_bar is kept,
    also when the normal is moved by 1 ulp or the strip is 1e-13 (relative) narrower."""
    a = _ulp_variants(torch.ones(2, dtype=torch.float64))
    h = torch.ones(a.shape[0])
    h[0] = 1 - 1e-13
    P = Parallelotope(torch.zeros(a.shape[0], 2), torch.eye(2).expand(a.shape[0], 2, 2))
    Q = P.intersect_strip(ds.Strip(a, torch.zeros(a.shape[0]), h))
    assert torch.allclose(Q.T, P.T, rtol=0, atol=1e-12)
    # a clear winner (1e-9 relative, far above the tie tolerance) is still taken
    R = P[0].intersect_strip(ds.Strip(torch.tensor([1.0, 1.0]), 0.0, 1 - 1e-9))
    assert not torch.allclose(R.T, P[0].T, rtol=0, atol=1e-3)


def test_intersect_strip_tie_is_differentiable_along_the_symmetry():
    """On the symmetric tie (a = 1, T = I) any offset and half-width keep the tie exact, so
    the chosen branch (lowest index) is smooth in them: gradcheck in float64."""
    c = torch.zeros(2, requires_grad=True)
    y = torch.tensor(0.3, requires_grad=True)
    h = torch.tensor(0.5, requires_grad=True)

    def f(c, y, h):
        Q = Parallelotope(c, torch.eye(2)).intersect_strip(ds.Strip(torch.ones(2), y, h))
        return Q.center, Q.T, Q.volume()

    assert torch.autograd.gradcheck(f, (c, y, h))


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_volume_closed_form_matches_lapack_batched_and_singular(n):
    """``volume`` takes the closed-form determinant up to n = 3 (LU above): equal to numpy's
    LAPACK determinant to rounding on a batch, 0 for a singular T (which only internal
    constructions can hold: the public constructor rejects it)."""
    g = torch.Generator().manual_seed(n)
    T = torch.randn(50, n, n, dtype=torch.float64, generator=g)
    T[0] = 0.0
    if n > 1:
        T[1, :, 1] = 2.0 * T[1, :, 0]  # rank n - 1
    P = Parallelotope._make(torch.zeros(50, n, dtype=torch.float64), T)  # singular: internal
    ref = 2.0**n * np.abs(np.linalg.det(T.numpy()))
    scale = 2.0**n * np.prod(np.abs(T.numpy()).sum(-1), -1)  # Hadamard-type magnitude
    np.testing.assert_allclose(P.volume().numpy(), ref, rtol=0, atol=1e-14 * scale.max())
    assert P.volume()[0] == 0.0
    if n > 1:
        assert P.volume()[1].item() <= 1e-14 * scale[1]
