"""The compiled runtime of a filter: ``compile()``, its time loop, ``step`` and ``streaming()``.

`SetFilter` defines what one step is (``predict`` then ``update``, on a `FilterState`); this
module runs that step fast. `compile_filter` compiles the step with ``torch.compile``
(on the flat form of the state, `diffsmf.filters.state.flat_step`), `run_steps` is the time
loop of ``forward`` (eager, Dynamo-compiled with guard skipping once the inputs are known, or
inside `streaming` the Dynamo-free steps of `diffsmf.filters.streaming`), `online_step`
is ``step``, and `compiled_loop` gives other time loops (the tuning pass) the same machinery.
The filter's methods ``compile``, ``eager``, ``compiled_function``, ``step``, ``streaming``
and ``forward`` delegate here.

The runtime keeps what it needs between calls in one `Runtime` object held by the filter
(``filt._runtime``, `runtime_of`), which is not part of the filter's configuration
(`diffsmf.filters.streaming.RUNTIME_ATTRS`).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import sys
import time
import types
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.convex import ConvexSet
from diffsmf.filters.measurements import check_step_y
from diffsmf.filters.state import FilterState, flat_args, flat_step, flat_steps
from diffsmf.filters.streaming import CaptureError, DirectSteps, config_key, known_options
from diffsmf.utils import progress_bar, retain_freed_memory, tracing

__all__ = [
    "COMPILE_OPTIONS",
    "GUARDED_STEPS",
    "compile_filter",
    "compile_options",
    "compiled_function",
    "compiled_hull_and_volume",
    "compiled_loop",
    "eager",
    "online_step",
    "run_steps",
    "skip_guards",
    "step_args",
    "streaming",
    "unflatten",
]

@dataclass(eq=False)
class Runtime:
    """What a compiled filter keeps between calls (one object per filter, `runtime_of`).

    Attributes:
        step: the compiled step ``(state, u, y) -> state`` (None: not compiled).
        steps: ``steps_per_call`` compiled steps in one graph, ``(state, us, ys) -> [state]``.
        steps_per_call: how many steps ``steps`` runs.
        out_type: the set type of the states the compiled step returns.
        compile_kwargs: the ``torch.compile`` arguments of `compile_filter`.
        functions: other compiled functions of the filter by name (`compiled_function`).
        progress: print a note per compile (``compile(progress=True)``).
        guarded_calls: compiled calls with Dynamo's full guard check (`run_steps`).
        direct_options: Inductor options for the Dynamo-free steps (None: not available).
        direct_cache: the Dynamo-free steps per configuration (`_direct_steps`).
        stream: the state of the open ``streaming()`` block (None outside one).
    """

    step: Callable[..., Any] | None = None
    steps: Callable[..., Any] | None = None
    steps_per_call: int = 1
    out_type: type | None = None
    compile_kwargs: dict | None = None
    functions: dict = field(default_factory=dict)
    progress: Any = False
    guarded_calls: int = 0
    direct_options: Any = None
    direct_cache: dict = field(default_factory=dict)
    stream: dict | None = None


def runtime_of(filt: nn.Module) -> Runtime:
    """The filter's `Runtime` (created empty on first use)."""
    rt = filt.__dict__.get("_runtime")
    if rt is None:
        rt = filt.__dict__["_runtime"] = Runtime()
    return rt


#: Compiled steps of a ``forward`` call that run Dynamo's full guard check (counted per call of
#: the compiled function, so eager steps such as CZSMF's growth phase do not count). From then
#: on the step's inputs are the previous compiled step's outputs and same-shaped slices of
#: ``y`` / ``u`` (the same tensor metadata as the step before, and the module does not change
#: inside the loop), so the guards are known to pass and only those that
#: tell cached graphs apart are run (``torch.compiler.set_stance(skip_guard_eval_unsafe=True)``;
#: about a third of a compiled B = 1 step was guard evaluation). ``forward`` resets the count.
GUARDED_STEPS = 2


#: Filter configurations whose Dynamo-free compiled steps are kept (see `_direct_steps`).
_DIRECT_CONFIGS = 4


#: Inductor options of `compile_filter`. A filter step is hundreds of operations on
#: ``[B, n, n]`` tensors with n = 1-32: Inductor vectorises along the innermost dimension, so
#: for small n its SIMD code is mostly tails and remainders, and g++ takes twice as long to build
#: it. Scalar code compiles in about half the time on spring_damper, no-grad and gradient
#: graphs alike, and runs no slower; the sets are the same (the same operations in scalar
#: code).
#: ``cpp_wrapper``: Inductor writes the code that calls the kernels (buffer allocations, size
#: and stride checks, library calls) in C++ instead of Python; at B = 1 that code was most of
#: a compiled step, which it makes nearly twice as fast for HSNSMF and ESMF at B = 1, with
#: the same sets and gradients and cold compiles within 25 %.
#: ``inplace_buffers`` off: torch 2.13's Inductor, writing a kernel's output over an input it
#: took for dead, computed CSTR's HSNSMF step (predict and update in one graph) wrong, the
#: bounds 4e5 from the eager step's; each half alone, or the step without in-place buffers
#: (or without any buffer reuse), gives the eager bounds to 2e-16.
#: ``memory_planning`` stays off (Inductor's default): its planner, which places a call's
#: intermediate buffers in one pool, gave a 6-state HSNSMF step other numbers than the eager
#: step (the bounds 0.26 apart) and failed on CSTR's step with a RecursionError. It saved
#: about 30 us per call at B = 1.
COMPILE_OPTIONS: dict[str, Any] = {
    "cpp.vec_isa_ok": False, "cpp_wrapper": True, "inplace_buffers": False,
}


def compile_options() -> dict[str, Any]:
    """`COMPILE_OPTIONS` that this torch's Inductor knows (`streaming.known_options`)."""
    return known_options(COMPILE_OPTIONS)


def _check_options(options: Any) -> dict[str, Any]:
    """``options`` of `compile_filter` as a dict, with a one-line ``ValueError``
    naming an option this torch's Inductor does not know (``torch.compile`` would list all
    of its hundreds of options in the message)."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ValueError(f"options: expected a dict of Inductor options, got {options!r}")
    import torch._inductor.config as cfg

    known = cfg.get_config_copy()
    bad = [k for k in options if k not in known]
    if bad:
        raise ValueError(f"options: unknown Inductor option(s) {bad} (see torch._inductor.config)")
    return options


def _own_code(fn: Any) -> Any:
    """A copy of the function ``fn`` with a code object of its own.

    Dynamo keeps its compiled graphs on the code object, at most ``recompile_limit`` (8) per
    code object, and with ``fullgraph=True`` one more is a hard error. Every filter's step is
    the same method, so without a copy each (filter, batch size, grad mode) compiled in one
    process would use up that one budget: the ninth, e.g. five filters at two batch sizes in a
    benchmark, raised ``FailOnRecompileLimitHit``. With the copy the budget is per ``compile()``.
    """
    code = fn.__code__.replace()  # an equal, distinct code object
    return types.FunctionType(code, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)


def _gc_paused() -> contextlib.AbstractContextManager:
    """Python's cyclic garbage collector off inside ``forward``'s time loop (restored after);
    a no-op while traced (``torch.compile`` of the whole module).

    The loop allocates Python objects every step (states, sets, and in eager mode thousands of
    tensors), which triggers the collector's scans of every tracked object in the process:
    4-5 % of a compiled step at B = 10,000 and 10-18 % of an eager step at B = 1 here. The
    steps make no reference cycles (``tests/test_compile_models.py`` checks every filter), so
    reference counting frees everything as before; a cycle would only wait for the loop's end.
    """
    return contextlib.nullcontext() if tracing() else _gc_off()


@contextlib.contextmanager
def _gc_off() -> Iterator[None]:
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def skip_guards() -> contextlib.AbstractContextManager:
    """Context that skips Dynamo's guard evaluation (see `GUARDED_STEPS`); a no-op on
    torch versions without ``set_stance(skip_guard_eval_unsafe=...)`` (before 2.6)."""
    set_stance = getattr(torch.compiler, "set_stance", None)
    if set_stance is None:
        return contextlib.nullcontext()
    try:
        return set_stance("default", skip_guard_eval_unsafe=True)
    except TypeError:  # a set_stance without the keyword
        return contextlib.nullcontext()


def _signature(state: FilterState, u: Tensor | None, y: Tensor) -> tuple:
    """What tells compiled step graphs apart, for `streaming`: the set type,
    shape / dtype / device / strides / requires_grad of every input tensor, the extras' keys
    and types, and the grad mode."""

    def meta(t: Any) -> Any:
        if isinstance(t, Tensor):
            return (tuple(t.shape), t.dtype, t.device, t.stride(), t.requires_grad)
        return type(t)

    S = state.set
    return (
        type(S), tuple(meta(t) for t in S._tensors()), meta(state.consistent),
        meta(state.bounded), tuple((k, meta(v)) for k, v in state.extras.items()), meta(u),
        meta(y), torch.is_grad_enabled(),
    )


def _pad_horizon(x: Tensor, K: int) -> Tensor:
    """``x [B, T, d]`` padded along T to a multiple of ``K`` by repeating its last step."""
    pad = -x.shape[1] % K
    if pad == 0:
        return x
    return torch.cat([x, x[:, -1:].expand(x.shape[0], pad, x.shape[2])], 1)


def _flat_hull(filt: nn.Module, *fields: Tensor, set_type: type) -> tuple[Tensor, Tensor]:
    """Interval hull bounds ``[N, n]`` of the set of type ``set_type`` with ``fields``
    (batch ``[N]``); compiled by `compiled_hull_and_volume`."""
    hull = set_type._from_tensors(fields).interval_hull()
    return hull.lower, hull.upper


def _flat_volume(filt: nn.Module, *fields: Tensor, set_type: type) -> Tensor:
    """Volume ``[N]`` of the set of type ``set_type`` with ``fields`` (batch ``[N]``);
    compiled by `compiled_hull_and_volume`."""
    return set_type._from_tensors(fields).volume()


# ------------------------------------------------------------------------------- compile
def compile_filter(
    filt: nn.Module, steps_per_call: int = 1, *, retain_memory: bool = False,
    progress: bool = False, **compile_kwargs: Any,
) -> None:
    """Compile the step of ``filt`` with ``torch.compile(fullgraph=True)`` (`SetFilter.compile`).

    The step (predict + update, the guard included) is traced once per state structure
    (set type and field shapes, batch size, input / measurement shapes) into a single
    graph without host syncs: in the traced code the argument checks that would
    synchronise are skipped (``forward`` still validates ``y`` and ``u`` once for the
    whole horizon, eagerly) and data-dependent branches take their branch-free general
    form (same sets up to rounding; every bound stays guaranteed). ``forward`` then runs
    the compiled step in its time loop (`run_steps`), and ``step`` is the online fast path
    (`online_step`); ``predict`` / ``update`` stay eager.

    Args:
        filt: the filter (a `SetFilter`).
        steps_per_call: ``K >= 1``, the steps of ``forward``'s loop that one compiled call
            runs (one graph of K unrolled steps). Each call of a compiled graph costs a
            fixed framework overhead (about 85 us on this 2-core CPU: Dynamo's frame,
            AOTAutograd's and Inductor's wrappers), which dominates small filters at
            batch 1 (the EKF's step is about 0.13 ms); ``K`` steps share it, at the
            price of a graph (and a compile time) about ``K`` times larger. A last part
            shorter than ``K`` runs the same graph on the last ``y`` / ``u`` repeated and
            its extra states are dropped (steps are causal: the kept states are
            unchanged). The online ``step`` always uses the one-step graph.
        progress: print a line to stderr when a compiled function is first called on a
            new signature (a new batch size, grad mode or set type: Dynamo compiles then,
            for seconds to minutes), and the time it took; off by default.
        retain_memory: opt in to `diffsmf.utils.retain_freed_memory` (glibc): the
            process keeps freed memory for reuse instead of page-faulting the step's
            buffers in again on every call (HSNSMF at B = 10,000: 10.5 % of the step was
            the kernel zeroing pages). Off by default: it is a process-wide setting, as
            ``MALLOC_TRIM_THRESHOLD_`` would be, and ``compile()`` changes no
            process-wide state unless asked.
        compile_kwargs: passed to `torch.compile` (default ``fullgraph=True,
            dynamic=False`` and, for Inductor, ``options=COMPILE_OPTIONS``: no SIMD
            vectorisation of the generated C++ kernels, which halves the compile time
            and is faster at run time for these small-matrix steps, and the C++ wrapper,
            which removes Python from the calls between kernels; pass e.g.
            ``options={"cpp.vec_isa_ok": None, "cpp_wrapper": False}`` for Inductor's
            defaults; Inductor's ``memory_planning`` stays off, see `COMPILE_OPTIONS`).

    Unlike ``nn.Module.compile`` this compiles the step, not the whole unrolled horizon,
    so compile time does not grow with T.
    """
    if isinstance(steps_per_call, bool) or not isinstance(steps_per_call, int) or (
        steps_per_call < 1
    ):
        raise ValueError(f"steps_per_call: must be an integer >= 1, got {steps_per_call!r}")
    if retain_memory:
        retain_freed_memory()
    kw = {"fullgraph": True, "dynamic": False, **compile_kwargs}
    # a fresh runtime; an open streaming() block keeps its state
    rt = Runtime(compile_kwargs=kw, progress=progress, stream=runtime_of(filt).stream)
    if kw.get("backend", "inductor") == "inductor" and "mode" not in kw:
        kw["options"] = {**compile_options(), **_check_options(kw.get("options"))}
        if set(kw) <= {"fullgraph", "dynamic", "options", "backend"} and not kw["dynamic"]:
            rt.direct_options = kw["options"]  # streaming() calls Inductor's graphs directly
    filt.__dict__["_runtime"] = rt
    # each its own code object (own recompile budget, see _own_code); compiled lazily
    one = _quiet(torch.compile(_own_code(flat_step).__get__(filt), **kw), filt, "step")
    multi = _quiet(torch.compile(_own_code(flat_steps).__get__(filt), **kw), filt,
                   f"{steps_per_call} steps")

    def compiled(state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
        if not filt._compile_ready(state):
            return filt._eager_step(state, u, y)
        rt.guarded_calls += 1  # see run_steps
        return unflatten(filt, one(*step_args(filt, state), u, y, type(state.set)))

    def compiled_steps(state: FilterState, us: Tensor | None, ys: Tensor) -> list[FilterState]:
        rt.guarded_calls += 1
        outs = multi(*step_args(filt, state), us, ys, type(state.set))
        return [unflatten(filt, o) for o in outs]

    rt.out_type = type(filt.initial_state(batch=1).set)
    rt.steps_per_call = steps_per_call
    rt.step, rt.steps = compiled, compiled_steps


@contextlib.contextmanager
def eager(filt: nn.Module) -> Iterator[nn.Module]:
    """Inside the block the compiled filter ``filt`` runs eagerly (`SetFilter.eager`); the
    compiled graphs are kept for after the block."""
    saved = runtime_of(filt)
    filt.__dict__["_runtime"] = Runtime(stream=saved.stream)
    try:
        yield filt
    finally:
        filt.__dict__["_runtime"] = saved


class _NoShimNotes(logging.Filter):
    """Drops Inductor's note that an op has no C shim and runs through its proxy executor (a
    working fallback the user cannot act on; it printed one line per op per compile)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "c-shim" not in str(record.msg)


_SHIM_FILTER = _NoShimNotes()


def _quiet(
    compiled: Callable[..., Any], filt: nn.Module | None = None, what: str = "step"
) -> Callable[..., Any]:
    """``compiled`` run with Inductor's proxy-executor notes filtered out, for the duration of
    each call only (the logger is left as it was). With ``compile(progress=True)`` on
    ``filt``, a call on a new signature (shapes, dtypes, grad mode: where Dynamo compiles
    anew) prints a note before and the time it took after, to stderr (`compile_note`)."""
    log = logging.getLogger("torch._inductor.ir")
    seen: set = set()

    def call(*args: Any, **kwargs: Any) -> Any:
        key = None
        if filt is not None and runtime_of(filt).progress:
            key = _call_signature(args)
            key = None if key in seen else key
        t0 = time.perf_counter()
        if key is not None:
            compile_note(filt, what, args)
        log.addFilter(_SHIM_FILTER)
        try:
            out = compiled(*args, **kwargs)
        finally:
            log.removeFilter(_SHIM_FILTER)
        if key is not None:
            seen.add(key)
            print(f"diffsmf: compiled in {time.perf_counter() - t0:.1f} s", file=sys.stderr,
                  flush=True)
        return out

    return call


def _call_signature(args: tuple) -> tuple:
    """What makes Dynamo compile a function anew: the tensors' shapes, dtypes and grad flags,
    the other arguments' types, and the grad mode."""
    parts: list[Any] = [torch.is_grad_enabled()]
    for a in args:
        if isinstance(a, Tensor):
            parts.append((tuple(a.shape), a.dtype, a.requires_grad))
        elif isinstance(a, (tuple, list)):
            parts.append(_call_signature(tuple(a)))
        else:
            parts.append(a if isinstance(a, type) or a is None else type(a))
    return tuple(parts)


def compile_note(filt: nn.Module, what: str, args: tuple) -> None:
    """One line on stderr: what is being compiled, for which batch, and roughly how long it
    takes."""
    first = next((a for a in args if isinstance(a, Tensor) and a.dim() > 0), None)
    batch = "" if first is None else f" for batch {first.shape[0]}"
    print(f"diffsmf: compiling {type(filt).__name__}'s {what}{batch} (once per batch size and "
          "grad mode; from about 10 s for a small model to minutes for a large one on a CPU)"
          "...", file=sys.stderr, flush=True)


def compiled_function(
    filt: nn.Module, name: str, fn: Callable[..., Any], **overrides: Any
) -> Callable[..., Any] | None:
    """``fn(filt, *args)`` compiled with the filter's `compile_filter` arguments (updated
    by ``overrides``, e.g. ``dynamic=None``), or None when the filter is not compiled.

    For steps that wrap the filter's own step (e.g. the tuning step of
    `diffsmf.tuning.losses`, which adds the consistency excess): ``fn`` gets a code object
    of its own (its own recompile budget) and is bound to the filter; the compiled function
    is cached under ``name`` until the next ``compile()``. Call it on `step_args` and
    rebuild the state with `unflatten`, as the compiled step does.
    """
    kw = runtime_of(filt).compile_kwargs
    if kw is None:
        return None
    cache = runtime_of(filt).functions
    if name not in cache:
        cache[name] = _quiet(
            torch.compile(_own_code(fn).__get__(filt), **{**kw, **overrides}), filt,
            name.replace("_", " "))
    return cache[name]


def step_args(filt: nn.Module, state: FilterState) -> tuple:
    """`diffsmf.filters.state.flat_args` for a compiled call; while a gradient is recorded
    for a trainable parameter (of the filter or its system), the state's floating tensors
    enter as grad leaves, so that every step of a training forward has one signature."""
    trains = torch.is_grad_enabled() and any(p.requires_grad for p in filt.parameters())
    return flat_args(state, grad_leaves=trains)


def unflatten(filt: nn.Module, out: tuple) -> FilterState:
    """The `FilterState` of a compiled step's output ``(fields, consistent, bounded,
    extras)`` (its set of the filter's compiled set type)."""
    fields, consistent, bounded, extras = out
    return FilterState(runtime_of(filt).out_type._from_tensors(fields), consistent, extras,
                       bounded)


# ------------------------------------------------------------------------------- time loops
def run_steps(
    filt: nn.Module, state: FilterState, y: Tensor, u: Tensor | None, progress: Any = False
) -> list[FilterState]:
    """The states of ``forward``'s time loop from ``state`` over ``y [B, T, m]`` (``u
    [B, T, p]`` or None, both validated): ``[state, state_1, ..., state_T]``, with a
    progress bar over the steps when ``progress`` asks (`diffsmf.utils.progress_bar`).

    Eager without ``compile()`` (or while traced); inside `streaming` in no-grad mode the
    Dynamo-free steps; else the Dynamo-compiled step (``K`` steps per call), whose guard
    evaluation is skipped after the first `GUARDED_STEPS` compiled calls."""
    bar = None if tracing() else progress_bar(progress, y.shape[1], type(filt).__name__, "step")
    try:
        return _run_steps(filt, state, y, u, bar)
    finally:
        if bar is not None:
            bar.close()


def _run_steps(
    filt: nn.Module, state: FilterState, y: Tensor, u: Tensor | None, bar: Any
) -> list[FilterState]:
    """`run_steps` with ``bar`` (or None) advanced by the steps done."""
    T = y.shape[1]
    states = [state]
    ys = y.unbind(1)
    us = [None] * T if u is None else u.unbind(1)
    rt = runtime_of(filt)
    if rt.step is None or tracing():
        with _gc_paused():
            for k in range(T):
                state = filt._eager_step(state, us[k], ys[k])
                states.append(state)
                if bar is not None:
                    bar.update(1)
        return states
    stream = rt.stream
    if stream is not None and stream["direct"] is not None and not torch.is_grad_enabled():
        try:
            with _gc_paused():
                for k in range(T):  # inside streaming(): the Dynamo-free compiled steps
                    state = _direct_call(filt, stream["direct"], state, us[k], ys[k])
                    states.append(state)
                    if bar is not None:
                        bar.update(1)
            return states
        except CaptureError as err:  # the whole horizon again, with Dynamo's step
            _drop_direct(stream, err)
            state, states = states[0], states[:1]
            if bar is not None and hasattr(bar, "reset"):
                bar.reset(total=T)
    rt.guarded_calls = 0  # compiled calls of this forward with Dynamo's full guard check
    K = rt.steps_per_call
    ys_pad = _pad_horizon(y, K)
    us_pad = None if u is None else _pad_horizon(u, K)
    with contextlib.ExitStack() as stack:
        stack.enter_context(_gc_paused())
        skipping, k = False, 0
        while k < T:
            if K == 1 or not filt._compile_ready(state):
                state = rt.step(state, us[k], ys[k])  # eager when not ready
                states.append(state)
                k += 1
                if bar is not None:
                    bar.update(1)
            else:  # K steps in one graph; a last part past T runs on repeated y / u
                chunk = slice(k, k + K)
                uk = None if us_pad is None else us_pad[:, chunk].contiguous()
                new = rt.steps(state, uk, ys_pad[:, chunk].contiguous())
                states.extend(new[: T - k])
                state = states[-1]
                if bar is not None:
                    bar.update(min(K, T - k))
                k += K
            if not skipping and rt.guarded_calls >= GUARDED_STEPS:
                stack.enter_context(skip_guards())  # once, for the rest of the loop
                skipping = True
    return states


@contextlib.contextmanager
def compiled_loop(
    filt: nn.Module, name: str, fn: Callable[..., Any]
) -> Iterator[Callable[..., tuple[FilterState, Any] | None] | None]:
    """A time loop over a compiled wrapper ``fn`` of the filter's step, as in ``forward``.

    ``fn(filt, fields, consistent, bounded, extras, set_type, *args) -> (flat, out)`` takes a
    state as flat tensors (`diffsmf.filters.state.state_from_flat` rebuilds it) and returns
    the new state as `diffsmf.filters.state.flat_state` gives it, and any output ``out``.
    It is compiled with the filter's `compile_filter` settings (`compiled_function`,
    cached under ``name``).

    Yields None when the filter is not compiled (or while tracing): run the loop eagerly.
    Otherwise yields ``run(state, *args)`` -> ``(new state, out)``, or None for a state that
    the compiled graph does not serve (run that step eagerly). As in ``forward``, after the
    first `GUARDED_STEPS` compiled calls inside the block Dynamo's guard evaluation is
    skipped for the rest of the block, so call ``run`` inside one block on inputs of one
    structure (one batch size, the states that ``run`` returned, same-shaped ``args``).
    """
    compiled = None if tracing() else compiled_function(filt, name, fn)
    if compiled is None:
        yield None
        return
    with contextlib.ExitStack() as stack:
        calls = 0

        def run(state: FilterState, *args: Any) -> tuple[FilterState, Any] | None:
            nonlocal calls
            if not filt._compile_ready(state):
                return None
            flat, out = compiled(*step_args(filt, state), type(state.set), *args)
            calls += 1
            if calls == GUARDED_STEPS:
                stack.enter_context(skip_guards())
            return unflatten(filt, flat), out

        yield run


# ------------------------------------------------------------------------------- online
def online_step(filt: nn.Module, state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
    """``SetFilter.step`` after ``compile()``: the compiled step on validated ``u``, ``y``
    (inside `streaming`: the Dynamo-free step in no-grad mode, else the Dynamo-compiled
    step with its guard checks skipped once two guarded calls saw the same structure)."""
    rt = runtime_of(filt)
    compiled, stream = rt.step, rt.stream
    if stream is not None and stream["direct"] is not None and not torch.is_grad_enabled():
        return _direct_step(filt, stream, state, u, y)
    u = filt._check_u(u, state)
    y = check_step_y(y, state, filt.system.m, filt.system.x0_set.dtype, filt.skip_nan)
    if stream is None:
        return compiled(state, u, y)
    sig = _signature(state, u, y)
    if sig != stream["sig"]:  # new input structure: full guard checks again
        stream.update(sig=sig, guarded=0)
    if stream["guarded"] >= GUARDED_STEPS:
        with skip_guards():
            return compiled(state, u, y)
    before = rt.guarded_calls
    new = compiled(state, u, y)
    stream["guarded"] += rt.guarded_calls > before  # a compiled call
    return new


@contextlib.contextmanager
def streaming(filt: nn.Module) -> Iterator[nn.Module]:
    """Online use of the compiled step without Dynamo.

    ``with filt.streaming(): state = filt.step(state, u, y)`` -- inside the block, after
    ``compile()`` with Inductor and in no-grad mode (``torch.no_grad()``), ``step``
    calls Inductor's compiled code directly, without Dynamo's frame and guards
    (`diffsmf.filters.streaming`): the step is captured once per input structure (set
    type, tensor shapes, strides, dtypes, devices, ``u`` given or not) with ``make_fx``,
    from the same branch-free code that ``torch.compile`` traces, and compiled by Inductor
    (seconds, once; reused by later blocks of the same configuration); the online step then
    skips Dynamo's per-call overhead (docs/filter_core.md). The inputs are still
    validated (``y`` shape, inf / NaN; ``u`` by the system). ``forward`` called inside
    the block runs the same captured step in its loop. While autograd records (or with
    another backend) a call runs the Dynamo-compiled step and skips its guard checks once
    two guarded calls have seen the same input structure.

    The contract: inside the block, do not change the filter or its system (attributes,
    submodules, which tensors are its parameters and buffers, what its functions read).
    Between blocks such changes are allowed: on entry, the filter's configuration
    (`diffsmf.filters.streaming.config_key`) selects the compiled steps, so a changed
    one is compiled anew. Parameters and buffers are inputs of the compiled step (their
    current values are used at every call). Without `compile` it changes nothing.
    """
    rt = runtime_of(filt)
    old = rt.stream
    rt.stream = {
        "sig": None, "guarded": 0, "direct": _direct_steps(filt),
        "n_inputs": filt.system.n_inputs, "m": filt.system.m,
        "dtype": filt.system.x0_set.dtype,
    }
    try:
        yield filt
    finally:
        runtime_of(filt).stream = old


def _direct_step(
    filt: nn.Module, stream: dict, state: FilterState, u: Tensor | None, y: Tensor
) -> FilterState:
    """``step`` inside `streaming` in no-grad mode: the inputs validated as in ``step``
    (the system's dimensions read once per block), then the Dynamo-free compiled step
    (`DirectSteps`)."""
    if u is not None or stream["n_inputs"]:
        u = filt._check_u(u, state)
    y = check_step_y(y, state, stream["m"], stream["dtype"], filt.skip_nan)
    try:
        return _direct_call(filt, stream["direct"], state, u, y)
    except CaptureError as err:
        _drop_direct(stream, err)
    return runtime_of(filt).step(state, u, y)


def _drop_direct(stream: dict, err: CaptureError) -> None:
    """A step that ``make_fx`` / Inductor could not capture: warn once and use the
    Dynamo-compiled step for the rest of the ``streaming()`` block."""
    warnings.warn(
        f"streaming(): the step could not be captured without Dynamo ({err}); the "
        "Dynamo-compiled step is used for the rest of this block", RuntimeWarning,
        stacklevel=5,
    )
    stream["direct"] = None


def _direct_call(
    filt: nn.Module, direct: DirectSteps, state: FilterState, u: Tensor | None, y: Tensor
) -> FilterState:
    """One step of the Dynamo-free compiled graph on validated ``u``, ``y`` (eager for a
    state that the graph does not serve, see ``SetFilter._compile_ready``)."""
    if not filt._compile_ready(state):
        return filt._eager_step(state, u, y)
    y = y.contiguous()  # one compiled step for every slice y[:, k] of a log
    u = None if u is None else u.contiguous()
    fields, consistent, bounded, extras = flat_args(state)
    return unflatten(filt, direct(fields, consistent, bounded, extras, u, y, type(state.set)))


def _direct_steps(filt: nn.Module) -> DirectSteps | None:
    """The Dynamo-free compiled steps (`diffsmf.filters.streaming`) for the filter's
    current configuration, or None when it is not compiled with Inductor."""
    rt = runtime_of(filt)
    options = rt.direct_options
    if options is None or rt.step is None:
        return None
    pins: list = []
    key = config_key(filt, pins)
    cache = rt.direct_cache
    if key not in cache:
        if len(cache) >= _DIRECT_CONFIGS:
            cache.pop(next(iter(cache)))
        # the pinned objects live as long as the key: no other can take their identity
        cache[key] = (DirectSteps(filt, options), pins)
    return cache[key][0]


# ------------------------------------------------------------------------------- results
def compiled_hull_and_volume(
    filt: nn.Module, sets: ConvexSet
) -> tuple[Tensor, Tensor, Tensor] | None:
    """``(lower, upper, volume)`` of the stacked zonotopes ``sets`` (batch ``[B, T+1]``:
    ``[B, T+1, n]`` twice and ``[B, T+1]``) by two compiled graphs, or None where they do
    not apply (use the eager hull and volume).

    After ``compile()``, in no-grad mode, a zonotope's hull and volume run as two compiled
    graphs with a dynamic batch dimension (one each whatever B and T): in 2-D the traced
    volume sums the generator-pair table in one fused loop (`PAIR_TABLE_MAX_M`) instead of
    the eager angle sort, which was about a quarter of a compiled MSZM ``forward`` at
    B = 10,000. The two volumes agree to a few ``m eps`` relative; the sets are untouched.
    From n = 3 the volume stays eager: it sums determinants over the n-subsets of the
    generators, or searches the bases of the outer parallelotope, and tracing that with a
    symbolic batch took over 15 minutes for MSZM on a 6-state model. Other set types (one
    batched determinant for their volume) and recorded gradients stay eager.
    """
    from diffsmf.sets.zonotope import Zonotope

    batch = sets.batch_shape
    if (
        type(sets) is not Zonotope or batch.numel() <= 1
        or torch.is_grad_enabled() or tracing()
    ):
        return None
    # two graphs: the two reductions fused into one graph run several times slower than
    # apart with the filter's scalar-code options (large batches)
    hull_fn = compiled_function(filt, "hull", _flat_hull, dynamic=None)
    volume_fn = (compiled_function(filt, "volume", _flat_volume, dynamic=None)
                 if sets.dim == 2 else None)  # None from n = 3 too (an eager volume)
    if hull_fn is None:  # None when the filter is not compiled
        return None
    fields = [t.reshape(-1, *t.shape[len(batch):]) for t in sets._tensors()]
    for t in fields:  # only the batch is dynamic: n and m pick Python branches (math.comb)
        torch._dynamo.maybe_mark_dynamic(t, 0)
        for d in range(1, t.dim()):
            torch._dynamo.mark_static(t, d)
    lo, hi = hull_fn(*fields, set_type=type(sets))
    vol = sets.volume() if volume_fn is None else volume_fn(*fields, set_type=type(sets))
    return lo.reshape(*batch, -1), hi.reshape(*batch, -1), vol.reshape(batch)
