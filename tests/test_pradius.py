"""The P-radius gain of PRad-A/B (Le et al. 2013, eq. 17): the LMI rebuilt here from the
paper's blocks holds for the returned gain (eigenvalues in numpy, independent of the solver and
of the module's own check), a perturbed gain breaks it at the design's beta, and the observers
contain the true states (tests/test_filters_containment.py)."""

from __future__ import annotations

import numpy as np
import pytest

import diffsmf as ds
from diffsmf.filters.pradius import pradius_gain

A = np.array([[0.0, -0.5], [1.0, 1.0]])
C = np.array([[-2.0, 1.0]])
E = np.array([[-0.12], [0.02]])
F = np.array([[0.2]])


def _lmi_min_eig(A, C, E, F, L, P, beta) -> float:
    Y = P @ L
    n, q, r = A.shape[0], E.shape[1], F.shape[1]
    M = np.zeros((n + q + r + n,) * 2)
    i1, i2, i3 = n, n + q, n + q + r
    M[:i1, :i1] = beta * P
    M[i1:i2, i1:i2] = E.T @ E
    M[i2:i3, i2:i3] = F.T @ F
    M[i3:, i3:] = P
    M[:i1, i3:] = A.T @ P - A.T @ C.T @ Y.T
    M[i1:i2, i3:] = E.T @ P - E.T @ C.T @ Y.T
    M[i2:i3, i3:] = F.T @ Y.T
    M = np.triu(M) + np.triu(M, 1).T
    return float(np.linalg.eigvalsh(M).min())


@pytest.mark.parametrize("per_output", [False, True])
def test_the_returned_gain_satisfies_the_lmi(per_output):
    g = pradius_gain(A, C, E, F, per_output=per_output)
    assert g.status == "verified" and 0 < g.beta < 1
    assert _lmi_min_eig(A, C, E, F, g.gain, g.P, g.beta) >= -1e-7
    assert np.linalg.eigvalsh(g.P).min() > 0
    bad = g.gain + np.array([[3.0], [-3.0]])  # the LMI can fail: a far gain breaks it
    assert _lmi_min_eig(A, C, E, F, bad, g.P, g.beta) < -1e-3


def test_two_outputs_design_per_output_or_jointly():
    s = ds.systems.get("mismatch_quadratic")
    a = ds.filters.get("PRad-A")(s)
    b = ds.filters.get("PRad-B")(s)
    assert a.strip_gain.shape == b.strip_gain.shape == (s.n, s.m)
    assert a.gain_design.status == b.gain_design.status == "verified"
    assert not np.allclose(a.strip_gain.numpy(), b.strip_gain.numpy())


def test_bad_matrices_name_the_argument():
    with pytest.raises(ValueError, match="^C: expected 1 rows"):
        pradius_gain(A, np.ones((1, 3)), E, F)
    with pytest.raises(ValueError, match="^E: has a NaN"):
        pradius_gain(A, C, np.array([[np.nan], [0.0]]), F)
