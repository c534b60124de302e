"""Tests of diffsmf.pwl: partitions, SCPLNN module, adaptive fit (Wang et al. 2009, sec. 3.1)."""

import json
import math

import pytest
import torch

from diffsmf.pwl import SCPLNN, fit_scplnn
from diffsmf.pwl.fit import fit_partition
from diffsmf.pwl.partition import (
    check_conforming,
    cone_partition,
    grid_partition,
    kuhn_simplices,
)

F64 = torch.float64




def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _f_seed(X):  # Wang et al. 2009 example: f(X) = -x1^2 x2
    return -X[..., 0] ** 2 * X[..., 1]


def _pwl_truth(X):
    """Continuous PWL with kinks on x0 = 0.5 and x_{i+1} = x_i (faces of the Kuhn grid with
    spacing 1/4): an independent closed form (max/abs of affine functions)."""
    f = (X[..., 0] - 0.5).abs() + 0.3 * X[..., -1]
    for i in range(X.shape[-1] - 1):
        f = f + (i + 1) * torch.clamp(X[..., i + 1] - X[..., i], min=0)
    return f


# ---------------------------------------------------------------- partitions
@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_cone_partition_conforming(n):
    lo, hi = -torch.ones(n, dtype=F64), 2 * torch.ones(n, dtype=F64)
    g = _gen(n)
    apex = lo + (hi - lo) * torch.rand(n, generator=g, dtype=F64)
    V, S = cone_partition(lo, hi, apex)
    assert S.shape[0] == 2 * n * math.factorial(n - 1)
    check_conforming(V, S)  # volumes sum to the box (scipy ConvexHull) and faces match
    # apex on a facet and at a corner: flat cones dropped, still a triangulation of the box
    apex2 = apex.clone()
    apex2[0] = hi[0]
    check_conforming(*cone_partition(lo, hi, apex2))
    if n > 1:
        check_conforming(*cone_partition(lo, hi, lo.clone()))


def test_kuhn_and_grid_partition():
    assert kuhn_simplices(3).shape == (6, 4)
    V, S = grid_partition(torch.zeros(3), torch.ones(3), [2, 1, 3])
    assert V.shape == (3 * 2 * 4, 3) and S.shape == (6 * 6, 4)
    check_conforming(V, S)


# ---------------------------------------------------------------- exactness and continuity
@pytest.mark.parametrize("n", [2, 3])
def test_exact_recovery_of_pwl_function(n):
    V, S = grid_partition(torch.zeros(n), torch.ones(n), 4)
    X = torch.rand(4000, n, generator=_gen(1), dtype=F64)
    model = fit_partition(X, _pwl_truth(X), V, S)
    Xt = torch.rand(2000, n, generator=_gen(2), dtype=F64)
    with torch.no_grad():
        err = (model(Xt)[:, 0] - _pwl_truth(Xt)).abs().max()
    assert float(err) < 1e-9
    assert float((model.weight.detach()[:, 0] - _pwl_truth(V)).abs().max()) < 1e-9


def _shared_faces(S):
    n1 = S.shape[1]
    faces = torch.cat([torch.cat([S[:, :j], S[:, j + 1:]], 1) for j in range(n1)]).sort(-1).values
    owner = torch.arange(S.shape[0]).repeat(n1)
    uniq, inv, counts = torch.unique(faces, dim=0, return_inverse=True, return_counts=True)
    order = torch.argsort(inv, stable=True)
    inv_s, own_s = inv[order], owner[order]
    first = torch.ones_like(inv_s, dtype=torch.bool)
    first[1:] = inv_s[1:] != inv_s[:-1]
    idx = first.nonzero().flatten()
    pairs = [(uniq[inv_s[i]], own_s[i], own_s[i + 1]) for i in idx.tolist()
             if counts[inv_s[i]] == 2]
    return pairs


@pytest.mark.parametrize("n", [2, 3])
def test_continuity_across_shared_faces(n):
    g = _gen(3)
    X = torch.rand(3000, n, generator=g, dtype=F64) * 2 - 1
    Y = torch.stack([torch.sin(2 * X.sum(-1)), X.pow(2).sum(-1)], -1)
    model, rep = fit_scplnn(X, Y, 0.05, max_regions=400)
    check_conforming(model.vertices, model.simplices)
    pairs = _shared_faces(model.simplices)
    assert len(pairs) > 50
    face = torch.stack([p[0] for p in pairs])
    s1 = torch.stack([p[1] for p in pairs])
    s2 = torch.stack([p[2] for p in pairs])
    w = torch.rand(len(pairs), n, generator=g, dtype=F64)
    w = w / w.sum(-1, keepdim=True)
    pts = (w[..., None] * model.vertices[face]).sum(1)  # random points of the shared faces
    with torch.no_grad():
        a, b = model.piece_eval(pts, s1), model.piece_eval(pts, s2)
    assert float((a - b).abs().max()) <= 1e-12
    # the regions' affine maps agree with forward inside each simplex
    R = model.regions()
    lam = torch.rand(model.n_regions, n + 1, generator=g, dtype=F64)
    lam = lam / lam.sum(-1, keepdim=True)
    inner = (lam[..., None] * R.vertices).sum(1)
    with torch.no_grad():
        ref = (R.A @ inner[..., None]).squeeze(-1) + R.b
        assert torch.allclose(model(inner), ref, atol=1e-11)


# ---------------------------------------------------------------- adaptive loop (Wang et al. 2009)
@pytest.mark.parametrize("eps", [0.1, 0.03, 0.01])
def test_adaptive_fit_reaches_eps_on_seed_function(eps):
    t = torch.linspace(-2, 2, 61, dtype=F64)
    X = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    model, rep = fit_scplnn(X, _f_seed(X), eps)
    assert rep.converged
    with torch.no_grad():
        err = (model(X)[:, 0] - _f_seed(X)).abs().max()  # independent of the report
    assert float(err) < eps
    assert abs(float(rep.max_error[0]) - float(err)) < 1e-12
    check_conforming(model.vertices, model.simplices)
    # held-out points between the samples: the error stays of the order of eps
    tm = (t[1:] + t[:-1]) / 2
    Xh = torch.stack(torch.meshgrid(tm, tm, indexing="ij"), -1).reshape(-1, 2)
    with torch.no_grad():
        held = (model(Xh)[:, 0] - _f_seed(Xh)).abs().max()
    assert float(held) < 10 * eps


def test_fit_with_known_vertex_values_and_region_bound():
    """vertex_fn + region_bound: interpolant of f split until a whole-simplex bound < eps; the
    bound (vertex mismatch 0 + (|Hess|/2) R^2, Hess f = 2 I) is checked on dense samples."""
    f = lambda X: (X ** 2).sum(-1, keepdim=True)  # noqa: E731

    def bound(V, W):  # [M, 3, 2], [M, 3, 1] -> [M, 1]
        mis = (f(V) - W).abs().amax(-2)
        d2 = (V[:, :, None] - V[:, None]).pow(2).sum(-1).amax((-1, -2))
        return mis + 1.0 * d2[:, None] / 3  # Jung: R^2 <= diam^2 / 3 in 2-D

    X = torch.rand(300, 2, generator=_gen(1), dtype=F64) * 2 - 1
    model, rep = fit_scplnn(X, f(X), 0.05, domain=(-torch.ones(2), torch.ones(2)),
                            vertex_fn=f, region_bound=bound, rule="edge")
    assert rep.converged and float(rep.bound_max) < 0.05
    check_conforming(model.vertices, model.simplices)
    assert torch.allclose(model.weight.detach(), f(model.vertices))
    Z = torch.rand(20000, 2, generator=_gen(2), dtype=F64) * 2 - 1
    with torch.no_grad():
        assert float((model(Z) - f(Z)).abs().max()) <= float(rep.bound_max)
    V = model.vertices[model.simplices]
    e = V[:, [1, 2, 0]] - V
    area = 0.5 * (e[:, 0, 0] * e[:, 1, 1] - e[:, 0, 1] * e[:, 1, 0]).abs()
    aspect = e.pow(2).sum(-1).amax(-1) / area
    assert float(aspect.max()) < 8  # diam^2 / area: 4 for the Kuhn right triangle


def test_fit_multi_output_eps_per_output_and_simplex_domain():
    X = torch.rand(1500, 3, generator=_gen(4), dtype=F64)
    Y = torch.stack([X.sum(-1) ** 2, torch.cos(2 * X[:, 0])], -1)
    eps = torch.tensor([0.05, 0.01], dtype=F64)
    model, rep = fit_scplnn(X, Y, eps, domain="simplex")
    assert not bool(model.box_domain)
    check_conforming(model.vertices, model.simplices)
    assert rep.converged and bool((rep.max_error < eps).all())
    with torch.no_grad():
        assert torch.allclose((model(X) - Y).abs().amax(0), rep.max_error)
    # beyond 5 inputs the domain defaults to an enclosing simplex
    X7 = torch.rand(100, 7, generator=_gen(5), dtype=F64)
    m7, r7 = fit_scplnn(X7, X7 @ torch.arange(7.0, dtype=F64), 0.1)
    assert not bool(m7.box_domain) and m7.n_regions == 1 and r7.converged


# ---------------------------------------------------------------- module API
def _small_model(seed=5):
    X = torch.rand(800, 2, generator=_gen(seed), dtype=F64) * 4 - 2
    model, _ = fit_scplnn(X, _f_seed(X), 0.2, domain=([-2, -2], [2, 2]))
    return model


def test_gradcheck_x_and_weight():
    model = _small_model()
    x = (torch.rand(5, 2, generator=_gen(6), dtype=F64) * 3 - 1.5).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: model(x), (x,))
    w0 = model.weight.detach().clone().requires_grad_(True)
    xd = x.detach()
    assert torch.autograd.gradcheck(
        lambda w: torch.func.functional_call(model, {"weight": w}, (xd,)), (w0,))
    y = model(x).sum()
    y.backward()
    assert model.weight.grad is not None and x.grad is not None


def test_batch_shapes_and_outside_policies():
    model = _small_model()
    x = torch.rand(3, 4, 2, generator=_gen(7), dtype=F64) * 4 - 2
    assert model(x).shape == (3, 4, 1)
    out = torch.tensor([[2.5, 0.0]], dtype=F64)
    with pytest.raises(ValueError, match="outside"):
        model(out)
    clamp = model(out, outside="clamp")
    assert torch.allclose(clamp, model(torch.tensor([[2.0, 0.0]], dtype=F64)))
    ext = model(out, outside="extrapolate")  # the boundary piece extended affinely
    s, _ = model.locate(out)
    assert torch.allclose(ext, model.piece_eval(out, s))
    with pytest.raises(ValueError, match="NaN"):
        model(torch.tensor([[float("nan"), 0.0]], dtype=F64))
    with pytest.raises(ValueError, match="x"):
        model(torch.zeros(3, dtype=F64))


def test_lipschitz_bound_valid_and_tight():
    model = _small_model()
    L = float(model.lipschitz_bound().detach())
    g = _gen(8)
    a = torch.rand(20000, 2, generator=g, dtype=F64) * 4 - 2
    b = (a + 0.05 * torch.randn(20000, 2, generator=g, dtype=F64)).clamp(-2, 2)
    with torch.no_grad():
        ratio = (model(a) - model(b)).norm(dim=-1) / (a - b).norm(dim=-1)
    assert float(ratio.max()) <= L * (1 + 1e-9)
    assert float(ratio.max()) >= 0.8 * L  # close to the bound (small steps inside pieces)


def test_interval_eval_contains_samples_and_vertices():
    model = _small_model()
    g = _gen(9)
    c = torch.rand(50, 2, generator=g, dtype=F64) * 3.6 - 1.8
    r = torch.rand(50, 2, generator=g, dtype=F64) * 0.4
    lo, hi = (c - r).clamp(-2, 2), (c + r).clamp(-2, 2)
    box = model.interval_eval((lo, hi))
    assert box.lower.shape == (50, 1)
    # worst case: box corners, plus the partition vertices lying in each box, plus samples
    u = torch.rand(50, 400, 2, generator=g, dtype=F64)
    corners = torch.stack([torch.where(torch.tensor([i & 1, i >> 1 & 1]).bool(), hi, lo)
                           for i in range(4)], 1)
    pts = torch.cat([lo[:, None] + u * (hi - lo)[:, None], corners], 1)
    with torch.no_grad():
        y = model(pts)  # [50, 404, 1]
        V = model.vertices[None]
        inb = ((V >= lo[:, None]) & (V <= hi[:, None])).all(-1)
        wv = model.weight.detach()[:, 0]
        vmin = torch.where(inb, wv, torch.inf).amin(-1)
        vmax = torch.where(inb, wv, -torch.inf).amax(-1)
    assert bool((y.amin(1) >= box.lower).all()) and bool((y.amax(1) <= box.upper).all())
    assert bool((vmin[:, None] >= box.lower).all()) and bool((vmax[:, None] <= box.upper).all())
    # the whole domain: exact range = min/max vertex value (up to the outward margin)
    whole = model.interval_eval((torch.tensor([-2.0, -2.0]), torch.tensor([2.0, 2.0])))
    assert abs(float(whole.lower.detach()[0]) - float(wv.min())) < 1e-7
    assert abs(float(whole.upper.detach()[0]) - float(wv.max())) < 1e-7
    with pytest.raises(ValueError, match="box"):
        model.interval_eval((torch.tensor([-3.0, 0.0]), torch.tensor([0.0, 1.0])))


def test_state_dict_json_roundtrip(tmp_path):
    model = _small_model()
    x = torch.rand(100, 2, generator=_gen(10), dtype=F64) * 4 - 2
    with torch.no_grad():
        y = model(x)
    other = SCPLNN(*grid_partition(torch.zeros(2), torch.ones(2), 1))  # 2 regions
    other.load_state_dict(model.state_dict())
    assert other.n_regions == model.n_regions
    with torch.no_grad():
        assert torch.equal(other(x), y)
        assert torch.equal(SCPLNN.from_state_dict(model.state_dict())(x), y)
    path = tmp_path / "m.pt"
    model.save(path)
    with torch.no_grad():
        assert torch.equal(SCPLNN.load(path)(x), y)
    text = json.dumps(model.to_json())
    back = SCPLNN.from_json(text)
    jpath = tmp_path / "m.json"
    jpath.write_text(text)
    with torch.no_grad():
        assert torch.equal(back(x), y)
        assert torch.equal(SCPLNN.from_json(jpath)(x), y)
    d = json.loads(text)
    A = torch.tensor(d["regions"][0]["A"])
    assert A.shape == (1, 2) and len(d["regions"]) == model.n_regions


# ---------------------------------------------------------------- max-min forms (eq. 12)
def test_maxmin_basis_equivalent_to_nodal_basis():
    V, S = grid_partition(torch.tensor([-2.0, -2.0]), torch.tensor([2.0, 2.0]), 3)
    X = torch.rand(500, 2, generator=_gen(11), dtype=F64) * 4 - 2
    Y = _f_seed(X) + 0.1 * torch.randn(500, generator=_gen(12), dtype=F64)
    nodal = fit_partition(X, Y, V, S)  # nodal (hat) basis, sparse normal equations
    Phi = nodal.maxmin_basis(X)  # eq. 12 max-min basis functions, no point location
    w = torch.linalg.lstsq(Phi, Y[:, None]).solution  # plain least squares in that basis
    Xt = torch.rand(300, 2, generator=_gen(13), dtype=F64) * 4 - 2
    with torch.no_grad():
        assert torch.allclose(nodal.maxmin_basis(Xt) @ w, nodal(Xt), atol=1e-9)
    X2 = torch.rand(800, 2, generator=_gen(5), dtype=F64) * 4 - 2
    interior, _ = fit_scplnn(X2, _f_seed(X2), 0.2, rule="interior")  # Wang et al. 2009 stellar
                                                                     # splits
    with pytest.raises(ValueError, match="star"):
        interior.maxmin_basis(Xt)


def test_lattice_form_matches_forward():
    X = torch.rand(300, 2, generator=_gen(14), dtype=F64) * 4 - 2
    model, _ = fit_scplnn(X, _f_seed(X), 1.0, domain=([-2, -2], [2, 2]))
    Xt = torch.rand(500, 2, generator=_gen(15), dtype=F64) * 4 - 2
    with torch.no_grad():
        assert torch.allclose(model.lattice_eval(Xt), model(Xt), atol=1e-10)


# ---------------------------------------------------------------- bad input
def test_bad_input():
    X = torch.rand(50, 2, generator=_gen(16), dtype=F64)
    Y = X.sum(-1)
    Xn = X.clone()
    Xn[3, 1] = float("nan")
    with pytest.raises(ValueError, match="X"):
        fit_scplnn(Xn, Y, 0.1)
    Yi = Y.clone()
    Yi[0] = float("inf")
    with pytest.raises(ValueError, match="Y"):
        fit_scplnn(X, Yi, 0.1)
    with pytest.raises(ValueError, match="eps"):
        fit_scplnn(X, Y, 0.0)
    with pytest.raises(ValueError, match="Y"):
        fit_scplnn(X, Y[:10], 0.1)
    with pytest.raises(ValueError, match="X"):
        fit_scplnn(X, Y, 0.1, domain=([0.5, 0.0], [1.0, 1.0]))
    with pytest.raises(ValueError, match="domain"):
        fit_scplnn(X, Y, 0.1, domain="sphere")


def test_few_samples_are_regularised():
    X = torch.tensor([[0.0, 0.0], [1.0, 0.2], [0.3, 1.0], [0.9, 0.9]], dtype=F64)
    Y = torch.tensor([0.0, 1.0, 3.0, -2.0], dtype=F64)
    model, rep = fit_scplnn(X, Y, 1e-6)
    assert rep.converged  # few samples: interpolated, unsampled vertices filled harmonically
    with torch.no_grad():
        grid = torch.rand(200, 2, generator=_gen(17), dtype=F64)
        assert torch.isfinite(model(grid)).all()
    with pytest.raises(ValueError, match="X"):  # one sample: no domain to infer
        fit_scplnn(X[:1], Y[:1], 0.1)
    m1, r1 = fit_scplnn(X[:1], Y[:1], 0.1, domain=([-1, -1], [1, 1]))  # given domain: constant
    assert r1.converged and float(r1.max_error[0]) < 1e-12
