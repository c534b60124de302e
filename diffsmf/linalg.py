"""Batched dense linear algebra with closed forms for the small matrices of a filter step.

The set filters call ``det``, ``solve`` and ``eigvalsh`` on many tiny matrices per step (the
Chisci basis search alone solves one ``n x n`` system per candidate basis and batch element).
LAPACK handles each matrix with a separate call (about 1 us per matrix, 10-30 us of fixed cost
per batched call on a CPU, and no fusion under ``torch.compile``), so at n = 1-3 these calls
dominated the step (about 40 % of a compiled HS-NSMF step at B = 10,000). Here the
small sizes use closed forms built from elementwise ops, which ``torch.compile`` fuses with
their neighbours and which cost one pass over the batch in eager mode; larger sizes fall back
to ``torch.linalg``. The closed forms are differentiable by autograd.

Accuracy (float64, relative to the matrix norm): ``det`` for n <= 3 is the cofactor
expansion, with rounding error below ``(n + 1)! eps`` times the product of the column norms
(the Hadamard bound); ``solve`` for n <= 2 is Cramer's rule, forward stable for 2 x 2
(Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., sec. 1.10.1); ``eigvalsh``
for n <= 2 is the characteristic-polynomial root ``(a + d) / 2 -+ sqrt(((a - d) / 2)^2 + b^2)``
with absolute error a few ``eps ||S||``, the same order as LAPACK's; ``eigh`` for n <= 2 adds
the rotation angle ``theta = atan2(b, (a - d) / 2) / 2`` of the eigenvectors (Golub & Van Loan,
*Matrix Computations*, 4th ed., sec. 8.5.2, the symmetric Schur decomposition), orthonormal to
a few ``eps``. ``cholesky`` for n <= 2 is the Cholesky-Banachiewicz recurrence that LAPACK's
``potf2`` runs (``l11 = sqrt(a)``, ``l21 = b / l11``, ``l22 = sqrt(d - l21^2)``, backward
stable, Higham sec. 10.1), ``solve_lower`` / ``cholesky_solve`` forward and back substitution
(Higham sec. 8.1). Every guaranteed caller
already pads for an error of this order (e.g. ``hessian_eig_lower_bound``: ``(8 n + 16) eps``).

A singular matrix gives ``inf`` / NaN entries in ``solve`` at n <= 2 instead of LAPACK's
exception (and a matrix that is not positive definite NaN entries in ``cholesky``); the
callers substitute a regular matrix first (basis search) or flag the non-finite result (the
filters' boundedness guard).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffsmf.utils import broadcast_shapes, tracing

__all__ = [
    "sym",
    "CLOSED_FORM_MAX_N", "SMALL_MATMUL_ELEMS", "SMALL_MATMUL_MAX", "cholesky", "cholesky_solve",
    "det", "eigh", "eigvalsh", "finite_or_eye", "lapack_cholesky", "matmul", "small_dot",
    "small_reduce", "small_sum", "solve", "solve_lower", "traced_matmul",
]

#: Largest size with a closed form: ``det`` up to 3, the others up to 2.
CLOSED_FORM_MAX_N = {
    "det": 3, "solve": 2, "eigvalsh": 2, "eigh": 2, "cholesky": 2, "cholesky_solve": 2,
    "solve_lower": 2,
}


#: ``matmul`` uses a broadcast multiply-and-sum when every dimension of the product is at most
#: this (Inductor fuses it; a BLAS call per 2 x 2 product costs a few microseconds) ...
SMALL_MATMUL_MAX = 4
#: ... or when the product has at most this many multiplications per matrix ``p q r`` (e.g. the
#: ``[9, 2] x [2, 2]`` axis points of the statistical linearisation at n = 2); larger products
#: go to BLAS, so the ``[..., p, q, r]`` temporary stays small.
SMALL_MATMUL_ELEMS = 64


def matmul(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` for ``A [..., p, q]``, ``B [..., q, r]`` (broadcast batch) -> ``[..., p, r]``:
    an elementwise multiply-and-sum when p, q, r <= `SMALL_MATMUL_MAX` or
    ``p q r <= SMALL_MATMUL_ELEMS``, else ``@``."""
    p, q, r = A.shape[-2], A.shape[-1], B.shape[-1]
    small = max(p, q, r) <= SMALL_MATMUL_MAX or p * q * r <= SMALL_MATMUL_ELEMS
    if small and B.shape[-2] == q:
        return _mul_sum(A, B)
    return A @ B


def traced_matmul(A: Tensor, B: Tensor, max_inner: int | None = SMALL_MATMUL_MAX) -> Tensor:
    """``A @ B`` in eager mode; while traced by ``torch.compile``, a multiply-and-sum when the
    inner dimension is at most ``max_inner`` (``None``: always; any outer sizes). Inductor fuses
    the sum into the surrounding kernel instead of an extern BLAS call, which cost 1-3 ms per
    ``[10000, 2, 2] x [10000, 2, 24]`` product, 5-14 % of a compiled HSNSMF / MSZM step; the
    constrained-zonotope LP's normal matrix and row-vector products use ``max_inner=None``
    (an extern batched product loops over the batch with one small BLAS call per matrix).

    For the set filters' hot products: their eager results (the audited sets) stay those of
    ``@`` bit for bit; the compiled step may differ in the last bits (another summation order,
    no FMA), as any compiled kernel may, within the rounding margins the filters add.
    """
    q = A.shape[-1]
    fuse = max_inner is None or q <= max_inner
    if tracing() and fuse and B.shape[-2] == q:
        return _mul_sum(A, B)
    if A.dim() == 3 and B.dim() == 3 and A.shape[0] == B.shape[0]:
        return torch.bmm(A, B)  # the kernel of ``@``, without its expand / view calls
    return A @ B


def _mul_sum(A: Tensor, B: Tensor) -> Tensor:
    """``A @ B`` as a broadcast multiply-and-sum over the inner dimension (elementwise ops)."""
    return (A.unsqueeze(-1) * B.unsqueeze(-3)).sum(-2)


def _check_square(name: str, M: Tensor) -> int:
    if M.dim() < 2 or M.shape[-1] != M.shape[-2]:
        raise ValueError(f"{name}: expected a square [..., n, n] tensor, got {tuple(M.shape)}")
    return M.shape[-1]


def _check_rhs(name: str, n: int, B: Tensor) -> None:
    """``B`` must be ``[..., n, k]`` for the ``n x n`` matrix named ``name``."""
    if B.dim() < 2 or B.shape[-2] != n:
        raise ValueError(
            f"B: expected [..., {n}, k] for {name} [..., {n}, {n}], got {tuple(B.shape)}"
        )


def sym(M: Tensor) -> Tensor:
    """The symmetric part ``(M + M') / 2`` of ``M [..., n, n]`` (rounding drift of a symmetric
    product removed)."""
    return 0.5 * (M + M.mT)


def det(M: Tensor) -> Tensor:
    """Determinant ``[..., n, n] -> [...]`` (closed form up to n = 3, else ``torch.linalg.det``)."""
    n = _check_square("M", M)
    if n == 1:
        return M[..., 0, 0]
    if n == 2:
        return M[..., 0, 0] * M[..., 1, 1] - M[..., 0, 1] * M[..., 1, 0]
    if n == 3:
        a, b, c = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
        d, e, f = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
        g, h, i = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
        return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return torch.linalg.det(M)


def solve(A: Tensor, B: Tensor) -> Tensor:
    """``X = A^-1 B`` for ``A [..., n, n]``, ``B [..., n, k]`` (broadcast batch) -> ``[..., n, k]``.

    Cramer's rule up to n = 2 (a singular ``A`` gives inf / NaN, no exception), else
    ``torch.linalg.solve`` (which raises for a singular ``A`` outside ``torch.compile``).
    """
    n = _check_square("A", A)
    _check_rhs("A", n, B)
    if n == 1:
        return B / A
    if n == 2:
        a, b = A[..., 0, 0, None], A[..., 0, 1, None]
        c, d = A[..., 1, 0, None], A[..., 1, 1, None]
        b0, b1 = B[..., 0, :], B[..., 1, :]
        D = a * d - b * c
        return torch.stack([(d * b0 - b * b1) / D, (a * b1 - c * b0) / D], -2)
    return torch.linalg.solve(A, B)


def eigvalsh(S: Tensor) -> Tensor:
    """Eigenvalues (ascending) of symmetric ``S [..., n, n]`` -> ``[..., n]``.

    Closed form up to n = 2 (the off-diagonal is read as ``(S_01 + S_10) / 2``), else
    ``torch.linalg.eigvalsh`` (which reads the lower triangle). A matrix with a NaN / inf entry
    gives NaN eigenvalues (the others are unaffected).
    """
    n = _check_square("S", S)
    if n == 1:
        return S[..., 0, :]
    if n == 2:
        a, d = S[..., 0, 0], S[..., 1, 1]
        b = 0.5 * (S[..., 0, 1] + S[..., 1, 0])
        m, h = 0.5 * (a + d), 0.5 * (a - d)
        # the tiny floor keeps the gradient finite at a double eigenvalue (sqrt'(0) = inf)
        r = torch.sqrt(h * h + b * b + torch.finfo(S.dtype).tiny)
        return torch.stack([m - r, m + r], -1)
    if not tracing() and S.device.type == "cpu" and _all_finite(S):
        return torch.linalg.eigvalsh(S)
    bad, safe = finite_or_eye(S)
    return torch.where(bad.unsqueeze(-1), torch.nan, torch.linalg.eigvalsh(safe))


def eigh(S: Tensor) -> tuple[Tensor, Tensor]:
    """Eigenvalues (ascending) ``[..., n]`` and orthonormal eigenvectors (columns) ``[..., n, n]``
    of symmetric ``S [..., n, n]``.

    Closed form up to n = 2 (no LAPACK call, no host sync: ``torch.linalg.eigh`` checks its
    result on the host, and at n = 2 each call cost about 50 us in a compiled step): the
    eigenvalues of `eigvalsh` and the rotation ``[[c, -s], [s, c]]`` by ``theta =
    atan2(b, (a - d) / 2) / 2``, columns reordered to ``[[-s, c], [c, s]]`` for ascending
    eigenvalues (``b = (S_01 + S_10) / 2``; ``S`` diagonal with ``a = d`` gives the identity).
    Eigenvector signs may differ from LAPACK's. Not differentiable at repeated eigenvalues (the
    callers wrap it in autograd Functions with their own backward), else ``torch.linalg.eigh``.
    A matrix with a NaN / inf entry gives NaN eigenvalues and eigenvectors (the others are
    unaffected).
    """
    n = _check_square("S", S)
    if n == 1:
        return S[..., 0, :], torch.ones_like(S)
    if n == 2:
        a, d = S[..., 0, 0], S[..., 1, 1]
        b = 0.5 * (S[..., 0, 1] + S[..., 1, 0])
        theta = 0.5 * torch.atan2(b, 0.5 * (a - d))
        c, s = torch.cos(theta), torch.sin(theta)
        V = torch.stack([torch.stack([-s, c], -1), torch.stack([c, s], -1)], -2)
        return eigvalsh(S), V
    bad, safe = finite_or_eye(S)
    evals, V = torch.linalg.eigh(safe)
    return (torch.where(bad.unsqueeze(-1), torch.nan, evals),
            torch.where(bad[..., None, None], torch.nan, V))


def _all_finite(S: Tensor) -> bool:
    """Eagerly, one host read: every entry of ``S`` finite (a NaN or inf makes the sum
    non-finite; a sum that overflows only takes the caller's masked path). Read without the
    gradient, so no warning while autograd records."""
    with torch.no_grad():
        return math.isfinite(float(S.sum()))


def finite_or_eye(S: Tensor) -> tuple[Tensor, Tensor]:
    """``(bad [...], S')``: ``bad`` where ``S [..., n, n]`` has a NaN / inf entry, and ``S``
    with those matrices replaced by the identity, so that LAPACK (which fails on the whole
    batch for one non-finite matrix) serves the others; the callers return NaN for ``bad``
    (a filter flags those elements). Branch-free."""
    bad = ~torch.isfinite(S).all(-1).all(-1)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    return bad, torch.where(bad[..., None, None], eye, S)


def cholesky(S: Tensor) -> Tensor:
    """Lower Cholesky factor ``L [..., n, n]`` of SPD ``S [..., n, n]`` (reads the lower
    triangle, as LAPACK does).

    Closed form up to n = 2 (no LAPACK call: it fuses under ``torch.compile``), else
    ``torch.linalg.cholesky_ex``. A matrix that is not positive definite (NaN, inf, or a
    non-positive pivot) gives NaN entries, no exception, at every n: LAPACK would fail the
    whole batch for one such matrix; the callers flag those elements (a filter's events).
    """
    n = _check_square("S", S)
    if n == 1:
        return torch.sqrt(S)
    if n == 2:
        l11 = torch.sqrt(S[..., 0, 0])
        l21 = S[..., 1, 0] / l11
        l22 = torch.sqrt(S[..., 1, 1] - l21 * l21)
        zero = torch.zeros_like(l11)
        return torch.stack([torch.stack([l11, zero], -1), torch.stack([l21, l22], -1)], -2)
    return lapack_cholesky(S)


def lapack_cholesky(S: Tensor) -> Tensor:
    """``torch.linalg.cholesky`` at every n (LAPACK's rounding, also for n <= 2), with NaN
    entries, not an exception for the batch, where ``S`` is not positive definite."""
    L, info = torch.linalg.cholesky_ex(S)
    return torch.where((info != 0)[..., None, None], torch.nan, L)


def solve_lower(L: Tensor, B: Tensor) -> Tensor:
    """``X = L^-1 B`` for lower-triangular ``L [..., n, n]``, ``B [..., n, k]`` (broadcast batch).

    Forward substitution up to n = 2, else ``torch.linalg.solve_triangular(L, B, upper=False)``.
    """
    n = _check_square("L", L)
    _check_rhs("L", n, B)
    if n == 1:
        return B / L
    if n == 2:
        x0 = B[..., 0, :] / L[..., 0, 0, None]
        x1 = (B[..., 1, :] - L[..., 1, 0, None] * x0) / L[..., 1, 1, None]
        return torch.stack([x0, x1], -2)
    return torch.linalg.solve_triangular(L, B, upper=False)


def cholesky_solve(B: Tensor, L: Tensor) -> Tensor:
    """``X = (L L')^-1 B`` for the lower Cholesky factor ``L [..., n, n]`` and ``B [..., n, k]``
    (argument order of ``torch.cholesky_solve``).

    Forward and back substitution up to n = 2, else ``torch.cholesky_solve``.
    """
    n = _check_square("L", L)
    if n > 2:
        return torch.cholesky_solve(B, L)
    z = solve_lower(L, B)
    if n == 1:
        return z / L
    x1 = z[..., 1, :] / L[..., 1, 1, None]
    x0 = (z[..., 0, :] - L[..., 1, 0, None] * x1) / L[..., 0, 0, None]
    return torch.stack([x0, x1], -2)


#: Outputs from which `small_sum` unrolls a reduction over 2 to 4 elements into adds.
UNROLL_MIN_OUTPUTS = 1024


def small_sum(x: Tensor, dim: int, keepdim: bool = False) -> Tensor:
    """``x.sum(dim, keepdim)`` with the same bits, cheaper for a large batch.

    A CPU sum over a dim of 2 to 4 elements costs 15-40 ns per output (its inner loop is that
    dim), an add of two slices about 1 ns; so with at least `UNROLL_MIN_OUTPUTS` outputs
    (eager) the sum is a left-to-right chain of adds of the slices, the order of torch's own
    sum up to 4 terms (checked bit for bit, inner and outer dims, B = 1 and 10,000). Otherwise
    (a small batch: one call instead of three or more; more than 4 elements; while tracing,
    where the compiler fuses the sum) ``x.sum`` itself.
    """
    k = x.shape[dim]
    if not 2 <= k <= 4 or x.numel() < UNROLL_MIN_OUTPUTS * k or tracing():
        return x.sum(dim, keepdim=keepdim)
    parts = x.unbind(dim)
    out = parts[0] + parts[1]
    for t in parts[2:]:
        out = out + t
    return out.unsqueeze(dim) if keepdim else out


#: A short dot product over the last dim is unrolled into slices when its output has at least
#: this many elements (torch's reduction over a trailing dim of size 2-4 costs ~100 ns per
#: output); smaller ones are a product and a sum (two ops).
SMALL_REDUCE_MIN_OUTPUTS = 1 << 14
SMALL_REDUCE_MAX_N = 4
#: Eagerly, `small_dot` with more than `SMALL_REDUCE_MAX_N` terms contracts with ``einsum``
#: (a batched matmul) from this many products on: 10-25x faster than the product and sum on
#: CPU at 60k-600k products, 2x slower below about 8k (its fixed cost).
EINSUM_MIN_PRODUCT = 1 << 13


def small_dot(a: Tensor, b: Tensor) -> Tensor:
    """``sum_j a[..., j] b[..., j]`` (broadcast) -> ``[...]``, cheaper for a large batch.

    Small outputs: a product and a sum (two ops). Large ones: the first product, then
    ``addcmul_`` in place (no temporary per term: a fresh large tensor costs its page
    faults); more than `SMALL_REDUCE_MAX_N` terms, eagerly: ``einsum``. They may differ in
    the last bits (order of the additions, a fused multiply-add), within the
    ``n eps sum |terms|`` that every caller's padding covers.
    """
    n = a.shape[-1]
    outputs = broadcast_shapes(a.shape[:-1], b.shape[:-1]).numel()
    if n > SMALL_REDUCE_MAX_N:
        if outputs * n >= EINSUM_MIN_PRODUCT and a.dtype == b.dtype and not tracing():
            # a broadcast product of many elements (e.g. every tangent point against every
            # vertex): einsum contracts it as a batched matmul, never materialising it
            return torch.einsum("...j,...j->...", a, b)
        return (a * b).sum(-1)
    if outputs < SMALL_REDUCE_MIN_OUTPUTS:
        return (a * b).sum(-1)
    out = a[..., 0] * b[..., 0]
    for j in range(1, n):
        out.addcmul_(a[..., j], b[..., j])
    return out


def small_reduce(t: Tensor, op: str) -> Tensor:
    """``t.sum(-1)`` / ``t.amin(-1)`` / ``t.any(-1)`` (``op``); unrolled into slices for a
    short last dim and a large output, like `small_dot` (the same floats for ``n <= 2``)."""
    n = t.shape[-1]
    if n > SMALL_REDUCE_MAX_N or math.prod(t.shape[:-1]) < SMALL_REDUCE_MIN_OUTPUTS:
        return getattr(t, op)(-1)
    f = {"sum": torch.add, "amin": torch.minimum, "any": torch.logical_or}[op]
    out = t[..., 0]
    for j in range(1, n):
        out = f(out, t[..., j])
    return out
