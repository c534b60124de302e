"""diffsmf.linalg: closed forms vs LAPACK (torch.linalg / numpy), gradients, degenerate cases."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from diffsmf import linalg
from diffsmf.sets.outer_parallelotope import _best_basis
from diffsmf.utils import traced


def _rand(n: int, batch: int = 50, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, n, n, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_det_matches_numpy(n: int) -> None:
    M = _rand(n)
    ref = np.linalg.det(M.numpy())
    np.testing.assert_allclose(linalg.det(M).numpy(), ref, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_solve_matches_numpy(n: int) -> None:
    A = _rand(n) + 3 * torch.eye(n, dtype=torch.float64)
    B = torch.randn(50, n, 4, dtype=torch.float64)
    ref = np.linalg.solve(A.numpy(), B.numpy())
    np.testing.assert_allclose(linalg.solve(A, B).numpy(), ref, rtol=1e-11, atol=1e-13)


def test_solve_broadcasts_like_torch() -> None:
    A = _rand(2, batch=6).reshape(2, 3, 2, 2) + 3 * torch.eye(2, dtype=torch.float64)
    B = torch.randn(3, 2, 5, dtype=torch.float64)
    torch.testing.assert_close(linalg.solve(A, B), torch.linalg.solve(A, B))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_eigvalsh_matches_numpy(n: int) -> None:
    M = _rand(n)
    S = M + M.mT
    ref = np.linalg.eigvalsh(S.numpy())
    np.testing.assert_allclose(linalg.eigvalsh(S).numpy(), ref, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_eigh_matches_numpy(n: int) -> None:
    """Eigenpairs against numpy's LAPACK ``eigh``, degenerate 2 x 2 cases included: a double
    eigenvalue, the zero matrix, diagonal with a < d, a negative off-diagonal, a matrix with
    a = d (theta = +-pi / 4). Eigenvectors are compared up to sign (projectors), except at the
    double eigenvalue, where any orthonormal basis is right."""
    M = _rand(n)
    S = M + M.mT
    if n == 2:
        extra = torch.tensor(
            [[[2.0, 0.0], [0.0, 2.0]], [[0.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, 3.0]],
             [[1.0, -0.5], [-0.5, 2.0]], [[1.0, 0.7], [0.7, 1.0]], [[1.0, -1e-12], [-1e-12, 1.0]]],
            dtype=torch.float64,
        )
        S = torch.cat([S, extra])
    lam, V = linalg.eigh(S)
    ref_l, ref_V = np.linalg.eigh(S.numpy())
    np.testing.assert_allclose(lam.numpy(), ref_l, rtol=1e-12, atol=1e-13)
    eye = torch.eye(n, dtype=torch.float64)
    torch.testing.assert_close(V.mT @ V, eye.expand_as(V), rtol=0, atol=1e-14)
    torch.testing.assert_close(V @ torch.diag_embed(lam) @ V.mT, S, rtol=1e-13, atol=1e-13)
    simple = (np.diff(ref_l, axis=-1) > 1e-6).all(-1) if n > 1 else np.ones(len(S), bool)
    P = torch.einsum("...ai,...bi->...iab", V, V)  # projector v_i v_i' per eigenvector i
    Pr = torch.einsum("...ai,...bi->...iab", *(torch.as_tensor(ref_V),) * 2)
    torch.testing.assert_close(P[simple], Pr[simple], rtol=0, atol=1e-10)


def test_eigvalsh_double_eigenvalue_and_gradient() -> None:
    S = torch.tensor([[2.0, 0.0], [0.0, 2.0]], dtype=torch.float64, requires_grad=True)
    lam = linalg.eigvalsh(S)
    torch.testing.assert_close(lam, torch.tensor([2.0, 2.0], dtype=torch.float64))
    (g,) = torch.autograd.grad(lam.sum(), S)
    assert torch.isfinite(g).all()
    torch.testing.assert_close(g, torch.eye(2, dtype=torch.float64))  # d trace / dS


def test_gradcheck_closed_forms() -> None:
    A = (_rand(2, batch=3) + 3 * torch.eye(2, dtype=torch.float64)).requires_grad_()
    B = torch.randn(3, 2, 2, dtype=torch.float64, requires_grad=True)
    M3 = _rand(3, batch=3).requires_grad_()
    S = _rand(2, batch=3)
    S = (S + S.mT + torch.tensor([[0.0, 0.0], [0.0, 1.0]], dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(linalg.solve, (A, B))
    assert torch.autograd.gradcheck(linalg.det, (M3,))
    assert torch.autograd.gradcheck(linalg.det, (A,))
    assert torch.autograd.gradcheck(lambda s: linalg.eigvalsh(0.5 * (s + s.mT)), (S,))


def test_singular_solve_is_not_finite() -> None:
    A = torch.tensor([[1.0, 2.0], [2.0, 4.0]], dtype=torch.float64)
    X = linalg.solve(A, torch.ones(2, 1, dtype=torch.float64))
    assert not torch.isfinite(X).all()


@pytest.mark.parametrize("fn", [linalg.det, linalg.eigvalsh])
def test_non_square_raises(fn) -> None:
    with pytest.raises(ValueError, match="square"):
        fn(torch.zeros(2, 3))


def test_solve_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="B: expected"):
        linalg.solve(torch.eye(2), torch.ones(3, 1))


def test_basis_tie_rule_is_deterministic() -> None:
    """Symmetric generators: several bases give the same |det T|; the lexicographically first
    one must win however the last bits fall (a 1-ulp perturbation of the entries)."""
    G = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]], dtype=torch.float64)  # all 3 bases: 4
    base, ok = _best_basis(G)
    assert bool(ok) and base.tolist() == [0, 1]
    eps = torch.finfo(torch.float64).eps
    g = torch.Generator().manual_seed(3)
    for _ in range(20):
        noise = 1 + eps * torch.randint(-2, 3, G.shape, generator=g).to(torch.float64)
        pert, _ = _best_basis(G * noise)
        assert pert.tolist() == base.tolist()


@pytest.mark.parametrize("shape_a,shape_b", [((5, 2, 3), (5, 3, 1)), ((3, 3), (4, 3, 2)),
                                             ((2, 4, 4), (4, 4)), ((6, 5), (5, 2)),
                                             ((9, 2), (7, 2, 2)), ((3, 9), (7, 9, 2)),
                                             ((9, 8), (8, 2)), ((7, 1, 40), (40, 1))])
def test_matmul_matches_operator(shape_a, shape_b) -> None:
    g = torch.Generator().manual_seed(1)
    A = torch.randn(*shape_a, generator=g, dtype=torch.float64)
    B = torch.randn(*shape_b, generator=g, dtype=torch.float64)
    # both paths: multiply-and-sum (at most SMALL_MATMUL_ELEMS products per matrix, e.g. the
    # axis points [9, 2] x [..., 2, 2], a 40-long contraction) and BLAS ([9, 8] x [8, 2])
    torch.testing.assert_close(linalg.matmul(A, B), A @ B, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize(
    "shape_a,shape_b", [((5, 2, 2), (5, 2, 24)), ((4, 2), (7, 2, 2)), ((3, 6, 4), (4, 3)),
                        ((3, 2, 8), (3, 8, 2))],
)
def test_traced_matmul_is_the_operator_eagerly_and_close_when_traced(shape_a, shape_b) -> None:
    """Eagerly ``traced_matmul`` is ``@`` bit for bit (the audited sets); traced, the multiply-
    and-sum (inner dimension <= SMALL_MATMUL_MAX) or ``@`` (the [.., 8] x [8, ..] case) agree
    with ``@`` to rounding, and so do their gradients."""
    g = torch.Generator().manual_seed(4)
    A = torch.randn(*shape_a, generator=g, dtype=torch.float64, requires_grad=True)
    B = torch.randn(*shape_b, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.equal(linalg.traced_matmul(A, B), A @ B)
    traced = torch.compile(linalg.traced_matmul, backend="eager", fullgraph=True)
    out = traced(A, B)
    torch.testing.assert_close(out, A @ B, rtol=1e-14, atol=1e-14)
    w = torch.randn(out.shape, generator=g, dtype=torch.float64)
    ga = torch.autograd.grad((out * w).sum(), (A, B))
    gb = torch.autograd.grad(((A @ B) * w).sum(), (A, B))
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_cholesky_and_solves_match_numpy(n: int) -> None:
    """Closed forms (n <= 2) and the LAPACK fallback (n = 3) against numpy / scipy, including
    an ill-conditioned SPD matrix (condition 1e12)."""
    import scipy.linalg

    A = _rand(n, seed=5)
    S = A @ A.mT + 1e-3 * torch.eye(n, dtype=A.dtype)
    S[0] = torch.diag(torch.logspace(0, -12, n, dtype=A.dtype)) if n > 1 else S[0]
    B = torch.randn(50, n, 3, dtype=A.dtype, generator=torch.Generator().manual_seed(6))
    L = linalg.cholesky(S)
    np.testing.assert_allclose(L.numpy(), np.linalg.cholesky(S.numpy()), rtol=1e-12, atol=1e-15)
    for i in range(50):
        Li, Bi = L[i].numpy(), B[i].numpy()
        ref = scipy.linalg.solve_triangular(Li, Bi, lower=True)
        np.testing.assert_allclose(linalg.solve_lower(L[i], B[i]).numpy(), ref, rtol=1e-10)
        ref = scipy.linalg.cho_solve((Li, True), Bi)
        np.testing.assert_allclose(linalg.cholesky_solve(B[i], L[i]).numpy(), ref, rtol=1e-9)


def test_cholesky_not_positive_definite_is_nan_and_gradcheck() -> None:
    """A matrix that is not positive definite gives NaN (no exception); the closed forms are
    differentiable (gradcheck in float64)."""
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64)
    assert torch.isnan(linalg.cholesky(bad)).any()
    A = _rand(2, batch=3, seed=7)
    S = (A @ A.mT + torch.eye(2, dtype=A.dtype)).requires_grad_(True)
    B = torch.randn(3, 2, 2, dtype=A.dtype, requires_grad=True)
    assert torch.autograd.gradcheck(lambda S: linalg.cholesky(0.5 * (S + S.mT)), (S,))
    assert torch.autograd.gradcheck(
        lambda S, B: linalg.cholesky_solve(B, linalg.cholesky(0.5 * (S + S.mT))), (S, B)
    )
    with pytest.raises(ValueError, match="B"):
        linalg.solve_lower(torch.eye(2, dtype=A.dtype), torch.ones(3, 1, dtype=A.dtype))


@pytest.mark.parametrize("max_inner,inner,fused", [
    (linalg.SMALL_MATMUL_MAX, 8, False), (None, 8, True), (None, 79, True), (2, 3, False),
    (2, 2, True),
])
def test_traced_matmul_max_inner_picks_the_fused_product(
    monkeypatch, max_inner, inner, fused
) -> None:
    """``max_inner`` bounds the inner dimension fused while traced (``None``: any, as the
    constrained-zonotope LP's ``A D A'`` uses); eagerly it is always ``@`` bit for bit."""
    g = torch.Generator().manual_seed(5)
    A = torch.randn(6, 3, inner, generator=g, dtype=torch.float64)
    B = torch.randn(6, inner, 4, generator=g, dtype=torch.float64)
    calls = []
    mul_sum = linalg._mul_sum
    monkeypatch.setattr(linalg, "_mul_sum", lambda a, b: calls.append(1) or mul_sum(a, b))
    assert torch.equal(linalg.traced_matmul(A, B, max_inner=max_inner), A @ B)
    assert not calls
    with traced():
        out = linalg.traced_matmul(A, B, max_inner=max_inner)
    assert len(calls) == int(fused)
    torch.testing.assert_close(out, A @ B, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("k", [2, 3, 4, 5])
@pytest.mark.parametrize("dim", [-1, -2])
def test_small_sum_same_bits_as_sum(k: int, dim: int) -> None:
    g = torch.Generator().manual_seed(k)
    scales = torch.logspace(-8, 8, k, dtype=torch.float64)
    for batch in (1, 3000):  # the plain sum, then the unrolled adds
        x = torch.randn(batch, k, k, generator=g, dtype=torch.float64) * scales
        for keep in (False, True):
            ref = x.sum(dim, keepdim=keep)
            out = linalg.small_sum(x, dim, keepdim=keep)
            assert out.shape == ref.shape and torch.equal(out, ref)


_SHAPES = st.lists(st.lists(st.integers(0, 3), max_size=4).map(tuple), min_size=1, max_size=4)


@settings(max_examples=300, deadline=None)
@given(_SHAPES)
def test_broadcast_shapes_agrees_with_torch(shapes):
    """`diffsmf.utils.broadcast_shapes` (plain Python, used on every eager step) gives
    ``torch.broadcast_shapes``'s result, and raises where it raises."""
    from diffsmf.utils import broadcast_shapes

    try:
        ref = torch.broadcast_shapes(*shapes)
    except RuntimeError:
        with pytest.raises(RuntimeError, match="cannot be broadcast"):
            broadcast_shapes(*shapes)
        return
    got = broadcast_shapes(*shapes)
    assert type(got) is torch.Size and got == ref


@pytest.mark.parametrize("sa,sb", [((4, 1, 6, 6), (65, 64, 1, 1, 1, 6)),  # einsum, broadcast
                                   ((3000, 5), (5,)),  # einsum, one operand shared
                                   ((2, 7), (3, 1, 7)),  # small: product and sum
                                   ((40, 1, 3), (1, 500, 3))])  # n <= 4: unrolled
def test_small_dot_matches_numpy(sa, sb) -> None:
    """`linalg.small_dot` on every path (product and sum, unrolled, einsum) against numpy's
    broadcast product and sum, to the rounding of n terms; the gradient flows."""
    g = torch.Generator().manual_seed(2)
    a = torch.randn(sa, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(sb, generator=g, dtype=torch.float64)
    out = linalg.small_dot(a, b)
    ref = (a.detach().numpy() * b.numpy()).sum(-1)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-13, atol=1e-13)
    (grad,) = torch.autograd.grad(out.sum(), a)
    (gref,) = torch.autograd.grad((a * b).sum(), a)
    torch.testing.assert_close(grad, gref, rtol=1e-12, atol=1e-12)


def _least_basis_volume(G: np.ndarray) -> tuple[float, dict]:
    """numpy brute force: |det T| of Chisci's parallelotope for every regular basis."""
    n, m = G.shape
    vols = {}
    for S in itertools.combinations(range(m), n):
        B = G[:, S]
        d = abs(np.linalg.det(B))
        if d > 1e-12 * np.prod(np.linalg.norm(B, axis=0)):
            vols[S] = d * np.abs(np.linalg.solve(B, G)).sum(1).prod()
    return min(vols.values()), vols


@pytest.mark.parametrize("n,m", [(4, 4), (4, 7), (5, 9), (6, 12), (8, 10)])
def test_best_basis_cramer_is_least_volume(n: int, m: int) -> None:
    """From n = 4 the basis search reads every basis' volume from determinants (Cramer's
    rule). Against a numpy brute force of determinants and solves: the chosen basis has the
    least volume (to 1e-9), rank-deficient and repeated generators included, and a batch
    gives each element its own answer."""
    g = torch.Generator().manual_seed(n * m)
    G = torch.randn(6, n, m, generator=g, dtype=torch.float64)
    G[1, :, 1] = G[1, :, 0]  # a repeated generator (singular when m = n)
    G[2, :, : m - n + 1] *= 1e-7  # short generators
    G[3] = G[3, :, :1] * torch.arange(1.0, m + 1, dtype=torch.float64)  # rank 1
    best, ok = _best_basis(G)
    assert best.shape == (6, n) and ok.tolist() == [True, m > n, True, False, True, True]
    for b in (0, 1, 2, 4, 5) if m > n else (0, 2, 4, 5):
        least, vols = _least_basis_volume(G[b].numpy())
        assert vols[tuple(best[b].tolist())] == pytest.approx(least, rel=1e-9)
        one, _ = _best_basis(G[b])
        assert one.tolist() == best[b].tolist()


@pytest.mark.parametrize("n,m", [(4, 7), (6, 12)])
def test_cramer_volumes_sparse_sum_matches_the_gathered_table(n: int, m: int, monkeypatch):
    """The eager CPU search sums each basis' exchanged determinants by a sparse 0/1 matrix
    product; the volumes equal the gathered table's to rounding, in one chunk and in chunks
    of one batch column, and the numpy brute force's (`_least_basis_volume`)."""
    from diffsmf.sets import combinatorics
    from diffsmf.sets import outer_parallelotope as zono

    g = torch.Generator().manual_seed(n + 3 * m)
    G = torch.randn(5, n, m, generator=g, dtype=torch.float64)
    idx = zono._combinations(m, n)
    flat = zono._abs_dets(G, idx).reshape(idx.shape[0], -1)
    ref = zono._cramer_volumes(flat, m, n)
    got = zono._cramer_volumes_sparse(flat, m, n)
    torch.testing.assert_close(got, ref, rtol=1e-13, atol=0)
    monkeypatch.setattr(combinatorics, "_CHUNK_ELEMS", 1)
    assert torch.equal(zono._cramer_volumes_sparse(flat, m, n), got)
    _, vols = _least_basis_volume(G[0].numpy())
    np.testing.assert_allclose(got[:, 0].numpy(), [vols[tuple(S)] for S in idx.tolist()],
                               rtol=1e-9)


@pytest.mark.parametrize("n,m", [(2, 5), (3, 7), (4, 8), (6, 12), (8, 10)])
def test_all_minors_match_determinants_and_the_lu_search(n: int, m: int, monkeypatch) -> None:
    """`_all_minors` (Laplace expansion, row by row) gives every n x n minor in the order of
    `_combinations`, against numpy's determinants, with a repeated column (zero minors) and
    columns of 1e-12, also in chunks of the batch; the basis search chooses the same bases
    with it as with one LU per basis (`_lu_abs_dets`)."""
    from diffsmf.sets import outer_parallelotope as zono

    g = torch.Generator().manual_seed(7 * n + m)
    G = torch.randn(4, n, m, generator=g, dtype=torch.float64)
    G[1, :, 1] = G[1, :, 0]
    G[2, :, n:] *= 1e-12  # a remainder box's tiny axis generators, say
    M = zono._all_minors(G)
    idx = zono._combinations(m, n)
    ref = np.array([[np.linalg.det(G[b][:, S].numpy()) for S in idx.tolist()] for b in range(4)])
    np.testing.assert_allclose(M.numpy(), ref, rtol=1e-10, atol=1e-13 * np.abs(ref).max())
    best, ok = _best_basis(G)
    # eagerly, a batch above MINOR_ELEMS is expanded in chunks where that is cheaper: the same
    # minors, bit for bit; else one LU per basis
    monkeypatch.setattr(zono, "MINOR_ELEMS", 1)
    ref_big = M.abs().movedim(-1, 0) if zono._laplace_pays(m, n) else zono._lu_abs_dets(G, idx)
    assert torch.equal(zono._abs_dets(G, idx), ref_big)
    monkeypatch.setattr(zono, "_abs_dets", zono._lu_abs_dets)
    best_lu, ok_lu = _best_basis(G)
    assert best.tolist() == best_lu.tolist() and ok.tolist() == ok_lu.tolist()


def test_eigvalsh_of_a_matrix_with_gradient_warns_nothing_and_flags_non_finite() -> None:
    """`linalg.eigvalsh` (n >= 3, eager): a matrix that records a gradient gives numpy's
    eigenvalues and its gradient without a warning from the finiteness read, and a non-finite
    matrix of the batch gives NaN eigenvalues while the others are unaffected."""
    import warnings

    A = torch.randn(2, 4, 4, dtype=torch.float64)
    S = (A + A.mT).requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ev = linalg.eigvalsh(S)
        ev.sum().backward()
    np.testing.assert_allclose(ev.detach().numpy(), np.linalg.eigvalsh(S.detach().numpy()),
                               rtol=1e-12, atol=1e-12)
    assert S.grad is not None and bool(torch.isfinite(S.grad).all())
    bad = S.detach().clone()
    bad[1, 0, 0] = torch.inf
    out = linalg.eigvalsh(bad)
    assert bool(torch.isnan(out[1]).all())
    np.testing.assert_allclose(out[0].numpy(), np.linalg.eigvalsh(bad[0].numpy()), rtol=1e-12,
                               atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.sampled_from([0.0, 1.0, -2.5, 3.0, np.inf, -np.inf, np.nan]), min_size=1,
             max_size=24),
    st.integers(1, 3),
)
def test_descending_order_is_torch_stable_sort_eager_and_traced(values, rows):
    """`descending_order` against ``torch.sort(descending=True, stable=True)``: ties (many,
    from a few distinct values), +-inf and NaN (the largest), eagerly and by the rank table
    that a traced step uses; the traced result is a permutation."""
    from diffsmf.utils import descending_order

    score = torch.tensor(values, dtype=torch.float64).roll(1).expand(rows, -1).clone()
    score[0] = torch.tensor(values, dtype=torch.float64)
    ref = torch.sort(score, dim=-1, descending=True, stable=True).indices
    assert torch.equal(descending_order(score), ref)
    with traced():
        got = descending_order(score)
    assert torch.equal(got, ref)
    assert torch.equal(got.sort(-1).values, torch.arange(len(values)).expand(rows, -1))


def test_reduction_orders_generators_the_same_eager_and_traced():
    """Girard's reduction of zonotopes with tied scores (axis-aligned generators score 0) keeps
    and boxes the same generators whether the order comes from a sort or from ranks."""
    from diffsmf.sets.zonotope import Zonotope

    g = torch.Generator().manual_seed(3)
    G = torch.randn(5, 3, 14, generator=g, dtype=torch.float64)
    G[..., 6:] = torch.diag_embed(torch.rand(5, 3, generator=g, dtype=torch.float64)).repeat(
        1, 1, 3)[..., :8]  # 8 axis-aligned columns: tied scores
    Z = Zonotope(torch.zeros(5, 3, dtype=torch.float64), G)
    eager = Z.reduce(3)
    with traced():
        rank = Z.reduce(3)
    assert torch.equal(eager.generators, rank.generators)
