"""ConstrainedZonotope (Scott 2016): LP bounds against scipy HiGHS, exact operations,
reductions (outer), conversions, membership, sampling, gradients, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import linprog

import diffsmf as ds
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope as CZ
from diffsmf.sets.constrained_zonotope import distance_lp
from diffsmf.sets.czono_lp import box_lp


def random_cz(B: int, n: int, m: int, k: int, seed: int = 0, feasible: bool = True) -> CZ:
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(B, n, generator=g)
    G = torch.randn(B, n, m, generator=g)
    A = torch.randn(B, k, m, generator=g)
    xi = (2 * torch.rand(B, m, generator=g) - 1) * 0.9
    b = (A @ xi.unsqueeze(-1)).squeeze(-1)
    if not feasible:
        b = b + 10 * A.abs().sum(-1)
    return CZ(c, G, A, b)


def lp_hull(Z: CZ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-coordinate HiGHS bounds (lower, upper [B, n]) and status (0 ok, 2 infeasible)."""
    B, n = Z.batch_shape[0], Z.dim
    lo, hi, st = np.zeros((B, n)), np.zeros((B, n)), np.zeros(B, dtype=int)
    for i in range(B):
        c, G = Z.center[i].numpy(), Z.generators[i].numpy()
        A, b = Z.A[i].numpy(), Z.b[i].numpy()
        kw = dict(A_eq=A, b_eq=b) if A.shape[0] else {}
        for j in range(n):
            for s in (1.0, -1.0):
                r = linprog(-s * G[j], bounds=[(-1, 1)] * G.shape[1], method="highs", **kw)
                st[i] = r.status
                if r.status != 0:
                    continue
                if s > 0:
                    hi[i, j] = c[j] - r.fun
                else:
                    lo[i, j] = c[j] + r.fun
    return lo, hi, st


@pytest.mark.parametrize("n,m,k", [(2, 6, 1), (3, 10, 3), (2, 20, 6), (4, 30, 12)])
def test_interval_hull_matches_highs(n, m, k):
    Z = random_cz(25, n, m, k, seed=n + m + k)
    H = Z.interval_hull()
    lo, hi, st = lp_hull(Z)
    assert (st == 0).all()
    scale = 1 + np.abs(hi).max()
    assert np.abs(H.upper.numpy() - hi).max() <= 1e-9 * scale
    assert np.abs(H.lower.numpy() - lo).max() <= 1e-9 * scale
    # outer: never inside the exact box (beyond HiGHS' own tolerance)
    assert (H.upper.numpy() >= hi - 1e-9).all() and (H.lower.numpy() <= lo + 1e-9).all()


def test_bounds_valid_when_solver_stops_early():
    """Any iteration count (even 0) gives a valid outer bound (weak duality)."""
    Z = random_cz(20, 3, 10, 4, seed=3)
    lo, hi, _ = lp_hull(Z)
    for iters in (0, 1, 2, 4):
        H = Z.interval_hull(iters=iters)
        assert (H.upper.numpy() >= hi - 1e-12).all()
        assert (H.lower.numpy() <= lo + 1e-12).all()
    # 0 iterations: never worse than the zonotope bound that ignores the constraints
    H0 = Z.interval_hull(iters=0)
    r = Z.generators.abs().sum(-1)
    assert (H0.upper <= Z.center + r + 1e-12).all()


def test_no_constraints_is_plain_zonotope():
    g = torch.Generator().manual_seed(0)
    c, G = torch.randn(5, 3, generator=g), torch.randn(5, 3, 7, generator=g)
    Z = CZ(c, G)
    Zr = ds.Zonotope(c, G)
    H, Hr = Z.interval_hull(), Zr.interval_hull()
    assert torch.allclose(H.lower, Hr.lower, atol=1e-12) and torch.allclose(
        H.upper, Hr.upper, atol=1e-12
    )
    d = torch.randn(5, 3, generator=g)
    assert torch.allclose(Z.support(d), Zr.support(d), atol=1e-12)
    assert not Z.is_empty().any()


def test_empty_sets_certified():
    Z = random_cz(15, 2, 8, 3, seed=5, feasible=False)
    _, _, st = lp_hull(Z)
    assert (st == 2).all()
    assert Z.is_empty().all()
    H = Z.interval_hull()
    assert ((H.lower > H.upper).any(-1)).all()
    assert (Z.volume() == 0).all()
    # feasible ones are never certified empty
    assert not random_cz(30, 2, 8, 3, seed=6).is_empty().any()


def test_small_empty_sets_certified():
    """Few generators and constraints, infeasible by a margin (HiGHS: infeasible): every one is
    certified empty. The 1-D ``xi = 5`` was not in an earlier version: a corrector step with every
    ``dz_j, dw_j > 0`` got a negative length and left the interior."""
    g = torch.Generator().manual_seed(11)
    cases = [(torch.tensor([[1.0]]), torch.tensor([5.0]))]
    for k, m in [(1, 1), (1, 2), (2, 2), (1, 3), (2, 3)]:
        for _ in range(10):
            A = torch.randn(k, m, generator=g)
            xi = torch.sign(torch.randn(m, generator=g)) * (1.1 + torch.rand(m, generator=g))
            cases.append((A, A @ xi))
    checked = 0
    for A, b in cases:
        m = A.shape[1]
        r = linprog(np.zeros(m), A_eq=A.numpy(), b_eq=b.numpy(), bounds=[(-1, 1)] * m,
                    method="highs")
        # infeasible with a margin: the box scaled by 0.98 around xi = 0 still misses
        r2 = linprog(np.zeros(m), A_eq=A.numpy(), b_eq=b.numpy(), bounds=[(-1.02, 1.02)] * m,
                     method="highs")
        if r.status != 2 or r2.status != 2:
            continue
        Z = CZ(torch.zeros(1), torch.ones(1, m), A, b)
        assert bool(Z.is_empty()), (A, b)
        checked += 1
    assert checked >= 20


def test_step_lengths_never_negative():
    """``min(1, tau / r)``: 1 where nothing blocks (r <= 0, -0.0 included), never negative."""
    from diffsmf.sets.czono_lp import _TAU, _dual_step, _primal_step

    one = torch.ones(1, 3)
    assert _dual_step(one, one, one, one).item() == 1.0  # every dz, dw > 0: r < 0
    assert _primal_step(torch.zeros(1, 3), one, one).item() == 1.0  # dx = 0: r = 0
    assert _primal_step(-torch.zeros(1, 3), one, one).item() == 1.0  # r = -0.0
    half = torch.full((1, 3), 0.5)
    # blocking: z + a dz > 0 needs a < 0.5 / 1 -> tau * 0.5
    assert _dual_step(half, one, -one, one).item() == pytest.approx(_TAU * 0.5, rel=1e-15)
    assert _primal_step(torch.full((1, 3), 4.0), one, one).item() == pytest.approx(_TAU / 4)


def test_tight_constraints_single_point():
    """Constraints that pin xi to a vertex of the box: the set is one point."""
    m = 4
    A = torch.eye(m)[:3]
    b = torch.tensor([1.0, -1.0, 1.0])
    G = torch.tensor([[1.0, 2.0, 0.5, 0.0], [0.0, 1.0, -1.0, 0.0]])
    Z = CZ(
        torch.zeros(2),
        G,
        torch.cat([A, torch.tensor([[0.0, 0, 0, 1.0]])]),
        torch.cat([b, torch.tensor([1.0])]),
    )
    p = G @ torch.tensor([1.0, -1.0, 1.0, 1.0])
    H = Z.interval_hull()
    assert torch.allclose(H.lower, p, atol=1e-8) and torch.allclose(H.upper, p, atol=1e-8)
    assert (H.lower <= p + 1e-12).all() and (H.upper >= p - 1e-12).all()
    assert bool(Z.contains(p, atol=1e-7))
    assert not bool(Z.contains(p + 0.1, atol=1e-7))


def test_support_matches_highs():
    Z = random_cz(10, 3, 9, 3, seed=8)
    d = torch.randn(10, 3, generator=torch.Generator().manual_seed(1))
    h = Z.support(d)
    for i in range(10):
        g = (d[i] @ Z.generators[i]).numpy()
        r = linprog(
            -g, A_eq=Z.A[i].numpy(), b_eq=Z.b[i].numpy(), bounds=[(-1, 1)] * 9, method="highs"
        )
        ref = float(d[i] @ Z.center[i]) - r.fun
        assert ref - 1e-12 <= float(h[i]) <= ref + 1e-9 * (1 + abs(ref))


def test_box_lp_direct():
    g = torch.Generator().manual_seed(2)
    A = torch.randn(50, 4, 12, generator=g)
    x0 = (2 * torch.rand(50, 12, generator=g) - 1) * 0.8
    b = (A @ x0.unsqueeze(-1)).squeeze(-1)
    obj = torch.randn(50, 12, generator=g)
    bound, lam, xi, x = box_lp(obj, A, b)
    for i in range(50):
        r = linprog(
            -obj[i].numpy(),
            A_eq=A[i].numpy(),
            b_eq=b[i].numpy(),
            bounds=[(-1, 1)] * 12,
            method="highs",
        )
        assert -r.fun - 1e-12 <= float(bound[i]) <= -r.fun + 1e-9
    assert (xi.abs() <= 1).all() and (x.abs() < 1).all()


def test_contains_against_highs():
    Z = random_cz(6, 2, 8, 2, seed=9)
    gen = torch.Generator().manual_seed(3)
    H = Z.interval_hull()
    pts = H.lower.unsqueeze(1) + torch.rand(6, 60, 2, generator=gen) * (
        H.upper - H.lower
    ).unsqueeze(1)
    pts = pts.transpose(0, 1)  # [60, 6, 2]
    got = Z.contains(pts, atol=1e-9)
    out = Z.excludes(pts)
    dist = distance_lp(Z, pts)
    assert got[dist <= 1e-12].all()  # inside (HiGHS): never reported outside
    far_out = dist > 1e-6
    # certified answers agree with HiGHS; points clearly outside are certified outside
    assert not (got & far_out).any()
    assert not (out & (dist <= 1e-12)).any()
    assert (out | ~(dist > 1e-3)).all()
    # points inside (hit-and-run samples) are certified inside
    x = Z.sample(40, generator=gen).transpose(0, 1)
    assert Z.contains(x, atol=1e-9).all()


def test_sample_inside_and_extreme_on_boundary():
    Z = random_cz(4, 2, 7, 2, seed=10)
    x = Z.sample(50, generator=torch.Generator().manual_seed(0)).transpose(0, 1)
    assert distance_lp(Z, x).max() <= 1e-9
    e = Z.sample_extreme(20, generator=torch.Generator().manual_seed(1)).transpose(0, 1)
    assert distance_lp(Z, e).max() <= 1e-9
    # boundary: a small step away from the centre of the hull leaves the set for some
    assert Z.sample(5).shape == (4, 5, 2)


def test_linear_map_and_minkowski_exact():
    Z = random_cz(5, 2, 6, 2, seed=11)
    M = torch.tensor([[1.0, 2.0], [0.0, -1.0], [0.5, 0.5]])
    d = torch.tensor([1.0, 2.0, 3.0])
    Y = Z.linear_map(M, d)
    assert Y.dim == 3 and Y.num_constraints == 2
    x = Z.sample(20, generator=torch.Generator().manual_seed(0))
    assert Y.contains((x @ M.T + d).transpose(0, 1), atol=1e-9).all()
    box = ds.Interval(torch.tensor([-0.1, 0.0]), torch.tensor([0.2, 0.3]))
    S = Z.minkowski_sum(box)
    HZ, HS = Z.interval_hull(), S.interval_hull()
    assert torch.allclose(HS.lower, HZ.lower + box.lower, atol=1e-9)
    assert torch.allclose(HS.upper, HZ.upper + box.upper, atol=1e-9)
    S2 = Z.minkowski_sum(Z)
    assert torch.allclose(
        S2.interval_hull().upper - S2.center, 2 * (HZ.upper - Z.center), atol=1e-8
    )


def _lp_hull_with(Z: CZ, rows: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray, i: int):
    """HiGHS hull of Z[i] cap {lo_b <= rows x <= hi_b}."""
    c, G = Z.center[i].numpy(), Z.generators[i].numpy()
    RG, Rc = rows @ G, rows @ c
    A_ub = np.vstack([RG, -RG])
    b_ub = np.concatenate([hi_b - Rc, -(lo_b - Rc)])
    out = []
    for j in range(Z.dim):
        for s in (1.0, -1.0):
            r = linprog(
                -s * G[j],
                A_ub=A_ub,
                b_ub=b_ub,
                A_eq=Z.A[i].numpy(),
                b_eq=Z.b[i].numpy(),
                bounds=[(-1, 1)] * G.shape[1],
                method="highs",
            )
            out.append(s * c[j] - r.fun)
    return np.array(out).reshape(Z.dim, 2)


def test_intersect_strip_and_halfspace_exact():
    Z = random_cz(4, 2, 6, 1, seed=12)
    H = Z.interval_hull()
    a = torch.tensor([1.0, -0.5])
    mid = (H.center * a).sum(-1)
    S = ds.Strip(a, mid, 0.2 * torch.ones(4))
    Zs = Z.intersect_strip(S)
    assert Zs.num_generators == 7 and Zs.num_constraints == 2
    Hs = Zs.interval_hull()
    for i in range(4):
        ref = _lp_hull_with(
            Z, a.numpy()[None], np.array([mid[i] - 0.2]), np.array([mid[i] + 0.2]), i
        )
        assert np.allclose(Hs.upper[i].numpy(), ref[:, 0], atol=1e-8)
        assert np.allclose(Hs.lower[i].numpy(), -ref[:, 1], atol=1e-8)
    Zh = Z.intersect_halfspace(a, mid)
    Hh = Zh.interval_hull()
    for i in range(4):
        ref = _lp_hull_with(Z, a.numpy()[None], np.array([-1e9]), np.array([mid[i]]), i)
        assert np.allclose(Hh.upper[i].numpy(), ref[:, 0], atol=1e-8)
        assert np.allclose(Hh.lower[i].numpy(), -ref[:, 1], atol=1e-8)
    # a half-space that misses the set: certified empty
    assert (
        Z.intersect_halfspace(a, (H.lower * a.clamp(min=0) + H.upper * a.clamp(max=0)).sum(-1) - 1)
        .is_empty()
        .all()
    )
    # several strips at once == one by one
    Z2 = Z.intersect_strips(
        torch.stack([a, torch.tensor([0.0, 1.0])]).expand(4, 2, 2),
        torch.stack([mid, H.center[:, 1]], -1),
        torch.full((4, 2), 0.3),
    )
    Z3 = Z.intersect_strip(ds.Strip(a, mid, 0.3 * torch.ones(4))).intersect_strip(
        ds.Strip(torch.tensor([0.0, 1.0]), H.center[:, 1], 0.3 * torch.ones(4))
    )
    assert torch.allclose(Z2.interval_hull().upper, Z3.interval_hull().upper, atol=1e-9)


def _outer(big: CZ, small: CZ, x: torch.Tensor) -> None:
    Hb, Hs = big.interval_hull(), small.interval_hull()
    assert (Hb.lower <= Hs.lower + 1e-9).all() and (Hb.upper >= Hs.upper - 1e-9).all()
    assert distance_lp(big, x).max() <= 1e-9


@pytest.mark.parametrize("heuristic", ["hull", "lp", "propagation"])
def test_constraint_elimination_outer(heuristic):
    Z = random_cz(6, 2, 10, 4, seed=13)
    x = Z.sample(30, generator=torch.Generator().manual_seed(0)).transpose(0, 1)
    for k in (3, 1, 0):
        Zr = Z.reduce_constraints(k, heuristic)
        assert Zr.num_constraints == k and Zr.num_generators == 10 - (4 - k)
        _outer(Zr, Z, x)
    assert isinstance(Z.to_zonotope(), ds.Zonotope)


def test_elimination_exact_when_bound_redundant():
    """xi_0 = xi_1 / 2: the bound |xi_0| <= 1 is implied, eliminating xi_0 is exact."""
    G = torch.tensor([[1.0, 0.0, 0.3], [1.0, 1.0, -0.2]])
    A = torch.tensor([[1.0, -0.5, 0.0]])
    Z = CZ(torch.zeros(2), G, A, torch.zeros(1))
    Zr = Z.reduce_constraints(0, "hull")
    H, Hr = Z.interval_hull(), Zr.interval_hull()
    assert torch.allclose(H.lower, Hr.lower, atol=1e-9) and torch.allclose(
        H.upper, Hr.upper, atol=1e-9
    )


@pytest.mark.parametrize("method", ["girard", "combastel"])
def test_generator_reduction_outer(method):
    Z = random_cz(6, 2, 14, 3, seed=14)
    x = Z.sample(30, generator=torch.Generator().manual_seed(1)).transpose(0, 1)
    Zr = Z.reduce_generators(8, method)
    assert Zr.num_generators == 8 and Zr.num_constraints == 3
    _outer(Zr, Z, x)
    r = torch.tensor([0.1, 0.2])
    Zb = Z.reduce_generators(8, method, box_radius=r)
    _outer(Zb, Z.minkowski_sum(ds.Interval(-r, r)), x)
    Zf = Z.reduce(9, 2)
    assert Zf.num_generators <= 9 and Zf.num_constraints == 2
    _outer(Zf, Z, x)


def test_rescale_is_exact():
    Z = random_cz(5, 2, 8, 3, seed=15)
    R = Z.rescale()
    H, HR = Z.interval_hull(), R.interval_hull()
    assert torch.allclose(H.lower, HR.lower, atol=1e-9) and torch.allclose(
        H.upper, HR.upper, atol=1e-9
    )
    assert (R.generators.abs() <= Z.generators.abs() + 1e-15).all()


def test_conversions():
    box = ds.Interval(torch.tensor([-1.0, 0.0]), torch.tensor([2.0, 0.5]))
    Zb = CZ.from_set(box)
    Hb = Zb.interval_hull()
    assert torch.allclose(Hb.lower, box.lower) and torch.allclose(Hb.upper, box.upper)
    Zz = ds.Zonotope(torch.zeros(2), torch.tensor([[1.0, 0.5, 0.2], [0.0, 1.0, -0.3]]))
    assert torch.allclose(CZ.from_set(Zz).interval_hull().upper, Zz.interval_hull().upper)
    P = ds.Parallelotope(torch.ones(2), torch.tensor([[1.0, 0.5], [0.0, 1.0]]))
    assert torch.allclose(CZ.from_set(P).interval_hull().upper, P.interval_hull().upper)
    E = ds.Ellipsoid(torch.zeros(2), torch.tensor([[2.0, 0.8], [0.8, 1.0]]))
    ZE = CZ.from_set(E)
    pts = E.sample_extreme(100, generator=torch.Generator().manual_seed(0))
    assert distance_lp(ZE, pts).max() == 0  # outer (HiGHS)
    assert ZE.contains(pts, atol=1e-7).all()  # boundary points: certified within 1e-7
    HE, HEh = ZE.interval_hull(), E.interval_hull()
    assert torch.allclose(HE.upper, HEh.upper, rtol=1e-6)  # the box hull is kept
    with pytest.raises(ValueError, match="S"):
        CZ.from_set(ds.Strip(torch.tensor([1.0, 0.0]), 0.0, 1.0))


def test_batch_utilities():
    Z = random_cz(4, 2, 5, 2, seed=16)
    assert Z.batch_shape == (4,) and Z.dim == 2 and Z.dtype == torch.float64
    assert Z[1:3].batch_shape == (2,)
    W = CZ(torch.zeros(2), torch.eye(2)).expand(3, 4)
    assert W.batch_shape == (3, 4)
    S = ds.stack([Z, Z], dim=1)
    assert S.batch_shape == (4, 2)
    P = Z.pad(9, 5)
    assert P.num_generators == 9 and P.num_constraints == 5
    assert torch.allclose(P.interval_hull().upper, Z.interval_hull().upper, atol=1e-8)
    # broadcasting of the fields
    B = CZ(torch.zeros(3, 2), torch.eye(2), torch.ones(1, 2), torch.zeros(1))
    assert B.batch_shape == (3,)
    with pytest.raises(AttributeError):
        Z.A = None


def test_bad_arguments():
    with pytest.raises(ValueError, match="center"):
        CZ(torch.tensor([float("nan"), 0.0]), torch.eye(2))
    with pytest.raises(ValueError, match="generators"):
        CZ(torch.zeros(2), torch.eye(3))
    with pytest.raises(ValueError, match="A"):
        CZ(torch.zeros(2), torch.eye(2), torch.ones(1, 3), torch.zeros(1))
    with pytest.raises(ValueError, match="b"):
        CZ(torch.zeros(2), torch.eye(2), torch.ones(1, 2), torch.zeros(2))
    with pytest.raises(ValueError, match="A"):
        CZ(torch.zeros(2), torch.eye(2), torch.ones(1, 2))
    with pytest.raises(ValueError, match="b"):
        CZ(torch.zeros(2), torch.eye(2), torch.ones(1, 2), torch.tensor([float("inf")]))
    Z = CZ(torch.zeros(2), torch.eye(2), torch.ones(1, 2), torch.zeros(1))
    with pytest.raises(ValueError, match="q"):
        Z.reduce_generators(2)
    with pytest.raises(ValueError, match="k"):
        Z.reduce_constraints(-1)
    for bad in ([1.0, 2.0], None, torch.zeros(2)):
        with pytest.raises(ValueError, match="S: expected a diffsmf set"):
            CZ.from_set(bad)
    with pytest.raises(ValueError, match="q: must be an integer"):  # a bool is not a count
        Z.reduce_generators(True)
    with pytest.raises(ValueError, match="k: must be an integer"):
        Z.reduce_constraints(False)
    with pytest.raises(ValueError, match="x"):
        Z.contains(torch.zeros(3))
    with pytest.raises(ValueError, match="halfwidth"):
        Z.intersect_strips(torch.ones(1, 2), torch.zeros(1), -torch.ones(1))


# ---------------------------------------------------------------------- gradients
def _fields(seed: int = 17):
    Z = random_cz(1, 2, 5, 2, seed=seed)
    return [t[0].clone().requires_grad_(True) for t in (Z.center, Z.generators, Z.A, Z.b)]


def test_gradcheck_interval_hull():
    c, G, A, b = _fields()

    def f(c, G, A, b):
        H = CZ(c, G, A, b).interval_hull()
        return torch.cat([H.lower, H.upper])

    assert torch.autograd.gradcheck(f, (c, G, A, b), eps=1e-6, atol=1e-6)


def test_gradcheck_outer_polygon_area():
    """The outer polygon's vertices are linear in the certified support values, so its area
    has the support's envelope gradient (the CZSMF area a user might tune on)."""
    c, G, A, b = _fields(5)

    def f(c, G, A, b):
        Z = CZ(c, G, A, b)
        return torch.cat([Z.outer_polygon_area(8).reshape(1), Z.outer_polygon_2d(8).reshape(-1)])

    assert torch.autograd.gradcheck(f, (c, G, A, b), eps=1e-6, atol=1e-6)


def test_gradcheck_linear_ops():
    c, G, A, b = _fields(18)
    M = torch.tensor([[1.0, 0.3], [-0.2, 0.9]], requires_grad=True)
    box = torch.tensor([0.1, 0.2], requires_grad=True)
    a = torch.tensor([0.7, -0.4], requires_grad=True)
    y = torch.tensor(0.05, requires_grad=True)
    s = torch.tensor(0.3, requires_grad=True)

    def f(c, G, A, b, M, box, a, y, s):
        Z = CZ(c, G, A, b).linear_map(M, torch.ones(2)).minkowski_sum(ds.Interval(-box, box))
        Z = Z.intersect_strip(ds.Strip(a, y, s))
        return torch.cat([Z.center, Z.generators.flatten(), Z.A.flatten(), Z.b])

    assert torch.autograd.gradcheck(f, (c, G, A, b, M, box, a, y, s))

    def g(c, G, A, b, a, y, s):
        Z = CZ(c, G, A, b).intersect_strip(ds.Strip(a, y, s))
        H = Z.interval_hull()
        return torch.cat([H.lower, H.upper])

    assert torch.autograd.gradcheck(g, (c, G, A, b, a, y, s), eps=1e-6, atol=1e-6)


def test_hull_elimination_duals_certify_result():
    """The ``"hull"`` elimination hands back the LP solutions of its result's hull: the hull
    they certify matches HiGHS on the result to 1e-9 and is never inside it; any other
    multipliers (garbage, early stop) still give outer bounds (weak duality)."""
    Z = random_cz(8, 3, 16, 5, seed=21)
    Zr, duals = Z._reduce_constraints(3, "hull")
    assert duals is not None and Zr.num_constraints == 3
    H = Zr._hull_from_duals(*duals)
    lo, hi, st = lp_hull(Zr)
    assert (st == 0).all()
    scale = 1 + np.abs(hi).max()
    assert np.abs(H.upper.numpy() - hi).max() <= 1e-9 * scale
    assert np.abs(H.lower.numpy() - lo).max() <= 1e-9 * scale
    assert (H.upper.numpy() >= hi - 1e-12 * scale).all()
    assert (H.lower.numpy() <= lo + 1e-12 * scale).all()
    lam, xi = duals
    bad = Zr._hull_from_duals(lam + torch.randn_like(lam), xi)
    assert (bad.upper.numpy() >= hi - 1e-12 * scale).all()
    assert (bad.lower.numpy() <= lo + 1e-12 * scale).all()
    # no reuse for the other heuristics
    assert Z._reduce_constraints(3, "propagation")[1] is None


def test_box_lp_early_stop_valid_and_accurate():
    """The eager early stop (``tol``) keeps the bound a certificate and within 1e-8 of
    HiGHS; ``tol=None`` runs the fixed count (the traced path)."""
    Z = random_cz(20, 2, 24, 6, seed=22)
    lo, hi, st = lp_hull(Z)
    scale = 1 + np.abs(hi).max()
    for tol in (None, 1e-9, 1e-6):
        g = Z.generators[:, 0]
        up = box_lp(g, Z.A, Z.b, 15, tol)[0].numpy() + Z.center[:, 0].numpy()
        assert (up >= hi[:, 0] - 1e-12 * scale).all()
        assert np.abs(up - hi[:, 0]).max() <= (1e-8 if tol != 1e-6 else 1e-5) * scale


def test_contains_boundary_points_certified():
    """Boundary points (``sample_extreme``) are inside by ``contains`` at 1e-9 (no
    certificate of a distance above 1e-9 exists for them)."""
    Z = random_cz(10, 2, 30, 6, seed=23)
    x = Z.sample_extreme(20, generator=torch.Generator().manual_seed(3)).transpose(0, 1)
    assert float(distance_lp(Z, x).max()) <= 1e-9
    assert bool(Z.contains(x, atol=1e-9).all())


@pytest.mark.parametrize("threads", [1, 2])
def test_contains_states_reached_by_vertex_noise(threads):
    """CZSMF sets are tight: true states driven by vertex noise lie on their boundary, where
    the feasible set of the membership LP is one point on the box's boundary and the
    interior-point iterate stalls ~1e-8 away. ``contains`` answers False only with a Farkas
    certificate that the point is farther than ``atol``, so all 640 states are inside
    (HiGHS puts them within 1e-9), at 1 and 2 threads; the same states pushed 100 atol or
    more outside (HiGHS distance) are all reported outside."""
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        sd = ds.systems.get("spring_damper")
        traj = sd.simulate(steps=15, batch=40, seed=0, noise="vertex")
        with torch.no_grad():
            sets = ds.filters.CZSMF(sd)(traj.y).sets
        assert float(distance_lp(sets, traj.x).max()) <= 1e-9
        assert bool(sets.contains(traj.x, atol=1e-9).all())
        assert not bool(sets.excludes(traj.x).any())
        g = torch.Generator().manual_seed(1)
        out = traj.x + 1e-6 * torch.randn(traj.x.shape, generator=g, dtype=torch.float64)
        dist = distance_lp(sets, out)
        got = sets.contains(out, atol=1e-9)
        far = dist >= 1e-7
        assert int(far.sum()) > 300  # most pushes leave the tight sets
        assert not bool(got[far].any())
        assert bool(got[dist <= 1e-12].all())
    finally:
        torch.set_num_threads(old)


def test_contains_tolerance_is_part_of_the_meaning():
    """A point at distance d (HiGHS) from the set: inside at ``atol >= 10 d``, outside at
    ``atol <= d / 100``; ``atol = 0`` is ``~excludes``."""
    Z = CZ(torch.zeros(2), torch.eye(2), torch.tensor([[1.0, 1.0]]), torch.tensor([0.0]))
    x = torch.tensor([0.5 + 1e-6, -0.5])  # the set is the segment t (1, -1): 5e-7 off it
    d = float(distance_lp(Z, x))
    assert d > 1e-7
    assert bool(Z.contains(x, atol=10 * d))
    assert not bool(Z.contains(x, atol=d / 100))
    assert bool(Z.contains(x, atol=0.0)) == (not bool(Z.excludes(x)))


def test_feasible_residual_reaches_a_box_vertex():
    """The only feasible point is a vertex of the box (the line ``v + t (1, -1, 0)`` leaves
    the box on both sides of ``v``); from an interior point 1e-7 away, as the stalled
    iterates are, the polish reaches it to rounding."""
    from diffsmf.sets.czono_lp import feasible_residual

    L = torch.tensor([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    v = torch.ones(3)
    r = L @ v
    x = v - torch.tensor([1e-7, 3e-7, 2e-7])
    before = float((L @ x - r).abs().max())
    after = float(feasible_residual(L, r, x))
    assert after <= 1e-15 and before > 1e-7
    assert float(feasible_residual(L, r + 0.1, x)) >= 0.1 - 1e-12  # infeasible: no certificate


def test_highs_reference_resolves_1e_9():
    """The reference LP runs HiGHS at feasibility 1e-10 (default 1e-7 reported 0 here)."""
    Z = CZ(torch.zeros(2), torch.eye(2), torch.tensor([[1.0, 1.0]]), torch.tensor([2.0]))
    d = distance_lp(Z, torch.tensor([[1.0 + 5e-9, 1.0], [1.0, 1.0]]))
    assert abs(float(d[0]) - 5e-9) < 1e-10 and float(d[1]) <= 1e-12


def test_box_lp_chunked_batch(monkeypatch):
    """A batch larger than ``czono_lp.CHUNK`` is iterated in chunks: every bound is still a
    certificate within 1e-9 of HiGHS, and a broadcast ``A`` (one per set, many objectives)
    gives the same bounds as the unchunked solve to the early-stop tolerance."""
    import diffsmf.sets.czono_lp as czlp

    g = torch.Generator().manual_seed(5)
    A = torch.randn(7, 3, 10, generator=g)
    x0 = (2 * torch.rand(7, 10, generator=g) - 1) * 0.8
    b = (A @ x0.unsqueeze(-1)).squeeze(-1)
    obj = torch.randn(6, 7, 10, generator=g)  # [6, 7]: 42 LPs sharing 7 constraint sets
    whole = box_lp(obj, A, b)[0]
    monkeypatch.setattr(czlp, "CHUNK", 8)  # 6 chunks, the last one short
    bound, lam, xi, x = box_lp(obj, A, b)
    assert bound.shape == lam.shape[:-1] == (6, 7) and xi.shape == x.shape == (6, 7, 10)
    for i in range(6):
        for j in range(7):
            r = linprog(-obj[i, j].numpy(), A_eq=A[j].numpy(), b_eq=b[j].numpy(),
                        bounds=[(-1, 1)] * 10, method="highs")
            assert -r.fun - 1e-12 <= float(bound[i, j]) <= -r.fun + 1e-9
    assert torch.allclose(bound, whole, rtol=0, atol=1e-8)
    assert (xi.abs() <= 1).all() and (x.abs() < 1).all()


def test_sample_of_an_empty_set_is_nan():
    """An empty element samples NaN (never points outside it); the others stay inside."""
    G, A = torch.eye(2).expand(2, 2, 2), torch.ones(2, 1, 2)
    Z = CZ(torch.zeros(2, 2), G, A, torch.tensor([[5.0], [0.5]]))  # xi1 + xi2 = 5: empty
    assert Z.is_empty().tolist() == [True, False]
    gen = torch.Generator().manual_seed(0)
    for pts in (Z.sample(16, gen), Z.sample_extreme(16, gen)):
        assert pts.shape == (2, 16, 2)
        assert torch.isnan(pts[0]).all()
        inside = pts[1]
        assert torch.isfinite(inside).all()
        assert (inside.abs() <= 1 + 1e-9).all()
        torch.testing.assert_close(inside.sum(-1), torch.full((16,), 0.5, dtype=inside.dtype))


def _exact_vertices_2d(Z: CZ, directions: int) -> np.ndarray:
    """HiGHS's optimal points of the support LPs in ``directions`` directions: vertices of the
    exact polygon (their convex hull is an inner polygon that tends to the set)."""
    c, G, A, b = (t.numpy() for t in (Z.center, Z.generators, Z.A, Z.b))
    kw = dict(A_eq=A, b_eq=b) if A.shape[0] else {}
    pts = []
    for t in np.arange(directions) * (2 * np.pi / directions):
        d = np.array([np.cos(t), np.sin(t)])
        r = linprog(-(G.T @ d), bounds=[(-1, 1)] * G.shape[1], method="highs", **kw)
        assert r.status == 0
        pts.append(c + G @ r.x)
    return np.array(pts)


def _polygon_area(V: np.ndarray) -> float:
    x, y = V[:, 0], V[:, 1]
    return 0.5 * abs(float((x * np.roll(y, -1) - np.roll(x, -1) * y).sum()))


@pytest.mark.parametrize("seed", [0, 2])
def test_outer_polygon_contains_the_exact_vertices_and_tends_to_the_area(seed):
    """``outer_polygon_2d`` (used by ``plot.polygon_2d`` for CZSMF sets and the documented
    CZSMF areas) against HiGHS: every exact vertex lies inside the polygon, and its area tends
    to the exact one from above (the inner hull of the exact vertices from below)."""
    from scipy.spatial import ConvexHull

    Z = random_cz(1, 2, 6, 2, seed=seed)[0]
    P = _exact_vertices_2d(Z, 720)
    inner = ConvexHull(P).volume
    # measured excess (seeds 0-2): 0.07-0.29 (k = 16), 0.03-0.04 (64), 0.002-0.003 (1024)
    for k, rel in ((16, 0.35), (64, 0.06), (1024, 0.005)):
        V = Z.outer_polygon_2d(k).numpy()  # [k, 2], counter-clockwise
        E = np.roll(V, -1, 0) - V
        cross = E[:, None, 0] * (P[None, :, 1] - V[:, None, 1]) - E[:, None, 1] * (
            P[None, :, 0] - V[:, None, 0])  # [k, points]: >= 0 left of every edge
        assert cross.min() >= -1e-9, (k, cross.min())
        area = _polygon_area(V)
        assert inner * (1 - 1e-12) <= area <= inner * (1 + rel), (k, area, inner)
        assert abs(float(Z.outer_polygon_area(k)) - area) <= 1e-12 * area


def test_outer_polygon_bad_input_and_batch_and_plot(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffsmf.plot import plot_set, polygon_2d

    Z = random_cz(3, 2, 5, 1, seed=4)
    V = Z.outer_polygon_2d(32)
    assert V.shape == (3, 32, 2)
    torch.testing.assert_close(V[1], Z[1].outer_polygon_2d(32), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="^outer_polygon_2d: needs a 2-D set"):
        random_cz(1, 3, 5, 1).outer_polygon_2d()
    with pytest.raises(ValueError, match="^k: at least 3"):
        Z.outer_polygon_2d(2)
    fig, ax = plt.subplots()
    patch = plot_set(ax, Z[0], label="CZSMF set")  # raised "cannot plot a ConstrainedZonotope"
    assert patch.get_xy().shape == (201, 2)  # closed polygon of 200 directions
    assert polygon_2d(Z[0], k=40).shape == (41, 2)
    empty = random_cz(1, 2, 5, 1, feasible=False)[0]
    with pytest.raises(ValueError, match="^S: the constrained zonotope is certified empty"):
        plot_set(ax, empty)
    plt.close(fig)
