"""The Dynamo-free online step (``diffsmf.filters.streaming``) inside ``filt.streaming()``.

After ``compile()`` with Inductor, ``step`` inside ``streaming()`` in no-grad mode captures the
step with ``make_fx`` and calls Inductor's code directly. These tests compile real Inductor
code (a few seconds each, the EKF's small step) and compare with the eager filter.
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf.filters import streaming
from diffsmf.utils import traced, tracing

_GAIN = 0.9  # read by _f below as a global: a change must give a new compiled step


def _f(x, u=None, theta=None):
    x1, x2 = x[..., 0], x[..., 1]
    return torch.stack([x1 + 0.1 * x2, _GAIN * x2 - 0.1 * torch.sin(x1)], -1)


def _h(x):
    return x[..., :1] + 0.1 * x[..., 1:] ** 2


def _system() -> ds.System:
    box = ds.Interval(torch.tensor([-1.0, -1.0]), torch.tensor([1.0, 1.0]))
    return ds.System(
        _f, _h, box, ds.Interval.from_center_radius(torch.zeros(2), torch.full((2,), 0.02)),
        ds.Interval.from_center_radius(torch.zeros(1), torch.full((1,), 0.05)),
        process_cov=torch.eye(2) * 1e-4, measurement_cov=torch.eye(1) * 1e-3, name="gain",
    )


@pytest.fixture(autouse=True)
def _fresh_dynamo():
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def _unique_graphs() -> int:
    return torch._dynamo.utils.counters["stats"]["unique_graphs"]


def _run(filt, y, B):
    st = filt.initial_state(batch=B)
    for k in range(y.shape[1]):
        st = filt.step(st, None, y[:, k])
    return st


def _close(a, b) -> None:
    """Same set and extras (the EKF's covariance) to rounding."""
    for x, y in zip(a.set._tensors(), b.set._tensors()):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14)
    assert a.extras.keys() == b.extras.keys()
    for k in a.extras:
        torch.testing.assert_close(a.extras[k], b.extras[k], rtol=1e-12, atol=1e-14)


def test_traced_makes_tracing_true():
    assert not tracing()
    with traced():
        assert tracing()
        with traced():
            assert tracing()
        assert tracing()
    assert not tracing()


def test_streaming_step_is_dynamo_free_and_matches_eager():
    """Inside ``streaming()`` (no grad) the compiled EKF step runs without Dynamo (no graph is
    captured by it), in ``step`` and in ``forward``'s loop, and gives the eager filter's
    states; the compiled steps are reused by the next block of the same configuration and
    by slices of ``y`` with other strides."""
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=8, batch=2, seed=3)
    eager, comp = ds.filters.EKF(s), ds.filters.EKF(s).compile()
    n0 = _unique_graphs()
    with torch.no_grad():
        ref = _run(eager, tr.y, 2)
        with comp.streaming():
            got = _run(comp, tr.y, 2)
            ((direct, _),) = comp._runtime.direct_cache.values()
            built = len(direct._entries)
        with comp.streaming():
            again = _run(comp, tr.y, 2)
            longer = s.simulate(steps=11, batch=2, seed=3).y  # other strides of y[:, k]
            _close(_run(comp, longer, 2), _run(eager, longer, 2))
            res, res_ref = comp(longer), eager(longer)  # forward's loop takes them too
    for f in ("lower", "upper", "center", "covariance"):
        torch.testing.assert_close(getattr(res, f), getattr(res_ref, f), rtol=1e-12, atol=1e-14)
    assert _unique_graphs() == n0  # Dynamo traced nothing
    assert built >= 1 and len(direct._entries) == built  # the later blocks compiled nothing
    for a, b in ((got, ref), (again, ref)):
        _close(a, b)
        assert torch.equal(a.consistent, b.consistent)


def test_a_changed_global_or_attribute_gives_a_new_compiled_step():
    """The captured step bakes in what the system's functions read; a change of a global they
    read (a number, or a tensor replaced by another) or of a filter attribute between
    ``streaming()`` blocks must not reuse it."""
    global _GAIN
    s = _system()
    tr = s.simulate(steps=4, batch=1, seed=0)
    comp = ds.filters.EKF(s).compile()
    old = _GAIN
    try:
        with torch.no_grad():
            for gain in (0.9, 0.5, 0.7, 0.3):
                # 0.7 and 0.3 as tensors: a tensor global is keyed by identity and version
                # (the cache pins the keyed objects, so no new tensor can take a keyed id)
                _GAIN = None
                _GAIN = gain if gain > 0.4 and gain != 0.7 else torch.tensor(gain)
                with comp.streaming():
                    got = _run(comp, tr.y, 1)
                ref = _run(ds.filters.EKF(s), tr.y, 1)
                _close(got, ref)
    finally:
        _GAIN = old
    assert len(comp._runtime.direct_cache) == 4
    key = streaming.config_key(comp)
    comp.skip_nan = True
    assert streaming.config_key(comp) != key
    comp.skip_nan = False
    assert streaming.config_key(comp) == key


def test_direct_step_validates_inputs_and_grad_mode_uses_dynamo(monkeypatch):
    """Bad ``y`` raises as in ``step`` (shape, inf, NaN); with autograd recording the call
    takes the Dynamo-compiled step instead (the direct graphs are no-grad only)."""
    s = ds.systems.get("spring_damper")
    comp = ds.filters.EKF(s).compile()
    st = comp.initial_state(batch=2)
    with torch.no_grad(), comp.streaming():
        for bad, msg in ((torch.zeros(1, 1), "shape"), (torch.zeros(2, 2), "shape"),
                         (torch.full((2, 1), float("inf")), "inf"),
                         (torch.full((2, 1), float("nan")), "NaN")):
            with pytest.raises(ValueError, match=f"y: .*{msg}"):
                comp.step(st, None, bad.double())
        with pytest.raises(ValueError, match="u: "):
            comp.step(st, torch.zeros(2, 1), torch.zeros(2, 1))
        comp.step(st, None, [[0.1], [0.2]])  # a nested list is converted as in step
    calls = []
    monkeypatch.setattr(comp._runtime, "step", lambda *a: calls.append(a) or a[0])
    with torch.enable_grad(), comp.streaming():
        comp.step(st, None, torch.zeros(2, 1, dtype=torch.float64))
    assert len(calls) == 1


def test_a_step_that_cannot_be_captured_falls_back_to_dynamo(monkeypatch):
    """If ``make_fx`` or Inductor fails on a step, ``streaming()`` warns once and the block
    goes on with the Dynamo-compiled step (here the ``"eager"`` backend's capture, fast),
    in ``step`` and in ``forward``: the states are the eager filter's."""
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=4, batch=2, seed=1)
    eager = ds.filters.EKF(s)
    comp = ds.filters.EKF(s).compile(backend="eager")
    comp._runtime.direct_options = ({}, {})  # as after an Inductor compile: streaming() tries

    def fail(*args, **kw):
        raise NotImplementedError("no fake implementation of some op")

    monkeypatch.setattr(streaming.DirectSteps, "_build", fail)
    with torch.no_grad():
        with comp.streaming(), pytest.warns(RuntimeWarning, match="could not be captured"):
            _close(_run(comp, tr.y, 2), _run(eager, tr.y, 2))
        with comp.streaming(), pytest.warns(RuntimeWarning, match="NotImplementedError"):
            res = comp(tr.y)
    torch.testing.assert_close(res.upper, eager(tr.y).upper, rtol=1e-12, atol=1e-14)


def test_streaming_combined_filter_matches_eager():
    """A set filter's captured step (the CombinedFilter: Kalman mean and covariance plus the
    outer Minkowski sums of its mean set) gives the eager states, online and in ``forward``."""
    s = ds.systems.get("radar")
    tr = s.simulate(steps=5, batch=2, seed=2)
    eager, comp = ds.filters.CombinedFilter(s), ds.filters.CombinedFilter(s).compile()
    with torch.no_grad():
        with comp.streaming():
            got = _run(comp, tr.y, 2)
            res = comp(tr.y)
        _close(got, _run(eager, tr.y, 2))
        ref = eager(tr.y)
    for f in ("lower", "upper", "volume"):
        torch.testing.assert_close(getattr(res, f), getattr(ref, f), rtol=1e-10, atol=1e-13)


def test_config_key_pins_every_object_it_keys_by_identity():
    """Every identity in the key belongs to an object in ``pins`` (kept alive with the cache
    entry, so that a new object cannot take over a keyed identity); the key is hashable and
    stable."""
    filt = ds.filters.HSNSMF(_system())
    pins: list = []
    key = streaming.config_key(filt, pins)
    assert hash(key) == hash(streaming.config_key(filt))
    ids = set()

    def walk(k):
        if isinstance(k, tuple):
            if len(k) >= 2 and k[0] in ("T", "id", "M") and isinstance(k[1], int):
                ids.add(k[1])
            for x in k:
                walk(x)

    walk(key)
    assert ids and ids <= {id(p) for p in pins}


def test_small_step_keeps_intermediates_on_the_stack_for_this_compile_only(monkeypatch):
    """A small captured step is compiled with its intermediates in stack arrays (the wrapper
    is Inductor's for the CPU again afterwards), and its outputs are fresh tensors: a state
    kept by the caller does not change when the next step runs."""
    from torch._inductor.codegen import common

    common.init_backend_registration()
    before = common.device_codegens["cpu"].cpp_wrapper_codegen
    used = []
    scoped = streaming._stack_arrays

    def spy(enable):
        used.append(enable)
        return scoped(enable)

    monkeypatch.setattr(streaming, "_stack_arrays", spy)
    s = ds.systems.get("spring_damper")
    y = s.simulate(steps=3, batch=2, seed=1).y
    eager, comp = ds.filters.EKF(s), ds.filters.EKF(s).compile()
    with torch.no_grad(), comp.streaming():
        st1 = comp.step(comp.initial_state(batch=2), None, y[:, 0])
        kept = [t.clone() for t in st1.set._tensors()]
        st2 = comp.step(st1, None, y[:, 1])
        ref1 = eager.step(eager.initial_state(batch=2), None, y[:, 0])
        ref2 = eager.step(ref1, None, y[:, 1])
    assert used == [True]
    assert common.device_codegens["cpu"].cpp_wrapper_codegen is before
    for a, b in zip(st1.set._tensors(), kept):
        assert torch.equal(a, b)
    _close(st1, ref1)
    _close(st2, ref2)


def test_streaming_compiles_with_the_filters_options_at_any_batch(monkeypatch):
    """The captured step goes to Inductor with the filter's `compile()` options and no
    memory planning (torch 2.13's planner gave wrong bounds); a small one keeps its
    intermediates on the stack, a large one does not. Inductor is replaced by the captured
    graph itself here, so the states must be the eager filter's."""
    seen = []

    def fake_inductor(gm, example, options=None):
        seen.append(options)
        return lambda *args: gm(*args)

    monkeypatch.setattr(torch._inductor, "compile", fake_inductor)
    s = ds.systems.get("spring_damper")
    eager, comp = ds.filters.EKF(s), ds.filters.EKF(s).compile()
    for B in (2, 4096):
        y = s.simulate(steps=2, batch=B, seed=0).y
        with torch.no_grad(), comp.streaming():
            _close(_run(comp, y, B), _run(eager, y, B))
    small, large = seen
    assert small["aot_inductor.allow_stack_allocation"] is True
    assert "aot_inductor.allow_stack_allocation" not in large
    assert not small["memory_planning"] and not large.get("memory_planning", False)
    # a small step stores values read more than twice or made by more than 16 ops (faster to
    # compile), unless it sorts (a library sort keeps tensor handles, one per stored value)
    assert small["realize_reads_threshold"] == 2 and small["realize_opcount_threshold"] == 16
    assert "realize_reads_threshold" not in large
    # MSZM's reduction orders its generators by ranks while traced, not by a sort: the
    # small-step options apply to it too
    mszm = ds.filters.MSZM(s).compile()
    y = s.simulate(steps=2, batch=2, seed=0).y
    with torch.no_grad(), mszm.streaming():
        _close(_run(mszm, y, 2), _run(ds.filters.MSZM(s), y, 2))
    assert seen[-1]["aot_inductor.allow_stack_allocation"] is True
    assert seen[-1]["realize_reads_threshold"] == 2


def test_has_sort_finds_sorts_in_a_captured_graph():
    from torch.fx.experimental.proxy_tensor import make_fx

    from diffsmf.filters.streaming import _has_sort

    x = torch.randn(5, dtype=torch.float64)
    assert _has_sort(make_fx(lambda t: torch.sort(t).values * 2)(x))
    assert _has_sort(make_fx(lambda t: t[torch.argsort(t)])(x))
    assert not _has_sort(make_fx(lambda t: (t * 2).exp().amax())(x))


def _inductor(fn, example):
    from torch._inductor import compile as inductor_compile
    from torch.fx.experimental.proxy_tensor import make_fx

    with torch.no_grad():  # as `DirectSteps` captures
        gm = make_fx(fn, tracing_mode="fake", _allow_non_fake_inputs=True)(*example)
        from diffsmf.filters.runtime import compile_options

        return inductor_compile(gm, example, options=compile_options())  # as `compile()`


def test_entry_calls_inductors_code_directly_only_where_the_wrappers_do_nothing():
    """`streaming._entry`: a graph with constants of its own and fresh outputs is called at its
    Inductor entry (the wrapped call's outputs, bit for bit, on new inputs too); a graph that
    returns one of its inputs keeps AOTAutograd's wrapper (which returns that input itself)."""
    w = torch.tensor([0.5, -2.0, 3.0])
    x, y = torch.randn(4, 3), torch.randn(4, 3)

    def fresh(a, b):
        return [torch.sin(a) * w + b, (a > b).all(-1)]

    compiled = _inductor(fresh, [x, y])
    call, head = streaming._entry(compiled, [x, y])
    assert call is compiled.current_callable and len(head) >= 1  # w is the graph's constant
    x2, y2 = torch.randn(4, 3), torch.randn(4, 3)
    got, ref = call([*head, x2, y2]), compiled(x2, y2)
    assert len(got) == 2 and all(torch.equal(a, b) for a, b in zip(got, ref))

    def alias(a, b):
        return [a, a * b]

    compiled = _inductor(alias, [x, y])
    call, head = streaming._entry(compiled, [x, y])
    assert head == [] and call([x, y])[0] is x  # the wrapper, which returns x itself
