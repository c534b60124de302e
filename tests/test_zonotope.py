"""Zonotope: exactness against scipy references, outer bounds, tightness, batching, gradients."""

import itertools

import numpy as np
import pytest
import torch
from scipy.optimize import linprog
from scipy.spatial import ConvexHull

import diffsmf as ds
from diffsmf.sets.zonotope import Zonotope


def rand_zono(n, m, batch=(), seed=0):
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(*batch, n, generator=g)
    G = torch.randn(*batch, n, m, generator=g)
    return Zonotope(c, G)


def all_vertices(Z):
    """c + G s over all sign vectors s (superset of the vertices), numpy [2^m, n]."""
    m = Z.num_generators
    s = np.array(list(itertools.product((-1.0, 1.0), repeat=m)))
    return Z.center.detach().numpy() + s @ Z.generators.detach().numpy().T


def lp_member(c, G, x, tol=1e-9):
    """Independent membership oracle: exists xi in [-1,1]^m with G xi = x - c."""
    m = G.shape[1]
    res = linprog(np.zeros(m), A_eq=G, b_eq=x - c, bounds=[(-1, 1)] * m, method="highs")
    return res.status == 0


def strip_vertices(c, G, a, y, h):
    """Vertices of Z cap S on the strip boundary: points of Z's edges (all xi_i = +-1
    except one) with a.x = y +- h. numpy [k, n]."""
    m = G.shape[1]
    out = []
    for j in range(m):
        others = [i for i in range(m) if i != j]
        for s in itertools.product((-1.0, 1.0), repeat=m - 1):
            base = c + G[:, others] @ np.array(s)
            aj = a @ G[:, j]
            if abs(aj) < 1e-12:
                continue
            for level in (y - h, y + h):
                t = (level - a @ base) / aj
                if abs(t) <= 1:
                    out.append(base + t * G[:, j])
    return np.array(out).reshape(-1, len(c))


# ---------------------------------------------------------------------- Wang et al. 2022 example
def test_wang2022_worked_example_outer_parallelotope():
    """Wang et al. 2022, under eq. 22: T = [[0.1992, 0.1042], [0.1195, 0.2345]] (4 decimals)."""
    Z = ds.Zonotope([0.4, 0.15], [[0.15, 0.08, 0.025, 0], [0.09, 0.18, 0, 0.025]])
    P = Z.to_parallelotope()
    ref = torch.tensor([[0.1992, 0.1042], [0.1195, 0.2345]])
    assert torch.allclose(P.T, ref, atol=5e-5)
    assert torch.allclose(P.center, torch.tensor([0.4, 0.15]))
    assert P.contains(torch.as_tensor(all_vertices(Z))).all()


# ---------------------------------------------------------------------- exact operations
@pytest.mark.parametrize("n,m,seed", [(2, 1, 0), (2, 5, 1), (2, 7, 2), (3, 3, 3), (3, 6, 4)])
def test_volume_matches_convex_hull(n, m, seed):
    Z = rand_zono(n, m, seed=seed)
    V = all_vertices(Z)
    ref = ConvexHull(V).volume if m >= n else 0.0
    assert Z.volume().item() == pytest.approx(ref, rel=1e-9, abs=1e-12)


def test_volume_rank_deficient_and_few_generators():
    Z = ds.Zonotope(torch.zeros(3), torch.tensor([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0], [0, 0, 1.0]]))
    assert Z.volume().item() == pytest.approx(0.0, abs=1e-12)
    assert rand_zono(3, 2).volume().item() == 0.0


def test_vertices_2d_are_the_hull():
    Z = rand_zono(2, 6, seed=5)
    V = Z.vertices_2d().numpy()
    hull = ConvexHull(all_vertices(Z))
    assert ConvexHull(V).volume == pytest.approx(hull.volume, rel=1e-12)
    # counter-clockwise: positive shoelace area
    x, y = V[:, 0], V[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    assert area == pytest.approx(hull.volume, rel=1e-12)


@pytest.mark.parametrize("n,m", [(2, 4), (3, 5), (3, 2), (4, 6)])
def test_contains_matches_lp_oracle(n, m):
    Z = rand_zono(n, m, seed=10 + n + m)
    g = torch.Generator().manual_seed(1)
    xi = 1.3 * (2 * torch.rand(60, m, generator=g) - 1)
    x = Z.center + xi @ Z.generators.T
    if m < n:  # points off the subspace too
        x = torch.cat([x, x[:20] + 0.1 * torch.randn(20, n, generator=g)])
    ours = Z.contains(x).numpy()
    c, G = Z.center.numpy(), Z.generators.numpy()
    ref = np.array([lp_member(c, G, xx) for xx in x.numpy()])
    assert (ours == ref).all()
    assert ours.any() and (~ours).any()


def test_lp_membership_fallback_is_exact_to_atol():
    """The LP fallback of ``contains`` (rank-deficient zonotopes in 3-D) verifies HiGHS's
    point: with HiGHS's default tolerance a point 5e-8 outside was accepted at atol 1e-9."""
    from diffsmf.sets.zonotope_contains import _lp_contains

    G = torch.tensor([[1.0, 0.5, 0.2], [0.0, 1.0, 0.3], [1.0, 1.5, 0.5]])  # rank 2
    vertex = G @ torch.ones(3)
    for eps, inside in [(5e-8, False), (5e-9, False), (5e-10, True), (0.0, True)]:
        x = vertex + torch.tensor([eps, 0.0, 0.0])
        assert _lp_contains(torch.zeros(3), G, x, 1e-9) is inside, eps
    Z = ds.Zonotope(torch.zeros(3), G)
    assert Z.contains(torch.stack([vertex, vertex + torch.tensor([5e-8, 0, 0])])).tolist() == [
        True, False]


def test_lp_membership_batched_in_torch_matches_highs():
    """n = 6 with 40 generators has C(40, 5) = 658,008 facet candidates: the LP path. Its
    batched torch certificate (then HiGHS for what torch leaves) against HiGHS's distance at
    feasibility 1e-10: inside (distance <= 1e-12) is accepted, 1e-6 outside is refused."""
    from diffsmf.sets import zonotope_contains as zmod

    Z = rand_zono(6, 40, seed=31)
    g = torch.Generator().manual_seed(2)
    d = torch.randn(80, 6, generator=g)
    vertex = torch.sign(d @ Z.generators) @ Z.generators.T  # support points (vertices) - c
    u = 10 ** (-5 + 4 * torch.rand(80, 1, generator=g))  # 1e-5 .. 0.1
    scale = torch.cat([1 - u[:40], torch.ones(10, 1), 1 + u[50:]])  # inside, on, outside
    x = Z.center + scale * vertex
    calls = []
    orig = zmod._torch_lp_contains
    zmod._torch_lp_contains = lambda *a: calls.append(1) or orig(*a)
    try:
        got = Z.contains(x).numpy()
    finally:
        zmod._torch_lp_contains = orig
    assert calls  # the batched path ran
    c, G = Z.center.numpy(), Z.generators.numpy()
    dist = np.array([
        linprog(np.r_[np.zeros(40), 1.0],
                A_ub=np.block([[G, -np.ones((6, 1))], [-G, -np.ones((6, 1))]]),
                b_ub=np.r_[p - c, c - p], bounds=[(-1, 1)] * 40 + [(0, None)], method="highs",
                options={"primal_feasibility_tolerance": 1e-10}).fun
        for p in x.numpy()
    ])
    assert got[dist <= 1e-12].all() and not got[dist >= 1e-6].any()
    assert (dist <= 1e-12).sum() >= 50 and (dist >= 1e-6).sum() >= 25


def test_support_and_interval_hull_exact():
    Z = rand_zono(3, 5, seed=7)
    V = all_vertices(Z)
    d = torch.randn(10, 3, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(Z.support(d), torch.as_tensor((d.numpy() @ V.T).max(1)))
    box = Z.interval_hull()
    assert np.allclose(box.lower.numpy(), V.min(0)) and np.allclose(box.upper.numpy(), V.max(0))
    assert torch.equal(Z.to_interval().upper, box.upper)


def test_linear_map_translate_minkowski_exact():
    Z = rand_zono(3, 4, seed=8)
    A = torch.randn(2, 3, generator=torch.Generator().manual_seed(2))
    b = torch.tensor([1.0, -2.0])
    W = Z.linear_map(A, b)
    V = all_vertices(Z) @ A.numpy().T + b.numpy()
    assert W.volume().item() == pytest.approx(ConvexHull(V).volume, rel=1e-9)
    assert torch.allclose(Z.translate(torch.ones(3)).center, Z.center + 1)
    box = ds.Interval(-torch.ones(3), 2 * torch.ones(3))
    S = Z.minkowski_sum(box)
    assert S.num_generators == 7
    assert torch.allclose(S.center, Z.center + 0.5)
    VS = (
        all_vertices(Z)[:, None, :] + np.array(list(itertools.product((-1, 2), repeat=3)))[None]
    ).reshape(-1, 3)
    assert S.volume().item() == pytest.approx(ConvexHull(VS).volume, rel=1e-9)
    P = ds.Parallelotope(torch.zeros(3), torch.eye(3))
    assert Z.minkowski_sum(P).num_generators == 7


def test_minkowski_broadcasts_batch():
    Z = rand_zono(2, 3, batch=(4,), seed=1)
    Z2 = rand_zono(2, 2, seed=2)
    S = Z.minkowski_sum(Z2)
    assert S.batch_shape == (4,) and S.num_generators == 5
    assert torch.allclose(S[1].volume(), Z[1].minkowski_sum(Z2).volume())


# ---------------------------------------------------------------------- outer bounds
@pytest.mark.parametrize("method", ["girard", "combastel", "pca", "chisci"])
def test_reduce_is_outer_and_of_target_order(method):
    Z = rand_zono(3, 12, batch=(5,), seed=3)
    R = Z.reduce(2, method=method)
    assert R.num_generators <= 6
    x = torch.cat([Z.sample(200), Z.sample_extreme(200)], -2).transpose(0, 1)
    assert R.contains(x).all()
    assert (R.volume() >= Z.volume() * (1 - 1e-12)).all()


@pytest.mark.parametrize("method", ["girard", "combastel", "pca", "chisci"])
def test_reduce_within_order_is_identity(method):
    Z = rand_zono(3, 6, seed=4)
    assert Z.reduce(2, method=method) is Z
    assert Z.reduce(2.5, method=method) is Z


def test_to_parallelotope_is_minimal_over_bases():
    Z = rand_zono(3, 6, seed=11)
    G = Z.generators.numpy()
    best = np.inf
    for S in itertools.combinations(range(6), 3):  # independent brute force (Chisci 1996)
        B = G[:, S]
        if abs(np.linalg.det(B)) < 1e-12:
            continue
        T = B @ np.diag(np.abs(np.linalg.solve(B, G)).sum(1))
        best = min(best, 8 * abs(np.linalg.det(T)))
    P = Z.to_parallelotope()
    assert P.volume().item() == pytest.approx(best, rel=1e-9)
    assert P.contains(torch.as_tensor(all_vertices(Z))).all()


def test_to_parallelotope_of_parallelotope_is_itself():
    P = ds.Parallelotope(torch.tensor([1.0, 2.0, 3.0]), torch.randn(3, 3))
    Q = P.to_zonotope().to_parallelotope()
    assert torch.allclose(Q.T, P.T, rtol=1e-12, atol=1e-14)
    assert torch.allclose(Q.center, P.center)


def test_to_parallelotope_degenerate_is_outer_and_regular():
    G = torch.tensor([[1.0, 2.0], [1.0, 2.0], [0.0, 0.0]])
    Z = ds.Zonotope(torch.zeros(3), G)
    P = Z.to_parallelotope()
    assert torch.linalg.matrix_rank(P.T) == 3
    assert P.contains(torch.as_tensor(all_vertices(Z))).all()


@pytest.mark.parametrize("n", [2, 3, 4])
def test_to_parallelotope_rank_deficient_batch_is_outer_and_regular(n):
    """Rank-deficient elements (rank n - 1, rank 1, no generator) take the fallback basis (the
    longest generator and axis generators): still regular and containing every vertex; the
    regular elements of the same batch keep the minimal-volume basis of a search on their own."""
    g = torch.Generator().manual_seed(40 + n)
    m = n + 2
    G = torch.randn(5, n, m, generator=g, dtype=torch.float64)
    G[1] = torch.randn(n, n - 1, generator=g, dtype=torch.float64) @ torch.randn(
        n - 1, m, generator=g, dtype=torch.float64)  # rank n - 1
    G[2] = torch.outer(torch.randn(n, generator=g, dtype=torch.float64),
                       torch.randn(m, generator=g, dtype=torch.float64))  # rank 1
    G[3] = 0.0
    c = torch.randn(5, n, generator=g, dtype=torch.float64)
    P = ds.Zonotope(c, G).to_parallelotope()
    assert (torch.linalg.matrix_rank(P.T) == n).all()
    for b in range(5):
        V = torch.as_tensor(all_vertices(ds.Zonotope(c[b], G[b])))
        assert P[b].contains(V).all(), b
    for b in (0, 4):  # regular: the same T as alone (the batch's fallback does not leak in;
        # the batch solves against the zero-padded [G, aug], rounding may differ by an ulp)
        alone = ds.Zonotope(c[b], G[b]).to_parallelotope()
        torch.testing.assert_close(P.T[b], alone.T, rtol=1e-13, atol=0)


def test_conversions_cover():
    Z = rand_zono(3, 5, seed=12)
    V = torch.as_tensor(all_vertices(Z))
    assert Z.to_interval().contains(V).all()
    E = Z.to_ellipsoid()
    assert E.contains(V).all()


# ---------------------------------------------------------------------- strips
@pytest.mark.parametrize("method", ["fradius", "volume", "bravo"])
@pytest.mark.parametrize("n,m", [(2, 4), (3, 5)])
def test_intersect_strip_outer(method, n, m):
    Z = rand_zono(n, m, seed=20 + n)
    g = torch.Generator().manual_seed(3)
    a = torch.randn(n, generator=g)
    y = (a @ Z.center).item() + 0.7
    S = ds.Strip(a, y, 0.8)
    R = Z.intersect_strip(S, method=method)
    assert R.num_generators == m + 1
    x = Z.sample(4000, generator=g)
    keep = S.contains(x)
    Vs = torch.as_tensor(strip_vertices(Z.center.numpy(), Z.generators.numpy(), a.numpy(), y, 0.8))
    Vz = torch.as_tensor(all_vertices(Z))
    Vz = Vz[S.contains(Vz)]
    assert keep.any() and len(Vs) > 0
    assert R.contains(x[keep]).all() and R.contains(Vs).all() and R.contains(Vz).all()
    assert R.volume() < Z.volume()


@pytest.mark.parametrize("method", ["fradius", "volume", "bravo"])
@pytest.mark.parametrize("n,m,shift", [(2, 4, 0.7), (3, 5, 1.1), (3, 6, 0.0)])
def test_intersect_strip_tightened_is_outer_and_no_wider(method, n, m, shift):
    """``tighten=True``: still an outer bound of Z cap S (sampled points and the exact
    vertices of the intersection). With the F-radius weight its range along the strip's
    normal is never wider than the published family's, ``(1 - t) rho + t sigma`` with the
    weight ``t`` moving to the narrower, cut strip; strictly narrower on a partial overlap."""
    Z = rand_zono(n, m, seed=50 + n + m)
    g = torch.Generator().manual_seed(7)
    a = torch.randn(n, generator=g, dtype=torch.float64)
    rho = float((a @ Z.generators).abs().sum())
    y = float(a @ Z.center) + shift * rho
    S = ds.Strip(a, y, 0.6 * rho)
    R = Z.intersect_strip(S, method=method, tighten=True)
    x = Z.sample(4000, generator=g)
    Vs = torch.as_tensor(strip_vertices(Z.center.numpy(), Z.generators.numpy(), a.numpy(), y,
                                        0.6 * rho))
    assert R.contains(x[S.contains(x)]).all() and R.contains(Vs).all()
    if method == "fradius":
        plain = Z.intersect_strip(S, method=method)
        along = float((a @ R.generators).abs().sum())
        before = float((a @ plain.generators).abs().sum())
        assert along <= before * (1 + 1e-12)
        if shift > 0:  # the strip reaches past Z: a partial overlap
            assert along < before * 0.99


def _bravo_numpy(c, G, p, y, sig):
    """Bravo, Alamo & Camacho 2006, Property 1, written out: for j = 0 (Z itself) and each
    generator j not orthogonal to p, ``T_i = g_i - (p.g_i / p.g_j) g_j``, ``T_j = sigma g_j /
    (p.g_j)``, centre ``c + (y - p.c) / (p.g_j) g_j``; the least ``det(T T')``, first on ties."""
    best = (np.linalg.det(G @ G.T), c, G)
    for j in range(G.shape[1]):
        pg = p @ G[:, j]
        if abs(pg) <= 1e-10 * np.linalg.norm(p) * np.linalg.norm(G[:, j]):
            continue
        T = G - np.outer(G[:, j], p @ G) / pg
        T[:, j] = sig * G[:, j] / pg
        d = np.linalg.det(T @ T.T)
        if d < best[0]:
            best = (d, c + (y - p @ c) / pg * G[:, j], T)
    return best[1], best[2]


@pytest.mark.parametrize("n,m,seed", [(2, 4, 0), (3, 6, 1), (4, 9, 2), (2, 3, 3)])
def test_bravo_weight_equals_its_written_out_reference(n, m, seed):
    Z = rand_zono(n, m, seed=seed)
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, generator=g, dtype=torch.float64)
    rho = float((a @ Z.generators).abs().sum())
    y, sig = float(a @ Z.center) + 0.3 * rho, 0.1 * rho
    R = Z.intersect_strip(ds.Strip(a, y, sig), method="bravo")
    c_ref, T_ref = _bravo_numpy(Z.center.numpy(), Z.generators.numpy(), a.numpy(), y, sig)
    np.testing.assert_allclose(R.center.numpy(), c_ref, rtol=1e-12, atol=1e-12)
    Rg = R.generators.numpy()  # the Alamo family's columns: g_j zeroed, sigma lambda appended
    np.testing.assert_allclose(Rg @ Rg.T, T_ref @ T_ref.T, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.abs(Rg).sum(1), np.abs(T_ref).sum(1), rtol=1e-10, atol=1e-12)
    assert not np.allclose(T_ref, Z.generators.numpy())  # a generator was replaced


@pytest.mark.parametrize("n,m,k,seed", [(2, 4, 2, 0), (3, 5, 2, 1), (3, 6, 3, 2)])
def test_intersect_strips_with_any_gain_is_outer(n, m, k, seed):
    """``Zonotope.intersect_strips``: for random gains (and the F-radius gain), every sampled
    point and every vertex of Z inside all k strips is in the result; without the strips'
    own generators ``L diag(w)`` it would not be (the test can fail)."""
    from diffsmf.filters.zonotope_gains import fradius_gain

    Z = rand_zono(n, m, seed=30 + seed)
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(k, n, generator=g, dtype=torch.float64)
    rho = (A @ Z.generators).abs().sum(-1)
    d = A @ Z.center + 0.3 * rho * torch.randn(k, generator=g, dtype=torch.float64)
    w = 0.5 * rho
    x = torch.cat([Z.sample(20000, generator=g), torch.as_tensor(all_vertices(Z))])
    x = x[((x @ A.T - d).abs() <= w).all(-1)]
    assert len(x) > 50
    G = Z.generators
    for L in [torch.randn(n, k, generator=g, dtype=torch.float64),
              fradius_gain(G @ G.T, A, w)]:
        R = Z.intersect_strips(A, d, w, L)
        assert R.num_generators == m + k
        assert R.contains(x).all()
        cut = ds.Zonotope(R.center, R.generators[:, :m])
        assert not cut.contains(x).all()
    assert R.volume() < Z.volume()


def test_intersect_strip_tightened_in_one_dimension_is_the_exact_intersection():
    """In one dimension the volume weight (lambda = 1) on the cut strip gives the interval
    Z cap S itself; the published family is no narrower than the narrower operand."""
    Z = ds.Zonotope(torch.tensor([0.0], dtype=torch.float64),
                    torch.tensor([[1.0, 0.5]], dtype=torch.float64))  # [-1.5, 1.5]
    S = ds.Strip(torch.tensor([1.0], dtype=torch.float64), 1.2, 0.5)  # [0.7, 1.7]
    H = Z.intersect_strip(S, method="volume", tighten=True).interval_hull()
    assert H.lower.item() == pytest.approx(0.7, abs=1e-12)
    assert H.upper.item() == pytest.approx(1.5, abs=1e-12)
    H0 = Z.intersect_strip(S, method="volume").interval_hull()
    assert (H0.upper - H0.lower).item() >= 1.0 - 1e-12


def test_intersect_strip_volume_method_beats_fradius_and_random_lambdas():
    Z = rand_zono(2, 5, seed=30)
    S = ds.Strip(torch.tensor([1.0, -0.5]), (torch.tensor([1.0, -0.5]) @ Z.center).item(), 0.4)
    Rv = Z.intersect_strip(S, "volume")
    Rf = Z.intersect_strip(S, "fradius")
    assert Rv.volume() <= Rf.volume() * (1 + 1e-12)
    # independent: volume of the Alamo family at random lambdas via ConvexHull
    G, p = Z.generators.numpy(), S.normal.numpy()
    rng = np.random.default_rng(0)
    for lam in rng.normal(scale=1.0, size=(40, 2)):
        Gl = np.concatenate([G - np.outer(lam, p @ G), 0.4 * lam[:, None]], 1)
        s = np.array(list(itertools.product((-1.0, 1.0), repeat=Gl.shape[1])))
        assert Rv.volume().item() <= ConvexHull(s @ Gl.T).volume * (1 + 1e-9)


@pytest.mark.parametrize("method", ["fradius", "volume"])
def test_intersect_strip_containing_and_empty(method):
    Z = rand_zono(3, 4, seed=40)
    a = torch.tensor([1.0, 0.0, 0.0])
    wide = ds.Strip(a, Z.center[0], 100.0)
    R = Z.intersect_strip(wide, method)
    assert torch.equal(R.generators[..., :4], Z.generators) and torch.equal(R.center, Z.center)
    assert (R.generators[..., 4] == 0).all()
    far = ds.Strip(a, Z.center[0] + 1e3, 1.0)
    E = Z.intersect_strip(far, method)
    assert torch.isfinite(E.generators).all()
    assert torch.equal(E.generators[..., :4], Z.generators) and not Z.intersects_strip(far)


@pytest.mark.parametrize("method", ["fradius", "volume"])
def test_intersect_strip_batched_equals_per_element(method):
    Z = rand_zono(3, 5, batch=(6,), seed=50)
    g = torch.Generator().manual_seed(0)
    a = torch.randn(6, 3, generator=g)
    S = ds.Strip(a, (a * Z.center).sum(-1) + torch.randn(6, generator=g), torch.rand(6) + 0.2)
    R = Z.intersect_strip(S, method)
    for i in range(6):
        Ri = Z[i].intersect_strip(S[i], method)
        assert torch.allclose(R.generators[i], Ri.generators, atol=1e-14)
        assert torch.allclose(R.center[i], Ri.center, atol=1e-14)


def test_batched_equals_per_element_volume_reduce_parallelotope():
    Z = rand_zono(3, 7, batch=(2, 3), seed=60)
    vol, P, R = Z.volume(), Z.to_parallelotope(), Z.reduce(1.5, "chisci")
    for i, j in itertools.product(range(2), range(3)):
        assert torch.allclose(vol[i, j], Z[i, j].volume())
        assert torch.allclose(P.T[i, j], Z[i, j].to_parallelotope().T)
        assert torch.allclose(R.generators[i, j], Z[i, j].reduce(1.5, "chisci").generators)


# ---------------------------------------------------------------------- gradients
def test_gradcheck_volume_of_linear_map():
    g = torch.Generator().manual_seed(0)
    c = torch.randn(3, generator=g)
    G = torch.randn(3, 5, generator=g, requires_grad=True)
    A = torch.randn(3, 3, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda G, A: Zonotope(c, G).linear_map(A).volume(), (G, A))


def test_gradcheck_minkowski_sum():
    g = torch.Generator().manual_seed(1)
    G1 = torch.randn(2, 3, generator=g, requires_grad=True)
    r = (torch.rand(2, generator=g) + 0.1).requires_grad_()

    def f(G1, r):
        S = Zonotope(torch.zeros(2), G1).minkowski_sum(ds.Interval(-r, r))
        return S.volume(), S.support(torch.tensor([0.3, -1.0]))

    assert torch.autograd.gradcheck(f, (G1, r))


@pytest.mark.parametrize("method", ["fradius", "volume"])
def test_gradcheck_intersect_strip(method):
    g = torch.Generator().manual_seed(2)
    c = torch.randn(2, generator=g, requires_grad=True)
    G = torch.randn(2, 4, generator=g, requires_grad=True)
    a = torch.tensor([1.0, 0.5])
    y = ((a @ c).detach() + 0.3).requires_grad_()
    h = torch.tensor(0.5, requires_grad=True)

    def f(c, G, y, h):
        R = Zonotope(c, G).intersect_strip(ds.Strip(a, y, h), method)
        return R.center, R.generators, R.volume()

    assert torch.autograd.gradcheck(f, (c, G, y, h))


def test_gradcheck_to_parallelotope_and_reduce():
    g = torch.Generator().manual_seed(3)
    G = torch.randn(2, 5, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda G: (
            Zonotope(torch.zeros(2), G).to_parallelotope().volume(),
            Zonotope(torch.zeros(2), G).reduce(1.5, "girard").generators,
        ),
        (G,),
    )


# ---------------------------------------------------------------------- bad input
def test_bad_input_names_argument():
    with pytest.raises(ValueError, match="generators"):
        ds.Zonotope([0.0, 0.0], [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="center"):
        ds.Zonotope([0.0, float("nan")], torch.eye(2))
    with pytest.raises(ValueError, match="generators"):
        ds.Zonotope([0.0, 0.0], [[float("inf"), 0.0], [0.0, 1.0]])
    Z = rand_zono(2, 3)
    with pytest.raises(ValueError, match="order"):
        Z.reduce(0.5)
    with pytest.raises(ValueError, match="method"):
        Z.reduce(1, method="magic")
    with pytest.raises(ValueError, match="method"):
        Z.intersect_strip(ds.Strip([1.0, 0.0], 0.0, 1.0), method="magic")
    with pytest.raises(ValueError, match="A"):
        Z.linear_map(torch.eye(3))
    with pytest.raises(ValueError, match="m"):
        Z.pad_generators(1)
    with pytest.raises(ValueError, match="x"):
        Z.contains(torch.zeros(3))


def test_pad_generators_same_set():
    Z = rand_zono(2, 3)
    P = Z.pad_generators(5)
    assert P.num_generators == 5 and torch.allclose(P.volume(), Z.volume())


# ---------------------------------------------------------------------- plotting
def test_plot_helpers_draw_every_set(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffsmf.plot import plot_set, polygon_2d

    Z = rand_zono(2, 4)
    fig, ax = plt.subplots()
    for S in (Z, Z.to_parallelotope(), Z.interval_hull(), Z.to_ellipsoid()):
        plot_set(ax, S)
    Z3 = rand_zono(3, 4)
    plot_set(ax, Z3, dims=(0, 2), edgecolor="C1")
    xy = polygon_2d(Z3, dims=(0, 2))
    assert ConvexHull(xy[:-1]).volume == pytest.approx(
        Z3.linear_map(torch.eye(3)[[0, 2]]).volume().item()
    )
    fig.savefig(tmp_path / "sets.png")
    plt.close(fig)
    with pytest.raises(ValueError, match="dims"):
        polygon_2d(Z3)


def test_plot_bounds_and_volumes(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffsmf.filters.base import FilterResult
    from diffsmf.plot import plot_bounds, plot_volumes

    Z = rand_zono(2, 3, batch=(2, 5))
    box = Z.interval_hull()
    res = FilterResult(
        sets=Z,
        center=Z.center,
        lower=box.lower,
        upper=box.upper,
        volume=Z.volume(),
        consistent=torch.ones(2, 5, dtype=torch.bool),
    )
    fig, (ax1, ax2) = plt.subplots(1, 2)
    plot_bounds(ax1, res, dim=1, truth=Z.center, label="zono")
    lines = ax1.get_lines()
    assert np.allclose(lines[0].get_ydata(), box.upper[0, :, 1].numpy())
    assert np.allclose(lines[1].get_ydata(), box.lower[0, :, 1].numpy())
    plot_volumes(ax2, {"a": res, "b": res})
    assert np.allclose(ax2.get_lines()[1].get_ydata(), Z.volume()[0].numpy())
    fig.savefig(tmp_path / "bounds.png")
    plt.close(fig)
    with pytest.raises(ValueError, match="dim"):
        plot_bounds(ax1, res, dim=2)


def test_intersect_strip_volume_lambda_near_lp_optimum_3d():
    """n-D volume-lambda vs the exact LP optimum (scipy linprog on numpy cofactors), with the
    family's volume measured by ConvexHull."""
    Z = rand_zono(3, 5, seed=70)
    G = Z.generators.numpy()
    p = np.array([0.7, -1.0, 0.4])
    rad = np.abs(p @ G).sum()
    y, sig = p @ Z.center.numpy() + 0.3 * rad, 0.3 * rad
    R = Z.intersect_strip(ds.Strip(torch.as_tensor(p), y, sig), "volume")
    Q = np.array(
        [
            [np.linalg.det(np.column_stack([G[:, list(T)], e])) for e in np.eye(3)]
            for T in itertools.combinations(range(5), 2)
        ]
    )
    K = len(Q)
    res = linprog(
        np.r_[np.zeros(3), np.ones(K)],
        A_ub=np.block([[Q, -np.eye(K)], [-Q, -np.eye(K)]]),
        b_ub=np.zeros(2 * K),
        A_eq=np.r_[p, np.zeros(K)][None],
        b_eq=[1.0],
        bounds=[(None, None)] * (3 + K),
        method="highs",
    )
    lam = res.x[:3]
    Gl = np.concatenate([G - np.outer(lam, p @ G), sig * lam[:, None]], 1)
    s = np.array(list(itertools.product((-1.0, 1.0), repeat=6)))
    best = min(ConvexHull(s @ Gl.T).volume, ConvexHull(all_vertices(Z)).volume)
    assert R.volume().item() <= best * 1.005


def test_align_and_cat_pad_generators_and_keep_the_sets():
    from diffsmf.sets import align, cat, stack

    g = torch.Generator().manual_seed(3)
    a = Zonotope(torch.randn(2, 3, generator=g), torch.randn(2, 3, 2, generator=g))
    b = Zonotope(torch.randn(4, 3, generator=g), torch.randn(4, 3, 5, generator=g))
    pa, pb = align([a, b])
    assert pa.generators.shape[-1] == pb.generators.shape[-1] == 5
    d = torch.randn(7, 1, 3, generator=g)
    assert torch.allclose(pa.support(d), a.support(d))  # zero generators: the same set
    assert align([a], count=4)[0].generators.shape[-1] == 4
    c = cat([a, b])
    assert c.batch_shape == (6,)
    assert torch.equal(c[:2].center, a.center) and torch.equal(c[2:].generators, pb.generators)
    assert torch.allclose(c[2:].support(d), b.support(d))
    p = ds.Parallelotope(torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3))
    assert torch.equal(cat([p, p]).T, stack([p, p]).T.reshape(4, 3, 3))
    with pytest.raises(ValueError, match="same type"):
        cat([a, p])
    with pytest.raises(ValueError, match="at least one"):
        cat([])


def test_planar_area_sorted_matches_pair_table_and_gradcheck():
    """The angle-sorted prefix-sum area equals the pair table (every |det|) on random,
    nearly parallel, repeated, opposite and zero generators; its gradient passes gradcheck."""
    from diffsmf.sets.combinatorics import _planar_area, _planar_pair_area

    g = torch.Generator().manual_seed(8)
    G = torch.randn(6, 2, 24, generator=g, dtype=torch.float64)
    G[1, :, 1:] = G[1, :, :1] * torch.linspace(-2, 2, 23, dtype=torch.float64)  # parallel
    G[1, 1, 5] += 1e-9  # and one nearly parallel
    G[2, :, 3] = G[2, :, 4]  # repeated
    G[3, :, 7] = -G[3, :, 2]  # opposite
    G[4, :, 10:] = 0.0  # zero padding (MSZM's fixed generator count)
    G[5, 1] = 0.0  # all on the x axis: area 0
    ref = _planar_pair_area(G)
    scale = G.abs().sum(-1).square().sum(-1)
    assert ((_planar_area(G) - ref).abs() <= 1e-14 * scale).all()
    assert (_planar_area(G) >= 0).all() and _planar_area(G)[5] == 0
    X = torch.randn(2, 2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(_planar_area, (X,))


def test_planar_volume_is_exact_for_many_generators():
    """2-D volume from the table of generator pairs: equals the subset sum and, for more pairs
    than MAX_VOLUME_SUBSETS, the area of the convex hull of the vertices (scipy)."""
    from scipy.spatial import ConvexHull

    from diffsmf.sets.combinatorics import MAX_VOLUME_SUBSETS, _combinations, _sum_abs_det

    g = torch.Generator().manual_seed(5)
    G = torch.randn(3, 2, 7, generator=g, dtype=torch.float64)
    Z = ds.Zonotope(torch.zeros(3, 2, dtype=torch.float64), G)
    ref = 4.0 * _sum_abs_det(G, _combinations(7, 2))
    torch.testing.assert_close(Z.volume(), ref, rtol=1e-14, atol=0)
    m = 300
    assert m * (m - 1) // 2 > MAX_VOLUME_SUBSETS
    big = ds.Zonotope(torch.zeros(2, dtype=torch.float64),
                      torch.randn(2, m, generator=g, dtype=torch.float64))
    area = ConvexHull(big.vertices_2d().numpy()).volume
    assert abs(big.volume().item() - area) <= 1e-10 * area
    empty = ds.Zonotope(torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, 2, 4))
    assert empty.volume().shape == (0,)


def test_outer_parallelogram_pair_table_matches_the_basis_search(monkeypatch):
    """2-D: the closed form from the pair table (`_outer_parallelogram`) takes the basis of the
    general search over C(m, 2) solves and its T within 1e-12 (relative), contains the
    zonotope, is the least over bases (numpy brute force), does not depend on the batch
    (chunked or not), and gives elements without a regular pair the fallback only."""
    from diffsmf.sets import outer_parallelotope as zmod

    g = torch.Generator().manual_seed(5)
    G = torch.randn(40, 2, 7, generator=g, dtype=torch.float64)
    G[3] = G[3, :, :1] * torch.arange(1.0, 8.0, dtype=torch.float64)  # rank 1
    G[4] = 0.0
    G[5, :, 2] = G[5, :, 4]  # a repeated generator (tied bases)
    G[6] *= 1e-120
    T = zmod._outer_parallelotope(G)
    Gn = G / G.abs().amax((-1, -2), keepdim=True).clamp_min(1e-150)
    best, ok = zmod._best_basis(Gn)  # the general search (a solve per basis)
    assert ok.sum() == 38 and not ok[3] and not ok[4]
    torch.testing.assert_close(T[ok], zmod._basis_T(G, best)[ok], rtol=1e-12, atol=0)
    Gn_np = Gn.numpy()
    for b in range(40):  # least |det T| over the bases, every vertex contained
        Zb = Zonotope(torch.zeros(2, dtype=torch.float64), G[b])
        P = ds.Parallelotope(torch.zeros(2, dtype=torch.float64), T[b])
        assert P.contains(Zb.vertices_2d(), atol=1e-300 if b == 6 else 1e-12).all()
        if ok[b]:
            vols = [
                abs(np.linalg.det(Gn_np[b][:, S] @ np.diag(
                    np.abs(np.linalg.solve(Gn_np[b][:, S], Gn_np[b])).sum(1))))
                for S in itertools.combinations(range(7), 2)
                if abs(np.linalg.det(Gn_np[b][:, S])) > 1e-12
            ]
            scale = float(G[b].abs().max()) ** 2
            assert abs(np.linalg.det(T[b].numpy())) == pytest.approx(min(vols) * scale, rel=1e-9)
        assert torch.equal(zmod._outer_parallelotope(G[b : b + 1])[0], T[b])  # batch-free
    monkeypatch.setattr(zmod, "_PAIR_CHUNK_ELEMS", 3 * 49)  # chunks of 3 elements
    assert torch.equal(zmod._outer_parallelotope(G), T)


@pytest.mark.parametrize(("k", "m", "scale"), [(2, 6, 1.0), (5, 20, 1.0), (5, 20, 1e6)])
def test_bravo_rank_one_determinants_equal_one_qr_per_candidate(k, m, scale):
    """The determinants of Bravo's candidates from one QR (``C_j C_j' = K + z_j z_j'``) equal
    the QR of each ``C_j``, also for candidates of size 1e6 (a generator nearly orthogonal to
    the strip), where ``C_j C_j'`` itself would lose every digit."""
    from diffsmf.sets.zonotope_strip import _gram_logdet, _rank_one_logdets

    g = torch.Generator().manual_seed(k + m)
    B = torch.randn(k, m, generator=g, dtype=torch.float64)
    Ul = scale * torch.randn(m, k, generator=g, dtype=torch.float64)
    v = torch.randn(m, generator=g, dtype=torch.float64)
    fast, regular = _rank_one_logdets(B, Ul, v)
    C = B.unsqueeze(0) - Ul.unsqueeze(-1) * v.reshape(1, 1, m)
    assert bool(regular)
    torch.testing.assert_close(fast, _gram_logdet(C), rtol=1e-9, atol=1e-9)


def test_intersect_strips_bad_input_names_the_argument():
    Z = ds.Zonotope(torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
    A, d, w = torch.ones(1, 2), torch.zeros(1), torch.ones(1)
    with pytest.raises(ValueError, match=r"^gain: expected \[\.\.\., 2, 1\]"):
        Z.intersect_strips(A, d, w, torch.ones(1, 2))
    with pytest.raises(ValueError, match=r"^normal: expected \[\.\.\., k, 2\]"):
        Z.intersect_strips(torch.ones(1, 3), d, w, torch.ones(2, 1))
    with pytest.raises(ValueError, match="^gain: contains NaN"):
        Z.intersect_strips(A, d, w, torch.full((2, 1), float("nan")))
    with pytest.raises(ValueError, match="^halfwidth: contains NaN or inf"):
        Z.intersect_strips(A, d, torch.full((1,), float("inf")), torch.ones(2, 1))
    R = Z.intersect_strips(A, d, w, torch.ones(2, 1, dtype=torch.float32))  # dtype follows Z
    assert R.center.dtype == torch.float64 and R.num_generators == 3


def test_bravo_determinants_of_a_batch_with_a_singular_element():
    """Where ``K`` is singular for one batch element (here: two generators in 3-D, every
    candidate's ``T`` of rank 2), that element takes the QR of each candidate and the other
    keeps the one-QR formula: the regular element equals the QR of each ``T``, the singular
    one's determinants are 0 (log below -30) as the true ones are."""
    from diffsmf.sets.zonotope_strip import _bravo_logdets, _gram_logdet

    g = torch.Generator().manual_seed(4)
    G = torch.randn(2, 3, 6, generator=g, dtype=torch.float64)
    G[1, :, 2:] = 0.0  # element 1: two generators, K singular
    p = torch.randn(2, 3, generator=g, dtype=torch.float64)
    sig = torch.tensor([0.3, 0.4], dtype=torch.float64)
    Gp = (p.unsqueeze(-1) * G).sum(-2)
    lam = (G / torch.where(Gp == 0, 1.0, Gp).unsqueeze(-2)).transpose(-1, -2)
    got = _bravo_logdets(G, p, sig, lam)
    for b in range(2):
        T = [G[b]] + [torch.cat([G[b] - lam[b, j].unsqueeze(-1) * Gp[b].unsqueeze(0),
                                 (sig[b] * lam[b, j]).unsqueeze(-1)], -1) for j in range(6)]
        ref = torch.stack([_gram_logdet(t) for t in T])
        valid = torch.cat([torch.ones(1, dtype=torch.bool), Gp[b] != 0])  # the candidates
        if b == 0:
            torch.testing.assert_close(got[b], ref, rtol=1e-8, atol=1e-8)
        else:
            assert (got[b][valid] < -30).all() and (ref[valid] < -30).all(), (got[b], ref)
