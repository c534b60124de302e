"""The compile-ready filter step, continued: the whole module under
``fullgraph=True``, user models written with ``@`` and ``/``, traced geometry against eager,
and the forward loop's garbage-collector and compiled hull / volume paths.

Split from ``tests/test_compile.py`` so that ``--dist loadfile`` spreads the compile tests
over the workers; the same ``"eager"``-backend approach (see there).
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf.filters.runtime import runtime_of

pytestmark = [pytest.mark.usefixtures("fresh_dynamo"), pytest.mark.slow]  # compiles: slow


@pytest.mark.parametrize(
    "name,system",
    [
        ("hsnsmf", "spring_damper"),
        ("mszm", "spring_damper"),
        ("cdsmf", "spring_damper"),
        ("esmf", "mismatch_quadratic"),  # square H: the two-sided update, traced branch-free
        ("ekf", "spring_damper"),
        ("combined", "radar"),
    ],
)
def test_whole_module_compiles_with_fullgraph(name, system):
    """``torch.compile(filt, fullgraph=True)`` (the whole unrolled forward, collect included)
    traces without a graph break and gives the eager result (ESMF on mismatch_quadratic, its
    two-sided update; the one-sided one compiles in
    ``test_compiled_step_is_one_graph_and_matches_eager``)."""
    s = ds.systems.get(system)
    tr = s.simulate(steps=2, batch=2, seed=0, noise="vertex")
    filt = ds.filters.by_name(name)(s)
    whole = torch.compile(filt, fullgraph=True, backend="eager")
    with torch.no_grad():
        rc, re = whole(tr.y, u=tr.u), filt(tr.y, u=tr.u)
    rtol = 1e-6 if name == "esmf" else 1e-10
    torch.testing.assert_close(rc.lower, re.lower, rtol=rtol, atol=1e-13)
    torch.testing.assert_close(rc.upper, re.upper, rtol=rtol, atol=1e-13)


def _matmul_division_system() -> ds.System:
    """A model written with ``@`` and ``/`` (as users write them): Dynamo used to trace
    ``x @ A`` on a jet as ``A @ x`` and interval division branched on the data."""
    A = torch.tensor([[0.9, 0.1], [-0.2, 0.8]], dtype=torch.float64)
    C = torch.tensor([[1.0], [0.5]], dtype=torch.float64)

    def f(x, u=None, th=None):
        return x @ A + 0.05 * x / (2.0 + x * x)

    def h(x):
        return x @ C + 0.1 * torch.sqrt(1.0 + x[..., :1] ** 2)

    return ds.System(f, h, ds.Interval([-0.5, -0.5], [0.5, 0.5]),
                     ds.Interval([-0.01, -0.01], [0.01, 0.01]), ds.Interval([-0.02], [0.02]))


@pytest.mark.parametrize("name", ["hsnsmf", "mszm", "esmf"])
def test_models_with_matmul_and_division_compile(name):
    s = _matmul_division_system()
    tr = s.simulate(steps=3, batch=3, seed=1, noise="vertex")
    with torch.no_grad():
        re = ds.filters.by_name(name)(s)(tr.y)
        rc = ds.filters.by_name(name)(s).compile(backend="eager")(tr.y)
    rtol = 1e-6 if name == "esmf" else 1e-10
    torch.testing.assert_close(rc.lower, re.lower, rtol=rtol, atol=1e-12)
    torch.testing.assert_close(rc.upper, re.upper, rtol=rtol, atol=1e-12)
    assert bool(rc.sets.contains(tr.x).all())


def test_interval_and_jet_matmul_under_compile():
    from diffsmf.interval import rounding
    from diffsmf.linearize.jets import jet_eval
    from diffsmf.sets.interval import interval_eval
    from diffsmf.utils import fix_dynamo_matmul

    assert fix_dynamo_matmul()
    A = torch.tensor([[1.0, 2.0], [-3.0, 0.5]], dtype=torch.float64)  # square: A @ x fits too
    lo = torch.tensor([[0.0, -1.0], [0.5, 0.2]], dtype=torch.float64)  # B = n = 2

    def model(x):  # captured by the engine at its first (eager) call, before compiling
        return (x * x) @ A

    def run(lo, hi):
        box = ds.Interval(lo, hi)
        right = interval_eval(lambda x: x @ A, box)
        left = interval_eval(lambda x: A @ x[0], box)
        jet = jet_eval(model, box, order=2)
        return right.lower, right.upper, left.lower, jet.val.upper, jet.grad.lower

    eager = run(lo, lo + 0.25)
    traced = torch.compile(run, backend="eager", fullgraph=True)(lo, lo + 0.25)
    # the same enclosures up to the rounding step, which is one ulp eagerly (nextafter) and
    # one to two ulps, or at least traced_floor near 0, while traced
    floor = rounding.traced_floor(torch.float64)
    for e, t in zip(eager, traced):
        torch.testing.assert_close(t, e, rtol=8 * torch.finfo(torch.float64).eps, atol=2 * floor)
    # and x @ A is x @ A, not A @ x (the two differ for this square A)
    mid = (lo + lo + 0.25) / 2
    assert bool(((traced[0] <= mid @ A) & (mid @ A <= traced[1])).all())


def test_traced_outer_parallelotope_matches_eager_on_degenerate_batches():
    """Traced (both branches computed, selected per element) and eager (regular elements only,
    or the fallback basis for the batch) give the same T, for regular and rank-deficient
    elements alike."""
    g = torch.Generator().manual_seed(3)
    G = torch.randn(6, 2, 4, generator=g, dtype=torch.float64)
    G[1] = torch.outer(torch.tensor([1.0, 2.0], dtype=torch.float64), G[1, 0])  # rank 1
    G[2] = 0.0  # no generator at all
    G[3, :, 2] = G[3, :, 0]  # parallel columns: ties between bases
    c = torch.zeros(6, 2, dtype=torch.float64)

    def outer(c, G):
        return ds.Zonotope(c, G).to_parallelotope().T

    traced = torch.compile(outer, backend="eager", fullgraph=True)(c, G)
    torch.testing.assert_close(traced, outer(c, G), rtol=0, atol=0)


def test_memory_and_materialize_helpers():
    import platform

    from diffsmf.utils import materialize, retain_freed_memory

    x = torch.randn(3, 2)
    assert materialize(x) is x  # eager: a no-op
    ok = retain_freed_memory()
    assert ok == (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc")
    assert retain_freed_memory() == ok  # idempotent


@pytest.mark.parametrize("name", ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf", "ekf", "combined"])
def test_forward_makes_no_reference_cycles(name):
    """forward pauses the cyclic garbage collector inside its loop: safe only while the steps
    make no reference cycles (which would then pile up until the loop ends)."""
    import gc

    s = ds.systems.get("vdp")
    tr = s.simulate(steps=6, batch=2, seed=0)
    filt = ds.filters.by_name(name)(s)
    gc.collect()
    gc.disable()
    try:
        with torch.no_grad():
            filt(tr.y, u=tr.u)
        filt(tr.y, u=tr.u)  # grad mode too
        assert gc.collect() == 0
    finally:
        gc.enable()


def test_compiled_forward_zonotope_hull_and_volume_match_eager():
    """After compile(), MSZM's forward computes the stacked zonotopes' hull and volume in
    compiled graphs with a dynamic batch dimension (the 2-D volume from the fused pair table):
    the same bounds and volumes as the eager forward (sorted area) up to rounding, for two
    horizons and batch sizes (one graph each), and eagerly again under a recorded gradient."""
    s = ds.systems.get("spring_damper")
    eager = ds.filters.MSZM(s)
    comp = ds.filters.MSZM(s).compile(backend="eager")
    for batch, steps in ((3, 4), (5, 2)):
        tr = s.simulate(steps=steps, batch=batch, seed=batch, noise="vertex")
        with torch.no_grad():
            re, rc = eager(tr.y), comp(tr.y)
        assert rc.volume.shape == (batch, steps + 1)
        torch.testing.assert_close(rc.volume, re.volume, rtol=1e-12, atol=0.0)
        torch.testing.assert_close(rc.lower, re.lower, rtol=1e-12, atol=1e-15)
        torch.testing.assert_close(rc.upper, re.upper, rtol=1e-12, atol=1e-15)
    assert {"hull", "volume"} <= set(comp._runtime.functions)
    # under a recorded gradient the hull and volume stay eager (no compiled backward for them)
    comp2 = ds.filters.MSZM(s).compile(backend="eager")
    tr = s.simulate(steps=2, batch=3, seed=0, noise="vertex")
    res = comp2(tr.y)
    res.volume[:, -1].log().sum().backward()
    assert comp2.raw_process_noise.grad is not None
    assert not {"hull", "volume"} & set(runtime_of(comp2).functions)


@pytest.mark.parametrize("m", [1, 2, 7, 24, 70])
def test_traced_planar_volume_matches_eager(m):
    """``Zonotope.volume`` in 2-D while traced (the pair table up to ``PAIR_TABLE_MAX_M``
    generators, the sorted sum above) against the eager sorted sum, with zero, parallel and
    opposite generators, and its gradient where the volume is smooth."""
    from diffsmf.sets.combinatorics import PAIR_TABLE_MAX_M
    from diffsmf.sets.zonotope import Zonotope

    assert 24 <= PAIR_TABLE_MAX_M < 70
    g = torch.Generator().manual_seed(m)
    G = torch.randn(4, 2, m, dtype=torch.float64, generator=g)
    G[1, :, 0] = 0.0  # a zero generator
    if m > 2:
        G[2, :, 1] = -3.0 * G[2, :, 2]  # opposite and parallel
        G[3] = G[3, :, :1].expand(2, m) * torch.linspace(-1, 1, m, dtype=torch.float64)  # flat
    c = torch.zeros(4, 2, dtype=torch.float64)
    fn = torch.compile(lambda c, G: Zonotope(c, G).volume(), backend="eager", fullgraph=True)
    G1 = G.clone().requires_grad_()
    G2 = G.clone().requires_grad_()
    ve, vt = Zonotope(c, G1).volume(), fn(c, G2)
    torch.testing.assert_close(vt, ve, rtol=1e-12, atol=1e-12 * float(ve.detach().abs().max()))
    ve.sum().backward()
    vt.sum().backward()
    # element 0 is generic; at zero or parallel generators |det| has several subgradients
    torch.testing.assert_close(G2.grad[0], G1.grad[0], rtol=1e-12, atol=1e-12)
