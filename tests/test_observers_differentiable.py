"""DifferentiableObserverDesign (cvxpylayers) against the cvxpy design and finite differences."""

import sys

import numpy as np
import pytest
import torch

from diffsmf.observers import DifferentiableObserverDesign, design_lipschitz_observer
from diffsmf.observers.lmi import _Search, lmi_problem, structure_keys

# Wang et al. 2009 example: structured nonlinearity B_f phi(H x), gamma = 1; max_gain makes it
# well-posed
A0 = np.array([[0.0, 1.0], [-1.0, 1.0]])
C0 = np.array([[1.0, 0.0]])
BF, H = np.array([[0.0], [1.0]]), np.eye(2)
KAPPA = 50.0


@pytest.fixture(scope="module")
def design():
    pytest.importorskip("cvxpylayers")
    d = design_lipschitz_observer(A0, C0, 1.0, 1.0, structure=(BF, H), max_gain=KAPPA)
    assert d.feasible
    return d


@pytest.fixture(scope="module")
def layer(design):
    return DifferentiableObserverDesign(2, 1, alpha=design.decay, structure=(BF, H), max_gain=KAPPA)


def _ref_bound(A, gamma, alpha):
    """Independent re-solve with cvxpy + Clarabel (the design's own SDP) at a fixed alpha."""
    prob, par, var, con = lmi_problem(2, 1, "continuous", False, True, *structure_keys(BF, H))
    par["margin"].value, par["kappa"].value = 1e-6, KAPPA
    par["A"].value, par["C"].value, par["g2"].value = A, C0, gamma**2
    pt = _Search(prob, par, var, con, "CLARABEL", 2)(alpha)
    assert pt.ok, pt.status
    return float(np.sqrt(pt.mu / (alpha * np.linalg.eigvalsh(pt.vals["P"])[0])))


def test_bound_and_gain_match_cvxpy_design(design, layer):
    L, bound, P, mu = layer(A0, C0, 1.0, 1.0, full=True)
    assert bound.item() == pytest.approx(design.bound, rel=1e-4)
    assert mu.item() == pytest.approx(design.mu, rel=1e-4)
    # the gain itself is not unique (flat optimum); the closed loop must be stable
    assert np.linalg.eigvals(A0 - L.detach().numpy() @ C0).real.max() < 0


def test_gradients_match_finite_differences(design, layer):
    A = torch.tensor(A0, requires_grad=True)
    gamma = torch.tensor(1.0, requires_grad=True)
    eps = torch.tensor(0.3, requires_grad=True)
    _, bound = layer(A, C0, gamma, eps)
    gA, gg, ge = torch.autograd.grad(bound, [A, gamma, eps])
    a, h = design.decay, 1e-4
    for i, j in [(0, 0), (0, 1), (1, 0), (1, 1)]:
        E = np.zeros((2, 2))
        E[i, j] = h
        fd = 0.3 * (_ref_bound(A0 + E, 1.0, a) - _ref_bound(A0 - E, 1.0, a)) / (2 * h)
        assert gA[i, j].item() == pytest.approx(fd, rel=1e-2, abs=1e-3)
    fd_g = 0.3 * (_ref_bound(A0, 1.0 + h, a) - _ref_bound(A0, 1.0 - h, a)) / (2 * h)
    assert gg.item() == pytest.approx(fd_g, rel=1e-2)
    assert ge.item() == pytest.approx(bound.item() / 0.3, rel=1e-12)  # eps scales the bound


def test_alpha_gradient_vanishes_at_searched_optimum(design, layer):
    alpha = torch.tensor(design.decay, requires_grad=True)
    _, bound = layer(A0, C0, 1.0, 1.0, alpha=alpha)
    (g,) = torch.autograd.grad(bound, alpha)
    # envelope theorem: the golden-section optimum is stationary in alpha
    assert abs(g.item()) * design.decay < 1e-2 * bound.item()


def test_batched_matches_single(layer):
    A = torch.tensor(A0).expand(3, 2, 2).clone()
    A[1, 1, 1] = 0.5
    gam = torch.tensor([1.0, 1.0, 0.8])
    L, b = layer(A, C0, gam, 1.0)
    assert L.shape == (3, 2, 1) and b.shape == (3,)
    for k in range(3):
        _, bk = layer(A[k], C0, gam[k], 1.0)
        assert b[k].item() == pytest.approx(bk.item(), rel=1e-6)


def test_discrete_time_matches_design():
    pytest.importorskip("cvxpylayers")
    Ad = np.eye(2) + 0.1 * A0  # Euler discretisation, h = 0.1
    d = design_lipschitz_observer(Ad, C0, 0.1, 1.0, time="discrete", structure=(BF, H))
    assert d.feasible
    lay = DifferentiableObserverDesign(2, 1, alpha=d.decay, time="discrete", structure=(BF, H))
    _, bound = lay(Ad, C0, 0.1, 1.0)
    assert bound.item() == pytest.approx(d.bound, rel=1e-3)


def test_missing_cvxpylayers_gives_clear_import_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "cvxpylayers.torch", None)  # import now fails
    with pytest.raises(ImportError, match=r"pip install diffsmf\[diff\]"):
        DifferentiableObserverDesign(2, 1, alpha=1.0)


def test_bad_input_and_infeasible(layer):
    with pytest.raises(ValueError, match="A must be"):
        layer(np.eye(3), C0, 1.0, 1.0)
    with pytest.raises(ValueError, match="lipschitz"):
        layer(A0, C0, -1.0, 1.0)
    with pytest.raises(ValueError, match="alpha"):
        DifferentiableObserverDesign(2, 1, alpha=2.0, time="discrete")
    with pytest.raises(RuntimeError, match="infeasible"):
        layer(A0, C0, 100.0, 1.0)
