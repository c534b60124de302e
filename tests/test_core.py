"""Tests of the shared pieces: System.simulate, Positive hyperparameters, the
filter base loop (NaN handling, result assembly) and the CLI dispatcher."""

import math
import warnings

import pytest
import torch

import diffsmf as ds
from diffsmf.cli import main as cli_main
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.utils import Positive, register_positive


def linear_system(n: int = 2) -> ds.System:
    A = torch.tensor([[0.9, 0.2], [0.0, 0.8]])[:n, :n]
    return ds.System(
        f=lambda x, u, th: x @ A.mT + u,
        h=lambda x: x[..., :1],
        x0_set=ds.Interval(-torch.ones(n), torch.ones(n)),
        process_noise=ds.Interval(-0.1 * torch.ones(n), 0.1 * torch.ones(n)),
        measurement_noise=ds.Interval(-torch.full((1,), 0.2), torch.full((1,), 0.2)),
        inputs=lambda k: torch.full((n,), 0.01 * k),
    )


def test_simulate_shapes_and_convention():
    sys = linear_system()
    tr = sys.simulate(steps=5, batch=7, seed=1)
    assert tr.x.shape == (7, 6, 2) and tr.y.shape == (7, 5, 1) and tr.u.shape == (7, 5, 2)
    assert tr.theta is None
    # x_k = f(x_{k-1}, u_{k-1}) + w_{k-1}: the residual must be a process-noise sample
    w = tr.x[:, 1:] - sys.f(tr.x[:, :-1], tr.u, None)
    assert (w.abs() <= 0.1 + 1e-12).all()
    # y[:, k-1] = h(x_k) + v_k
    v = tr.y - sys.h(tr.x[:, 1:])
    assert (v.abs() <= 0.2 + 1e-12).all()
    assert sys.x0_set.contains(tr.x[:, 0]).all()


def test_simulate_vertex_noise_hits_the_bounds_and_is_seeded():
    sys = linear_system()
    a = sys.simulate(steps=4, batch=50, seed=3, noise="vertex")
    b = sys.simulate(steps=4, batch=50, seed=3, noise="vertex")
    assert torch.equal(a.x, b.x)
    w = a.x[:, 1:] - sys.f(a.x[:, :-1], a.u, None)
    assert torch.allclose(w.abs(), torch.full_like(w, 0.1))
    with pytest.raises(ValueError, match="noise"):
        sys.simulate(steps=2, noise="gaussian")


def test_simulate_gaussian_parts_have_their_covariance():
    Q = torch.tensor([[0.04, 0.01], [0.01, 0.09]])
    sys = ds.System(
        f=lambda x, u, th: x,
        h=lambda x: x,
        x0_set=ds.Interval(torch.zeros(2), torch.zeros(2)),
        process_cov=Q,
    )
    tr = sys.simulate(steps=1, batch=20000, seed=0)
    emp = torch.cov(tr.x[:, 1].T)
    assert torch.allclose(emp, Q, atol=4e-3)
    with pytest.raises(ValueError, match="process_cov"):
        ds.System(lambda x, u, t: x, lambda x: x, ds.Interval(torch.zeros(2), torch.ones(2)),
                  process_cov=-torch.eye(2))


def test_simulated_data_carry_no_graph_unless_asked():
    """A learnable model: the simulated trajectory is data (it feeds any number of training
    steps, as torch.distributions' sample); ``differentiable=True`` keeps the graph (rsample):
    the gradient of the final state's sum through one step of ``x + a x`` is ``x0`` summed."""
    a = torch.nn.Parameter(torch.tensor(0.5))
    sys_ = ds.System(lambda x: x + a * x, lambda x: x[..., :1], ds.Interval([1.0, 2.0], [1.0, 2.0]))
    tr = sys_.simulate(steps=1)
    assert not tr.x.requires_grad and not tr.y.requires_grad
    opt = torch.optim.SGD([a], lr=0.1)
    for _ in range(2):  # a second backward through the same data: no freed graph
        opt.zero_grad()
        ((tr.y - a) ** 2).sum().backward()
        opt.step()
    tr = sys_.simulate(steps=1, differentiable=True)
    (g,) = torch.autograd.grad(tr.x[:, -1].sum(), a)
    assert g.item() == pytest.approx(3.0)
    with torch.no_grad():
        assert not sys_.simulate(steps=1, differentiable=True).x.requires_grad


def test_system_rejects_bad_sets():
    with pytest.raises(ValueError, match="x0_set"):
        ds.System(lambda x, u, t: x, lambda x: x, x0_set=torch.zeros(2))
    with pytest.raises(ValueError, match="measurement_noise"):
        ds.System(lambda x, u, t: x, lambda x: x[..., :1],
                  ds.Interval(torch.zeros(2), torch.ones(2)),
                  measurement_noise=ds.Interval(torch.zeros(2), torch.ones(2)))


class _Holder(torch.nn.Module):
    bound = Positive()

    def __init__(self, v):
        super().__init__()
        register_positive(self, "bound", v)


def test_positive_parameter_roundtrip_and_gradient():
    m = _Holder(torch.tensor([1e-3, 2.0, 0.0]))
    assert torch.allclose(m.bound, torch.tensor([1e-3, 2.0, 0.0]))
    m.bound.sum().backward()
    assert m.raw_bound.grad is not None and torch.isfinite(m.raw_bound.grad).all()
    m.bound = torch.tensor([5.0, 6.0, 7.0])
    assert torch.allclose(m.bound, torch.tensor([5.0, 6.0, 7.0]))
    with pytest.raises(ValueError, match="bound"):
        m.bound = torch.tensor([-1.0, 1.0, 1.0])


def test_positive_value_reused_without_grad_follows_every_change():
    m = _Holder(torch.tensor([1.0, 2.0]))
    opt = torch.optim.SGD(m.parameters(), lr=0.5)

    def reference():
        return m.bound_scale * torch.nn.functional.softplus(m.raw_bound.detach())

    with torch.no_grad():
        first = m.bound
        assert m.bound is first  # reused while nothing changed
    m.bound.sum().backward()  # recorded: a fresh value with its graph
    opt.step()  # in-place change of raw
    with torch.no_grad():
        assert torch.equal(m.bound, reference()) and not torch.equal(m.bound, first)
    m.bound = torch.tensor([3.0, 4.0])  # the setter
    with torch.no_grad():
        assert torch.equal(m.bound, torch.tensor([3.0, 4.0]))
    m.load_state_dict({**m.state_dict(), "raw_bound": torch.zeros(2)})
    with torch.no_grad():
        assert torch.equal(m.bound, reference())
    assert m.bound.requires_grad


def test_measurement_events_table_matches_the_bit_rule():
    from diffsmf.filters.events import LOSES_BOUND, FilterEvent
    from diffsmf.filters.state import measurement_events
    from diffsmf.utils import traced

    codes = torch.arange(2 * max(FilterEvent))
    skipped = ((codes & LOSES_BOUND) != 0) * int(FilterEvent.MEASUREMENT_SKIPPED)
    expected = (codes & ~LOSES_BOUND) | skipped
    assert torch.equal(measurement_events(codes), expected)
    with traced():
        assert torch.equal(measurement_events(codes), expected)


class _IntervalFilter(SetFilter):
    """Exact box filter for the linear test system with H = [1, 0] (reference for the loop)."""

    A = torch.tensor([[0.9, 0.2], [0.0, 0.8]])

    def _predict(self, state, u=None):
        box = state.set.linear_map(self.A).interval_hull()
        box = ds.Interval(box.lower + u, box.upper + u).minkowski_sum(self.process_noise_box())
        return state.replace(set=box)

    def _update(self, state, y):
        box, v = state.set, self.measurement_noise_box()
        lo = torch.maximum(box.lower[..., 0], y[..., 0] - v.upper[0])
        hi = torch.minimum(box.upper[..., 0], y[..., 0] - v.lower[0])
        ok = lo <= hi
        lo, hi = torch.where(ok, lo, box.lower[..., 0]), torch.where(ok, hi, box.upper[..., 0])
        new = ds.Interval(torch.stack([lo, box.lower[..., 1]], -1),
                          torch.stack([hi, box.upper[..., 1]], -1))
        return FilterState(set=new, consistent=ok)


def test_predict_hook_checks_u_and_an_overridden_predict_still_runs():
    """``predict`` validates ``u`` before the subclass's ``_predict`` hook; a subclass that
    overrides ``predict`` itself (without the hook) still filters, with the same sets."""
    sys = linear_system()
    tr = sys.simulate(steps=4, batch=3, seed=1, noise="vertex")
    filt = _IntervalFilter(sys)
    with pytest.raises(ValueError, match="u"):
        filt.predict(filt.initial_state(batch=3), torch.zeros(3, 5))

    class Overridden(_IntervalFilter):
        def predict(self, state, u=None):
            return self._predict(state, u)

    ref, got = filt(tr.y, u=tr.u), Overridden(sys)(tr.y, u=tr.u)
    torch.testing.assert_close(got.lower, ref.lower, rtol=0, atol=0)
    torch.testing.assert_close(got.upper, ref.upper, rtol=0, atol=0)


def test_filter_loop_contains_truth_and_handles_nan():
    sys = linear_system()
    tr = sys.simulate(steps=6, batch=64, seed=2, noise="vertex")
    filt = _IntervalFilter(sys)
    res = filt(tr.y, u=tr.u)
    assert res.sets.batch_shape == (64, 7) and res.volume.shape == (64, 7)
    assert res.sets.contains(tr.x).all() and res.consistent.all()
    y = tr.y.clone()
    y[3, 2] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        filt(y, u=tr.u)
    res_skip = _IntervalFilter(sys, skip_nan=True)(y, u=tr.u)
    assert res_skip.sets.contains(tr.x).all()
    assert torch.equal(res_skip.volume[:3], res.volume[:3])
    with pytest.raises(ValueError, match="y"):
        filt(tr.y[..., :0], u=tr.u)


def test_cli_help_and_unknown_command(capsys):
    assert cli_main(["--help"]) == 0
    assert "demo" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli_main(["no-such-command"])


def test_lazy_subpackages_resolve_and_unknown_names_raise():
    assert callable(ds.audit.containment) and callable(ds.pwl.fit_scplnn)
    assert callable(ds.observers.design_lipschitz_observer)
    with pytest.raises(AttributeError, match="no_such_name"):
        ds.no_such_name


def test_sets_promote_lower_precision_inputs_to_float64():
    """The outward rounding margins are float64 margins: float32 input must not stay float32."""
    f32 = torch.float32
    with pytest.warns(UserWarning, match="center: a float32 tensor, in which 0.4 is 0.40000"):
        Z = ds.Zonotope(torch.tensor([0.4, 0.15], dtype=f32), torch.eye(2, dtype=f32))
    E = ds.Ellipsoid(torch.zeros(2, dtype=f32), torch.eye(2, dtype=f32))
    I = ds.Interval(torch.zeros(2, dtype=f32), torch.ones(2, dtype=f32))
    P = ds.Parallelotope(torch.zeros(2, dtype=f32), torch.eye(2))
    for S in (Z, E, I, P):
        assert S.center.dtype == torch.float64
    assert I.contains(torch.full((2,), 0.5, dtype=f32))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_a_rounded_lower_precision_set_bound_is_flagged_at_the_users_line(dtype):
    """0.01 in float32 is 0.009999999776...: a noise bound written as 0.01 would be built on a
    smaller number. The constructor warns, naming the argument, at the caller's line; values
    that are their own decimals (0.5, integers, inf) and float64 or list input pass silently."""
    with pytest.warns(UserWarning, match=r"^upper: a .* tensor, in which .* is") as rec:
        ds.Interval(torch.tensor([-0.5, -2.0]), torch.tensor([0.5, 0.01], dtype=dtype))
    assert [w.filename for w in rec] == [__file__]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds.Interval(torch.tensor([-0.5, -math.inf], dtype=dtype), torch.tensor([0.5, 3.0]))
        ds.Interval([-0.01], [0.01])
        ds.Interval(torch.tensor([-0.01], dtype=torch.float64), torch.tensor([0.01]).double())
        ds.Zonotope(torch.zeros(2, dtype=dtype), 0.25 * torch.eye(2, dtype=dtype))
