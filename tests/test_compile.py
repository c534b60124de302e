"""The compile-ready filter step: one graph, no breaks, the same sets.

``torch.compile(..., fullgraph=True)`` raises on any graph break, so compiling the step with
the ``"eager"`` backend (Dynamo's capture without Inductor's code generation, seconds instead
of minutes on this CPU) checks that a whole predict + update step is traced into one graph:
no ``.item()``, no host syncs, no Python branch on tensor values. The compiled filter must
give the eager filter's sets. Inductor itself (the ``filt.compile()`` default) compiles the
same graph; its speed is measured in ``benchmarks/filters_bench.py --compiled``.
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds

CASES = [
    ("hsnsmf", "spring_damper"),
    ("mszm", "spring_damper"),
    ("FRad-B", "spring_damper"),  # MSZM's strip weights: the gains and Bravo's choice
    ("FRad-C", "mismatch_quadratic"),
    ("VolMin-B", "spring_damper"),
    ("zbsmf", "vdp"),
    ("ESO-B", "mismatch_quadratic"),  # the ellipsoidal strip observers, two outputs
    ("cdsmf", "spring_damper"),
    ("esmf", "spring_damper"),
    ("esmf", "mismatch_quadratic"),  # square H: the two-sided update, traced branch-free
    ("ekf", "spring_damper"),
    ("interval", "vdp"),
    ("combined", "radar"),
]


pytestmark = [pytest.mark.usefixtures("fresh_dynamo"), pytest.mark.slow]  # compiles: slow


@pytest.fixture(scope="module")
def hsnsmf_eager_compiled():
    """One compiled HSNSMF (spring_damper, ``"eager"`` backend) shared by the tests of the
    forward / online paths: each compiled filter traces its own graphs (one per batch size and
    grad mode), so sharing it keeps the module's tracing to a few graphs. Each test leaves it as
    it found it (no streaming block open)."""
    s = ds.systems.get("spring_damper")
    return s, ds.filters.HSNSMF(s).compile(backend="eager")


@pytest.mark.parametrize("name,system", CASES)
def test_compiled_step_is_one_graph_and_matches_eager(name, system, hsnsmf_eager_compiled):
    s = ds.systems.get(system)
    tr = s.simulate(steps=3, batch=2, seed=0, noise="vertex")
    eager = ds.filters.by_name(name)(s)
    if name == "hsnsmf":
        comp = hsnsmf_eager_compiled[1]
    else:
        comp = ds.filters.by_name(name)(s).compile(backend="eager")  # fullgraph=True by default
    with torch.no_grad():
        re = eager(tr.y, u=tr.u)
        rc = comp(tr.y, u=tr.u)
    # the traced Jacobian is forward-mode (equal up to rounding); ESMF's rho minimises a flat
    # volume function, where a rounding-level change moves the argmin by ~sqrt(eps)
    rtol = 1e-6 if name == "esmf" else 1e-10
    torch.testing.assert_close(rc.lower, re.lower, rtol=rtol, atol=1e-13)
    torch.testing.assert_close(rc.upper, re.upper, rtol=rtol, atol=1e-13)
    assert torch.equal(rc.consistent, re.consistent)
    assert torch.equal(rc.bounded, re.bounded)


@pytest.mark.parametrize(
    "name,system",
    [("hsnsmf", "spring_damper"), ("cdsmf", "spring_damper"), ("esmf", "mismatch_quadratic"),
     ("combined", "spring_damper")],
)
def test_compiled_step_differentiable(name, system):
    """Gradients flow through the compiled step and equal the eager ones (ESMF's rho step
    takes its derivatives in forward mode while tracing: Dynamo cannot trace
    ``autograd.grad``). The ``"eager"`` backend runs Dynamo's captured graph (the traced code
    path, a third of aot_eager's time here); AOTAutograd's forward / backward split, the
    path Inductor takes, is checked for HSNSMF, MSZM and the EKF through the tuning step in
    tests/test_training_compiled.py."""
    s = ds.systems.get(system)
    tr = s.simulate(steps=3, batch=2, seed=0, noise="vertex")
    filt = ds.filters.by_name(name)(s).compile(backend="eager")
    filt(tr.y).volume[:, 1:].log().mean().backward()
    ref = ds.filters.by_name(name)(s)
    ref(tr.y).volume[:, 1:].log().mean().backward()
    got = {k: p.grad for k, p in filt.named_parameters() if p.grad is not None}
    want = {k: p.grad for k, p in ref.named_parameters() if p.grad is not None}
    assert got.keys() == want.keys() and "raw_process_noise" in got
    assert any(bool((g != 0).any()) for g in got.values())
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-8, atol=1e-12, msg=k)


def test_grad_mode_initial_state_uses_the_same_graph():
    """While training, the constant initial state and the later states (functions of the
    parameters) enter the compiled step with the same ``requires_grad`` signature: one graph
    for the whole horizon (two before: about 40 s more of Inductor compile for HSNSMF at
    B = 64), and the parameters' gradients are the eager ones."""
    graphs = []

    def counting(gm, inputs):  # Dynamo's graphs, run as captured
        graphs.append(gm)
        return gm.forward

    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=4, batch=2, seed=5)
    comp = ds.filters.HSNSMF(s).compile(backend=counting)
    comp(tr.y).volume[:, 1:].log().mean().backward()
    assert len(graphs) == 1
    ref = ds.filters.HSNSMF(s)
    ref(tr.y).volume[:, 1:].log().mean().backward()
    for name, p in ref.named_parameters():
        if p.grad is not None:
            got = dict(comp.named_parameters())[name].grad
            torch.testing.assert_close(got, p.grad, rtol=1e-8, atol=1e-12)
    with torch.no_grad():  # no gradient recorded: the state is left as it is
        comp(tr.y)
    assert len(graphs) == 2  # the no-grad graph


def test_compiled_forward_across_batch_sizes_and_grad_modes(hsnsmf_eager_compiled):
    """``forward`` skips Dynamo's guard checks after its first compiled steps; switching the
    batch size or the grad mode between calls must still pick (or build) the right graph."""
    s, comp = hsnsmf_eager_compiled
    eager = ds.filters.HSNSMF(s)
    for batch, grad in ((2, False), (3, False), (2, True), (3, False), (2, False)):
        tr = s.simulate(steps=5, batch=batch, seed=batch)
        with torch.set_grad_enabled(grad):
            rc, re = comp(tr.y), eager(tr.y)
        assert rc.volume.requires_grad == grad
        torch.testing.assert_close(rc.lower, re.lower, rtol=1e-10, atol=1e-13)
        torch.testing.assert_close(rc.upper, re.upper, rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("name,system", [("hsnsmf", "spring_damper"), ("cdsmf", "spring_damper")])
def test_online_step_runs_the_compiled_step(name, system, hsnsmf_eager_compiled, monkeypatch):
    """``filt.step`` after ``compile()`` (one measurement at a time, the online fast path)
    runs the compiled graph, not the eager step, and gives ``forward``'s eager sets (CDSMF's
    first step, which carries the initial box, included)."""
    s = ds.systems.get(system)
    tr = s.simulate(steps=4, batch=2, seed=1, noise="vertex")
    eager = ds.filters.by_name(name)(s)
    if name == "hsnsmf":
        comp = hsnsmf_eager_compiled[1]
    else:
        comp = ds.filters.by_name(name)(s).compile(backend="eager")
    calls = []
    inner = comp._runtime.step
    monkeypatch.setattr(comp._runtime, "step", lambda *a: calls.append(1) or inner(*a))
    with torch.no_grad():
        ref = eager(tr.y)
        st = comp.initial_state(batch=2)
        for k in range(4):
            st = comp.step(st, None, tr.y[:, k])
    assert len(calls) == 4
    hull = st.set.interval_hull()
    torch.testing.assert_close(hull.lower, ref.lower[:, -1], rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(hull.upper, ref.upper[:, -1], rtol=1e-10, atol=1e-13)


def test_online_step_validates_y(hsnsmf_eager_compiled):
    """The compiled graph skips value checks, so ``step`` checks ``y`` first: shape for the
    state's batch, inf, NaN (unless ``skip_nan``: then the update is skipped, as eagerly)."""
    s, filt = hsnsmf_eager_compiled
    tr = s.simulate(steps=2, batch=2, seed=0)
    st = filt.initial_state(batch=2)
    for bad, msg in ((tr.y[:1, 0], "shape"), (tr.y[:, :1], "shape"),
                     (torch.full((2, 1), float("inf"), dtype=torch.float64), "inf"),
                     (torch.full((2, 1), float("nan"), dtype=torch.float64), "NaN")):
        with pytest.raises(ValueError, match=f"y: .*{msg}"):
            filt.step(st, None, bad)
    big = torch.zeros(65, 1, dtype=torch.float64)  # more than _SMALL_Y entries: tensor check
    big[64] = float("inf")
    with pytest.raises(ValueError, match="y: contains inf"):
        filt.step(filt.initial_state(batch=65), None, big)
    skip = ds.filters.HSNSMF(s, skip_nan=True).compile(backend="eager")
    y = tr.y[:, 0].clone()
    y[1] = float("nan")
    with torch.no_grad():
        new = skip.step(skip.initial_state(batch=2), None, y)
        ref = ds.filters.HSNSMF(s, skip_nan=True).step(skip.initial_state(batch=2), None, y)
    torch.testing.assert_close(new.set.interval_hull().lower, ref.set.interval_hull().lower,
                               rtol=1e-10, atol=1e-13)


def test_streaming_skips_guards_only_for_a_known_structure(monkeypatch, hsnsmf_eager_compiled):
    """``with filt.streaming():`` skips Dynamo's guard checks after two guarded compiled calls
    with the same input structure, and checks fully again when the structure changes (batch
    size, grad mode): the sets stay those of the eager filter throughout."""
    import diffsmf.filters.runtime as runtime

    skipped = []
    real = runtime.skip_guards
    monkeypatch.setattr(runtime, "skip_guards", lambda: skipped.append(1) or real())
    s, comp = hsnsmf_eager_compiled
    eager = ds.filters.HSNSMF(s)
    with comp.streaming():
        for batch, grad in ((2, False), (3, False), (2, True)):
            tr = s.simulate(steps=6, batch=batch, seed=batch)
            n0 = len(skipped)
            with torch.set_grad_enabled(grad):
                st = comp.initial_state(batch=batch)
                for k in range(6):
                    st = comp.step(st, None, tr.y[:, k])
                ref = eager(tr.y)
            # the initial state (an expanded set, no bounded flag) has a structure of its own;
            # from the second step on the structure repeats: 2 guarded calls, then skips
            assert len(skipped) - n0 == 6 - 1 - runtime.GUARDED_STEPS
            hull = st.set.interval_hull()
            torch.testing.assert_close(hull.lower, ref.lower[:, -1], rtol=1e-10, atol=1e-13)
            torch.testing.assert_close(hull.upper, ref.upper[:, -1], rtol=1e-10, atol=1e-13)
    assert comp._runtime.stream is None
    n0 = len(skipped)
    comp.step(comp.initial_state(batch=2), None, tr.y[:2, 0])  # outside the block: guarded
    assert len(skipped) == n0


def test_compiled_loop_restores_the_garbage_collector(hsnsmf_eager_compiled):
    import gc

    s, filt = hsnsmf_eager_compiled
    tr = s.simulate(steps=3, batch=2, seed=0)
    with torch.no_grad():
        filt(tr.y)
    assert gc.isenabled()
    gc.disable()
    try:
        with torch.no_grad():
            filt(tr.y)
        assert not gc.isenabled()  # left as the caller had it
    finally:
        gc.enable()
