"""Interval arithmetic (Song et al. 2017, sec. 3) and the box set: enclosure against sampled
points."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import diffsmf as ds
from diffsmf.sets.interval import Interval, interval_eval
from diffsmf.utils import HIGHS_OPTIONS

SETTINGS = settings(max_examples=25, deadline=None)


def _iv(seed: int, shape=(6,), scale=3.0, positive=False) -> Interval:
    g = torch.Generator().manual_seed(seed)
    c = scale * (2 * torch.rand(shape, generator=g) - 1)
    r = scale * torch.rand(shape, generator=g)
    if positive:
        c = c.abs() + r + 1e-3
    return Interval(c - r, c + r)


def _points(x: Interval, k: int = 400, seed: int = 0) -> torch.Tensor:
    """Samples inside, plus the two endpoints -> [k + 2, *shape]."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand((k, *x.shape), generator=g)
    pts = x.lower + u * (x.upper - x.lower)
    return torch.cat([x.lower.unsqueeze(0), x.upper.unsqueeze(0), pts])


def _encloses(res: Interval, vals: torch.Tensor) -> bool:
    """All finite sampled values lie in ``res`` (non-finite ones: x / 0 samples)."""
    ok = (vals >= res.lower) & (vals <= res.upper)
    return bool((ok | ~torch.isfinite(vals)).all())


# ---------------------------------------------------------------------------- arithmetic
@SETTINGS
@given(st.integers(0, 10_000))
def test_binary_ops_enclose_samples(seed):
    x, y = _iv(seed), _iv(seed + 1)
    px, py = _points(x, seed=seed), _points(y, seed=seed + 7)
    for op in (lambda a, b: a + b, lambda a, b: a - b, lambda a, b: a * b):
        assert _encloses(op(x, y), op(px, py))
    q = x / y
    vals = px / py
    assert _encloses(q, vals)


def test_division_by_zero_containing_interval_is_extended():
    x = Interval(torch.tensor([1.0, -1.0, 1.0]), torch.tensor([2.0, 1.0, 2.0]))
    y = Interval(torch.tensor([0.0, -1.0, -2.0]), torch.tensor([1.0, 1.0, 0.0]))
    q = x / y
    assert q.lower[0] == pytest.approx(1.0) and math.isinf(q.upper[0])
    assert math.isinf(q.lower[1]) and math.isinf(q.upper[1])
    assert math.isinf(q.lower[2]) and q.upper[2] == pytest.approx(-0.5)
    px, py = _points(x), _points(y)
    assert _encloses(q, px / py)


@SETTINGS
@given(st.integers(0, 10_000), st.integers(-4, 5))
def test_integer_powers_enclose_and_are_tight(seed, p):
    x = _iv(seed, positive=p < 0)
    res = x**p
    vals = _points(x) ** p
    assert _encloses(res, vals)
    if p > 0:  # exact range up to a few ulps (even powers: minimum 0 inside)
        tol = 1e-2 * (1 + vals.abs().amax(0))
        assert ((vals.amin(0) - res.lower) <= tol).all()
        assert ((res.upper - vals.amax(0)) <= tol).all()


def test_even_power_known_value():
    r = Interval(-2.0, 1.0) ** 2
    assert r.lower.item() == 0.0 and r.upper.item() == pytest.approx(4.0, rel=1e-15)
    assert r.upper.item() >= 4.0
    r3 = Interval(-2.0, 1.0) ** 3
    assert r3.lower.item() <= -8.0 and r3.upper.item() >= 1.0


@SETTINGS
@given(st.integers(0, 10_000), st.floats(0.01, 30.0))
def test_trig_enclose_and_tight(seed, scale):
    x = _iv(seed, shape=(8,), scale=scale)
    px = _points(x, k=4000)
    for fn in (torch.sin, torch.cos):
        res = fn(x)
        vals = fn(px)
        assert _encloses(res, vals)
        # tight: the sampled range reaches close to the computed one
        assert (res.upper - vals.amax(0)).max() < 1e-3 + 1e-5 * scale
        assert (vals.amin(0) - res.lower).max() < 1e-3 + 1e-5 * scale


def test_trig_exact_extrema():
    x = Interval(torch.tensor([0.0, 0.1, -0.1, 3.0]), torch.tensor([2 * math.pi, 0.2, 0.1, 3.3]))
    s = torch.sin(x)
    assert s.lower[0] == -1 and s.upper[0] == 1
    assert s.lower[1] <= math.sin(0.1) and s.upper[1] >= math.sin(0.2)
    assert s.upper[1] - math.sin(0.2) < 1e-15
    c = torch.cos(x)
    assert c.upper[2] == 1.0 and c.lower[2] <= math.cos(0.1)
    assert c.lower[3] == -1.0  # pi in [3, 3.3]


@SETTINGS
@given(st.integers(0, 10_000))
def test_unary_monotone_enclose(seed):
    x = _iv(seed)
    xp = _iv(seed, positive=True)
    for fn, iv in (
        (torch.exp, x),
        (torch.tanh, x),
        (torch.abs, x),
        (torch.square, x),
        (torch.log, xp),
        (torch.sqrt, xp),
        (torch.sigmoid, x),
        (torch.atan, x),
        (torch.sinh, x),
        (torch.cosh, x),
        (torch.expm1, x),
        (torch.log1p, xp),
        (torch.erf, x),
        (torch.nn.functional.softplus, x),
    ):
        assert _encloses(fn(iv), fn(_points(iv))), fn


def test_log_sqrt_domain_errors():
    with pytest.raises(ValueError, match="x"):
        torch.log(Interval(-1.0, 1.0))
    with pytest.raises(ValueError, match="x"):
        Interval(-1.0, 1.0).sqrt()


def test_outward_rounding_is_strict():
    a = Interval(torch.tensor([0.1]), torch.tensor([0.1]))
    s = a + a
    assert s.lower < 0.2 < s.upper or (s.lower < s.upper)
    # 0.1 + 0.1 == 0.2 in float64; the bound moves at least 1 and at most 4 ulps outward
    lo, hi = s.lower.item(), s.upper.item()
    assert lo <= np.nextafter(0.2, -1.0) and lo >= 0.2 - 4 * np.spacing(0.2)
    assert hi >= np.nextafter(0.2, 1.0) and hi <= 0.2 + 4 * np.spacing(0.2)
    z = Interval(torch.tensor([0.0]), torch.tensor([0.0])) + Interval(torch.tensor([0.0]))
    assert z.lower.item() == 0.0 == z.upper.item()  # exact zero sums stay exact
    tiny = Interval(torch.tensor([1e-200]), torch.tensor([1e-200]))
    u = tiny * tiny  # underflows to 0: the enclosure must still contain 1e-400 > 0
    assert u.lower.item() <= 0.0 < u.upper.item()
    big = Interval(torch.tensor([1e308]), torch.tensor([1e308])) * 10.0  # overflows to inf
    assert big.upper.item() == float("inf") and big.lower.item() <= np.finfo(np.float64).max
    m = a * 3.0
    assert m.lower.item() < 0.30000000000000004 and m.upper.item() >= 0.30000000000000004


@SETTINGS
@given(st.integers(0, 10_000))
def test_matmul_point_and_interval_matrix(seed):
    g = torch.Generator().manual_seed(seed)
    x = _iv(seed, shape=(4,))
    A = torch.randn(3, 4, generator=g)
    AI = Interval(A - 0.1, A + 0.2)
    px = _points(x, k=300)  # [k, 4]
    assert _encloses(A @ x, px @ A.T)
    assert _encloses(x @ A.T, px @ A.T)
    pa = AI.lower + torch.rand(300, 3, 4, generator=g) * AI.width
    vals = (pa @ px[:300].unsqueeze(-1)).squeeze(-1)
    assert _encloses(AI @ x, vals)
    # interval matrix x interval matrix
    B = _iv(seed + 3, shape=(4, 2))
    pb = B.lower + torch.rand(300, 4, 2, generator=g) * B.width
    assert _encloses(AI @ B, pa @ pb)


def test_sum_and_mean():
    x = _iv(3, shape=(5, 7))
    px = _points(x)
    assert _encloses(x.sum(-1), px.sum(-1))
    assert _encloses(torch.sum(x, 0), px.sum(1))
    assert _encloses(x.sum(), px.sum((1, 2)))
    assert _encloses(x.mean(-1), px.mean(-1))


# ---------------------------------------------------------------------------- torch integration
def test_natural_extension_of_user_function():
    def f(x):
        return torch.stack([x[..., 0] ** 2 * x[..., 1], torch.sin(x[..., 1])], -1)

    def g(x):  # mixes tensors, matmul, cat, reshape, exp/tanh, python numbers
        A = torch.tensor([[1.0, -2.0, 0.5], [0.3, 0.0, 1.0]])
        y = x @ A.T + torch.tensor([0.1, -0.2])
        one = torch.ones_like(x[..., :1])
        z = torch.cat([torch.tanh(y), torch.exp(-0.5 * x[..., :1]), one], -1)
        return (2.0 - z.reshape(*z.shape[:-1], 2, 2).unsqueeze(0)).sum(-1).squeeze(0) / 3.0

    box = Interval(torch.tensor([-1.0, 0.5, -0.3]), torch.tensor([0.5, 2.5, 0.8]))
    pts = _points(box, k=3000)
    for fn in (f, g):
        res = interval_eval(fn, box)
        assert isinstance(res, Interval)
        assert _encloses(res, fn(pts))


def test_torch_function_dispatch_and_indexing():
    x = _iv(5, shape=(3, 4))
    assert isinstance(torch.stack([x[:, 0], torch.zeros(3)], -1), Interval)
    assert torch.stack([x[:, 0], x[:, 1]], 0).shape == (2, 3)
    assert x.unsqueeze(0).shape == (1, 3, 4) and x.reshape(12).shape == (12,)
    assert x[..., 1:3].shape == (3, 2) and x.T.shape == (4, 3)
    t = torch.ones(4) * x  # Tensor.__mul__ -> Interval
    assert isinstance(t, Interval)
    u = torch.ones(4) - x
    assert _encloses(u, 1 - _points(x))
    w = torch.where(torch.tensor([True, False, True, False]), x, 0.0)
    assert isinstance(w, Interval)


def test_gradients_flow_through_bounds():
    lo = torch.tensor([-0.7, 0.3, 1.1], requires_grad=True)
    hi = torch.tensor([0.2, 0.9, 1.5], requires_grad=True)

    def fn(lo, hi):
        x = Interval(lo, hi)
        y = interval_eval(lambda z: torch.exp(z) * z[..., 1:2] + torch.sin(z) ** 2, x)
        return y.lower, y.upper

    assert torch.autograd.gradcheck(fn, (lo, hi))


# ---------------------------------------------------------------------------- box set
def test_box_set_methods():
    g = torch.Generator().manual_seed(1)
    B = Interval(
        torch.tensor([[0.0, -1.0, 2.0], [1.0, 1.0, 1.0]]),
        torch.tensor([[1.0, 2.0, 2.5], [1.5, 3.0, 1.2]]),
    )
    assert torch.allclose(B.volume(), torch.tensor([1.5, 0.5 * 2 * 0.2]))
    assert B.batch_shape == (2,) and B.dim == 3
    x = B.sample(500, g)
    assert x.shape == (2, 500, 3) and B.contains(x.transpose(0, 1)).all()
    v = B.sample_extreme(50, g)
    assert ((v == B.lower.unsqueeze(-2)) | (v == B.upper.unsqueeze(-2))).all()
    d = torch.randn(2, 3, generator=g)
    h = B.support(d)
    ref = (B.vertices() @ d.unsqueeze(-1)).squeeze(-1).amax(-1)
    assert torch.allclose(h, ref)
    assert B.interval_hull() is B
    assert not B.contains(torch.tensor([5.0, 0.0, 0.0])).any()


@SETTINGS
@given(st.integers(0, 10_000), st.integers(2, 5))
def test_conversions_cover_the_box(seed, n):
    B = _iv(seed, shape=(3, n))
    V = B.vertices()  # [3, 2^n, n]
    E = B.to_ellipsoid()
    assert E.contains(V.transpose(0, 1), atol=0.0).all()
    # erratum check: 2 r^2 does NOT cover beyond 2-D
    if n > 2:
        E2 = ds.Ellipsoid(B.center, torch.diag_embed(2 * B.radius**2))
        assert not E2.contains(V.transpose(0, 1), atol=0.0).all()
    Z = B.to_zonotope()
    assert Z.contains(V.transpose(0, 1)).all()
    assert torch.allclose(Z.volume(), B.volume())
    P = B.to_parallelotope()
    assert P.contains(V.transpose(0, 1)).all()
    assert torch.allclose(P.volume(), B.volume())


def test_zero_radius_component_floor():
    B = Interval(torch.tensor([0.0, 1.0]), torch.tensor([0.0, 2.0]))
    E = B.to_ellipsoid()
    assert E.contains(B.vertices()).all()
    assert E.volume() > 0


@SETTINGS
@given(st.integers(0, 10_000))
def test_linear_map_minkowski_intersect_hull(seed):
    g = torch.Generator().manual_seed(seed)
    B, C = _iv(seed, shape=(3,)), _iv(seed + 1, shape=(3,))
    A = torch.randn(2, 3, generator=g)
    Z = B.linear_map(A, torch.ones(2))
    x = B.sample_extreme(200, g)
    assert Z.contains(x @ A.T + 1).all()
    S = B.minkowski_sum(C)
    assert isinstance(S, Interval)
    assert S.contains(B.sample_extreme(200, g) + C.sample_extreme(200, g)).all()
    H = B.hull(C)
    assert H.contains(B.sample(100, g)).all() and H.contains(C.sample(100, g)).all()
    Ii = B.intersect(C)
    pts = H.sample(2000, g)
    both = B.contains(pts) & C.contains(pts)
    if Ii.is_empty():
        assert not both.any()
    else:
        assert Ii.contains(pts[both]).all()
        assert (Ii.contains(pts) <= both | Ii.contains(pts)).all()


def test_minkowski_with_other_sets_delegates():
    B = Interval(torch.zeros(2), torch.ones(2))
    Z = ds.Zonotope(torch.zeros(2), torch.eye(2))
    out = B.minkowski_sum(Z)
    assert isinstance(out, ds.Zonotope)
    assert out.contains(torch.tensor([2.0, 2.0])) and not out.contains(torch.tensor([2.1, 0.0]))


def test_gradcheck_linear_map_volume():
    lo = torch.tensor([0.1, -0.3], requires_grad=True)
    w = torch.tensor([0.5, 0.8], requires_grad=True)
    A = torch.tensor([[1.0, 0.4], [-0.3, 2.0]], requires_grad=True)

    def fn(lo, w, A):
        return Interval(lo, lo + w).linear_map(A).volume()

    assert torch.autograd.gradcheck(fn, (lo, w, A))


def test_batched_equals_per_element():
    B = _iv(11, shape=(4, 3))
    f = lambda z: torch.sin(z) * z**2 - torch.exp(z[..., :1])  # noqa: E731
    full = interval_eval(f, B)
    for i in range(4):
        one = interval_eval(f, B[i])
        assert torch.equal(one.lower, full.lower[i]) and torch.equal(one.upper, full.upper[i])


def test_validation_names_argument():
    with pytest.raises(ValueError, match="lower"):
        Interval(torch.tensor([float("nan")]), torch.tensor([1.0]))
    with pytest.raises(ValueError, match="upper"):
        Interval(torch.tensor([0.0]), torch.tensor([float("nan")]))
    with pytest.raises(ValueError, match="lower"):
        Interval(torch.tensor([2.0]), torch.tensor([1.0]))
    with pytest.raises(ValueError, match="upper"):
        Interval(torch.zeros(3), torch.ones(2))
    with pytest.raises(ValueError, match="radius"):
        Interval.from_center_radius(torch.zeros(2), torch.tensor([1.0, -1.0]))
    B = Interval.from_center_radius(torch.zeros(2), torch.ones(2))
    assert B.contains(torch.tensor([1.0, -1.0]), atol=0.0)


def test_point_intervals_enclose_exact_values():
    """Outward rounding: degenerate inputs must enclose the exact (high-precision) result."""
    from fractions import Fraction

    import mpmath

    mpmath.mp.prec = 200
    g = torch.Generator().manual_seed(42)
    x = torch.randn(150, generator=g) * 10.0 ** torch.randint(-3, 4, (150,), generator=g)
    y = torch.randn(150, generator=g) * 10.0 ** torch.randint(-3, 4, (150,), generator=g)
    X, Y = Interval(x, x), Interval(y, y)
    for res, exact in (
        (X + Y, lambda a, b: Fraction(a) + Fraction(b)),
        (X - Y, lambda a, b: Fraction(a) - Fraction(b)),
        (X * Y, lambda a, b: Fraction(a) * Fraction(b)),
        (X / Y, lambda a, b: Fraction(a) / Fraction(b)),
        (X**3, lambda a, b: Fraction(a) ** 3),
    ):
        for i in range(150):
            v = exact(x[i].item(), y[i].item())
            assert Fraction(res.lower[i].item()) <= v <= Fraction(res.upper[i].item())
    xs = x.clamp(-600, 600)
    Xs = Interval(xs, xs)
    ax = x.abs() + 1e-3
    AX = Interval(ax, ax)
    for res, fn, pts in (
        (torch.exp(Xs), mpmath.exp, xs),
        (torch.sin(Xs), mpmath.sin, xs),
        (torch.cos(Xs), mpmath.cos, xs),
        (torch.tanh(Xs), mpmath.tanh, xs),
        (torch.log(AX), mpmath.log, ax),
        (torch.sqrt(AX), mpmath.sqrt, ax),
        (torch.atan(Xs), mpmath.atan, xs),
        (torch.sinh(Xs), mpmath.sinh, xs),
        (torch.cosh(Xs), mpmath.cosh, xs),
        (torch.erf(Xs), mpmath.erf, xs),
        (torch.expm1(Xs), mpmath.expm1, xs),
        (torch.log1p(AX), mpmath.log1p, ax),
        (torch.sigmoid(Xs), lambda v: 1 / (1 + mpmath.exp(-v)), xs),
    ):
        for i in range(150):
            v = fn(mpmath.mpf(pts[i].item()))
            assert mpmath.mpf(res.lower[i].item()) <= v <= mpmath.mpf(res.upper[i].item()), fn


def _kth_neighbour(x: np.ndarray, k: int, direction: float) -> np.ndarray:
    out = x.copy()
    with np.errstate(over="ignore"):  # the largest float's neighbour is inf
        for _ in range(k):
            out = np.nextafter(out, direction)
    return out


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_traced_rounding_moves_k_ulps_and_never_makes_a_subnormal(dtype) -> None:
    """The compiled rounding step moves a bound out by at least k ulps (numpy's nextafter k
    times, an overflowed bound made finite), by at most (2k - 1) eps max(|x|, floor / eps) and
    one rounding; NaN stays NaN, an infinity in the direction stays, and no result is
    subnormal, also at 0, subnormals, the largest float and the infinities. `down`, `up` and
    `outward` take this step while traced."""
    from diffsmf.interval import rounding

    g = torch.Generator().manual_seed(0)
    x = torch.randn(20_000, generator=g, dtype=torch.float64)
    x = x * torch.exp(100 * torch.randn(20_000, generator=g, dtype=torch.float64))
    fi = torch.finfo(dtype)
    special = torch.tensor([0.0, -0.0, fi.tiny * fi.eps, -fi.tiny * fi.eps, fi.tiny, 1.0,
                            fi.max, -fi.max, math.inf, -math.inf, math.nan], dtype=dtype)
    t = torch.cat([x.to(dtype), special])
    tn = t.numpy()
    nan, fin = np.isnan(tn), ~np.isnan(tn)
    floor = rounding.traced_floor(dtype)
    assert floor * floor >= fi.tiny
    for k in (1, 2, 5):
        for d in (-math.inf, math.inf):
            on = rounding._traced_step(t, k, d).numpy()
            assert np.array_equal(np.isnan(on), nan)
            clipped = np.clip(tn, -fi.max, fi.max)
            ref = _kth_neighbour(clipped, k, d)
            assert ((on[fin] >= ref[fin]) if d > 0 else (on[fin] <= ref[fin])).all()
            keep = np.isinf(tn) & (np.sign(tn) == np.sign(d))
            assert np.array_equal(on[keep], tn[keep])
            f = fin & ~np.isinf(on)
            mag = np.maximum(np.abs(tn[f]), floor / fi.eps)
            bound = (2 * k - 1) * fi.eps * mag * (1 + 4 * fi.eps) + np.spacing(np.abs(on[f]))
            assert (np.abs(on[f] - clipped[f]) <= bound).all()
            assert not ((on != 0) & (np.abs(on) < fi.tiny)).any()  # no subnormal result

    def traced(v):
        return (rounding.down(v, 2), rounding.up(v), rounding.outward(torch.stack([v, v])),
                rounding.outward(v, point=True))

    lo, hi, both, point = torch.compile(traced, backend="eager", fullgraph=True)(t)
    for got, k, d in ((lo, 2, -math.inf), (hi, 1, math.inf), (both[0], 1, -math.inf),
                      (both[1], 1, math.inf), (point[0], 1, -math.inf), (point[1], 1, math.inf)):
        ref = rounding._traced_step(t, k, d)
        torch.testing.assert_close(got, ref, rtol=0, atol=0, equal_nan=True)


def _lp_hull(lo, hi, a, y, w):
    """Exact hull of the box [lo, hi] cut by |a.x - y| <= w, by scipy HiGHS (None: empty)."""
    import numpy as np
    from scipy.optimize import linprog

    n = len(lo)
    A_ub, b_ub = np.vstack([a, -a]), np.array([y + w, w - y])
    out = []
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1.0
        kw = {"bounds": list(zip(lo, hi)), "method": "highs", "options": HIGHS_OPTIONS}
        r1 = linprog(e, A_ub=A_ub, b_ub=b_ub, **kw)
        r2 = linprog(-e, A_ub=A_ub, b_ub=b_ub, **kw)
        if r1.status == 2:
            return None
        out.append((r1.fun, -r2.fun))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_intersect_strip_is_the_exact_hull_of_box_and_strip(seed):
    """Against HiGHS's min / max of every coordinate over the box cut by the strip: the same
    bounds to 1e-9, never inside them (outward), and a zero slope leaves its coordinate."""
    import numpy as np

    g = torch.Generator().manual_seed(seed)
    n = 2 + seed % 3
    lo = torch.randn(n, generator=g, dtype=torch.float64)
    hi = lo + 0.1 + torch.rand(n, generator=g, dtype=torch.float64)
    a = torch.randn(n, generator=g, dtype=torch.float64)
    a[0] = 0.0 if seed % 2 else a[0]
    box = Interval(lo, hi)
    mid = float(a @ box.center)
    y, w = mid + 0.3 * float(a.abs() @ box.radius), 0.25 * float(a.abs() @ box.radius)
    got = box.intersect_strip(ds.Strip(a, y, w))
    ref = _lp_hull(lo.numpy(), hi.numpy(), a.numpy(), y, w)
    assert ref is not None
    ref_lo, ref_hi = np.array(ref).T
    x = box.sample(20000, generator=g)
    keep = ds.Strip(a, y, w).contains(x)
    assert keep.any() and got.contains(x[keep]).all()  # outward: every point of the cut
    np.testing.assert_allclose(got.lower.numpy(), ref_lo, atol=1e-9)
    np.testing.assert_allclose(got.upper.numpy(), ref_hi, atol=1e-9)
    if seed % 2:
        assert got.lower[0] == lo[0] and got.upper[0] == hi[0]


def test_intersect_strip_with_infinite_bounds_and_an_empty_cut():
    inf = float("inf")
    box = Interval(torch.tensor([-inf, 0.0, 0.0]), torch.tensor([inf, 1.0, 1.0]))
    a = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)
    got = box.intersect_strip(ds.Strip(a, 0.5, 0.5))  # 0 <= x0 + x1 <= 1
    assert not torch.isnan(got.lower).any() and not torch.isnan(got.upper).any()
    assert got.lower[0] == pytest.approx(-1.0) and got.upper[0] == pytest.approx(1.0)
    assert got.lower[1] == 0.0 and got.upper[1] == 1.0  # x0 is unbounded: x1 keeps its box
    far = box.intersect_strip(ds.Strip(torch.tensor([0.0, 1.0, 0.0]), 5.0, 1.0))
    assert torch.equal(far.lower, box.lower) and torch.equal(far.upper, box.upper)  # empty


def test_intersect_strip_batched_and_differentiable():
    g = torch.Generator().manual_seed(3)
    lo = torch.randn(4, 3, generator=g, dtype=torch.float64)
    r = (0.2 + torch.rand(4, 3, generator=g, dtype=torch.float64)).requires_grad_()
    a = torch.randn(4, 3, generator=g, dtype=torch.float64)
    y = (a * lo).sum(-1)
    w = torch.full((4,), 0.3, dtype=torch.float64, requires_grad=True)

    def hull(r, w):
        out = Interval(lo, lo + r).intersect_strip(ds.Strip(a, y, w))
        return out.lower, out.upper

    assert torch.autograd.gradcheck(hull, (r, w))
    one = Interval(lo[1], lo[1] + r[1]).intersect_strip(ds.Strip(a[1], y[1], w[1]))
    both = hull(r, w)
    assert torch.equal(one.lower, both[0][1]) and torch.equal(one.upper, both[1][1])


def test_intersect_strip_bad_strips_name_the_argument():
    box = Interval(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    with pytest.raises(ValueError, match="strip: normal has dim 3, set has dim 2"):
        box.intersect_strip(ds.Strip(torch.ones(3), 0.5, 0.1))
    with pytest.raises(ValueError, match="strip: expected a Strip"):
        box.intersect_strip("x")
