"""Soundness properties (hypothesis) of every outer-bounding zonotope/parallelotope operation.

Random sets in 2-5 D with generators of mixed scales (1e-2 .. 1e2). Each output must contain
points sampled in the inputs and their worst-case (extreme) points; for strip intersections the
points satisfying the strip, including the exact vertices of Z cap S on the strip boundary.
"""

import itertools

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import diffsmf as ds

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)


@st.composite
def zonotopes(draw, max_m=None):
    n = draw(st.integers(2, 5))
    # m >= n: full-dimensional (rank-deficient zonotopes use the slow LP membership test,
    # covered in test_zonotope.py)
    m = draw(st.integers(n, max_m if max_m is not None else 3 * n))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    scales = 10 ** (4 * torch.rand(m, generator=g) - 2)
    c = 10 * torch.randn(n, generator=g)
    G = torch.randn(n, m, generator=g) * scales
    return ds.Zonotope(c, G), g


def points(S, g, k=200):
    """Sampled interior points and extreme points of S -> [2k, n]."""
    return torch.cat([S.sample(k, generator=g), S.sample_extreme(k, generator=g)], 0)


def random_strip(Z, g, frac):
    n = Z.dim
    a = torch.randn(n, generator=g)
    mid = (a @ Z.center).item()
    rad = (Z.support(a) - a @ Z.center).item()
    y = mid + frac * rad
    return ds.Strip(a, y, 0.3 * rad + 1e-9), a.numpy(), y, 0.3 * rad + 1e-9


def zono_cut_vertices(c, G, a, y, h):
    m = G.shape[1]
    out = []
    for j in range(m):
        others = [i for i in range(m) if i != j]
        aj = a @ G[:, j]
        if abs(aj) < 1e-12 * np.abs(G[:, j]).sum():
            continue
        for s in itertools.product((-1.0, 1.0), repeat=m - 1):
            base = c + G[:, others] @ np.array(s)
            for level in (y - h, y + h):
                t = (level - a @ base) / aj
                if abs(t) <= 1:
                    out.append(base + t * G[:, j])
    return torch.as_tensor(np.array(out).reshape(-1, len(c)))


@SETTINGS
@given(zonotopes(), st.integers(1, 5))
def test_linear_map_is_sound(zg, k):
    Z, g = zg
    k = min(k, Z.dim)  # image stays full-dimensional
    A = torch.randn(k, Z.dim, generator=g)
    x = points(Z, g)
    assert Z.linear_map(A, torch.ones(k)).contains(x @ A.T + 1).all()


@SETTINGS
@given(zonotopes(), st.sampled_from(["zonotope", "interval", "parallelotope"]))
def test_minkowski_sum_is_sound(zg, kind):
    Z, g = zg
    n = Z.dim
    if kind == "zonotope":
        O = ds.Zonotope(torch.randn(n, generator=g), torch.randn(n, 2, generator=g))
    elif kind == "interval":
        lo = torch.randn(n, generator=g)
        O = ds.Interval(lo, lo + torch.rand(n, generator=g))
    else:
        O = ds.Parallelotope(torch.randn(n, generator=g), torch.randn(n, n, generator=g))
    S = Z.minkowski_sum(O)
    assert S.contains(points(Z, g) + points(O, g)).all()


@SETTINGS
@given(
    zonotopes(),
    st.sampled_from(["girard", "combastel", "pca", "chisci"]),
    st.sampled_from([1, 1.5, 2, 3]),
)
def test_reduce_is_sound(zg, method, order):
    Z, g = zg
    R = Z.reduce(order, method=method)
    assert R.num_generators <= max(int(order * Z.dim), Z.num_generators if R is Z else 0)
    assert R.contains(points(Z, g)).all()


@SETTINGS
@given(zonotopes())
def test_conversions_are_sound(zg):
    Z, g = zg
    x = points(Z, g)
    P = Z.to_parallelotope()
    assert P.contains(x).all()
    assert (P.volume() >= Z.volume() * (1 - 1e-9)).all()
    assert Z.to_interval().contains(x).all()
    assert Z.to_ellipsoid().contains(x).all()


@SETTINGS
@given(zonotopes(max_m=7), st.sampled_from(["fradius", "volume"]), st.floats(-1.2, 1.2))
def test_zonotope_strip_intersection_is_sound(zg, method, frac):
    Z, g = zg
    S, a, y, h = random_strip(Z, g, frac)
    R = Z.intersect_strip(S, method=method)
    assert torch.isfinite(R.generators).all() and R.num_generators == Z.num_generators + 1
    x = points(Z, g, 400)
    x = x[S.contains(x)]
    assert R.contains(x).all()
    V = zono_cut_vertices(Z.center.numpy(), Z.generators.numpy(), a, y, h)
    assert R.contains(V).all()


@SETTINGS
@given(zonotopes(), st.floats(-1.2, 1.2))
def test_parallelotope_strip_intersection_is_sound(zg, frac):
    Z, g = zg
    P = ds.Parallelotope(Z.center, torch.randn(Z.dim, Z.dim, generator=g))
    S, a, y, h = random_strip(P.to_zonotope(), g, frac)
    Q = P.intersect_strip(S)
    assert torch.isfinite(Q.T).all()
    x = points(P, g, 400)
    x = x[S.contains(x)]
    assert Q.contains(x).all()
    V = zono_cut_vertices(P.center.numpy(), P.T.numpy(), a, y, h)
    assert Q.contains(V).all()
