"""A user's own model, checked where the ``System`` is built: what the engine cannot see or
enclose is reported by ``System(...)`` naming ``f`` or ``h``; keyword parameters with defaults
are accepted; a fitted PWL model is enclosed wherever the model calls it; a filter on a fit
without its certified error warns; shape errors name the argument the user got wrong."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import diffsmf as ds

F64 = torch.float64
DT = 0.05


def _box(lo, hi) -> ds.Interval:
    return ds.Interval(torch.tensor(lo, dtype=F64), torch.tensor(hi, dtype=F64))


X0 = _box([0.3, -0.2], [0.5, 0.2])
W = _box([-1e-3, -1e-3], [1e-3, 1e-3])
V = _box([-0.01], [0.01])


def pendulum(x, u=None, theta=None):
    th, om = x[..., 0], x[..., 1]
    return torch.stack([th + DT * om, om - DT * 9.81 * torch.sin(th)], -1)


def h(x):
    return x[..., :1]


# ------------------------------------------------------------------ checks at System(...)
def _detached(x, u=None, theta=None):
    return pendulum(x).detach()


def _float32(x, u=None, theta=None):
    return pendulum(x.float()).double()


def _numpy_part(x, u=None, theta=None):
    s = torch.as_tensor(np.sin(x[..., 0].detach().numpy()))  # invisible to the engine
    return torch.stack([x[..., 0] + DT * x[..., 1], x[..., 1] - DT * 9.81 * s], -1)


@pytest.mark.parametrize(
    ("f", "what"),
    [(_detached, r"\.detach\(\)"), (_float32, "cast of the state to torch.float32"),
     (_numpy_part, "computed outside torch")],
)
def test_system_reports_what_the_engine_cannot_see_naming_f(f, what):
    with pytest.raises(ValueError, match=rf"^f: .*{what}"):
        ds.System(f, h, X0, W, V)


def test_system_reports_a_numpy_part_of_h():
    def h_np(x):
        return torch.as_tensor(np.tanh(x[..., :1].detach().numpy()))

    with pytest.raises(ValueError, match="^h: .*computed outside torch"):
        ds.System(pendulum, h_np, X0, W, V)


def test_numpy_part_is_found_with_x0_a_point_at_the_capture_example():
    """x0 = 0 is where the capture's example lies; the off-centre trial point still sees it."""
    x0 = _box([0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="^f: .*computed outside torch"):
        ds.System(_numpy_part, h, x0, W, V)


def test_keyword_parameters_with_defaults_are_accepted():
    def f_kw(x, u=None, theta=None, gain=9.81, dt=DT):
        th, om = x[..., 0], x[..., 1]
        return torch.stack([th + dt * om, om - dt * gain * torch.sin(th)], -1)

    def f2_kw(x, scale=1.0):  # f(x) with a defaulted extra: called as f(x, u) -> u is None
        return pendulum(x)

    ref = ds.System(pendulum, h, X0, W, V)
    tr = ref.simulate(8, batch=3, seed=1, noise="vertex")
    want = ds.filters.HSNSMF(ref)(tr.y)
    got = ds.filters.HSNSMF(ds.System(f_kw, h, X0, W, V))(tr.y)
    assert torch.equal(got.lower, want.lower) and torch.equal(got.upper, want.upper)
    assert bool(got.sets.contains(tr.x).all())
    assert ds.System(lambda x, u=None, theta=None, k=0.5: pendulum(x), h, X0, W, V).n == 2
    with pytest.raises(ValueError, match="^f: .*needs 4 positional arguments"):
        ds.System(lambda x, u, theta, k: pendulum(x), h, X0, W, V)
    del f2_kw


# ------------------------------------------------------------------ fitted PWL models inside f
@pytest.fixture(scope="module")
def scalar_fits():
    g = torch.Generator().manual_seed(0)
    X = torch.rand(300, 1, dtype=F64, generator=g) * 2 - 1
    m1, _ = ds.pwl.fit_scplnn(X, torch.sin(2 * X), eps=0.05, progress=False)
    m2, _ = ds.pwl.fit_scplnn(X, torch.cos(X), eps=0.05, progress=False)
    return m1, m2


def test_fits_called_inside_f_are_enclosed_wherever_f_keeps_them(scalar_fits):
    """Two scalar fits concatenated: kept in a dict, in a list of an object, or called from
    f(x) (wrapped as f(x, u, theta)), each fit is one enclosed operation (before, the floor of
    its simplex lookup met 'no inclusion rule'); the sets equal those of the same model with
    the fits as globals, which the engine always found."""
    m1, m2 = scalar_fits
    X0s = _box([-0.2, -0.2], [0.2, 0.2])
    Ws = _box([-1e-3, -1e-3], [1e-3, 1e-3])

    def by_global(x, u=None, theta=None):
        return torch.cat([0.5 * m1(x[..., :1]), 0.5 * m2(x[..., 1:]) - 0.4], -1)

    fits = {"a": m1, "b": m2}

    def by_dict(x, u=None, theta=None):
        return torch.cat([0.5 * fits["a"](x[..., :1]), 0.5 * fits["b"](x[..., 1:]) - 0.4], -1)

    class Holder:
        models = [m1, m2]

    def by_holder(x):
        return torch.cat([0.5 * Holder.models[0](x[..., :1]),
                          0.5 * Holder.models[1](x[..., 1:]) - 0.4], -1)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fits carry no certificate (tested below)
        ref = ds.System(by_global, h, X0s, Ws, V)
        tr = ref.simulate(6, batch=4, seed=2, noise="vertex")
        want = ds.filters.HSNSMF(ref, remainder="mean-value")(tr.y)
        for f in (by_dict, by_holder):
            got = ds.filters.HSNSMF(ds.System(f, h, X0s, Ws, V), remainder="mean-value")(tr.y)
            assert torch.equal(got.lower, want.lower) and torch.equal(got.upper, want.upper)
            assert bool(got.sets.contains(tr.x).all())


def test_a_filter_on_an_uncertified_fit_warns_and_a_certified_one_does_not():
    g = torch.Generator().manual_seed(3)
    X = torch.rand(500, 2, dtype=F64, generator=g) * 2 - 1

    def plant(x):
        return 0.9 * torch.stack([x[..., 0] + 0.1 * torch.sin(x[..., 1]), x[..., 1]], -1)

    model, _ = ds.pwl.fit_scplnn(X, plant(X), eps=0.02, progress=False)
    X0s = _box([-0.2, -0.2], [0.2, 0.2])
    bare = ds.System(model, h, X0s, _box([-1e-3] * 2, [1e-3] * 2), V)
    assert bare.uncertified_fit
    with pytest.warns(UserWarning, match=r"fitted SCPLNN without a certified error.*as_system"
                      ) as rec:
        ds.filters.HSNSMF(bare)
    assert rec[0].filename == __file__  # at the user's line
    with pytest.warns(UserWarning, match="fitted SCPLNN"):
        ds.filters.CombinedFilter(bare)
    cert = ds.pwl.certify_error(model, plant)
    good = ds.pwl.as_system(model, h, X0s, _box([-1e-3] * 2, [1e-3] * 2), V, certificate=cert)
    assert not good.uncertified_fit
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds.filters.HSNSMF(good, remainder="mean-value")
    assert not ds.System(pendulum, h, X0, W, V).uncertified_fit


# ------------------------------------------------------------------ shape errors
def test_shape_errors_name_what_the_user_passed():
    sys_u = ds.systems.get("bilinear")  # two inputs
    tr = sys_u.simulate(10, batch=2, seed=0)
    filt = ds.filters.HSNSMF(sys_u)
    with pytest.raises(ValueError, match=r"^y: shape \(10, 2, 1\) and u: shape \(2, 10, 2\) "
                       r"disagree on which dimension is time"):
        filt(tr.y.transpose(0, 1), u=tr.u)
    with pytest.raises(ValueError, match=r"^y: shape \(2, 10, 1\) and u: shape \(10, 2, 2\)"):
        filt(tr.y, u=tr.u.transpose(0, 1))
    sd = ds.systems.get("spring_damper")
    y = sd.simulate(10, batch=2, seed=0).y  # [2, 10, 1]
    with pytest.raises(ValueError, match=r"^y: expected shape \[B, T, 1\] .*got \(2, 10\); "
                       r"with one output keep its dimension: y.unsqueeze\(-1\)"):
        ds.filters.HSNSMF(sd)(y[..., 0])
    res = ds.filters.HSNSMF(sd)(y[0])  # [T, m]: one trajectory
    assert res.lower.shape == (1, 11, 2)


# ------------------------------------------------------------------ progress
class _Counter:
    """A bar factory as ``progress=``: records totals and updates."""

    def __init__(self) -> None:
        self.made: list[dict] = []
        self.done = 0
        self.closed = 0

    def __call__(self, **kwargs):
        self.made.append(kwargs)
        return self

    def update(self, n: int = 1) -> None:
        self.done += n

    def close(self) -> None:
        self.closed += 1


def test_forward_shows_progress_over_the_steps_and_sets_are_unchanged():
    sd = ds.systems.get("spring_damper")
    tr = sd.simulate(7, batch=3, seed=0, noise="vertex")
    filt = ds.filters.HSNSMF(sd)
    bar = _Counter()
    with torch.no_grad():
        res = filt(tr.y, progress=bar)
        ref = filt(tr.y)
    assert bar.made == [{"total": 7, "desc": "HSNSMF", "unit": "step"}]
    assert bar.done == 7 and bar.closed == 1
    assert torch.equal(res.lower, ref.lower) and torch.equal(res.upper, ref.upper)
    with pytest.raises(ValueError, match="^progress: expected True, False or a callable"):
        filt(tr.y, progress="yes")


@pytest.mark.slow
def test_compile_progress_notes_each_new_batch_size_once(capsys):
    sd = ds.systems.get("spring_damper")
    tr = sd.simulate(3, batch=2, seed=0)
    filt = ds.filters.EKF(sd).compile(backend="eager", progress=True)
    with torch.no_grad():
        filt(tr.y)
        first = capsys.readouterr().err
        filt(tr.y)
        again = capsys.readouterr().err
        filt(tr.y[:1])
        other = capsys.readouterr().err
    assert "diffsmf: compiling EKF's step for batch 2" in first
    assert "diffsmf: compiled in" in first
    assert again == ""
    assert "for batch 1" in other
    quiet = ds.filters.EKF(sd).compile(backend="eager")
    with torch.no_grad():
        quiet(tr.y)
    assert "compiling" not in capsys.readouterr().err


# ------------------------------------------------------------------ fit loss
def test_fit_loss_gradients_match_central_differences_in_a_network_weight():
    """``fit_loss`` (volume + consistency + prediction) through HSNSMF with an absolute
    Stirling step, differentiated in the last-layer weights of a small network inside f:
    autograd against central differences, in float64."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(1, 3), torch.nn.Tanh(),
                              torch.nn.Linear(3, 1)).double()

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, x, u=None, theta=None):
            th, om = x[..., 0], x[..., 1]
            fr = self.net(om.unsqueeze(-1)).squeeze(-1)
            return torch.stack([th + DT * om, om + DT * (-9.81 * torch.sin(th) + fr)], -1)

    system = ds.System(Model(), h, X0, _box([-0.05, -0.05], [0.05, 0.05]), V)
    y = ds.System(pendulum, h, X0, W, V).simulate(4, batch=2, seed=0).y
    filt = ds.filters.HSNSMF(system, stirling_step=0.1)
    weight = net[2].weight
    loss, terms = ds.tuning.fit_loss(filt, y)
    assert set(terms) == {"log_volume", "consistency", "prediction"}
    loss.backward()
    grad = weight.grad.clone()
    eps = 1e-6
    num = torch.zeros_like(grad)
    with torch.no_grad():
        for j in range(weight.numel()):
            weight.view(-1)[j] += eps
            up = float(ds.tuning.fit_loss(filt, y)[0])
            weight.view(-1)[j] -= 2 * eps
            down = float(ds.tuning.fit_loss(filt, y)[0])
            weight.view(-1)[j] += eps
            num.view(-1)[j] = (up - down) / (2 * eps)
    assert bool(grad.abs().sum() > 0)
    assert torch.allclose(grad, num, rtol=1e-5, atol=1e-8), (grad, num)


def test_a_model_that_fails_off_centre_is_named():
    """A module with its own inclusion rule whose forward refuses part of x0_set (a lookup
    table that ends inside it): the off-centre trial point names f and the failure."""

    class Table(torch.nn.Module):
        def forward(self, x):
            if bool((x[..., :1] > 0.43).any()):
                raise RuntimeError("lookup table ends at 0.43")
            return torch.sin(x[..., :1])

        def interval_enclosure(self, lo, hi):  # on 0 <= x_0 <= pi / 2: sin up, cos down
            zero = torch.zeros_like(lo[..., 1:])
            jlo = torch.cat([torch.cos(hi[..., :1]), zero], -1).unsqueeze(-2)  # [..., 1, 2]
            jhi = torch.cat([torch.cos(lo[..., :1]), zero], -1).unsqueeze(-2)
            return torch.sin(lo[..., :1]), torch.sin(hi[..., :1]), jlo, jhi

    table = Table()

    def fragile(x, u=None, theta=None):
        return torch.cat([x[..., :1] + DT * x[..., 1:], x[..., 1:] - DT * table(x)], -1)

    with pytest.raises(ValueError, match=r"^f: f\(x\) at x = .*lookup table ends at 0.43"):
        ds.System(fragile, h, X0, W, V)


def test_tune_and_audit_are_quiet_by_default_and_take_a_bar_factory():
    import inspect

    sd = ds.systems.get("spring_damper")
    tr = sd.simulate(6, batch=4, seed=0, noise="vertex")
    filt = ds.filters.HSNSMF(sd)
    bar = _Counter()
    ds.tuning.tune(filt, ds.tuning.Data(tr.y), params=("process_noise",), epochs=3,
                   batch_size=4, progress=bar)
    assert bar.made == [{"total": 3, "desc": "tune", "unit": "epoch"}] and bar.done == 3
    audit_bar = _Counter()
    rep = ds.audit.containment(filt, trials=5, steps=4, progress=audit_bar)
    assert audit_bar.done == 5 and audit_bar.closed == 1 and rep.trials == 5
    assert inspect.signature(ds.tuning.tune).parameters["progress"].default is False


def test_a_module_subclass_with_a_rule_but_an_inherited_forward_is_one_operation():
    """``class Saturated(nn.Hardtanh)`` adds only ``interval_enclosure``; kept in a list that
    the engine cannot see from ``f``, it is still enclosed by its own rule (a box that is
    deliberately wider than the exact one shows which enclosure was used)."""

    class Saturated(torch.nn.Hardtanh):
        def interval_enclosure(self, lo, hi):
            d = lo.shape[-1]
            eye = torch.eye(d, dtype=lo.dtype).expand(*lo.shape[:-1], d, d)
            return lo.clamp(-1, 1) - 0.5, hi.clamp(-1, 1) + 0.5, 0 * eye, eye

    parts = [Saturated()]

    def f(x, u=None, theta=None):
        return 0.9 * x + 0.1 * parts[0](x)

    system = ds.System(f, h, X0, W, V)
    from diffsmf.interval.engine import StepModel, enclose

    box = ds.Interval(X0.lower.unsqueeze(0), X0.upper.unsqueeze(0))
    enc = enclose(StepModel(system.f, None, None), box, 1)
    exact = 0.9 * X0.upper + 0.1 * X0.upper.clamp(-1, 1)
    assert bool((enc.val.upper[0] >= exact + 0.05 - 1e-12).all())  # the rule's +0.5, times 0.1
    assert torch.nn.Hardtanh.forward is not None and "forward" not in vars(Saturated)
    assert torch.equal(Saturated()(torch.tensor([2.0])), torch.tensor([1.0]))  # restored
