"""Exact box enclosures of an SCPLNN (value range and gradient hull), against independent
references: polygon clipping in 2-D, scipy HiGHS LPs per piece in 3-D, sampling and autograd."""

import numpy as np
import pytest
import torch

from diffsmf.pwl import SCPLNN, fit_scplnn
from diffsmf.pwl.partition import grid_partition

F64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _fitted_2d(seed: int) -> SCPLNN:
    g = _gen(seed)
    X = torch.rand(1500, 2, generator=g, dtype=F64) * 4 - 2
    Y = torch.stack([torch.sin(2 * X[:, 0]) * X[:, 1], X[:, 0] ** 2 - X[:, 1] + seed], -1)
    model, _ = fit_scplnn(X, Y, eps=0.15, seed=seed)
    return model


def _kuhn_2d() -> SCPLNN:
    """A model on a Kuhn grid (axis-parallel and diagonal edges: degenerate alignments)."""
    V, S = grid_partition(torch.tensor([-2.0, -2.0]), torch.tensor([2.0, 2.0]), [4, 4])
    W = torch.stack([torch.sin(3 * V[:, 0]) + V[:, 1] ** 2, V[:, 0] * V[:, 1]], -1)
    return SCPLNN(V, S, W)


def _random_boxes(n: int, k: int, seed: int, lo=-2.0, hi=2.0, grid: float | None = None):
    g = _gen(seed)
    a = lo + (hi - lo) * torch.rand(k, n, generator=g, dtype=F64)
    b = lo + (hi - lo) * torch.rand(k, n, generator=g, dtype=F64)
    if grid is not None:  # bounds on the grid lines (boxes touching simplices exactly)
        a, b = (a / grid).round() * grid, (b / grid).round() * grid
    small = torch.rand(k, 1, generator=g, dtype=F64) < 0.3  # some small boxes
    b = torch.where(small, a + 0.05 * (b - a), b)
    return torch.minimum(a, b), torch.maximum(a, b)


# ---------------------------------------------------------------- references
def _clip(poly: np.ndarray, axis: int, bound: float, upper: bool) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon [k, 2] to x_axis <= / >= bound."""
    if len(poly) == 0:
        return poly
    s = (bound - poly[:, axis]) if upper else (poly[:, axis] - bound)
    out = []
    for i in range(len(poly)):
        j = (i + 1) % len(poly)
        if s[i] >= 0:
            out.append(poly[i])
        if (s[i] >= 0) != (s[j] >= 0) and s[i] != s[j]:
            t = s[i] / (s[i] - s[j])
            out.append(poly[i] + t * (poly[j] - poly[i]))
    return np.array(out).reshape(-1, 2)


def _reference_2d(model: SCPLNN, lo: np.ndarray, hi: np.ndarray):
    """Exact range and gradient hull by clipping every triangle to the box (numpy)."""
    R = model.regions()
    V, A, b = R.vertices.numpy(), R.A.detach().numpy(), R.b.detach().numpy()
    vmin = np.full(A.shape[1], np.inf)
    vmax = -vmin
    jlo = np.full(A.shape[1:], np.inf)
    jhi = -jlo
    for k in range(len(V)):
        poly = V[k]
        for ax in range(2):
            poly = _clip(poly, ax, lo[ax], False)
            poly = _clip(poly, ax, hi[ax], True)
        if len(poly) == 0:
            continue
        vals = poly @ A[k].T + b[k]
        vmin, vmax = np.minimum(vmin, vals.min(0)), np.maximum(vmax, vals.max(0))
        jlo, jhi = np.minimum(jlo, A[k]), np.maximum(jhi, A[k])
    return vmin, vmax, jlo, jhi


def _reference_lp(model: SCPLNN, lo: np.ndarray, hi: np.ndarray):
    """Exact range and gradient hull by scipy HiGHS LPs over box ∩ simplex, piece by piece."""
    from scipy.optimize import linprog

    from diffsmf.utils import HIGHS_OPTIONS

    R = model.regions()
    A, b = R.A.detach().numpy(), R.b.detach().numpy()
    Bm = model.bary.numpy()  # lam = Bm[:, :n] x + Bm[:, n] >= 0
    n = lo.shape[0]
    vmin = np.full(A.shape[1], np.inf)
    vmax = -vmin
    jlo = np.full(A.shape[1:], np.inf)
    jhi = -jlo
    bounds = list(zip(lo, hi))
    for k in range(A.shape[0]):
        Aub, bub = -Bm[k, :, :n], Bm[k, :, n]
        feas = linprog(np.zeros(n), A_ub=Aub, b_ub=bub, bounds=bounds, method="highs",
                       options=HIGHS_OPTIONS)
        if feas.status != 0:
            continue
        jlo, jhi = np.minimum(jlo, A[k]), np.maximum(jhi, A[k])
        for o in range(A.shape[1]):
            for sign in (1.0, -1.0):
                r = linprog(sign * A[k, o], A_ub=Aub, b_ub=bub, bounds=bounds, method="highs",
                            options=HIGHS_OPTIONS)
                v = sign * r.fun + b[k, o]
                vmin[o], vmax[o] = min(vmin[o], v), max(vmax[o], v)
    return vmin, vmax, jlo, jhi


def _assert_equal_ref(model, lo, hi, ref, atol=1e-9):
    vl, vh, jl, jh = model.interval_enclosure(lo, hi, margin=0.0)
    for i in range(lo.shape[0]):
        rl, rh, rjl, rjh = ref(model, lo[i].numpy(), hi[i].numpy())
        np.testing.assert_allclose(vl[i].detach().numpy(), rl, rtol=0, atol=atol)
        np.testing.assert_allclose(vh[i].detach().numpy(), rh, rtol=0, atol=atol)
        np.testing.assert_allclose(jl[i].detach().numpy(), rjl, rtol=0, atol=atol)
        np.testing.assert_allclose(jh[i].detach().numpy(), rjh, rtol=0, atol=atol)


# ---------------------------------------------------------------- exactness
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_enclosure_equals_clipping_reference_2d(seed):
    model = _fitted_2d(seed)
    lo, hi = _random_boxes(2, 40, seed)
    _assert_equal_ref(model, lo, hi, _reference_2d)


def test_enclosure_exact_on_kuhn_grid_with_aligned_boxes():
    """Boxes whose bounds lie on the grid lines: faces parallel to box faces, touching pieces."""
    model = _kuhn_2d()
    lo, hi = _random_boxes(2, 60, 7, grid=0.5)
    _assert_equal_ref(model, lo, hi, _reference_2d)


def test_enclosure_equals_highs_lp_reference_3d():
    g = _gen(3)
    X = torch.rand(3000, 3, generator=g, dtype=F64) * 2 - 1
    Y = torch.sin(2 * X[:, 0]) * X[:, 1] + X[:, 2].abs()
    model, _ = fit_scplnn(X, Y, eps=0.25)
    assert 20 < model.n_regions < 400
    lo, hi = _random_boxes(3, 6, 4, -1.0, 1.0)
    _assert_equal_ref(model, lo, hi, _reference_lp, atol=1e-8)


def test_enclosure_1d_matches_vertex_enumeration():
    V = torch.tensor([[-1.0], [-0.2], [0.3], [1.0]])
    S = torch.tensor([[0, 1], [1, 2], [2, 3]])
    model = SCPLNN(V, S, torch.tensor([[1.0], [-2.0], [0.5], [0.0]]))
    lo = torch.tensor([[-1.0], [-0.5], [0.0], [0.3]])
    hi = torch.tensor([[1.0], [0.0], [0.3], [0.3]])
    vl, vh, jl, jh = (t.detach() for t in model.interval_enclosure(lo, hi, margin=0.0))
    for i in range(4):  # breakpoints inside the box plus its ends
        pts = torch.cat([lo[i], hi[i], V[:, 0][(V[:, 0] >= lo[i]) & (V[:, 0] <= hi[i])]])
        y = model(pts[:, None])[:, 0].detach()
        assert float(vl[i, 0]) == pytest.approx(float(y.min()), abs=1e-12)
        assert float(vh[i, 0]) == pytest.approx(float(y.max()), abs=1e-12)
    slopes = model.regions().A[:, 0, 0].detach()
    assert torch.allclose(jl[0, 0, 0], slopes.min()) and torch.allclose(jh[0, 0, 0], slopes.max())
    # the point 0.3 is a breakpoint: both adjacent slopes (Clarke), a single value
    assert torch.allclose(jl[3, 0, 0], slopes[1:].min()) and torch.allclose(
        jh[3, 0, 0], slopes[1:].max())
    assert vl[3, 0] == vh[3, 0]


# ---------------------------------------------------------------- soundness
@pytest.mark.parametrize("seed", [0, 1])
def test_samples_and_autograd_gradients_inside(seed):
    model = _fitted_2d(seed)
    lo, hi = _random_boxes(2, 30, 10 + seed)
    vl, vh, jl, jh = model.interval_enclosure(lo, hi)
    u = torch.rand(30, 2000, 2, generator=_gen(seed), dtype=F64)
    x = lo[:, None] + u * (hi - lo)[:, None]
    corners = torch.stack(torch.meshgrid([torch.tensor([0.0, 1.0])] * 2, indexing="ij"), -1)
    x = torch.cat([x, lo[:, None] + corners.reshape(1, -1, 2) * (hi - lo)[:, None]], 1)
    with torch.no_grad():
        y = model(x)
    assert bool((y >= vl[:, None]).all() and (y <= vh[:, None]).all())
    J = torch.func.vmap(torch.func.jacrev(model))(x.reshape(-1, 2)).reshape(*x.shape[:2], 2, 2)
    assert bool((J >= jl[:, None]).all() and (J <= jh[:, None]).all())


def test_degenerate_box_gives_point_value_and_clarke_hull():
    model = _kuhn_2d()
    g = _gen(5)
    x = torch.rand(20, 2, generator=g, dtype=F64) * 4 - 2
    x[0] = torch.tensor([0.0, 1.0])  # a grid vertex: every piece of its star
    vl, vh, jl, jh = model.interval_enclosure(x, x)
    y = model(x).detach()
    assert torch.allclose(vl, y, atol=1e-9, rtol=0) and torch.allclose(vh, y, atol=1e-9, rtol=0)
    s, _ = model.locate(x[1:])
    A = model.regions().A.detach()
    assert torch.allclose(jl[1:], A[s], atol=1e-9) and torch.allclose(jh[1:], A[s], atol=1e-9)
    star = (model.vertices[model.simplices] - x[0]).norm(dim=-1).amin(-1) < 1e-12
    assert int(star.sum()) == 6
    assert torch.allclose(jl[0], A[star].amin(0)) and torch.allclose(jh[0], A[star].amax(0))


def test_batch_dims_broadcast_and_chunks(monkeypatch):
    import diffsmf.pwl.enclosure as enc

    model = _fitted_2d(0)
    lo, hi = _random_boxes(2, 12, 3)
    full = model.interval_enclosure(lo, hi)
    out = model.interval_enclosure(lo.reshape(3, 4, 2), hi.reshape(3, 4, 2))
    assert out[0].shape == (3, 4, 2) and out[2].shape == (3, 4, 2, 2)
    monkeypatch.setattr(enc, "CHUNK_ELEMS", 1)  # one box per chunk
    chunked = model.interval_enclosure(lo, hi)
    for a, b, c in zip(full, out, chunked):
        assert torch.equal(a, b.reshape(a.shape)) and torch.equal(a, c)


def test_invariant_to_the_order_of_simplices_and_of_their_vertices():
    model = _fitted_2d(0)
    g = _gen(4)
    S = model.simplices[torch.randperm(model.n_regions, generator=g)]
    S = torch.gather(S, 1, torch.argsort(torch.rand(S.shape, generator=g), 1))
    other = SCPLNN(model.vertices, S, model.weight.detach())
    lo, hi = _random_boxes(2, 30, 5)
    for a, b in zip(model.interval_enclosure(lo, hi), other.interval_enclosure(lo, hi)):
        assert torch.allclose(a, b, atol=1e-12, rtol=0)


def test_dense_path_equals_sparse_path_and_runs_under_vmap():
    """Fixed-shape evaluation of every (box, face) pair (used under tracing) = the pruned one."""
    from diffsmf.pwl.enclosure import box_enclosure

    model = _fitted_2d(2)
    lo, hi = _random_boxes(2, 25, 6)
    tables, A = model._get("encl"), model.regions().A.detach()
    W = model.weight.detach()
    sparse = box_enclosure(tables, W, A, lo, hi, sparse=True)
    dense = box_enclosure(tables, W, A, lo, hi, sparse=False)
    for a, b in zip(sparse, dense):
        assert torch.equal(a, b)
    with torch.no_grad():
        vm = torch.func.vmap(lambda a, b: model.interval_enclosure(a, b))(lo, hi)
        ref = model.interval_enclosure(lo, hi)
    for a, b in zip(vm, ref):
        assert torch.equal(a, b)


# ---------------------------------------------------------------- outside the domain
def test_box_leaving_domain_gives_nan_or_clamped_enclosure():
    model = _kuhn_2d()
    lo = torch.tensor([[1.5, -1.0], [-1.0, -1.0]])
    hi = torch.tensor([[2.5, 0.0], [1.0, 1.0]])  # the first leaves x0 <= 2
    vl, vh, jl, jh = model.interval_enclosure(lo, hi)  # outside="error": domain exit
    assert bool(vl[0].isnan().all() and jh[0].isnan().all())
    assert bool(torch.isfinite(vl[1]).all() and torch.isfinite(jh[1]).all())
    vl, vh, jl, jh = (t.detach() for t in model.interval_enclosure(lo, hi, outside="clamp"))
    x = lo[0] + torch.rand(4000, 2, generator=_gen(1), dtype=F64) * (hi[0] - lo[0])
    x = torch.cat([x, torch.tensor([[2.0, -1.0], [2.5, 0.0], [1.5, -1.0]])])
    y = model(x, outside="clamp").detach()
    assert bool((y >= vl[0]).all() and (y <= vh[0]).all())
    ref = _reference_2d(model, np.array([1.5, -1.0]), np.array([2.0, 0.0]))
    np.testing.assert_allclose(vl[0].numpy(), ref[0], atol=1e-9)
    np.testing.assert_allclose(vh[0].numpy(), ref[1], atol=1e-9)
    assert bool((jl[0, :, 0] <= 0).all() and (jh[0, :, 0] >= 0).all())  # clamped column: 0
    J = torch.func.vmap(torch.func.jacrev(lambda z: model(z, outside="clamp")))(x)
    assert bool((J >= jl[0]).all() and (J <= jh[0]).all())


def test_simplex_domain_exact_inside_and_nan_when_leaving():
    """A non-box domain (the enclosing simplex): exact inside, NaN for a box not inside."""
    g = _gen(11)
    X = torch.rand(1500, 2, generator=g, dtype=F64) * 2 - 1
    model, _ = fit_scplnn(X, torch.sin(2 * X[:, 0]) + X[:, 1] ** 2, eps=0.1, domain="simplex")
    assert not bool(model.box_domain)
    lo, hi = _random_boxes(2, 15, 12, -1.0, 1.0)  # the simplex contains the samples' box
    _assert_equal_ref(model, lo, hi, _reference_2d)
    V = model.vertices
    far = V[V[:, 0].argmax()]  # a corner of the domain simplex: boxes around it leave it
    out = model.interval_enclosure((far - 0.05)[None], (far + 0.05)[None], outside="clamp")
    assert all(bool(t.isnan().all()) for t in out)


def test_bad_boxes_raise_naming_the_argument():
    model = _kuhn_2d()
    with pytest.raises(ValueError, match="lo, hi"):
        model.interval_enclosure(torch.tensor([0.0, 1.0]), torch.tensor([0.5, 0.0]))
    with pytest.raises(ValueError, match="lo"):
        model.interval_enclosure(torch.zeros(3), torch.ones(3))
    with pytest.raises(ValueError, match="outside"):
        model.interval_enclosure(torch.zeros(2), torch.ones(2), outside="wrap")
    out = model.interval_enclosure(torch.tensor([0.0, 1.0]), torch.tensor([0.5, 0.0]),
                                   check=False)
    assert bool(out[0].isnan().all())


# ---------------------------------------------------------------- derivatives
def test_differentiable_in_bounds_and_weights():
    model = _fitted_2d(1)
    lo, hi = _random_boxes(2, 5, 2)
    lo.requires_grad_(True)
    hi.requires_grad_(True)
    vl, vh, jl, jh = model.interval_enclosure(lo, hi)
    (vh - vl).sum().add((jh - jl).sum()).backward()
    assert lo.grad is not None and bool(torch.isfinite(lo.grad).all())
    gw = model.weight.grad
    assert bool(torch.isfinite(gw).all()) and float(gw.abs().sum()) > 0
    # d(max over the box)/d(weights) equals the barycentric weights of the maximiser
    model.weight.grad = None
    vl, vh, _, _ = model.interval_enclosure(lo.detach(), hi.detach())
    vh[0, 0].backward()
    assert float(model.weight.grad[:, 0].sum()) == pytest.approx(1.0, abs=1e-9)


def test_first_order_jet_of_the_model():
    """The model inside the engine: a leaf whose Jacobian hull enters the chain rule; its
    Hessian enclosure is unbounded wherever the box meets more than one piece."""
    from diffsmf.linearize.jets import jet_eval
    from diffsmf.sets import Interval

    model = _fitted_2d(0)
    lo, hi = _random_boxes(2, 4, 8)
    M = torch.tensor([[0.5, 0.2], [-0.3, 0.4]])
    out = jet_eval(lambda x: model(0.5 * x @ M.T), Interval(lo, hi), order=1)
    assert out.shape == (4, 2) and out.grad.shape == (4, 2, 2)
    x = lo[:, None] + torch.rand(4, 500, 2, generator=_gen(0), dtype=F64) * (hi - lo)[:, None]
    J = torch.func.vmap(torch.func.jacrev(lambda z: model(0.5 * z @ M.T)))(x.reshape(-1, 2))
    J = J.reshape(4, 500, 2, 2)
    assert bool((J >= out.grad.lower[:, None]).all() and (J <= out.grad.upper[:, None]).all())
    H = jet_eval(model, Interval(lo, hi), order=2).hess
    assert H.shape == (4, 2, 2, 2)
