"""Strip {x : |a.x - o| <= h}: membership, maps, Minkowski sum, batch utilities, validation."""

import pytest
import torch

import diffsmf as ds
from diffsmf.sets.strip import Strip


def _strip(batch=(4,), n=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Strip(
        torch.randn(*batch, n, generator=g),
        torch.randn(batch, generator=g),
        0.1 + torch.rand(batch, generator=g),
    )


def test_contains_against_definition():
    S = _strip()
    g = torch.Generator().manual_seed(1)
    x = 2 * torch.randn(1000, 4, 3, generator=g)
    ref = ((x * S.normal).sum(-1) - S.offset).abs() <= S.halfwidth
    assert torch.equal(S.contains(x, atol=0.0), ref)
    assert torch.equal(S.normalized().contains(x, atol=0.0), ref)
    assert S.contains(S.center).all()
    assert torch.allclose(S.residual(S.center), torch.zeros(4), atol=1e-12)


def test_from_bounds_and_measurement():
    S = Strip.from_bounds(torch.tensor([1.0, 0.0]), -1.0, 3.0)
    assert S.offset.item() == 1.0 and S.halfwidth.item() == 2.0
    C = torch.tensor([[1.0, 2.0], [0.0, 1.0]])
    M = Strip.from_measurement(C, torch.tensor([1.0, 2.0]), torch.tensor([0.1, 0.2]))
    assert M.batch_shape == (2,)
    assert M.contains(torch.tensor([1.0 - 2 * 2.1, 2.1])).all()


def test_translate_and_linear_map_membership():
    S = _strip(seed=2)
    g = torch.Generator().manual_seed(3)
    A = torch.randn(4, 3, 3, generator=g) + 3 * torch.eye(3)
    b = torch.randn(4, 3, generator=g)
    x = 2 * torch.randn(500, 4, 3, generator=g)
    y = (A @ x.unsqueeze(-1)).squeeze(-1) + b
    T = S.linear_map(A, b)
    clear = (S.residual(x).abs() - S.halfwidth).abs() > 1e-6  # away from the boundary
    assert torch.equal(T.contains(y, atol=0.0)[clear], S.contains(x, atol=0.0)[clear])
    U = S.translate(b)
    assert (U.contains(x + b, atol=1e-9) == S.contains(x, atol=1e-9)).all()


def test_minkowski_sum_with_bounded_sets():
    S = _strip(seed=4)
    g = torch.Generator().manual_seed(5)
    B = ds.Interval(-torch.rand(4, 3, generator=g), torch.rand(4, 3, generator=g))
    W = S.minkowski_sum(B)
    # exact: the sum's extent along a is [lo - h_B(-a), hi + h_B(a)]
    on_edge = S.center + (S.halfwidth / (S.normal**2).sum(-1)).unsqueeze(-1) * S.normal
    pts = on_edge + B.sample_extreme(200, g).movedim(-2, 0)  # edge of S + corners of B
    assert W.contains(pts).all()
    assert torch.allclose(
        W.halfwidth, S.halfwidth + 0.5 * (B.support(S.normal) + B.support(-S.normal))
    )


def test_support_volume_and_unbounded():
    S = _strip(seed=6)
    assert torch.isinf(S.volume()).all()
    h = S.support(2 * S.normal)
    assert torch.allclose(h, 2 * S.offset + 2 * S.halfwidth)
    assert torch.isinf(S.support(torch.ones(4, 3))).all()
    S1 = Strip(torch.tensor([[2.0]]), torch.tensor([1.0]), torch.tensor([0.5]))
    assert S1.volume().item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="unbounded"):
        S.sample(3)


def test_batch_utilities():
    S = _strip((2, 3), seed=7)
    assert S[0].batch_shape == (3,) and S[:, 1].batch_shape == (2,)
    T = ds.stack([S[0], S[1]])
    assert torch.equal(T.normal, S.normal) and torch.equal(T.halfwidth, S.halfwidth)
    W = ds.where(torch.tensor([[True, False, True]]).expand(2, 3), S, S.translate(torch.ones(3)))
    assert torch.equal(W.offset[:, 0], S.offset[:, 0])
    E = S.expand(5, 2, 3)
    assert E.batch_shape == (5, 2, 3)
    # broadcasting of a shared normal against batched offsets
    B = Strip(torch.tensor([1.0, 0.0]), torch.zeros(4), torch.ones(4))
    assert B.normal.shape == (4, 2)


def test_intersects_strip_exact_for_boxes():
    g = torch.Generator().manual_seed(8)
    box = ds.Interval(-torch.ones(6, 2), torch.ones(6, 2))
    a = torch.randn(6, 2, generator=g)
    reach = a.abs().sum(-1)
    off = torch.tensor([0.0, 1.0, -1.0, 2.0, 3.0, -3.0]) * reach
    S = Strip(a, off, 0.5 * reach)
    expect = off.abs() <= 1.5 * reach
    assert torch.equal(box.intersects_strip(S), expect)


def test_validation_names_argument():
    with pytest.raises(ValueError, match="halfwidth"):
        Strip(torch.ones(2), 0.0, -1.0)
    with pytest.raises(ValueError, match="normal"):
        Strip(torch.zeros(2), 0.0, 1.0)
    with pytest.raises(ValueError, match="offset"):
        Strip(torch.ones(2), float("nan"), 1.0)
    with pytest.raises(ValueError, match="offset"):
        Strip(torch.ones(3, 2), torch.zeros(4), 1.0)
    with pytest.raises(ValueError, match="lower"):
        Strip.from_bounds(torch.ones(2), 1.0, 0.0)
    with pytest.raises(ValueError, match="A"):
        _strip().linear_map(torch.randn(2, 3))


def _sd_parallelotope(batch=3):
    g = torch.Generator().manual_seed(3)
    c = torch.tensor([0.2, 0.3], dtype=torch.float64) + 0.05 * torch.randn(batch, 2, generator=g)
    T = 0.1 * torch.eye(2, dtype=torch.float64) + 0.03 * torch.randn(batch, 2, 2, generator=g)
    return ds.sets.Parallelotope(c, T)


def test_sequential_update_degenerate_rows_one_rule():
    """A zero normal is checked for consistency (``|offset| <= halfwidth``) and skipped; a
    non-finite normal or offset and a NaN half-width are skipped; all flag
    DEGENERATE_STRIP, and the set is only cut by the regular strips."""
    from diffsmf.filters.events import FilterEvent
    from diffsmf.filters.strips import measurement_strips, sequential_strip_update

    P = _sd_parallelotope()
    cut = lambda S, st: S.intersect_strip(st)  # noqa: E731
    a = torch.tensor([[[0.0, 0.0], [1.0, 0.0]]] * 3, dtype=torch.float64)
    d = torch.tensor([[0.5, 0.2], [2.0, 0.2], [0.5, 0.2]], dtype=torch.float64)
    w = torch.tensor([[1.0, 0.05], [1.0, 0.05], [float("nan"), 0.05]], dtype=torch.float64)
    new, ok, ev = sequential_strip_update(P, a, d, w, cut)
    one = P.intersect_strip(Strip(a[:, 1], d[:, 1], w[:, 1]))
    assert ok.tolist() == [True, False, True]  # |2| > 1: no state meets the zero row
    assert ((ev & FilterEvent.DEGENERATE_STRIP) != 0).all()
    for b in (0, 2):
        assert torch.equal(new.T[b], one.T[b]) and torch.equal(new.center[b], one.center[b])
    assert torch.equal(new.T[1], P.T[1])  # inconsistent: the input set
    a2 = a.clone()
    a2[0, 1, 0] = float("inf")
    new, ok, ev = sequential_strip_update(P, a2, d, torch.ones_like(d), cut)
    assert torch.equal(new.T[0], P.T[0]) and bool(ok[0]) and int(ev[0]) != 0
    # measurement_strips: the same rule, a degenerate row becomes all of R^n
    vbox = ds.sets.Interval(torch.tensor([-1e-3]), torch.tensor([1e-3]))
    H = torch.zeros(3, 1, 2, dtype=torch.float64)
    n_, o_, h_, ev = measurement_strips(
        lambda x: x[..., :1] ** 2, lambda *args: ds.sets.Interval(torch.zeros(3, 1),
                                                               torch.zeros(3, 1)),
        P, P.center, H, torch.zeros(3, 1), vbox, events=True,
    )
    assert torch.isinf(h_).all() and (n_[..., 0] == 1).all() and (o_ == 0).all()
    assert ((ev & FilterEvent.DEGENERATE_STRIP) != 0).all()


def test_affine_strips_match_the_general_path_and_contain_the_states():
    """An affine h: the strips from its exact slopes with the padding alone equal the Stirling
    strips with the DC remainder to rounding, and contain every state consistent with y."""
    from diffsmf.filters.strips import _affine_strips, _strips
    from diffsmf.linearize import dc_remainder, jacobian, stirling_jacobian

    s = ds.systems.get("spring_damper")
    P = _sd_parallelotope(batch=4)
    c = P.center
    g = torch.Generator().manual_seed(5)
    x = P.sample(64, generator=g)  # [4, 64, 2]
    vbox = ds.sets.Interval(torch.tensor([-1e-3]), torch.tensor([1e-3]))
    v = torch.where(torch.rand(4, 1, generator=g) < 0.5, -1e-3, 1e-3).to(torch.float64)
    y = s.h(x[:, 0]) + v  # the first sample's measurement
    a1, d1, w1 = _affine_strips(s.h, P, c, jacobian(s.h, c), y, vbox, s)
    H = stirling_jacobian(s.h, c, 1e-3)
    a2, d2, w2, _ = _strips(s.h, dc_remainder, P, c, H, y, vbox, s)
    torch.testing.assert_close(a1, a2, rtol=1e-14, atol=0)
    torch.testing.assert_close(d1, d2, rtol=1e-13, atol=1e-16)
    torch.testing.assert_close(w1, w2, rtol=1e-12, atol=0)
    strip = Strip(a1[:, 0], d1[:, 0], w1[:, 0])
    assert strip.contains(x[:, 0], atol=0.0).all()
