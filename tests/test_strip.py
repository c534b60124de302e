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
