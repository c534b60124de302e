"""The default fit (conforming longest-edge bisection + held-out
samples) controls the error between samples, reaches eps in 4-D, and does not depend on the
thread count. References: exact function values on grids, scipy's LinearNDInterpolator."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from diffsmf.pwl import fit_scplnn
from diffsmf.pwl.fit import default_max_regions
from diffsmf.pwl.partition import BisectionRefiner, check_conforming, grid_partition

F64 = torch.float64




def _peak(Z):  # smooth 2-D function with a peak (the benchmark's, docs/pwl.md)
    return torch.exp(-3 * (Z ** 2).sum(-1))


def _grid(lo, hi, k, X=None):
    t = torch.linspace(lo, hi, k, dtype=F64)
    G = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    if X is not None:  # inside the samples' bounding box (every method's domain)
        G = torch.maximum(torch.minimum(G, X.amax(0)), X.amin(0))
    return G


def _min_angle(V, S):
    """Smallest interior angle (degrees) of 2-D triangles V[S]."""
    P = V[S]
    ang = []
    for i in range(3):
        a, b, c = P[:, i], P[:, (i + 1) % 3], P[:, (i + 2) % 3]
        u, v = b - a, c - a
        cos = (u * v).sum(-1) / (u.norm(dim=-1) * v.norm(dim=-1))
        ang.append(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))))
    return float(torch.stack(ang).min())


def test_bisection_refiner_conforming_and_shape_regular():
    """Random longest-edge bisections of a Kuhn square stay conforming, never below 45/2
    degrees (Rivara: at least half the initial minimum angle), and refining a cube in 3-D
    stays conforming too."""
    for n, steps in ((2, 400), (3, 150)):
        V, S = grid_partition(torch.zeros(n), torch.ones(n), 1)
        ref = BisectionRefiner(V, S)
        rng = np.random.default_rng(n)
        for _ in range(steps):
            live = ref.live
            ref.refine(int(live[rng.integers(len(live))]))
        check_conforming(ref.V, ref.S)  # scipy ConvexHull volume + shared faces
        if n == 2:
            assert _min_angle(ref.V, ref.S) >= 22.5 - 1e-9


def test_peak_heldout_close_to_eps_and_beats_delaunay_interpolation():
    """On the peak function, the fit's error on a dense grid between the samples stays within
    2x eps, the held-out estimate in the report is of that order, and it is as accurate as
    LinearNDInterpolator on all samples with far fewer vertices."""
    from scipy.interpolate import LinearNDInterpolator

    X = torch.rand(3000, 2, generator=torch.Generator().manual_seed(0), dtype=F64) * 4 - 2
    eps = 0.01
    model, rep = fit_scplnn(X, _peak(X), eps)
    assert rep.converged and rep.heldout_samples == 300
    G = _grid(-2, 2, 101, X)
    with torch.no_grad():
        err = float((model(G)[:, 0] - _peak(G)).abs().max())
    assert err <= 2.2 * eps
    assert float(rep.heldout_max_error[0]) <= 2 * eps
    lnd = LinearNDInterpolator(X.numpy(), _peak(X).numpy())(G.numpy())
    ok = np.isfinite(lnd)
    lnd_err = float(np.abs(lnd[ok] - _peak(G).numpy()[ok]).max())
    assert err <= 1.05 * lnd_err and rep.vertices <= len(X) / 5
    check_conforming(model.vertices, model.simplices)
    assert _min_angle(model.vertices, model.simplices) >= 22.5 - 1e-9


def test_old_rule_slivers_vs_bisection():
    """The stellar rule (Wang et al. 2009 interior splits) leaves thin triangles; bisection does
    not."""
    X = torch.rand(2000, 2, generator=torch.Generator().manual_seed(1), dtype=F64) * 4 - 2
    m_old, _ = fit_scplnn(X, _peak(X), 0.02, rule="interior")
    m_new, _ = fit_scplnn(X, _peak(X), 0.02)
    assert _min_angle(m_new.vertices, m_new.simplices) > 2 * _min_angle(m_old.vertices,
                                                                        m_old.simplices)


@pytest.mark.parametrize("d", [3, 4])
def test_sum_of_sines_reaches_eps_in_higher_dimensions(d):
    """sum_i sin x_i on [-1, 1]^d, eps 0.05 (d = 5 is in the benchmark: 15 s)."""
    g = torch.Generator().manual_seed(d)
    N = 20_000 if d == 4 else 8000
    X = torch.rand(N, d, generator=g, dtype=F64) * 2 - 1
    f = lambda Z: torch.sin(Z).sum(-1)  # noqa: E731
    model, rep = fit_scplnn(X, f(X), 0.05)
    assert rep.converged and float(rep.max_error[0]) < 0.05
    assert rep.regions <= default_max_regions(d)
    Xt = torch.rand(5000, d, generator=g, dtype=F64) * 2 - 1
    Xt = torch.maximum(torch.minimum(Xt, X.amax(0)), X.amin(0))
    with torch.no_grad():
        err = (model(Xt)[:, 0] - f(Xt)).abs()
    assert float(err.max()) < 3 * 0.05 and float(err.pow(2).mean().sqrt()) < 0.02
    with torch.no_grad():  # the reported training error is the model's, at every sample
        assert float((model(X)[:, 0] - f(X)).abs().max()) == pytest.approx(
            float(rep.max_error[0]), abs=1e-12)


def test_seed_function_eps_001_converges_on_grid_samples():
    """61x61 grid samples of -x1^2 x2 at eps 0.01 (samples on vertices and edges of
    the mesh) converge; grid samples lying on a face mark every region sharing that face."""
    t = torch.linspace(-2, 2, 61, dtype=F64)
    X = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    y = -X[:, 0] ** 2 * X[:, 1]
    model, rep = fit_scplnn(X, y, 0.01)
    assert rep.converged and rep.rounds < 60
    with torch.no_grad():
        assert float((model(X)[:, 0] - y).abs().max()) < 0.01


def _fingerprint(threads):
    torch.set_num_threads(threads)
    X = torch.rand(3000, 2, generator=torch.Generator().manual_seed(2), dtype=F64) * 4 - 2
    model, rep = fit_scplnn(X, -X[:, 0] ** 2 * X[:, 1], 0.03)
    return rep.regions, model.weight.detach().clone()


def test_fit_independent_of_thread_count():
    old = torch.get_num_threads()
    try:
        r1, w1 = _fingerprint(1)
        r2, w2 = _fingerprint(2)
    finally:
        torch.set_num_threads(old)
    assert r1 == r2 and torch.equal(w1, w2)
    code = ("import torch; from diffsmf.pwl import fit_scplnn; F64 = torch.float64; "
            "X = torch.rand(3000, 2, generator=torch.Generator().manual_seed(2), dtype=F64) "
            "* 4 - 2; m, r = fit_scplnn(X, -X[:, 0] ** 2 * X[:, 1], 0.03); "
            "print(r.regions, repr(float(m.weight.detach().double().sum())))")
    env = dict(os.environ, OMP_NUM_THREADS="2", MKL_NUM_THREADS="2")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120, check=True).stdout.split()
    assert int(out[0]) == r1 and float(out[1]) == float(w1.sum())


def test_certified_bound_with_bisection_rule():
    """vertex_fn + region_bound with the default rule: converged, the bound holds on dense
    samples, and the mesh stays shape-regular."""
    f = lambda X: (X ** 2).sum(-1, keepdim=True)  # noqa: E731

    def bound(V, W):  # vertex mismatch (0) + (|Hess|/2) R^2 with R^2 <= diam^2 / 3 in 2-D
        d2 = (V[:, :, None] - V[:, None]).pow(2).sum(-1).amax((-1, -2))
        return (f(V) - W).abs().amax(-2) + d2[:, None] / 3

    X = torch.rand(300, 2, generator=torch.Generator().manual_seed(1), dtype=F64) * 2 - 1
    model, rep = fit_scplnn(X, f(X), 0.05, domain=(-torch.ones(2), torch.ones(2)),
                            vertex_fn=f, region_bound=bound)
    assert rep.converged and float(rep.bound_max) < 0.05
    Z = torch.rand(20000, 2, generator=torch.Generator().manual_seed(2), dtype=F64) * 2 - 1
    with torch.no_grad():
        assert float((model(Z) - f(Z)).abs().max()) <= float(rep.bound_max)
    assert _min_angle(model.vertices, model.simplices) >= 22.5 - 1e-9
    assert math.isfinite(float(rep.heldout_max_error[0]))
