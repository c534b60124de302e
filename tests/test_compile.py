"""The compile-ready filter step (issue 11): one graph, no breaks, the same sets.

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
    ("cdsmf", "spring_damper"),
    ("esmf", "spring_damper"),
    ("esmf", "mismatch_quadratic"),  # square H: the two-sided update, traced branch-free
    ("ekf", "spring_damper"),
    ("combined", "radar"),
]


@pytest.fixture(autouse=True, scope="module")
def _fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


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


def test_czsmf_compiled_step_is_one_graph():
    """CZSMF at its caps: one graph (``fullgraph=True``, static shapes); the growing first
    steps run eagerly (``CZSMF._compile_ready``). Fast caps and 2 LP iterations keep the
    trace short; the LPs are unrolled with their fixed count while tracing."""
    from diffsmf.filters.czsmf import CZSMF

    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=5, batch=2, seed=0, noise="vertex")
    kw = dict(max_generators=8, max_constraints=2, elimination="propagation", lp_iters=2)
    eager = CZSMF(s, **kw)
    comp = CZSMF(s, **kw).compile(backend="eager")
    torch._dynamo.utils.counters.clear()  # not cleared by torch._dynamo.reset()
    with torch.no_grad():
        re = eager(tr.y, u=tr.u)
        rc = comp(tr.y, u=tr.u)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1
    torch.testing.assert_close(rc.lower, re.lower, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(rc.upper, re.upper, rtol=1e-10, atol=1e-13)
    assert torch.equal(rc.consistent, re.consistent)
    assert torch.equal(rc.bounded, re.bounded)


@pytest.mark.parametrize(
    "name,system", [("hsnsmf", "spring_damper"), ("cdsmf", "spring_damper"), ("ekf", "bilinear")]
)
def test_steps_per_call_one_graph_same_sets(name, system):
    """``compile(steps_per_call=2)``: forward runs 2 steps per compiled call in one graph (the
    last, shorter part on repeated y / u, its extra states dropped) and gives the eager sets;
    CDSMF's first step (the initial box in its extras) runs in the same graph."""
    s = ds.systems.get(system)
    tr = s.simulate(steps=5, batch=2, seed=1, noise="vertex")  # 5 = 2 + 2 + 1 (+ 1 padded)
    eager = ds.filters.by_name(name)(s)
    comp = ds.filters.by_name(name)(s).compile(steps_per_call=2, backend="eager")
    calls, inner = [], comp._compiled_steps
    comp._compiled_steps = lambda *a: calls.append(1) or inner(*a)
    torch._dynamo.utils.counters.clear()
    with torch.no_grad():
        re = eager(tr.y, u=tr.u)
        rc = comp(tr.y, u=tr.u)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1
    assert len(calls) == 3  # 2 + 2 + 1 (+ 1 padded), CDSMF's first step included
    assert rc.lower.shape == re.lower.shape == (2, 6, s.n)
    torch.testing.assert_close(rc.lower, re.lower, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(rc.upper, re.upper, rtol=1e-10, atol=1e-13)
    assert torch.equal(rc.consistent, re.consistent)


def test_steps_per_call_gradients_and_online_step():
    """Gradients through the K-step graph equal the eager ones (the padded steps feed no
    loss); the online ``step`` still runs one step per call; a bad K raises."""
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=5, batch=2, seed=0)
    filt = ds.filters.HSNSMF(s).compile(steps_per_call=2, backend="eager")
    filt(tr.y).volume[:, 1:].log().mean().backward()
    ref = ds.filters.HSNSMF(s)
    ref(tr.y).volume[:, 1:].log().mean().backward()
    torch.testing.assert_close(
        filt.raw_process_noise.grad, ref.raw_process_noise.grad, rtol=1e-8, atol=1e-12
    )
    with torch.no_grad():
        st, se = filt.initial_state(batch=2), ref.initial_state(batch=2)
        for k in range(3):
            st, se = filt.step(st, None, tr.y[:, k]), ref.step(se, None, tr.y[:, k])
        torch.testing.assert_close(st.set.interval_hull().upper, se.set.interval_hull().upper)
    for bad in (0, 1.5, True, "2"):
        with pytest.raises(ValueError, match="steps_per_call"):
            ds.filters.HSNSMF(s).compile(steps_per_call=bad)


def test_czsmf_steps_per_call():
    """CZSMF with K steps per call: the growing steps run eagerly, then K-step calls at the
    caps; the same sets as eager."""
    from diffsmf.filters.czsmf import CZSMF

    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=9, batch=2, seed=0, noise="vertex")
    kw = dict(max_generators=8, max_constraints=2, elimination="propagation", lp_iters=2)
    eager = CZSMF(s, **kw)
    comp = CZSMF(s, **kw).compile(steps_per_call=2, backend="eager")
    with torch.no_grad():
        re, rc = eager(tr.y), comp(tr.y)
    torch.testing.assert_close(rc.lower, re.lower, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(rc.upper, re.upper, rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("name,system", [c for c in CASES if c != ("esmf", "spring_damper")])
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


def test_many_compiled_filters_in_one_process():
    """Dynamo keeps at most 8 graphs per code object; each ``compile()`` traces its own copy
    of the step, so nine compiled filters in one process do not hit that limit (with
    the shared method the ninth raised ``FailOnRecompileLimitHit``)."""
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=2, batch=9, seed=0)
    with torch.no_grad():
        for b in range(1, 10):  # nine filters, each with its own batch size (the EKF: fast)
            res = ds.filters.EKF(s).compile(backend="eager")(tr.y[:b])
            assert res.lower.shape == (b, 3, 2)


def test_inductor_default_options_match_eager():
    """The real default path, Inductor with :data:`COMPILE_OPTIONS` (scalar C++ kernels and
    the C++ wrapper), 2 steps per call on a 5-step horizon: the eager EKF's results (the EKF:
    a compile of seconds)."""
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=5, batch=2, seed=3)
    comp = ds.filters.EKF(s).compile(steps_per_call=2)
    with torch.no_grad():
        rc, re = comp(tr.y), ds.filters.EKF(s)(tr.y)
    torch.testing.assert_close(rc.lower, re.lower, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(rc.upper, re.upper, rtol=1e-10, atol=1e-13)


def test_compile_options(monkeypatch):
    """``compile()`` passes :data:`COMPILE_OPTIONS` (no SIMD kernels, C++ wrapper, planned
    buffers) to Inductor, lets the caller override them, leaves them out for another backend or
    a ``mode``, and drops an option that this torch's Inductor does not know."""
    from diffsmf.filters import base

    seen = []
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: seen.append(kw) or fn)
    s = ds.systems.get("spring_damper")
    ds.filters.EKF(s).compile()
    assert seen[-1]["options"] == {
        "cpp.vec_isa_ok": False, "cpp_wrapper": True, "memory_planning": True
    }
    assert seen[-1]["fullgraph"]
    ds.filters.EKF(s).compile(options={"cpp.vec_isa_ok": None, "max_autotune": False})
    assert seen[-1]["options"] == {
        "cpp.vec_isa_ok": None, "cpp_wrapper": True, "memory_planning": True,
        "max_autotune": False,
    }
    ds.filters.EKF(s).compile(backend="eager")
    assert "options" not in seen[-1]
    ds.filters.EKF(s).compile(mode="default")
    assert "options" not in seen[-1]
    with pytest.raises(ValueError, match=r"options: unknown Inductor option\(s\) \['no_such'\]"):
        ds.filters.EKF(s).compile(options={"no_such": 1})
    with pytest.raises(ValueError, match="options: expected a dict"):
        ds.filters.EKF(s).compile(options=["cpp.vec_isa_ok"])
    monkeypatch.setitem(base.COMPILE_OPTIONS, "cpp.no_such_option", 1)
    assert base._compile_options() == {
        "cpp.vec_isa_ok": False, "cpp_wrapper": True, "memory_planning": True
    }


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
    inner = comp._compiled_step
    monkeypatch.setattr(comp, "_compiled_step", lambda *a: calls.append(1) or inner(*a))
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
    import diffsmf.filters.base as base

    skipped = []
    real = base._skip_guards
    monkeypatch.setattr(base, "_skip_guards", lambda: skipped.append(1) or real())
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
            assert len(skipped) - n0 == 6 - 1 - base._GUARDED_STEPS
            hull = st.set.interval_hull()
            torch.testing.assert_close(hull.lower, ref.lower[:, -1], rtol=1e-10, atol=1e-13)
            torch.testing.assert_close(hull.upper, ref.upper[:, -1], rtol=1e-10, atol=1e-13)
    assert comp._stream is None
    n0 = len(skipped)
    comp.step(comp.initial_state(batch=2), None, tr.y[:2, 0])  # outside the block: guarded
    assert len(skipped) == n0


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
    from diffsmf.linearize.jets import jet_eval
    from diffsmf.sets.interval import interval_eval
    from diffsmf.utils import fix_dynamo_matmul

    assert fix_dynamo_matmul()
    A = torch.tensor([[1.0, 2.0], [-3.0, 0.5]], dtype=torch.float64)  # square: A @ x fits too
    lo = torch.tensor([[0.0, -1.0], [0.5, 0.2]], dtype=torch.float64)  # B = n = 2

    def run(lo, hi):
        box = ds.Interval(lo, hi)
        right = interval_eval(lambda x: x @ A, box)
        left = interval_eval(lambda x: A @ x[0], box)
        jet = jet_eval(lambda x: (x * x) @ A, box, order=2)
        return right.lower, right.upper, left.lower, jet.val.upper, jet.grad.lower

    eager = run(lo, lo + 0.25)
    traced = torch.compile(run, backend="eager", fullgraph=True)(lo, lo + 0.25)
    for e, t in zip(eager, traced):
        torch.testing.assert_close(t, e, rtol=0, atol=0)
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
    assert {"hull", "volume"} <= set(comp._compiled_functions)
    # under a recorded gradient the hull and volume stay eager (no compiled backward for them)
    comp2 = ds.filters.MSZM(s).compile(backend="eager")
    tr = s.simulate(steps=2, batch=3, seed=0, noise="vertex")
    res = comp2(tr.y)
    res.volume[:, -1].log().sum().backward()
    assert comp2.raw_process_noise.grad is not None
    assert not {"hull", "volume"} & set(getattr(comp2, "_compiled_functions", {}))


@pytest.mark.parametrize("m", [1, 2, 7, 24, 70])
def test_traced_planar_volume_matches_eager(m):
    """``Zonotope.volume`` in 2-D while traced (the pair table up to ``PAIR_TABLE_MAX_M``
    generators, the sorted sum above) against the eager sorted sum, with zero, parallel and
    opposite generators, and its gradient where the volume is smooth."""
    from diffsmf.sets.zonotope import PAIR_TABLE_MAX_M, Zonotope

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
    torch.testing.assert_close(vt, ve, rtol=1e-12, atol=1e-12 * float(ve.abs().max()))
    ve.sum().backward()
    vt.sum().backward()
    # element 0 is generic; at zero or parallel generators |det| has several subgradients
    torch.testing.assert_close(G2.grad[0], G1.grad[0], rtol=1e-12, atol=1e-12)
