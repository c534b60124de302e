"""Built-in systems of Wang et al. 2022, Song et al. 2017 and Wang et al. 2009: paper values,
simulation, interval extensions.

Independent references: the papers' numbers (Table 2 steady state, switching schedules),
scipy's ODE solver for the Euler-discretised continuous models, sampling for enclosures.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

import diffsmf as ds
from diffsmf.sets import Interval
from diffsmf.sets.interval import interval_eval

OURS = ["bilinear", "spring_damper", "mismatch_quadratic", "fermenter", "vdp"]


def test_registry_lists_builtins():
    assert set(OURS) <= set(ds.systems.names())
    with pytest.raises(ValueError, match="name"):
        ds.systems.get("no_such_system")


@pytest.mark.parametrize("name", OURS)
@pytest.mark.parametrize("noise", ["uniform", "vertex"])
def test_simulates_finite_over_horizon(name, noise):
    sys = ds.systems.get(name)
    tr = sys.simulate(sys.horizon, batch=64, seed=3, noise=noise)
    assert tr.x.shape == (64, sys.horizon + 1, sys.n)
    assert tr.y.shape == (64, sys.horizon, sys.m)
    assert torch.isfinite(tr.x).all() and torch.isfinite(tr.y).all()
    assert sys.x0_set.contains(tr.x[:, 0]).all()
    # measurement noise stays inside its bound: y - h(x) in V
    assert sys.measurement_noise.contains(tr.y - sys.h(tr.x[:, 1:])).all()


def test_sized_name_spec():
    """``get("NAME:N")`` is ``get("NAME", n=N)``; bad specs name the problem."""
    a = ds.systems.get("oscillator_chain:4", dt=0.02)
    b = ds.systems.get("oscillator_chain", n=4, dt=0.02)
    assert (a.n, a.m, a.name) == (b.n, b.m, b.name) == (4, 2, "oscillator_chain(n=4)")
    x = torch.linspace(-0.3, 0.4, 4, dtype=torch.float64)
    torch.testing.assert_close(a.f(x), b.f(x), rtol=0, atol=0)
    for spec, kw, match in [
        ("oscillator_chain:", {}, "NAME:N with N >= 1"),
        ("oscillator_chain:0", {}, "NAME:N with N >= 1"),
        ("oscillator_chain:2.5", {}, "NAME:N with N >= 1"),
        ("oscillator_chain:4", {"n": 4}, "gives the size and so does n=4"),
        ("vdp:3", {}, "system 'vdp' has no size argument"),
        ("nope:3", {}, "unknown system 'nope'"),
    ]:
        with pytest.raises(ValueError, match=match):
            ds.systems.get(spec, **kw)
        with pytest.raises(ValueError, match=match):
            ds.systems.check_name(spec, **kw)
    ds.systems.check_name("oscillator_chain:16")  # valid: no error, nothing built


def test_bilinear_paper_values():
    sys = ds.systems.get("bilinear")
    x = torch.tensor([[0.4, -0.3]])
    u = sys.input_at(0, 1)
    torch.testing.assert_close(u, torch.tensor([[0.6, 0.6]]))
    torch.testing.assert_close(sys.f(x, u, None), torch.tensor([[0.5 * 0.4 * -0.3 + 0.6,
                                                                 0.2 * 0.09 + 0.6]]))
    hull = sys.x0_set.interval_hull()
    torch.testing.assert_close(hull.lower, torch.tensor([-0.3, 0.2]))
    torch.testing.assert_close(hull.upper, torch.tensor([-0.1, 0.4]))


def test_mismatch_quadratic_schedule_and_noise():
    sys = ds.systems.get("mismatch_quadratic")
    sched = [float(sys.theta_schedule(k)) for k in (0, 30, 31, 70, 71, 99)]
    assert sched == [0.11, 0.11, 0.06, 0.06, 0.26, 0.26]
    torch.testing.assert_close(sys.theta_nominal, torch.tensor([0.16]))
    assert sys.x0_set.contains(sys.paper_x0)
    torch.testing.assert_close(sys.process_noise.upper, torch.full((2,), 1e-3))
    torch.testing.assert_close(sys.measurement_noise.upper, torch.full((2,), 1e-2))
    tr = sys.simulate(100, batch=2)
    assert tr.theta[0, 30, 0] == 0.11 and tr.theta[0, 31, 0] == 0.06 and tr.theta[0, 71, 0] == 0.26


def _fermenter_rhs(t, z, D, Sf):
    X, S, P = z
    mu = 0.48 * (1 - P / 50) * S / (1.2 + S + S**2 / 22)
    return [-D * X + mu * X, D * (Sf - S) - mu * X / 0.4, -D * P + (2.2 * mu + 0.2) * X]


def test_fermenter_table2_steady_state_and_ode_reference():
    sys = ds.systems.get("fermenter")
    x0 = sys.paper_x0
    # the paper's initial state is the steady state of eq. 42-43 for the Table 2 values
    rate = (sys.f(x0, None, sys.theta_nominal) - x0) / 1.0
    assert rate.abs().max() < 1e-3
    assert sys.x0_set.contains(x0)
    # Euler (dt = 1 h) vs scipy RK45 over the first regime switch
    tr = sys.simulate(120, batch=1, x0=x0.unsqueeze(0))
    sol_a = solve_ivp(_fermenter_rhs, (0, 80), x0.numpy(), args=(0.15, 20.0), rtol=1e-9)
    sol_b = solve_ivp(_fermenter_rhs, (80, 120), sol_a.y[:, -1], args=(0.09, 17.0), rtol=1e-9)
    np.testing.assert_allclose(tr.x[0, 120].numpy(), sol_b.y[:, -1], rtol=2e-2, atol=2e-2)
    assert [tuple(sys.theta_schedule(k).tolist()) for k in (79, 80, 200, 201)] == [
        (0.15, 20.0), (0.09, 17.0), (0.09, 17.0), (0.21, 23.0)]
    P = sys.parameters
    torch.testing.assert_close(P.lower, torch.tensor([0.09, 17.0]))
    torch.testing.assert_close(P.upper, torch.tensor([0.21, 23.0]))


def test_vdp_matches_ode_reference_and_input():
    sys = ds.systems.get("vdp", dt=0.01, horizon=200)
    assert math.isclose(float(sys.input_at(50, 1)), math.sin(0.5))
    x0 = sys.paper_x0
    tr = sys.simulate(200, batch=1, x0=x0.unsqueeze(0))

    def rhs(t, z):
        return [z[1], z[1] - z[0] - z[0] ** 2 * z[1] + math.sin(t)]

    ref = solve_ivp(rhs, (0, 2.0), x0.numpy(), rtol=1e-10, atol=1e-12).y[:, -1]
    np.testing.assert_allclose(tr.x[0, -1].numpy(), ref, atol=3e-2)  # Euler O(dt) + noise
    assert sys.x0_set.contains(x0)


def test_spring_damper_overrides_and_errors():
    sys = ds.systems.get("spring_damper", dt=0.05, x0_radius=0.2)
    x = torch.tensor([0.1, 0.2])
    expected = torch.tensor([0.1 + 0.05 * 0.2,
                             0.2 + 0.05 * (-1.5 * 0.1 * (1 - 3 * 0.01) - 1.24 * 0.2)])
    torch.testing.assert_close(sys.f(x, None, None), expected)
    torch.testing.assert_close(sys.x0_set.interval_hull().upper, torch.tensor([0.4, 0.5]))
    with pytest.raises(ValueError, match="dt"):
        ds.systems.get("spring_damper", dt=0.0)
    with pytest.raises(ValueError, match="w"):
        ds.systems.get("bilinear", w=-1.0)


@pytest.mark.parametrize("name", OURS)
def test_models_run_on_intervals_and_enclose_samples(name):
    sys = ds.systems.get(name)
    box = sys.x0_set.interval_hull()
    u = sys.input_at(0, 1)
    th = sys.parameters if sys.parameters is not None else None
    F = interval_eval(lambda x: sys.f(x, u, th), box)
    Hy = interval_eval(sys.h, box)
    xs = box.sample(500, generator=torch.Generator().manual_seed(0))
    th_s = None if th is None else th.sample(500, generator=torch.Generator().manual_seed(1))
    fx = sys.f(xs, u, th_s)
    assert isinstance(F, Interval)
    assert ((fx >= F.lower) & (fx <= F.upper)).all()
    hx = sys.h(xs)
    assert ((hx >= Hy.lower) & (hx <= Hy.upper)).all()
