"""Noise sets used as given: a zonotope or ellipsoidal W is not replaced by
its interval hull.

References: a numpy implementation of Alamo et al. 2005 (zonotope prediction with the noise
generators, F-radius strip intersection, no reduction) on a linear system, and containment of
true states under worst-case noise drawn from the vertices / boundary of W itself.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import diffsmf as ds

F64 = torch.float64
A = np.array([[0.9, 0.2], [-0.1, 0.95]])
C = np.array([[1.0, 0.5]])
GW = np.array([[-0.12], [0.02]])  # one-generator zonotope noise
SIGMA = 0.05


def _linear_system(W: ds.sets.ConvexSet) -> ds.System:
    At, Ct = torch.tensor(A, dtype=F64), torch.tensor(C, dtype=F64)

    def f(x, u=None, theta=None):
        return x @ At.T

    def h(x):
        return x @ Ct.T

    x0 = ds.Interval(torch.tensor([0.5, -0.3], dtype=F64) - 0.2,
                     torch.tensor([0.5, -0.3], dtype=F64) + 0.2)
    V = ds.Interval(torch.tensor([-SIGMA], dtype=F64), torch.tensor([SIGMA], dtype=F64))
    return ds.System(f, h, x0, W, V, name="linear")


def _zono_W() -> ds.Zonotope:
    return ds.Zonotope(torch.zeros(2, dtype=F64), torch.tensor(GW, dtype=F64))


def _alamo_numpy(y: np.ndarray, c0: np.ndarray, r0: np.ndarray) -> np.ndarray:
    """Alamo 2005 on one trajectory ``y [T, 1]`` -> interval hull half-widths ``[T+1, 2]``
    and centres, without reduction: ``c+ = A c``, ``G+ = [A G, G_W]``; strip ``|p x - y| <=
    sigma``: ``lam = G G' p / (p' G G' p + sigma^2)``, ``c += lam (y - p c)``,
    ``G = [(I - lam p') G, sigma lam]``."""
    c, G = c0.copy(), np.diag(r0)
    out = [np.concatenate([c, np.abs(G).sum(1)])]
    for k in range(y.shape[0]):
        c, G = A @ c, np.hstack([A @ G, GW])
        p = C[0]
        Gp = G.T @ p
        lam = G @ Gp / (Gp @ Gp + SIGMA**2)
        c = c + lam * (y[k, 0] - p @ c)
        G = np.hstack([G - np.outer(lam, Gp), SIGMA * lam[:, None]])
        out.append(np.concatenate([c, np.abs(G).sum(1)]))
    return np.stack(out)


def test_box_noise_set_is_the_box():
    s = ds.systems.get("spring_damper")
    filt = ds.filters.HSNSMF(s)
    W, B = filt.process_noise_set(), filt.process_noise_box()
    assert isinstance(W, ds.Interval)
    assert torch.equal(W.lower, B.lower) and torch.equal(W.upper, B.upper)


def test_mszm_equals_alamo_2005_with_zonotope_noise():
    s = _linear_system(_zono_W())
    tr = s.simulate(steps=20, batch=3, seed=0, noise="vertex")
    filt = ds.filters.MSZM(s, order=60, strip_method="fradius")  # room for every generator
    with torch.no_grad():
        res = filt(tr.y)
    for b in range(3):
        ref = _alamo_numpy(tr.y[b].numpy(), np.array([0.5, -0.3]), np.array([0.2, 0.2]))
        lo, hi = ref[:, :2] - ref[:, 2:], ref[:, :2] + ref[:, 2:]
        np.testing.assert_allclose(res.lower[b].numpy(), lo, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(res.upper[b].numpy(), hi, rtol=1e-9, atol=1e-9)
    # the hull of W (the old behaviour) is strictly looser
    boxW = _linear_system(_zono_W().interval_hull())
    with torch.no_grad():
        old = ds.filters.MSZM(boxW, order=60, strip_method="fradius")(tr.y)
    w_new = (res.upper - res.lower)[:, -1].mean()
    w_old = (old.upper - old.lower)[:, -1].mean()
    assert w_new < w_old


@pytest.mark.parametrize("name", ["hsnsmf", "mszm", "cdsmf", "esmf"])
@pytest.mark.parametrize("kind", ["zonotope", "ellipsoid"])
def test_containment_with_non_box_noise(name, kind):
    if kind == "zonotope":
        W = _zono_W()
    else:
        W = ds.Ellipsoid(torch.zeros(2, dtype=F64), torch.tensor([[0.01, 0.004], [0.004, 0.003]],
                                                                 dtype=F64))
    s = _linear_system(W)
    tr = s.simulate(steps=15, batch=200, seed=3, noise="vertex")
    filt = ds.filters.by_name(name)(s)
    with torch.no_grad():
        res = filt(tr.y)
        hull = ds.filters.by_name(name)(_linear_system(W.interval_hull()))(tr.y)
    assert res.sets.contains(tr.x).all()
    assert res.consistent.all()
    v, vh = res.volume[:, 5:].mean(), hull.volume[:, 5:].mean()
    if kind == "ellipsoid" and name in ("hsnsmf", "mszm"):
        assert v <= vh * (1 + 1e-12)  # a zonotope cannot hold an ellipsoid: its hull is used
    else:
        assert v < vh  # W as given is tighter than its hull box


def test_process_noise_set_scales_and_differentiates():
    s = _linear_system(_zono_W())
    filt = ds.filters.MSZM(s)
    W = filt.process_noise_set()
    assert torch.allclose(W.generators, torch.tensor(GW, dtype=F64))
    filt.process_noise = torch.tensor([0.06, 0.02], dtype=F64)  # half the hull in x1
    assert torch.allclose(filt.process_noise_set().generators,
                          torch.tensor([[-0.06], [0.02]], dtype=F64))

    def g(raw):
        filt.raw_process_noise.data.copy_(raw.detach())
        sc = filt.process_noise_scale * torch.nn.functional.softplus(raw)
        r0 = filt.process_noise_hull_radius
        return (sc / r0).unsqueeze(-1) * torch.tensor(GW, dtype=F64)

    raw = filt.raw_process_noise.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(g, (raw,))
    tr = s.simulate(steps=3, batch=2, seed=0)
    filt.process_noise = torch.tensor([0.12, 0.02], dtype=F64)
    filt(tr.y).volume[:, 1:].log().mean().backward()
    assert filt.raw_process_noise.grad is not None
    assert torch.isfinite(filt.raw_process_noise.grad).all()


# ---------------------------------------------------------------------------- V as given (ESMF)
C2 = np.array([[1.0, 0.5], [0.0, 1.0]])
SV = np.array([[0.004, 0.0018], [0.0018, 0.0012]])  # correlated ellipsoidal measurement noise


def _two_output_system(V: ds.sets.ConvexSet) -> ds.System:
    At, Ct = torch.tensor(A, dtype=F64), torch.tensor(C2, dtype=F64)
    x0 = ds.Interval(torch.tensor([0.3, -0.2], dtype=F64), torch.tensor([0.7, 0.2], dtype=F64))
    W = ds.Interval(torch.full((2,), -0.01, dtype=F64), torch.full((2,), 0.01, dtype=F64))
    return ds.System(lambda x, u=None, theta=None: x @ At.T, lambda x: x @ Ct.T, x0, W, V,
                     name="linear2")


def _ell_V() -> ds.Ellipsoid:
    return ds.Ellipsoid(torch.zeros(2, dtype=F64), torch.tensor(SV, dtype=F64))


def test_measurement_noise_set_scales_like_the_process_set():
    filt = ds.filters.ESMF(_two_output_system(_ell_V()))
    V = filt.measurement_noise_set()
    assert isinstance(V, ds.Ellipsoid)
    torch.testing.assert_close(V.shape, torch.tensor(SV, dtype=F64))
    filt.measurement_noise = filt.measurement_noise * torch.tensor([0.5, 1.0], dtype=F64)
    S = filt.measurement_noise_set().shape
    torch.testing.assert_close(S[0, 0], torch.tensor(SV[0, 0] / 4, dtype=F64))
    torch.testing.assert_close(S[0, 1], torch.tensor(SV[0, 1] / 2, dtype=F64))


def _numpy_update(c: np.ndarray, P: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Song et al. 2017, eq. 36-39 with R = SV (the ellipsoidal V itself), volume-minimal rho found
    by a dense grid + golden search in numpy (independent of diffsmf)."""
    from scipy.optimize import minimize_scalar

    e = y - C2 @ c
    G = C2 @ P @ C2.T

    def parts(rho):
        D = rho * G + (1 - rho) * SV
        K = rho * P @ C2.T @ np.linalg.inv(D)
        xi = 1 - rho * (1 - rho) * e @ np.linalg.solve(D, e)
        return xi / (1 - rho) * (P - K @ C2 @ P), c + K @ e

    def logdet(rho):
        return np.linalg.slogdet(parts(rho)[0])[1]

    grid = np.linspace(1e-6, 1 - 1e-6, 2001)
    i = int(np.argmin([logdet(r) for r in grid]))
    res = minimize_scalar(logdet, bounds=(grid[max(i - 1, 0)], grid[min(i + 1, 2000)]),
                          method="bounded", options={"xatol": 1e-12})
    P2, c2 = parts(res.x)
    assert 0.05 < res.x < 0.97  # an interior optimum (else the test would check an edge case)
    return c2, P2


def test_esmf_update_uses_the_ellipsoidal_V_exactly():
    """One update from a known prior: ESMF with an ellipsoidal V (linear h, so the remainder is
    only the rounding floor) equals the Song et al. 2017 intersection with V itself, not with the
    covering ellipsoid of V's box."""
    s = _two_output_system(_ell_V())
    filt = ds.filters.ESMF(s)
    c = torch.tensor([[0.5, 0.0]], dtype=F64)
    P = torch.tensor([[[2e-3, 5e-4], [5e-4, 1.5e-3]]], dtype=F64)
    y = torch.tensor([[0.52, 0.01]], dtype=F64)
    st = ds.filters.FilterState(set=ds.Ellipsoid(c, P), consistent=torch.ones(1, dtype=bool))
    with torch.no_grad():
        new = filt.update(st, y).set
    c_ref, P_ref = _numpy_update(c[0].numpy(), P[0].numpy(), y[0].numpy())
    np.testing.assert_allclose(new.center[0].numpy(), c_ref, rtol=1e-6, atol=1e-8)
    ld, ld_ref = np.linalg.slogdet(new.shape[0].numpy())[1], np.linalg.slogdet(P_ref)[1]
    assert abs(ld - ld_ref) < 1e-6  # the same volume (up to the outward rounding margins)
    assert ld >= ld_ref - 1e-9  # and never inside the exact family optimum


@pytest.mark.parametrize("kind", ["ellipsoid", "zonotope"])
def test_esmf_contains_and_beats_the_hull_with_non_box_V(kind):
    if kind == "ellipsoid":
        V = _ell_V()
    else:
        V = ds.Zonotope(torch.zeros(2, dtype=F64), torch.tensor([[0.06, 0.01], [0.03, -0.02]],
                                                                  dtype=F64))
    s = _two_output_system(V)
    tr = s.simulate(steps=15, batch=200, seed=5, noise="vertex")
    with torch.no_grad():
        res = ds.filters.ESMF(s)(tr.y)
        hull = ds.filters.ESMF(_two_output_system(V.interval_hull()))(tr.y)
    assert res.sets.contains(tr.x).all()
    assert res.consistent.all()
    assert res.volume[:, 5:].mean() < hull.volume[:, 5:].mean()


def test_esmf_gradcheck_in_the_ellipsoidal_V_scale():
    """The ESMF set is differentiable in the measurement-noise scale of an ellipsoidal V."""
    s = _two_output_system(_ell_V())
    tr = s.simulate(steps=2, batch=1, seed=1, noise="vertex")
    filt = ds.filters.ESMF(s)

    def vol(raw):
        res = torch.func.functional_call(filt, {"raw_measurement_noise": raw}, (tr.y,))
        return res.volume[:, -1]

    raw = filt.raw_measurement_noise.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(vol, (raw,), eps=1e-6, atol=1e-8, rtol=1e-4)


def test_the_noise_half_widths_have_their_own_name_and_the_old_one_warns():
    system = ds.systems.get("spring_damper")
    filt = ds.filters.HSNSMF(system, process_half_widths=[1e-3, 2e-3])
    assert filt.process_half_widths.tolist() == [1e-3, 2e-3]
    assert torch.equal(filt.measurement_half_widths, system.measurement_noise.radius)
    with pytest.warns(DeprecationWarning, match="process_noise: the filter's noise"):
        assert torch.equal(filt.process_noise, filt.process_half_widths)
    with pytest.warns(DeprecationWarning, match="measurement_noise: renamed"):
        old = ds.filters.HSNSMF(system, measurement_noise=[0.05])
    assert old.measurement_half_widths.tolist() == [0.05]
    with pytest.raises(ValueError, match="process_half_widths: give it or its deprecated"):
        ds.filters.HSNSMF(system, process_half_widths=1e-3, process_noise=1e-3)
    with pytest.raises(ValueError, match="process_half_widths"):
        ds.filters.HSNSMF(system, process_half_widths=[-1.0, 1.0])
    # the stored parameter keeps its name: state dicts, tuning names and bounds files
    assert "raw_process_noise" in dict(filt.named_parameters())
