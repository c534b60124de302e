"""Tuning through the compiled step (``tune(compile=True)``), ``SetFilter.eager()``, and the
guarded step on filters whose predicted and updated sets differ in size (CZSMF).

The compiled rows use Dynamo's ``"aot_eager"`` backend (the capture and AOTAutograd's forward /
backward split without Inductor's code generation: seconds instead of minutes); the path they
exercise is the one ``filt.compile()`` takes with Inductor.
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf.convex import where
from diffsmf.sets import ConstrainedZonotope, Zonotope
from diffsmf.tuning import LossWeights, tune
from diffsmf.tuning.losses import consistency_excess, filter_with_predictions, total_loss

pytestmark = pytest.mark.slow  # compiles the tuning step


@pytest.fixture(scope="module")
def sd():
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=8, batch=6, seed=0, noise="vertex")
    y = tr.y.clone()
    y[0, 3] += 0.3  # one measurement far outside: the guard of filter_with_predictions runs
    return s, y


def _pass(filt, y):
    out = filter_with_predictions(filt, y)
    loss, _ = total_loss(out, None, LossWeights(), use_containment=False, use_consistency=True)
    loss.backward()
    grads = [p.grad.clone() for p in (filt.raw_process_noise, filt.raw_measurement_noise)]
    return out, grads


# with tests/test_compile.py::test_compiled_step_differentiable (HSNSMF, CDSMF, ESMF,
# CombinedFilter) every filter's compiled gradients are checked against eager ones
@pytest.mark.parametrize("name", ["hsnsmf", "mszm", "ekf"])
def test_compiled_guarded_step_equals_eager(sd, name):
    s, y = sd
    eager = ds.filters.by_name(name)(s)
    comp = ds.filters.by_name(name)(s).compile(backend="aot_eager")
    oe, ge = _pass(eager, y)
    oc, gc = _pass(comp, y)
    assert not oe.result.consistent[0, 4]  # the guarded step
    assert torch.equal(oe.result.consistent, oc.result.consistent)
    # rounding-level differences between the traced and the eager evaluation order
    torch.testing.assert_close(oc.result.volume, oe.result.volume, rtol=1e-11, atol=0)
    torch.testing.assert_close(oc.excess, oe.excess, rtol=1e-12, atol=1e-15)
    for a, b in zip(gc, ge):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-15)
    assert "guarded_step" in comp._runtime.functions  # the compiled path ran


def test_tune_compiled_follows_eager(sd):
    s, y = sd
    kw = dict(epochs=3, batch_size=6, progress=False, seed=1)
    re, _ = tune(ds.filters.HSNSMF(s), y, **kw)
    fc = ds.filters.HSNSMF(s).compile(backend="aot_eager")
    rc, _ = tune(fc, y, compile=True, **kw)  # already compiled: used as it is
    for k in re.final:  # rounding-level gradient differences, grown by 3 Adam steps: 2e-6
        torch.testing.assert_close(torch.tensor(rc.final[k]), torch.tensor(re.final[k]),
                                   rtol=1e-5, atol=1e-12)
    assert all(rc.final[k] != rc.initial[k] for k in rc.final)  # it did tune
    with pytest.raises(ValueError, match="compile"):
        tune(ds.filters.HSNSMF(s), y, compile="yes", **kw)


def test_eager_block_bypasses_the_compiled_step(sd):
    s, y = sd

    def refuse(gm, example_inputs):
        raise AssertionError("compiled code called inside eager()")

    f = ds.filters.HSNSMF(s).compile(backend=refuse)
    ref = ds.filters.HSNSMF(s)(y[:2])
    with f.eager():
        res = f(y[:2])
        out = filter_with_predictions(f, y[:2])
    torch.testing.assert_close(res.volume, ref.volume, rtol=0, atol=0)
    torch.testing.assert_close(out.result.volume[:, :1], ref.volume[:, :1], rtol=0, atol=0)
    assert f._runtime.step is not None  # kept for after the block
    with pytest.raises(Exception, match="eager"):
        f(y[:2])


def test_czsmf_guard_with_an_inconsistent_measurement(sd):
    """CZSMF's predicted set has more generators than its update: the guard's select used to
    raise a size mismatch; now the sets are aligned (padded) first."""
    s, y = sd
    out = filter_with_predictions(ds.filters.CZSMF(s), y[:2, :5])
    assert not out.result.consistent[0, 4] and out.result.bounded.all()


def test_czsmf_excess_of_a_point_of_the_predicted_set_is_not_positive():
    """A constrained zonotope is not symmetric about its centre: the output range comes from
    both support values (the symmetric formula reported 81 noise units for a consistent y)."""
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=3, batch=4, seed=0, noise="vertex")
    f = ds.filters.CZSMF(s)
    st = f.initial_state(batch=4)
    for k in range(2):
        st = f.update(f.predict(st), tr.y[:, k])
    pred = f.predict(st).set
    x = pred.sample_extreme(64, generator=torch.Generator().manual_seed(0)).transpose(0, 1)
    assert bool(pred.contains(x, atol=1e-9).all())  # x [64, 4, n]: boundary points
    yv = s.h(x) + f.measurement_noise_center  # a noise-free measurement of a point in the set
    e = torch.stack([consistency_excess(f, pred, yk) for yk in yv])
    assert float(e.detach().max()) <= 1e-6
    assert float(e.detach().max()) > -1.0  # the sampled range reaches near the edge


def test_where_aligns_sets_of_different_sizes():
    g = torch.Generator().manual_seed(0)
    a = Zonotope(torch.randn(3, 2, generator=g), torch.randn(3, 2, 4, generator=g))
    b = Zonotope(torch.randn(3, 2, generator=g), torch.randn(3, 2, 6, generator=g))
    cond = torch.tensor([True, False, True])
    w = where(cond, a, b)
    assert w.generators.shape == (3, 2, 6)
    d = torch.randn(3, 2, generator=g)
    torch.testing.assert_close(w.support(d), torch.where(cond, a.support(d), b.support(d)))
    ca = ConstrainedZonotope.from_set(a).intersect_halfspace(d, a.support(d) - 0.1)
    cb = ConstrainedZonotope.from_set(b)
    cw = where(cond, ca, cb)
    assert cw.num_constraints == ca.num_constraints and cw.num_generators == 6
    torch.testing.assert_close(cw.support(d), torch.where(cond, ca.support(d), cb.support(d)),
                               rtol=1e-6, atol=1e-9)


def test_cli_compile_option(tmp_path, capsys):
    import argparse

    from diffsmf.cli import main as diffsmf_main
    from diffsmf.cli.tune import _merge_config, add_arguments

    ap = argparse.ArgumentParser()
    add_arguments(ap)
    assert _merge_config(ap.parse_args(["--compile"])).compile is True
    assert _merge_config(ap.parse_args([])).compile is False
    bad = tmp_path / "bad.toml"
    bad.write_text('compile = "yes"\n')
    assert diffsmf_main(["tune", "--config", str(bad), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "compile" in err[0] and "true or false" in err[0]


def test_a_step_that_does_not_compile_tunes_eagerly_with_a_warning(sd):
    s, y = sd

    def broken(gm, example_inputs):
        raise RuntimeError("no C++ compiler found")

    kw = dict(epochs=2, batch_size=6, progress=False, seed=1)
    ref, _ = tune(ds.filters.HSNSMF(s), y, **kw)
    f = ds.filters.HSNSMF(s).compile(backend=broken)
    with pytest.warns(RuntimeWarning, match="could not be compiled.*tuning eagerly"):
        rep, _ = tune(f, y, compile=True, **kw)
    assert rep.final == ref.final  # the eager loop, bit for bit
