"""Iterative-learning intermittent fault estimation (the iterative-learning fault-estimation
abstract; Shi-He-Zhou line)."""

import numpy as np
import pytest
import torch

from diffsmf.observers import ILCFaultEstimator, design_ilc, intermittent_fault_example
from diffsmf.observers.ilc import _roesser_blocks


@pytest.fixture(scope="module")
def setup():
    sysm = intermittent_fault_example()
    d = design_ilc(sysm.A, sysm.C, sysm.F)
    return sysm, d


def test_design_verified_independently(setup):
    sysm, d = setup
    assert d.feasible, d.message
    M = _roesser_blocks(sysm.A, sysm.C, sysm.F, d.L, d.K, d.P1, d.P2, d.gamma_w**2,
                        d.rho**2)
    assert np.linalg.eigvalsh(M).max() < 0
    assert 0 < d.contraction < 1
    assert np.abs(np.linalg.eigvals(sysm.A - d.L @ sysm.C)).max() < 1


def test_fault_error_monotone_with_uncertainty_active(setup):
    sysm, d = setup
    assert np.abs(sysm.D).max() > 0 and np.ptp(sysm.sigma) > 1  # uncertainty is active
    est = ILCFaultEstimator(sysm.A, sysm.B, sysm.C, sysm.F, design=d)
    fhat, err = est.run(sysm, 30)
    e = err[:, 0].numpy()
    assert e[0] == pytest.approx(np.abs(sysm.fault).max())  # trial 1: no estimate yet
    assert np.all(np.diff(e) <= 1e-9)  # monotone over trials
    assert e[-1] < 0.01  # stated threshold (docs/observers.md)


def test_weighted_trial_norm_contracts_nominal(setup):
    """Proven statement (w = 0, e_k(0) = 0): sum_t |Δf_{k+1}|_P2^2 <= rho^2 sum_t |Δf_k|_P2^2."""
    sysm, d = setup
    sysm = intermittent_fault_example()
    sysm.D = np.zeros_like(sysm.D)
    est = ILCFaultEstimator(sysm.A, sysm.B, sysm.C, sysm.F, design=d)
    fhat, _ = est.run(sysm, 8)
    df = torch.as_tensor(sysm.fault) - fhat[:, 0]  # [trials, N, q]
    P2 = torch.as_tensor(d.P2)
    V = torch.einsum("ktq,qr,ktr->k", df, P2, df).numpy()
    assert np.all(V[1:] <= d.contraction**2 * V[:-1] + 1e-12)


def test_batched_trial_and_bad_input(setup):
    sysm, d = setup
    est = ILCFaultEstimator(sysm.A, sysm.B, sysm.C, sysm.F, design=d)
    _, err2 = est.run(sysm, 3, batch=2)
    assert torch.allclose(err2[:, 0], err2[:, 1])
    with pytest.raises(ValueError, match="column rank"):
        design_ilc(sysm.A, sysm.C, np.array([[0.0], [0.0], [1.0]]))
    with pytest.raises(ValueError, match="rho"):
        design_ilc(sysm.A, sysm.C, sysm.F, rho=1.5)
