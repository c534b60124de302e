"""diffsmf.linearize: point Jacobians, interval jets and guaranteed remainder bounds.

References are independent: central finite differences, analytic derivatives of quadratics,
autograd Hessians sampled over the box, dense sampling plus the vertices of each set.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import diffsmf as ds
from diffsmf.linearize import (
    dc_remainder,
    diagonal_shift,
    hessian,
    hessian_eig_lower_bound,
    interval_hessian,
    interval_jacobian,
    jacobian,
    jet_eval,
    lagrange_remainder,
    parameter_deviation,
    stirling_jacobian,
)
from diffsmf.linearize.jacobians import stirling_value_jacobian
from diffsmf.sets import Ellipsoid, Interval, Parallelotope, Zonotope

GEN = torch.Generator().manual_seed(1234)
U = torch.tensor([[0.3], [-0.2], [0.5]])  # a batched closure, as filters build fn


def smooth(x: torch.Tensor) -> torch.Tensor:
    """A smooth R^2 -> R^3 test map closing over a batched tensor U [3, 1]."""
    a, b = x[..., 0], x[..., 1]
    return torch.stack(
        [a * b**2 + U[..., 0], torch.sin(a) * torch.exp(0.5 * b), a / (2.0 + b**2) - b**3], -1
    )


def fd_jacobian(fn, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    cols = []
    for j in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[..., j] = h
        cols.append((fn(x + e) - fn(x - e)) / (2 * h))
    return torch.stack(cols, -1)


def test_jacobian_matches_finite_differences_with_batched_closure():
    x = torch.randn(3, 2, generator=GEN)
    J = jacobian(smooth, x)
    assert J.shape == (3, 3, 2)
    torch.testing.assert_close(J, fd_jacobian(smooth, x), atol=1e-8, rtol=1e-7)


def test_jacobian_broadcasts_unbatched_x_against_closure():
    x = torch.randn(2, generator=GEN)

    def fn(z):
        return torch.sin(z) * U  # broadcasts z [2] against U [3, 1] -> [3, 2]

    J = jacobian(fn, x)
    assert J.shape == (3, 2, 2)
    torch.testing.assert_close(J, torch.diag_embed(torch.cos(x) * U))


def test_hessian_matches_finite_differences_of_jacobian_and_is_symmetric():
    x = torch.randn(3, 2, generator=GEN)
    H = hessian(smooth, x)
    assert H.shape == (3, 3, 2, 2)
    ref = fd_jacobian(lambda z: jacobian(smooth, z), x)  # [3, k, n, n]
    torch.testing.assert_close(H, ref, atol=1e-7, rtol=1e-6)
    torch.testing.assert_close(H, H.mT)


def test_jacobian_and_hessian_are_differentiable():
    x = torch.randn(3, 2, generator=GEN, requires_grad=True)
    assert torch.autograd.gradcheck(lambda z: jacobian(smooth, z), (x,))
    assert torch.autograd.gradcheck(lambda z: hessian(smooth, z).sum(-1), (x,))


def test_stirling_exact_on_quadratics_for_any_step():
    A = torch.randn(2, 3, 3, generator=GEN)
    b = torch.randn(2, 3, generator=GEN)

    def quad(x):  # fn_i = x' A_i x + b_i . x
        return torch.einsum("...i,kij,...j->...k", x, A, x) + x @ b.T

    x = torch.randn(4, 3, generator=GEN)
    analytic = torch.einsum("kij,...j->...ki", A + A.mT, x) + b  # [4, 2, 3]
    for h in (1e-3, 0.7, torch.tensor([0.1, 2.0, 5.0])):
        torch.testing.assert_close(stirling_jacobian(quad, x, h), analytic, atol=1e-9, rtol=1e-9)


def test_stirling_value_jacobian_is_the_two_calls():
    """The filters' one-call form: fn(x) and the Stirling slopes, bit for bit those of
    ``fn(x)`` and `stirling_jacobian` (steps ``[n]`` or one per batch element)."""
    x = torch.randn(3, 2, generator=GEN)  # the batch of the closure U [3, 1]
    for h in (torch.tensor([0.1, 2.0]), torch.rand(3, 2, generator=GEN) + 0.1):
        fx, J = stirling_value_jacobian(smooth, x, h)
        assert torch.equal(fx, smooth(x))
        assert torch.equal(J, stirling_jacobian(smooth, x, h))


def test_stirling_differentiable_in_step_and_batched_steps():
    x = torch.randn(3, 2, generator=GEN)
    h = torch.tensor([0.3, 0.2], requires_grad=True)
    assert torch.autograd.gradcheck(lambda s: stirling_jacobian(smooth, x, s), (h,))
    hb = torch.rand(3, 2, generator=GEN) + 0.1  # one step per batch element

    def g(z):
        return torch.stack([z[..., 0] * z[..., 1] ** 2, torch.sin(z[..., 0]) * z[..., 1]], -1)

    S = stirling_jacobian(g, x, hb)
    for i in range(3):
        torch.testing.assert_close(S[i], stirling_jacobian(g, x[i], hb[i]))
    with pytest.raises(ValueError, match="h"):
        stirling_jacobian(smooth, x, 0.0)


# ------------------------------------------------------------------------- interval jets
def _encloses(I: Interval, pts: torch.Tensor) -> bool:
    return bool(((pts >= I.lower) & (pts <= I.upper)).all())


def all_ops(x):
    """Exercises every supported jet rule."""
    a, b = x[..., 0], x[..., 1]
    W = torch.tensor([[1.0, -2.0], [0.5, 3.0]])
    lin = F.linear(x, W, torch.tensor([0.1, 0.2])) + (x @ W.T) * 0.5
    parts = [
        torch.exp(a) - torch.log(b) * 2.0,
        torch.sqrt(b) / (1.0 + a**2) + torch.tanh(a) * torch.sigmoid(b),
        torch.atan(a * b) + torch.cos(b) ** 3 - (-a).abs() * b.reciprocal(),
        2.0**a + a**-2 + b**1.5 - torch.square(a - b),
    ]
    return torch.cat([torch.stack(parts, -1), lin, (x * x).sum(-1, keepdim=True)], -1)


def test_interval_jets_enclose_every_supported_op():
    c = torch.tensor([[0.7, 1.5], [1.2, 0.8]])
    box = Interval(c - 0.2, c + 0.25)
    out = jet_eval(all_ops, box)
    pts = box.sample(400, generator=GEN).movedim(-2, 0)  # [400, 2, 2]
    assert _encloses(out.val, all_ops(pts))
    assert _encloses(out.grad, jacobian(all_ops, pts))
    assert _encloses(out.hess, hessian(all_ops, pts))


def test_unsupported_op_raises_naming_it():
    box = Interval(torch.zeros(2), torch.ones(2))
    with pytest.raises(NotImplementedError, match="floor"):
        interval_hessian(lambda x: torch.floor(x) * x, box)


@pytest.mark.parametrize(
    "fn, match",
    [
        (lambda x: 0.9 * x.detach(), "detach"),
        (lambda x: x.float() * 2, "cast of the state"),
        (lambda x: x if x[..., 0] else -x, "reads a value of the state in Python"),
        (lambda x: x * float(x.sum()), "reads a value of the state in Python"),
    ],
)
def test_model_errors_in_jets_are_user_errors(fn, match):
    """What the engine cannot enclose raises a JetError (ValueError: one line in the CLI)."""
    from diffsmf.linearize import JetError

    box = Interval(torch.zeros(2), torch.ones(2))
    with pytest.raises(JetError, match=match) as info:
        interval_hessian(fn, box)
    assert isinstance(info.value, ValueError) and isinstance(info.value, NotImplementedError)


def test_domain_boundary_gives_the_enclosure_inside_the_domain():
    box = Interval(torch.tensor([[-0.5, 1.0], [0.5, 1.0]]), torch.tensor([[1.0, 2.0], [1.0, 2.0]]))
    out = jet_eval(lambda x: torch.sqrt(x), box)
    assert float(out.val.lower[0, 0]) == 0.0 and torch.isinf(out.grad.upper[0, 0]).any()
    assert torch.isfinite(out.val.lower[1]).all() and torch.isfinite(out.hess.lower[1]).all()


def _system_fns(sys):
    u = sys.input_at(0, 1)
    th = sys.theta_nominal
    return [lambda x: sys.f(x, u, th), sys.h]


@pytest.mark.parametrize("name", ["bilinear", "spring_damper", "mismatch_quadratic",
                                  "fermenter", "vdp", "radar"])
def test_interval_hessian_encloses_sampled_hessians_of_builtin_systems(name):
    sys = ds.systems.get(name)
    box = sys.x0_set.interval_hull()
    if name == "radar":  # range/bearing: keep the box away from the origin
        box = Interval(box.center - 0.1 * box.radius, box.center + 0.1 * box.radius)
    pts = box.sample(300, generator=GEN)  # [300, n]
    for fn in _system_fns(sys):
        H = interval_hessian(fn, box)
        J = interval_jacobian(fn, box)
        assert _encloses(H, hessian(fn, pts))
        assert _encloses(J, jacobian(fn, pts))


def test_eig_lower_bound_below_sampled_matrices():
    c = torch.randn(5, 3, 3, generator=GEN)
    c = c + c.mT
    r = torch.rand(5, 3, 3, generator=GEN)
    r = r + r.mT
    H = Interval(c - r, c + r)
    lam = hessian_eig_lower_bound(H)
    w = diagonal_shift(H)
    assert (w >= 0).all()
    for _ in range(50):
        t = torch.rand(5, 3, 3, generator=GEN)
        M = H.lower + (H.upper - H.lower) * (t + t.mT) / 2
        assert (torch.linalg.eigvalsh(M)[..., 0] >= lam).all()
        assert (torch.linalg.eigvalsh(M + 2 * torch.diag_embed(w))[..., 0] >= -1e-12).all()


# ------------------------------------------------------------------------- remainders
def bilin(x):
    """Wang et al. 2022, eq. 42 map plus a transcendental term; closes over a batched input."""
    u = torch.tensor([[0.6, 0.6]]).expand(4, 2)
    return torch.stack([0.5 * x[..., 0] * x[..., 1], 0.2 * x[..., 1] ** 2 + torch.sin(
        x[..., 0])], -1) + u


def _sets():
    c = torch.randn(4, 2, generator=GEN) * 0.5
    G = torch.randn(4, 2, 3, generator=GEN) * 0.2
    return {
        "interval": Interval(c - 0.2, c + 0.3),
        "zonotope": Zonotope(c, G),
        "parallelotope": Parallelotope(c, G[..., :2]),
        "ellipsoid": Ellipsoid(c, G @ G.mT + 0.01 * torch.eye(2)),
    }


METHODS = {
    "dc": dc_remainder,
    "lagrange": lagrange_remainder,
    "dc+lagrange": lambda *a: dc_remainder(*a, with_lagrange=True),
}


@pytest.mark.parametrize("set_name", ["interval", "zonotope", "parallelotope", "ellipsoid"])
def test_remainders_contain_sampled_and_vertex_errors(set_name):
    S = _sets()[set_name]
    pts = torch.cat([S.sample(2000, generator=GEN), S.sample_extreme(300, generator=GEN)], -2)
    if hasattr(S, "vertices"):
        pts = torch.cat([pts, S.vertices()], -2)
    pts = pts.movedim(-2, 0)  # [K, 4, 2]
    c = S.center + 0.02  # an expansion point off the centre
    for J in (jacobian(bilin, c), stirling_jacobian(bilin, c, 0.1)):
        err = bilin(pts) - bilin(c) - ((pts - c).unsqueeze(-2) * J).sum(-1)
        for name, rem in METHODS.items():
            R = rem(bilin, S, c, J)
            assert R.shape == (4, 2), name
            assert _encloses(R, err), f"{name} misses a point on {set_name}"


def test_dc_on_many_generator_zonotopes_planar_and_3d():
    def f3(x):
        return torch.stack([x[..., 0] * x[..., 1] * x[..., 2], torch.cos(x[..., 0] + x[..., 2]),
                            x[..., 1] ** 2 - x[..., 0]], -1)

    for n, fn in ((2, bilin), (3, f3)):
        Z = Zonotope(torch.randn(4, n, generator=GEN) * 0.3,
                     torch.randn(4, n, 10, generator=GEN) * 0.05)  # 2^10 > MAX_VERTICES
        pts = torch.cat([Z.sample(2000, generator=GEN), Z.sample_extreme(500, generator=GEN)],
                        -2).movedim(-2, 0)
        c = Z.center
        J = stirling_jacobian(fn, c, 0.05)
        err = fn(pts) - fn(c) - ((pts - c).unsqueeze(-2) * J).sum(-1)
        R = dc_remainder(fn, Z, c, J)
        assert _encloses(R, err)
        if n == 3:  # box-corner fallback is intersected with the Lagrange bound
            assert (R.width <= lagrange_remainder(fn, Z, c, J).width + 1e-15).all()


def test_dc_without_vertex_tangents_and_in_chunks_encloses_sampled_errors(monkeypatch):
    import diffsmf.linearize.dc as rem

    def f7(x):  # n = 7: 128 box corners, more than the vertex tangents are used for
        return torch.stack([torch.sin(x[..., 0] * x[..., 1]) + x[..., 6] ** 2,
                            x[..., 2] * x[..., 3] - torch.cos(x[..., 4] + x[..., 5])], -1)

    c = torch.randn(3, 7, generator=GEN) * 0.3
    S = Interval(c - 0.1, c + 0.15)
    pts = torch.cat([S.sample(3000, generator=GEN), S.sample_extreme(500, generator=GEN)],
                    -2).movedim(-2, 0)
    J = stirling_jacobian(f7, c, 0.05)
    err = f7(pts) - f7(c) - ((pts - c).unsqueeze(-2) * J).sum(-1)
    R = dc_remainder(f7, S, c, J)
    assert _encloses(R, err)
    assert (R.width <= 2 * lagrange_remainder(f7, S, c, J).width).all()  # a real bound
    # tangent planes at the 16 corners of a 4-D box, in one chunk and one point per chunk
    S4, c4 = Interval(c[..., :4] - 0.1, c[..., :4] + 0.2), c[..., :4]

    def f4(x):
        return f7(torch.cat([x, x[..., :3] * 0.5], -1))

    one = dc_remainder(f4, S4, c4, None)
    monkeypatch.setattr(rem, "_TANGENT_ELEMS", 1)
    many = dc_remainder(f4, S4, c4, None)
    assert torch.equal(one.lower, many.lower) and torch.equal(one.upper, many.upper)


def _f5(x):
    """A smooth R^n -> R^3 map of every coordinate (n >= 3)."""
    a, b, c = x[..., 0], x[..., 1], x[..., 2]
    rest = (x[..., 3:] ** 2).sum(-1)
    return torch.stack([a * b * c + torch.sin(rest), torch.exp(0.4 * a) * b - rest * c,
                        torch.cos(a + x[..., -1]) + c**3], -1)


def _vertex_tangent_cases():
    """Sets whose vertex tangents fill at least `_GEMM_MIN_PAIRS` (tangent, vertex) pairs: a
    5-D parallelotope (32 vertices) and a 3-D zonotope of 6 generators (64 sign vectors)."""
    c5 = torch.randn(2, 5, generator=GEN) * 0.3
    T5 = torch.randn(2, 5, 5, generator=GEN) * 0.06 + 0.12 * torch.eye(5)
    c3 = torch.randn(3, 3, generator=GEN) * 0.3
    G3 = torch.randn(3, 3, 6, generator=GEN) * 0.07
    return [Parallelotope(c5, T5), Zonotope(c3, G3)]


@pytest.mark.parametrize("case", [0, 1])
def test_dc_matrix_product_table_encloses_and_matches_the_broadcast_table(case, monkeypatch):
    """From 32 x 33 (tangent, vertex) pairs the eager table is a matrix product of the
    vertices' features and each tangent plane's coefficients; it encloses sampled and
    vertex errors, and it gives the broadcast table's bounds to rounding (both are padded)."""
    import diffsmf.linearize.dc as rem

    S = _vertex_tangent_cases()[case]
    c = S.center
    J = stirling_jacobian(_f5, c, 0.05)
    pts = torch.cat([S.sample(3000, generator=GEN), S.sample_extreme(1000, generator=GEN)],
                    -2).movedim(-2, 0)
    err = _f5(pts) - _f5(c) - ((pts - c).unsqueeze(-2) * J).sum(-1)
    calls = []
    gemm = rem._dc_bounds_gemm
    monkeypatch.setattr(rem, "_dc_bounds_gemm", lambda *a: calls.append(1) or gemm(*a))
    with torch.no_grad():
        R = dc_remainder(_f5, S, c, J)
        assert calls, "the matrix-product table was not used"
        assert _encloses(R, err)
        monkeypatch.setattr(rem, "_GEMM_MIN_PAIRS", 1 << 40)
        ref = dc_remainder(_f5, S, c, J)
    scale = ref.upper.abs().amax() + ref.lower.abs().amax()
    torch.testing.assert_close(R.lower, ref.lower, rtol=0, atol=1e-14 * float(scale))
    torch.testing.assert_close(R.upper, ref.upper, rtol=0, atol=1e-14 * float(scale))
    # and in chunks of one batch element
    monkeypatch.setattr(rem, "_GEMM_MIN_PAIRS", 1 << 10)
    monkeypatch.setattr(rem, "_GEMM_CHUNK_ELEMS", 1)
    with torch.no_grad():
        one = dc_remainder(_f5, S, c, J)
    assert torch.equal(one.lower, R.lower) and torch.equal(one.upper, R.upper)


def test_dc_matrix_product_table_while_traced_matches_eager(monkeypatch):
    """A compiled step takes the matrix-product table too (Dynamo with the eager backend):
    the same bounds as the eager call to rounding."""
    import diffsmf.linearize.dc as rem

    S = _vertex_tangent_cases()[0]
    J = stirling_jacobian(_f5, S.center, 0.05)

    def bounds(c, T):
        R = dc_remainder(_f5, Parallelotope(c, T), c, J)
        return R.lower, R.upper

    calls = []
    gemm = rem._dc_bounds_gemm
    monkeypatch.setattr(rem, "_dc_bounds_gemm", lambda *a: calls.append(1) or gemm(*a))
    with torch.no_grad():
        lo, up = bounds(S.center, S.T)
        n_eager = len(calls)
        tlo, tup = torch.compile(bounds, backend="eager", fullgraph=True)(S.center, S.T)
    assert n_eager == 1 and len(calls) == 2
    scale = float(up.abs().amax() + lo.abs().amax())
    torch.testing.assert_close(tlo, lo, rtol=0, atol=1e-14 * scale)
    torch.testing.assert_close(tup, up, rtol=0, atol=1e-14 * scale)
    # a large batch in small chunks: eagerly one chunk per element, while traced at most one
    # per tangent point (the chunks are unrolled in the graph)
    chunks = []
    chunk = rem._gemm_chunk
    monkeypatch.setattr(rem, "_gemm_chunk", lambda *a: chunks.append(1) or chunk(*a))
    monkeypatch.setattr(rem, "_GEMM_CHUNK_ELEMS", 1)
    c40 = S.center[:1].expand(40, 5) + 0.01 * torch.randn(40, 5, generator=GEN)
    T40 = S.T[:1].expand(40, 5, 5)
    J40 = stirling_jacobian(_f5, c40, 0.05)

    def bounds40(c, T):
        R = dc_remainder(_f5, Parallelotope(c, T), c, J40)
        return R.lower, R.upper

    with torch.no_grad():
        elo, eup = bounds40(c40, T40)
        assert len(chunks) == 40
        chunks.clear()
        tlo, tup = torch.compile(bounds40, backend="eager", fullgraph=True)(c40, T40)
    assert len(chunks) == 20  # 40 elements, at most 33 chunks: 2 per chunk
    torch.testing.assert_close(tlo, elo, rtol=0, atol=1e-14 * float(eup.abs().amax()))
    torch.testing.assert_close(tup, eup, rtol=0, atol=1e-14 * float(eup.abs().amax()))


def test_dc_matrix_product_table_gradcheck():
    # a generic parallelotope (a symmetric one ties vertices, where the bound has kinks)
    g = torch.Generator().manual_seed(3)
    c0 = (0.3 * torch.randn(1, 5, generator=g)).requires_grad_()
    T0 = (0.1 * torch.eye(5) + 0.03 * torch.randn(5, 5, generator=g)).unsqueeze(0)
    T0.requires_grad_()

    def bounds(c, T):
        R = dc_remainder(_f5, Parallelotope(c, T), c, stirling_jacobian(_f5, c, 0.05))
        return torch.cat([R.lower, R.upper], -1)

    assert torch.autograd.gradcheck(bounds, (c0, T0))


def test_value_and_jacobian_with_stacked_points_matches_jacobian():
    from diffsmf.linearize.jacobians import value_and_jacobian

    x = torch.randn(5, 3, 2, generator=GEN)  # [points, batch, n] against U [3, 1]
    for fn in (smooth, lambda z: smooth(z)[..., :1], lambda z: torch.cat([smooth(z)] * 2, -1)):
        y, J = value_and_jacobian(fn, x, points=True)
        torch.testing.assert_close(J, jacobian(fn, x), rtol=0, atol=0)
        torch.testing.assert_close(y, fn(x), rtol=0, atol=0)
    xg = x.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda z: value_and_jacobian(smooth, z, points=True)[1], (xg,))


def test_dc_is_exact_at_vertices_for_a_convex_quadratic_upper_bound():
    # r(x) = |x - c|^2 on a box: alpha = 0 and the DC upper bound is the max over vertices
    S = Interval(torch.tensor([0.0, 0.0]), torch.tensor([1.0, 2.0]))
    c = S.center
    R = dc_remainder(lambda x: (x**2).sum(-1, keepdim=True), S, c, None)
    torch.testing.assert_close(R.upper, torch.tensor([0.5**2 + 1.0**2]), atol=1e-12, rtol=0)
    torch.testing.assert_close(R.lower, torch.tensor([0.0]), atol=1e-12, rtol=0)


def test_linear_functions_give_zero_remainders():
    A = torch.randn(3, 2, generator=GEN)
    b = torch.randn(3, generator=GEN)

    def lin(x):
        return x @ A.T + b

    for S in _sets().values():
        c = S.center
        J = jacobian(lin, c)
        for rem in METHODS.values():
            R = rem(lin, S, c, J)
            assert R.lower.abs().max() < 1e-12 and R.upper.abs().max() < 1e-12
        dev = parameter_deviation(lambda x, u, th: x @ A[:2].T, S, Interval(torch.zeros(1),
                                                                             torch.ones(1)))
        assert dev.lower.abs().max() < 1e-12 and dev.upper.abs().max() < 1e-12


def test_remainders_gradcheck_wrt_zonotope_fields():
    c0 = torch.tensor([[0.3, -0.2]], requires_grad=True)
    G0 = torch.tensor([[[0.2, 0.05, 0.01], [-0.04, 0.15, 0.03]]], requires_grad=True)

    def fn(x):
        return torch.stack([x[..., 0] * x[..., 1] + torch.sin(x[..., 1]),
                            torch.exp(0.3 * x[..., 0]) * x[..., 1] ** 2], -1)

    for rem in (dc_remainder, lagrange_remainder):
        def bounds(c, G, rem=rem):
            R = rem(fn, Zonotope(c, G), c, stirling_jacobian(fn, c, 0.05))
            return torch.cat([R.lower, R.upper], -1)

        assert torch.autograd.gradcheck(bounds, (c0, G0))

    h0 = torch.tensor([0.05, 0.08], requires_grad=True)  # the Stirling step (a hyperparameter)
    Z = Zonotope(c0.detach(), G0.detach())

    def by_step(h):
        R = dc_remainder(fn, Z, Z.center, stirling_jacobian(fn, Z.center, h))
        return torch.cat([R.lower, R.upper], -1)

    assert torch.autograd.gradcheck(by_step, (h0,))


def test_parameter_deviation_contains_switching_mismatch():
    for name in ("mismatch_quadratic", "fermenter"):
        sys = ds.systems.get(name)
        box = sys.x0_set.interval_hull()
        S = Interval(box.center - 0.5 * box.radius, box.center + 0.5 * box.radius)
        P = sys.parameters
        dev = parameter_deviation(sys.f, S, P)
        xs = S.sample(500, generator=GEN)
        th = torch.cat([P.vertices(), P.sample(50, generator=GEN)], 0)  # [T, q]
        d = sys.f(xs.unsqueeze(0), None, th.unsqueeze(1)) - sys.f(xs, None, P.center)
        assert _encloses(dev, d), name
        # the mean-value form is close to the exact range (tight in the parameter direction)
        assert (dev.width <= 1.5 * (d.amax((0, 1)) - d.amin((0, 1))) + 1e-9).all(), name


def test_parameter_deviation_gradcheck_wrt_set_and_parameter_bounds():
    sys = ds.systems.get("fermenter")
    c0 = (sys.paper_x0 + 0.1).unsqueeze(0).requires_grad_()
    G0 = torch.tensor([[[0.2, 0.05], [-0.04, 0.15], [0.1, 0.02]]], requires_grad=True)
    lo0 = sys.parameters.lower.clone().requires_grad_()
    hi0 = sys.parameters.upper.clone().requires_grad_()

    def dev(c, G, lo, hi):
        D = parameter_deviation(sys.f, Zonotope(c, G), Interval(lo, hi))
        return torch.cat([D.lower, D.upper], -1)

    assert torch.autograd.gradcheck(dev, (c0, G0, lo0, hi0))


def test_remainder_bad_input():
    S = Interval(torch.zeros(2), torch.ones(2))
    with pytest.raises(ValueError, match="c"):
        dc_remainder(bilin, S, torch.zeros(3), None)
    with pytest.raises(ValueError, match="params"):
        parameter_deviation(lambda x, u, th: x, S, torch.zeros(1))
