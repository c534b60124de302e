"""A fitted SCPLNN as a System's dynamics with its certified error (diffsmf.pwl.certified) and
the pendulum example (samples -> fit_scplnn -> HSNSMF, audited on the true pendulum)."""

import importlib.util
from pathlib import Path

import pytest
import torch

import diffsmf as ds
from diffsmf.pwl import (
    SCPLNN,
    ErrorCertificate,
    SCPLNNDynamics,
    as_system,
    certify_error,
    fit_scplnn,
)
from diffsmf.pwl.partition import grid_partition

F64 = torch.float64
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load_example():
    spec = importlib.util.spec_from_file_location("pendulum_scplnn",
                                                  EXAMPLES / "pendulum_scplnn.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _smooth(x):
    return torch.stack([torch.sin(1.5 * x[..., 0]) * x[..., 1], 0.3 * x[..., 0] ** 2
                        + torch.cos(x[..., 1])], -1)


def _fitted(seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(3000, 2, generator=g, dtype=F64) * 2 - 1
    model, _ = fit_scplnn(X, _smooth(X), eps=0.02)
    return model, X


# ---------------------------------------------------------------- the certificate
def test_certified_error_is_exact_for_a_parabola_interpolant():
    """x^2 on a 1-D grid of spacing h: the interpolant's max error is h^2 / 4 at the midpoints,
    and the bound (vertex mismatch 0 + r' H r / 8 = h^2 2 / 8) equals it."""
    V, S = grid_partition(torch.tensor([-1.0]), torch.tensor([1.0]), 8)
    model = SCPLNN(V, S, V ** 2)
    cert = certify_error(model, lambda x: x ** 2)
    h = 0.25
    assert float(cert.bound[0]) == pytest.approx(h * h / 4, rel=1e-8)
    x = torch.linspace(-1, 1, 20001, dtype=F64)[:, None]
    err = (model(x) - x ** 2).abs().max().detach()
    assert float(err) == pytest.approx(h * h / 4, rel=1e-6)
    assert cert.method == "certified"


def test_certified_error_bounds_dense_samples_of_a_fitted_model():
    model, X = _fitted()
    cert = certify_error(model, _smooth)
    u = torch.rand(200_000, 2, generator=torch.Generator().manual_seed(9), dtype=F64)
    x = model.lower + u * (model.upper - model.lower)  # the certificate holds on the domain
    with torch.no_grad():
        err = (model(x) - _smooth(x)).abs().amax(0)
    assert bool((err <= cert.bound).all())
    assert bool((cert.bound < 4 * err + 1e-3).all())  # not vacuous
    cert.check(model, (X, _smooth(X)))


def test_certificate_check_refuses_another_model_and_contradicting_samples():
    model, X = _fitted()
    cert = certify_error(model, _smooth)
    with pytest.raises(ValueError, match="certificate: contradicted"):
        cert.check(model, (X, _smooth(X) + 1.0))
    tiny = ErrorCertificate.given(model, 1e-6)
    with pytest.raises(ValueError, match="certificate: contradicted"):
        tiny.check(model, (X, _smooth(X)))
    with torch.no_grad():
        model.weight[0, 0] += 0.1
    with pytest.raises(ValueError, match="certificate: made for another model"):
        cert.check(model)
    bad = ErrorCertificate(torch.tensor([float("nan"), 0.0]), cert.lower, cert.upper,
                           cert.fingerprint, "given")
    with pytest.raises(ValueError, match="certificate: bound"):
        bad.check(model)


# ---------------------------------------------------------------- the System
def test_as_system_adds_the_error_to_the_process_noise_and_checks_inputs():
    model, X = _fitted()
    cert = certify_error(model, _smooth)
    w = torch.full((2,), 0.01)
    x0 = ds.Interval(torch.tensor([-0.2, -0.2]), torch.tensor([0.2, 0.2]))
    sysm = as_system(model, lambda x: x[..., :1], x0, ds.Interval(-w, w), None,
                     certificate=cert)
    W = sysm.process_noise
    assert torch.allclose(W.upper, w + cert.bound) and torch.allclose(W.lower, -w - cert.bound)
    with pytest.raises(ValueError, match="certificate"):
        as_system(model, lambda x: x[..., :1], x0, certificate=cert.bound)
    far = ds.Interval(torch.tensor([0.5, 0.5]), torch.tensor([1.5, 0.6]))
    with pytest.raises(ValueError, match="x0_set"):
        as_system(model, lambda x: x[..., :1], far, certificate=cert)
    # the dynamics: clamped points, enclosures that end at the domain
    f = sysm.f
    edge = torch.tensor([[float(model.upper[0]), 0.0]])
    assert torch.equal(f(torch.tensor([[2.0, 0.0]])), model(edge))
    vl, vh, jl, jh = f.interval_enclosure(torch.tensor([[0.5, 0.0], [0.0, 0.0]]),
                                          torch.tensor([[1.5, 0.1], [0.1, 0.1]]))
    assert bool(vl[0].isnan().all()) and bool(torch.isfinite(jh[1]).all())


def test_dynamics_with_inputs_encloses_over_states_at_the_input():
    g = torch.Generator().manual_seed(1)
    Z = torch.rand(3000, 3, generator=g, dtype=F64) * 2 - 1  # [x1, x2, u]
    Y = torch.stack([Z[:, 0] + 0.1 * Z[:, 1], 0.9 * Z[:, 1] + 0.1 * torch.sin(3 * Z[:, 0])
                     + 0.2 * Z[:, 2]], -1)
    model, _ = fit_scplnn(Z, Y, eps=0.05)
    f = SCPLNNDynamics(model, n_inputs=1)
    x, u = torch.rand(4, 2, generator=g, dtype=F64) - 0.5, torch.rand(4, 1, generator=g) - 0.5
    assert torch.equal(f(x, u), model(torch.cat([x, u], -1)))
    vl, vh, jl, jh = f.interval_enclosure(x - 0.1, x + 0.1, u)
    assert jl.shape == (4, 2, 2)
    pts = x[:, None] + 0.2 * torch.rand(4, 300, 2, generator=g, dtype=F64) - 0.1
    y = f(pts, u[:, None].expand(-1, 300, -1)).detach()
    assert bool((y >= vl[:, None]).all() and (y <= vh[:, None]).all())
    with pytest.raises(ValueError, match="model"):
        SCPLNNDynamics(model, n_inputs=0)
    with pytest.raises(ValueError, match="u:"):
        f(x)


# ---------------------------------------------------------------- the example
@pytest.fixture(scope="module")
def pendulum():
    ex = _load_example()
    model, report, cert, X, Y = ex.fit(samples=6000, eps=0.006)
    return ex, model, report, cert, X, Y


def test_pendulum_fit_is_certified_and_enclosures_are_sound(pendulum):
    ex, model, report, cert, X, Y = pendulum
    assert report.converged and bool((cert.bound < 0.006).all())
    assert bool((report.max_error <= cert.bound).all())
    g = torch.Generator().manual_seed(2)
    lo = torch.tensor([-1.4, -3.8]) + torch.rand(20, 2, generator=g, dtype=F64) * torch.tensor(
        [2.6, 7.4])
    hi = lo + torch.tensor([0.1, 0.2])
    vl, vh, jl, jh = model.interval_enclosure(lo, hi)
    x = lo[:, None] + torch.rand(20, 500, 2, generator=g, dtype=F64) * (hi - lo)[:, None]
    truth = ex.pendulum(x)
    assert bool((truth >= vl[:, None] - cert.bound).all())  # the true map, via the certificate
    assert bool((truth <= vh[:, None] + cert.bound).all())


def test_pendulum_hsnsmf_first_order_remainder_contains_the_true_states(pendulum):
    ex, model, report, cert, X, Y = pendulum
    from diffsmf.audit import containment

    system, truth = ex.model_system(model, cert, X, Y), ex.true_system()
    filt = ds.filters.HSNSMF(system, remainder="mean-value")
    rep = containment(filt, truth, trials=8, steps=30, noise="vertex")
    assert rep.violations == 0 and rep.unbounded == 0 and rep.mean_volume > 0


def test_pendulum_hsnsmf_default_remainder(pendulum):
    """``HSNSMF(system)`` with its default remainder: the engine bounds the PWL model as a
    leaf (first order where the set meets several pieces)."""
    from diffsmf.audit import containment

    ex, model, report, cert, X, Y = pendulum
    system, truth = ex.model_system(model, cert, X, Y), ex.true_system()
    rep = containment(ds.filters.HSNSMF(system), truth, trials=8, steps=30, noise="vertex")
    assert rep.violations == 0 and rep.unbounded == 0


def test_pendulum_example_runs_and_plots(tmp_path, pendulum):
    ex = pendulum[0]
    out = ex.run(trials=3, steps=10, samples=4000, eps=0.008)
    assert out["audit"].violations == 0 and out["states_in_domain"]
    path = tmp_path / "p.png"
    ex.figure(out, path)
    assert path.stat().st_size > 10_000
