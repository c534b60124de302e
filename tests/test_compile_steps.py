"""The compile-ready filter step, continued: CZSMF's graph, several steps per
compiled call, many compiled filters in one process, and the Inductor options.

Split from ``tests/test_compile.py`` so that ``--dist loadfile`` spreads the compile tests
over the workers; the same ``"eager"``-backend approach (see there).
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds

pytestmark = [pytest.mark.usefixtures("fresh_dynamo"), pytest.mark.slow]  # compiles: slow


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
    calls, inner = [], comp._runtime.steps
    comp._runtime.steps = lambda *a: calls.append(1) or inner(*a)
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


def test_compiled_zonotope_volumes_of_two_systems_in_one_process():
    """The compiled hull and volume graphs of MSZM keep only the batch dynamic: after a 2-D
    system's, a 3-D system's sets (other n and m) compile again instead of tracing
    ``math.comb`` of a symbolic generator count (which raised ``Unsupported``), and the
    volumes equal the eager ones; from n = 3 the volume is eager."""
    with torch.no_grad():
        for name in ("bilinear", "cstr"):
            s = ds.systems.get(name)
            tr = s.simulate(steps=4, batch=5, seed=1, noise="vertex")
            filt = ds.filters.by_name("mszm")(s).compile(backend="eager")
            for b in (5, 3):  # two batch sizes: the batch dimension becomes dynamic
                u = None if tr.u is None else tr.u[:b]
                rc = filt(tr.y[:b], u=u)
                re = ds.filters.by_name("mszm")(s)(tr.y[:b], u=u)
                torch.testing.assert_close(rc.volume, re.volume, rtol=1e-9, atol=0.0)
            # the volume is compiled in 2-D only (from n = 3 its trace can take minutes)
            assert ("volume" in filt._runtime.functions) == (s.n == 2)


def test_inductor_default_options_match_eager():
    """The real default path, Inductor with `COMPILE_OPTIONS` (scalar C++ kernels and
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
    """``compile()`` passes `COMPILE_OPTIONS` (no SIMD kernels, C++ wrapper; no memory
    planning, no in-place buffers) to Inductor, lets the caller override them, leaves them
    out for another backend or a ``mode``, and drops an option that this torch's Inductor
    does not know."""
    from diffsmf.filters import runtime

    seen = []
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: seen.append(kw) or fn)
    s = ds.systems.get("spring_damper")
    ds.filters.EKF(s).compile()
    # (no memory planning, no in-place buffers: torch 2.13's Inductor miscompiled steps)
    default = {"cpp.vec_isa_ok": False, "cpp_wrapper": True, "inplace_buffers": False}
    assert [kw["options"] for kw in seen[-2:]] == [default] * 2  # one step and K steps
    assert all(kw["fullgraph"] for kw in seen[-2:])
    ds.filters.EKF(s).compile(options={"cpp.vec_isa_ok": None, "max_autotune": False})
    assert seen[-1]["options"] == {
        "cpp.vec_isa_ok": None, "cpp_wrapper": True, "inplace_buffers": False,
        "max_autotune": False,
    }
    n = len(seen)
    ds.filters.EKF(s).compile(options={"memory_planning": True})  # the user's, if asked
    assert len(seen) == n + 2 and seen[-1]["options"]["memory_planning"] is True
    ds.filters.EKF(s).compile(backend="eager")
    assert "options" not in seen[-1]
    ds.filters.EKF(s).compile(mode="default")
    assert "options" not in seen[-1]
    with pytest.raises(ValueError, match=r"options: unknown Inductor option\(s\) \['no_such'\]"):
        ds.filters.EKF(s).compile(options={"no_such": 1})
    with pytest.raises(ValueError, match="options: expected a dict"):
        ds.filters.EKF(s).compile(options=["cpp.vec_isa_ok"])
    monkeypatch.setitem(runtime.COMPILE_OPTIONS, "cpp.no_such_option", 1)
    assert runtime.compile_options() == {
        "cpp.vec_isa_ok": False, "cpp_wrapper": True, "inplace_buffers": False,
    }
