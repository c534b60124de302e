"""The guarantee engine against sampling: every rule encloses sampled values and autograd
derivatives on random boxes; non-smooth models, branches, domains and the extension point."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

import diffsmf as ds
from diffsmf.interval import enclose, inclusion
from diffsmf.interval.rules import supported_ops
from diffsmf.sets import Interval

torch.set_default_dtype(torch.float64)
M = torch.tensor([[0.5, -1.0, 0.2], [0.3, 0.4, -0.7], [1.1, 0.0, 0.6]])
NET = torch.nn.Sequential(torch.nn.Linear(3, 6), torch.nn.ReLU(), torch.nn.Linear(6, 6),
                          torch.nn.Tanh(), torch.nn.Linear(6, 6), torch.nn.SiLU(),
                          torch.nn.Linear(6, 3)).double()

#: one model per op family: name -> (model, category of the main op)
MODELS = {
    "polynomial": lambda x: torch.stack([x[..., 0] ** 2 * x[..., 1], x[..., 1] * x[..., 2],
                                         x[..., 0] ** 3 - x[..., 2]], -1),
    "exp_log": lambda x: torch.exp(x) + torch.log(x ** 2 + 1) + torch.log1p(x ** 2)
    + torch.expm1(x),
    "roots": lambda x: torch.sqrt(x ** 2 + 0.5) + torch.rsqrt(x ** 2 + 1) + (x ** 2 + 1) ** 1.5,
    "trig": lambda x: torch.sin(x) * torch.cos(x) + torch.tan(0.3 * x) + torch.atan(x),
    "arc": lambda x: torch.asin(0.3 * x) + torch.acos(0.3 * x),
    "hyperbolic": lambda x: torch.sinh(x) + torch.cosh(x) + torch.tanh(x),
    "smooth_act": lambda x: torch.sigmoid(x) + torch.erf(x) + F.softplus(x) + F.gelu(x)
    + F.silu(x) + torch.reciprocal(x ** 2 + 1),
    "kinks": lambda x: torch.relu(x) + F.leaky_relu(x, 0.1) + F.elu(x) + F.hardtanh(x)
    + torch.clamp(x, -0.2, 0.3) + x.abs() + torch.maximum(x, x.flip(-1))
    + torch.minimum(x, 0.1 * x),
    "moving": lambda x: torch.roll(x, 1, -1) * x.flip(-1) + x.unsqueeze(-1).squeeze(-1)
    + x.reshape(*x.shape[:-1], 3, 1).transpose(-1, -2).reshape(x.shape)
    + torch.cat([x[..., 1:], x[..., :1]], -1) + torch.stack(x.unbind(-1), -1),
    "reductions": lambda x: x.sum(-1, keepdim=True) + x.mean(-1, keepdim=True)
    + x.prod(-1, keepdim=True) + torch.cumsum(x, -1) + x.amax(-1, keepdim=True)
    + torch.linalg.vector_norm(x, dim=-1, keepdim=True) + torch.logsumexp(x, -1, keepdim=True),
    "linalg": lambda x: torch.einsum("ij,...j->...i", M, x) + F.linear(x, M, torch.ones(3))
    + (x @ M) * (M @ x.unsqueeze(-1)).squeeze(-1),
    "atan2": lambda x: torch.stack([torch.atan2(x[..., 0] + 3, x[..., 1]),
                                    torch.atan2(x[..., 1], x[..., 2] + 3), x[..., 0]], -1),
    "mlp": NET,
}


def _derivatives(fn, xs):
    xs = xs.clone().requires_grad_(True)
    y = fn(xs)
    k = y.shape[-1]
    J = torch.stack([torch.autograd.grad(y[..., i].sum(), xs, create_graph=True)[0]
                     for i in range(k)], -2)
    H = torch.stack([torch.stack([
        torch.autograd.grad(J[..., i, j].sum(), xs, retain_graph=True, allow_unused=True)[0]
        if J.requires_grad else torch.zeros_like(xs) for j in range(3)], -2) for i in range(k)], -3)
    return y.detach(), J.detach(), H.detach()


def _inside(v, I, tol=1e-10):
    return bool(((v >= I.lower - tol) & (v <= I.upper + tol)).all())


@pytest.mark.parametrize("name", sorted(MODELS))
@settings(max_examples=12, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-3, 0.1, 0.6]))
def test_rules_enclose_sampled_values_and_derivatives(name, seed, scale):
    fn = MODELS[name]
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(4, 3, generator=g) * 0.6
    r = torch.rand(4, 3, generator=g) * scale
    box = Interval(c - r, c + r)
    E = enclose(fn, box, 2)
    xs = c + r * (2 * torch.rand(300, 4, 3, generator=g) - 1)
    xs = torch.cat([xs, box.lower[None], box.upper[None], c[None]])
    y, J, H = _derivatives(fn, xs)
    assert _inside(y, E.val)
    # the rules enclose the derivatives where they exist (away from the kinks of "kinks")
    assert _inside(J, E.grad)
    assert _inside(H, E.hess, 1e-8)


def test_every_registered_category_is_documented():
    cats = supported_ops()
    for cat in ("elementwise", "non-smooth", "branch", "moving", "reduction",
                "linear algebra", "activation"):
        assert cat in cats and cats[cat]


def test_branch_on_the_state_encloses_values_and_gives_no_derivative():
    box = Interval(torch.tensor([[-0.5], [0.2]]), torch.tensor([[0.5], [0.6]]))
    E = enclose(lambda x: torch.where(x > 0, x ** 2, -x), box, 2)
    assert E.val.lower[0, 0] <= 0.0 and E.val.upper[0, 0] >= 0.5  # hull of both branches
    assert torch.isinf(E.grad.upper[0]).all()  # undecided: the function may jump
    assert torch.isfinite(E.grad.upper[1]).all() and E.val.lower[1, 0] >= 0.04 - 1e-12


def test_domain_boundary_encloses_the_part_inside_and_poles_are_nan():
    """sqrt / asin of a box reaching outside their domain enclose the part inside it (the true
    states lie there), with no derivative at the boundary; log reaches -inf there; a box
    across a pole of tan is NaN, for that element only."""
    lo = torch.tensor([[-0.1, 1.0], [0.5, 1.0]])
    box = Interval(lo, lo + 0.5)
    E = enclose(lambda x: torch.sqrt(x) + torch.asin(0.5 * x), box, 2)
    assert float(E.val.lower[0, 0]) <= 0.0 and math.isfinite(float(E.val.upper[0, 0]))
    assert torch.isinf(E.grad.upper[0, 0]).any()
    assert torch.isfinite(E.val.lower[1]).all() and torch.isfinite(E.hess.lower[1]).all()
    assert float(enclose(torch.log, box, 0).val.lower[0, 0]) == -math.inf
    T = enclose(torch.tan, Interval(torch.tensor([[1.4], [0.0]]), torch.tensor([[1.7], [0.2]])), 2)
    assert torch.isnan(T.val.lower[0]).all() and torch.isfinite(T.val.lower[1]).all()


def test_user_inclusion_rule_is_used_as_a_leaf():
    calls = []

    def rule(lo, hi):
        calls.append(1)
        return torch.tanh(lo), torch.tanh(hi), (1 - torch.tanh(hi.abs().maximum(lo.abs())) ** 2
                                                ).unsqueeze(-2) * torch.eye(lo.shape[-1]), \
            torch.eye(lo.shape[-1]).expand(*lo.shape, lo.shape[-1])

    @inclusion(rule)
    def sat(x):
        return torch.tanh(x)

    box = Interval(torch.full((2, 2), -0.3), torch.full((2, 2), 0.4))
    E = enclose(lambda x: 2.0 * sat(x), box, 2)
    assert calls and _inside(2 * torch.tanh(box.sample(50)).movedim(-2, 0), E.val)
    assert torch.isinf(E.hess.upper).any()  # a leaf has a first-order bound only
    assert torch.allclose(sat(box.lower), torch.tanh(box.lower))  # unchanged outside


def test_enclosure_bounds_are_differentiable():
    def bounds(c):
        E = enclose(lambda x: torch.sin(x) * x[..., :1] + F.softplus(x), Interval(c - 0.1, c + 0.1),
                    2)
        return E.val.upper.sum() + E.grad.lower.sum() + E.hess.upper.sum()

    c = torch.tensor([[0.3, -0.2]], requires_grad=True)
    assert torch.autograd.gradcheck(bounds, (c,))


def _ring(n):
    def f(x, u, th):
        return 0.8 * x + 0.1 * torch.tanh(torch.roll(x, 1, -1)) - 0.05 * torch.clamp(x, -0.3, 0.3)

    def h(x):
        return x[..., ::2] + 0.1 * torch.relu(x[..., 1::2])

    w = 0.01 * torch.ones(n)
    v = 0.02 * torch.ones(n // 2)
    return ds.System(f, h, Interval(-0.5 * torch.ones(n), 0.5 * torch.ones(n)),
                     Interval(-w, w), Interval(-v, v))


@pytest.mark.parametrize("filt", ["HSNSMF", "MSZM"])
def test_nonsmooth_ring_model_is_contained(filt):
    """A ring of coupled states (roll, tanh, clamp) measured through relu: vertex noise."""
    sys_ = _ring(16)
    traj = sys_.simulate(steps=8, batch=3, seed=1, noise="vertex")
    with torch.no_grad():
        res = getattr(ds.filters, filt)(sys_)(traj.y)
    assert bool(res.bounded.all()) and bool(res.sets.contains(traj.x).all())


def test_relu_mlp_dynamics_is_contained():
    torch.manual_seed(3)
    net = torch.nn.Sequential(torch.nn.Linear(2, 16), torch.nn.ReLU(), torch.nn.Linear(16, 2))
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(0.3)

    def f(x, u, th):
        return 0.9 * x + 0.1 * net(x)

    sys_ = ds.System(f, lambda x: x[..., :1], Interval(-0.5 * torch.ones(2), 0.5 * torch.ones(2)),
                     Interval(-0.01 * torch.ones(2), 0.01 * torch.ones(2)),
                     Interval(-0.02 * torch.ones(1), 0.02 * torch.ones(1)))
    traj = sys_.simulate(steps=15, batch=8, seed=0, noise="vertex")
    with torch.no_grad():
        res = ds.filters.HSNSMF(sys_)(traj.y)
    assert bool(res.bounded.all()) and bool(res.sets.contains(traj.x).all())
    assert float(res.volume[:, -1].max()) < 1.0 and math.isfinite(float(res.volume.sum()))


def _relu_net_system(seed: int = 5):
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(2, 8), torch.nn.ReLU(), torch.nn.Linear(8, 2))
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(0.3)

    def f(x):
        return 0.9 * x + 0.1 * net(x)

    return net, ds.System(f, lambda x: x[..., :1], Interval([-0.5, -0.5], [0.5, 0.5]),
                          Interval([-0.01, -0.01], [0.01, 0.01]), Interval([-0.02], [0.02]))


@pytest.mark.parametrize("filt, remainder", [
    ("HSNSMF", "auto"), ("HSNSMF", "lagrange"), ("MSZM", "auto"), ("CDSMF", "auto")])
def test_relu_network_weights_get_the_gradient_of_the_set_volume(filt, remainder):
    """Learning a ReLU network jointly with the filter: the Hessian enclosure is unbounded at
    the kinks, and the remainders mask it; its zero gradient must not become ``0 * inf =
    NaN`` in the weights' gradients. Autograd against central differences of the loss, with
    an absolute Stirling step (the relative one follows the set without gradient, by design:
    `diffsmf.filters.params.stirling_steps`)."""
    net, system = _relu_net_system()
    y = system.simulate(steps=4, batch=2, seed=0, noise="vertex").y

    def loss():
        filt_ = getattr(ds.filters, filt)(system, remainder=remainder, stirling_step=0.1)
        return filt_(y).volume[:, 1:].log().mean()

    loss().backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in net.parameters())
    W, h = net[2].weight, 1e-6
    i = int(W.grad.abs().argmax())
    with torch.no_grad():
        W.view(-1)[i] += h
        up_ = loss()
        W.view(-1)[i] -= 2 * h
        down_ = loss()
        W.view(-1)[i] += h
    fd = float(up_ - down_) / (2 * h)
    assert W.grad.view(-1)[i].item() == pytest.approx(fd, rel=1e-6, abs=1e-8)


def test_bound_products_have_the_plain_gradients_and_none_from_infinite_operands():
    """`arith.times` / `arith.mm`: the plain product's values and, for finite operands, its
    gradients (gradcheck); an infinite operand gives the other one no NaN gradient."""
    from diffsmf.interval.arith import mm, times

    x = torch.randn(3, 1, 4, requires_grad=True)
    y = torch.randn(2, 4, requires_grad=True)
    A = torch.randn(4, 5, requires_grad=True)
    v = torch.randn(4, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: times(a, b), (x, y))
    assert torch.autograd.gradcheck(lambda a: times(a, a), (x,))
    for args in ((x, A), (v, A), (A.mT, v), (torch.randn(2, 3, 4, dtype=x.dtype), A)):
        assert torch.autograd.gradcheck(lambda a, b: mm(a, b), args)
        assert torch.equal(mm(*args), args[0] @ args[1])
    bad = torch.tensor([math.inf, -math.inf, math.nan, 2.0])
    out = times(v, bad)
    torch.where(torch.isfinite(out), out, 0.0).sum().backward()
    assert torch.equal(v.grad, torch.tensor([0.0, 0.0, 0.0, 2.0]))
    v.grad = None
    out = mm(bad.reshape(1, 4), A)
    torch.testing.assert_close(out, bad.reshape(1, 4) @ A, rtol=0, atol=0, equal_nan=True)
    A.grad = None
    torch.where(torch.isfinite(out), out, 0.0).sum().backward()
    assert bool(torch.isfinite(A.grad).all())


def _coverage_ways():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parent.parent / "benchmarks" / "model_coverage.py"
    spec = importlib.util.spec_from_file_location("model_coverage", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_COVERAGE = _coverage_ways()


@pytest.mark.parametrize("name", sorted(_COVERAGE.WAYS))
def test_ordinary_ways_of_writing_a_model_run_and_are_contained(name):
    """The 36 ways of benchmarks/model_coverage.py through HSNSMF (vertex noise, short)."""
    s = _COVERAGE.system(_COVERAGE.WAYS[name])
    tr = s.simulate(steps=3, batch=2, seed=0, noise="vertex")
    with torch.no_grad():
        res = ds.filters.HSNSMF(s)(tr.y)
    assert bool(res.bounded.all()) and bool(res.sets.contains(tr.x.detach()).all())


@pytest.mark.parametrize("name", sorted(_COVERAGE.WAYS))
def test_ordinary_ways_of_writing_a_model_give_finite_gradients(name):
    """The 36 ways through HSNSMF with the Lagrange remainder (the interval Hessian is used
    directly, so unbounded entries meet the bounds' products): the gradients of the log set
    volume in the noise bounds, the Stirling step and a network's weights are finite."""
    assert _COVERAGE.finite_gradients(_COVERAGE.WAYS[name], "hsnsmf", "lagrange", 2, 3)


def test_inclusion_needs_a_rule_function():
    with pytest.raises(ValueError, match="rule: must be a function"):
        inclusion(None)
    with pytest.raises(ValueError, match="decorates a function"):
        inclusion(lambda lo, hi: (lo, hi, lo, hi))(3.0)


def _stacked_vs_separate(fn, lo, hi, monkeypatch):
    from diffsmf.interval import capture

    box = Interval(torch.tensor(lo), torch.tensor(hi))
    with torch.no_grad():
        stacked = enclose(fn, box, 2)
        monkeypatch.setattr(capture, "STACKED_MAX", 0)  # separate bounds, each product checked
        separate = enclose(fn, box, 2)
    for a, b in ((stacked.val, separate.val), (stacked.grad, separate.grad),
                 (stacked.hess, separate.hess)):
        assert torch.equal(a.lower, b.lower) and torch.equal(a.upper, b.upper)


def test_stacked_bounds_give_the_same_enclosures_as_separate_bounds(monkeypatch):
    def f(x):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 + 0.1 * x2, x2 - 0.3 * x1 * (1.0 - 3.0 * x1**2) - x2 / 3.0,
                            torch.sqrt(x2 + 1.0) * torch.tanh(x1), -x1 * x2 + 2.0], -1)

    _stacked_vs_separate(f, [[-0.4, 0.1], [0.2, -0.5]], [[0.3, 0.6], [0.2, 0.5]], monkeypatch)


def test_stacked_products_fall_back_on_zero_times_infinity(monkeypatch):
    # an unbounded box times exact zeros: 0 * inf := 0 (the one deferred check fails, and the
    # evaluation is repeated with each product checked)
    def f(x):
        return torch.stack([x[..., 0] * torch.tensor(0.0), x[..., 0] * x[..., 1]], -1)

    lo, hi = [[-math.inf, 0.0]], [[1.0, 0.0]]
    _stacked_vs_separate(f, lo, hi, monkeypatch)
    with torch.no_grad():
        e = enclose(f, Interval(torch.tensor(lo), torch.tensor(hi)), 2)
    assert not torch.isnan(e.val.lower).any() and not torch.isnan(e.grad.lower).any()
    assert e.val.lower[0, 0] <= 0 <= e.val.upper[0, 0] and e.val.upper[0, 0] < 1e-300


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, math.inf, math.nan]))
def test_fused_product_sum_equals_two_products_and_a_sum(seed, special):
    """The engine's fused ``x1 y1 + x2 y2`` (stacked mode) has the bounds of two outward
    products and an outward sum, also with infinite and NaN operands (then it declines)."""
    from diffsmf.interval import arith

    g = torch.Generator().manual_seed(seed)

    def iv(*shape):
        t = torch.randn(2, *shape, generator=g, dtype=torch.float64)
        t[0, ..., 0] = special if special == 0.0 else -special
        return Interval._pair(torch.sort(t, dim=0).values)

    x1, x2, y1, y2 = iv(3, 1, 2), iv(3, 1, 2), iv(1, 2), iv(1, 2)
    prev = arith.stacking(True)
    try:
        fused = arith.mul_sum(x1, y1, x2, y2)
        ref = arith.add(arith.mul(x1, y1), arith.mul(x2, y2), exact_zero=False)
    finally:
        arith.stacking(prev)
    if fused is None:  # declined: a NaN product (0 * inf or a NaN operand)
        assert special != 0.0
        return
    assert torch.equal(fused.lower, ref.lower) and torch.equal(fused.upper, ref.upper)


_NONNEG = st.one_of(st.just(0.0), st.just(math.inf), st.just(5e-324),
                    st.floats(0.0, 1e300, allow_nan=False))


@settings(max_examples=60, deadline=None)
@given(x=st.lists(_NONNEG, min_size=2, max_size=2), n=st.lists(_NONNEG, min_size=2, max_size=2),
       num=st.floats(1e-3, 1e3), t=st.floats(0.0, 1.0))
def test_quotient_of_nonnegative_intervals_encloses_the_quotients(x, n, num, t):
    """`arith.quotient_nonneg`: ``num / [x]`` and ``[n] / [x]`` on non-negative intervals
    (ends at 0, inf and the smallest subnormal included) contain the quotient of points
    between the ends (numpy, the exact IEEE quotient rounded to nearest, lies within one ulp
    of the enclosure's own), and the stacked bounds give the same bits as separate ones."""
    import numpy as np

    from diffsmf.interval import arith

    lo, hi = sorted(x)
    nlo, nhi = sorted(n)
    X = Interval(torch.tensor([lo]), torch.tensor([hi]))
    N = Interval(torch.tensor([nlo]), torch.tensor([nhi]))
    xs = lo + t * (hi - lo) if math.isfinite(hi - lo) else (hi if t > 0.5 else lo)
    for top, pts in ((num, [num]), (N, [nlo, nhi])):
        prev = arith.stacking(False)
        try:
            plain = arith.quotient_nonneg(top, X)
            arith.stacking(True)
            stacked = arith.quotient_nonneg(top, X)
        finally:
            arith.stacking(prev)
        for a, b in ((plain.lower, stacked.lower), (plain.upper, stacked.upper)):
            torch.testing.assert_close(a, b, rtol=0.0, atol=0.0, equal_nan=True)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ends = np.float64(pts[0]) / np.float64(hi), np.float64(pts[-1]) / np.float64(lo)
            qs = [np.float64(p) / np.float64(xs) for p in pts]
        # a bound is NaN exactly where its end quotient is 0 / 0 or inf / inf (documented)
        assert [math.isnan(e) for e in ends] == [math.isnan(plain.lower.item()),
                                                 math.isnan(plain.upper.item())]
        for q in qs:
            assert not plain.lower.item() > q and not q > plain.upper.item(), (q, plain)


@pytest.mark.parametrize("fn", [torch.sqrt, torch.exp, torch.sin, torch.tanh])
def test_unary_of_the_input_box_selects_its_derivatives(fn):
    """A unary function of the input box itself takes its derivative enclosures by selection
    (`jet.register_seed`): zero off the diagonal exactly, inside the enclosures of the same
    function reached through an interval product (``x * 1.0``), and containing the sampled
    autograd derivatives."""
    lo = torch.tensor([[0.3, 1.0, 2.5]])
    box = Interval(lo, lo + torch.tensor([[0.2, 0.5, 1e-3]]))
    sel = enclose(fn, box, 2)
    prod = enclose(lambda x: fn(x * 1.0), box, 2)
    eye = torch.eye(3, dtype=torch.bool)
    assert torch.equal(sel.grad.lower[0][~eye], torch.zeros(6))
    hess_off = ~eye.reshape(1, 3, 3) | ~eye.reshape(3, 3, 1)  # all but (i, i, i)
    assert torch.equal(sel.hess.lower[0][hess_off], torch.zeros(int(hess_off.sum())))
    for a, b in ((sel.grad, prod.grad), (sel.hess, prod.hess)):
        assert bool((a.lower >= b.lower).all() and (a.upper <= b.upper).all())
    xs = box.lower + torch.rand(64, 3) * (box.upper - box.lower)
    _, J, H = _derivatives(fn, xs)
    assert bool(((sel.grad.lower <= J) & (J <= sel.grad.upper)).all())
    assert bool(((sel.hess.lower <= H) & (H <= sel.hess.upper)).all())


_SPECIAL = st.sampled_from([0.0, -0.0, math.inf, -math.inf, math.nan, 1e-300, -2.5, 3.0])


def _special_interval(draw_vals, shape):
    """Interval ``[shape]`` from sorted pairs of drawn values (a NaN bound kept as drawn)."""
    t = torch.tensor(draw_vals, dtype=torch.float64).reshape(2, *shape)
    lo, hi = torch.minimum(t[0], t[1]), torch.maximum(t[0], t[1])  # NaN propagates: NaN bounds
    return Interval._make(lo, hi)


@settings(max_examples=80, deadline=None)
@given(st.lists(_SPECIAL, min_size=12, max_size=12), st.lists(_SPECIAL, min_size=6, max_size=6),
       st.booleans())
def test_stacked_branch_free_products_equal_the_general_rule(va, vb, point):
    """`arith._mul_stacked_general` (the traced engine's product of stacked bounds) gives the
    bits of the general rule, ``0 * inf := 0`` and NaN operands (NaN results) included, for
    two intervals and for a point times an interval."""
    from diffsmf.interval import arith

    a = _special_interval(va, (2, 3))  # [2, 3] against [3]: broadcasting
    b = _special_interval(vb, (3,))
    if point:
        b = Interval._make(b.lower, b.lower)
    ref = arith._mul_general(a, b)
    prev = arith.stacking(True)
    try:
        sa = Interval._pair(torch.stack([a.lower, a.upper]))
        sb = b if point else Interval._pair(torch.stack([b.lower, b.upper]))
        ta, tb = arith._stacked_pair(sa, sb, outer=True)
        got = arith._mul_stacked_general(sa, sb, ta, tb)
    finally:
        arith.stacking(prev)
    for g, r in ((got.lower, ref.lower), (got.upper, ref.upper)):
        assert torch.equal(torch.isnan(g), torch.isnan(r))
        assert torch.equal(g.nan_to_num(7.0), r.nan_to_num(7.0))


def test_traced_programs_stacked_and_separate_give_the_same_enclosures(monkeypatch):
    """While traced (Dynamo, eager backend), the engine evaluates stacked bounds
    (`capture.TRACED_STACKING`): the same bits as separate bounds, for an unbounded box with
    exact zeros (``0 * inf``) and a box partly outside sqrt's domain; a NaN bound gives no
    output two finite bounds in either mode."""
    from diffsmf.interval import capture

    def f(x):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 * torch.tensor(0.0) + x1 * x2, torch.sqrt(x2 + 1.0) * torch.tanh(x1),
                            x2 / (2.0 + x1 * x1) - 0.3 * x1**3 + x2**2], -1)

    lo = torch.tensor([[-math.inf, 0.0], [-0.4, -0.5], [-3.0, -2.0], [math.nan, 0.1]],
                      dtype=torch.float64)
    hi = torch.tensor([[1.0, 0.0], [0.3, 0.6], [-2.0, 0.5], [0.2, 0.3]], dtype=torch.float64)

    def run(lo, hi):
        e = enclose(f, Interval._make(lo, hi), 2)  # (no validation: a NaN bound on purpose)
        return [t for iv in (e.val, e.grad, e.hess) for t in (iv.lower, iv.upper)]

    with torch.no_grad():
        enclose(f, Interval._make(lo, hi), 2)  # captured eagerly first
        out = {}
        for flag in (True, False):
            monkeypatch.setattr(capture, "TRACED_STACKING", flag)
            torch._dynamo.reset()
            out[flag] = torch.compile(run, backend="eager", fullgraph=True)(lo, hi)
    torch._dynamo.reset()
    for s, p in zip(out[True], out[False]):  # rows 0-2: the same bits
        assert torch.equal(s[:3], p[:3])
    assert not torch.isnan(out[True][0][0]).any()  # 0 * inf := 0 on the unbounded row
    for flag in (True, False):  # the NaN bound: no output enclosed by two finite bounds
        lo_, hi_ = out[flag][0][3], out[flag][1][3]
        assert not bool((torch.isfinite(lo_) & torch.isfinite(hi_)).any())
