"""Streaming: compiled filter steps called without Dynamo (the fast path of ``streaming()``).

A call of a ``torch.compile``-d step passes through Dynamo's frame (guard evaluation, or
entering and leaving its skip-guards stance) and AOTAutograd's and Inductor's wrappers before
the kernels run: at batch 1 that is most of a small filter's online step
(docs/filter_core.md). Inside `SetFilter.streaming` the filter does not change (its
documented contract), so the guards have nothing to check. There the step is

1. captured once per input structure with ``make_fx`` on fake tensors, running the same
   branch-free code that ``torch.compile`` traces (`diffsmf.utils.traced`; a host sync
   or a branch on a tensor value raises instead of being baked in), with the filter's
   parameters and buffers as explicit inputs (``torch.func.functional_call``), so that their
   current values are read at every call;
2. compiled by Inductor (``torch._inductor.compile``, the filter's compile options); on the
   CPU, a graph whose intermediates are small (`STACK_BYTES`) keeps them in stack arrays of
   the C++ wrapper (`_stack_arrays`) instead of one tensor handle each;
3. called directly on the flat state tensors.

Which compiled step a call may use is decided by `config_key` (the filter's
configuration, computed once per ``streaming()`` block) and the call's input structure (set
type, tensor shapes, strides, dtypes, devices; computed at every call). Only the no-grad mode
takes this path; while autograd records, ``step`` uses the Dynamo-compiled graph.
"""

from __future__ import annotations

import contextlib
import functools
import operator
import types
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.filters.state import flat_step
from diffsmf.utils import traced

#: Attributes of a filter that change while it runs, not its configuration.
RUNTIME_ATTRS = frozenset({"_runtime"})

#: Compiled structures kept per configuration (least recently used dropped first).
MAX_ENTRIES = 8

#: A captured CPU step whose intermediate values (every node of the graph, summed) take at
#: most this many bytes is compiled with its C++ wrapper's intermediates in stack arrays.
#: Inductor's wrapper otherwise creates one tensor handle per intermediate buffer at every
#: call: about 130 for HSNSMF at batch 1, 65 of the 100 us of its online step (the kernel
#: itself runs in 5 us). Inductor applies its own limit to what it puts on the stack (100 KB
#: after fusion and reuse) and allocates as usual above it.
STACK_BYTES = 1 << 20
_STACK_OPTIONS = {"aot_inductor.allow_stack_allocation": True, "memory_planning": False}

#: Inductor options for a small captured step (`STACK_BYTES`) without library sorts, under
#: the filter's own: an intermediate read more than twice, or computed by more than 16 ops, is
#: stored once instead of recomputed inside every loop that reads it. The code to generate
#: and compile shrinks, and at batch 1 the step is no slower where the stored values live in
#: stack arrays: on spring_damper at B = 1 both HSNSMF and MSZM compile faster and step at
#: least as fast as with Inductor's defaults (`benchmarks/streaming_bench.py`). A step with
#: sorts keeps tensor handles, one more per stored value at every call, and a large batch pays
#: for the stores: both keep the defaults.
SMALL_STEP_OPTIONS = {"realize_reads_threshold": 2, "realize_opcount_threshold": 16}
_SORTS = ("sort", "argsort", "topk", "kthvalue", "msort")


def _value_key(v: Any, pins: list, depth: int = 0) -> Any:
    """A hashable stand-in for a value the step may read, which changes when the value does:
    numbers and strings by value; tensors by identity and in-place version; containers, sets
    (``_tensors()``) and modules by their items; functions by their code, defaults, closure
    cells and the globals their code names (what ``f(x, u, theta)`` of a user's system reads);
    any other object by identity. Nested values are followed 6 levels deep. Every object keyed
    by its identity is appended to ``pins``: the cache keeps them alive with the key, so that
    no other object can take over a keyed identity."""
    if v is None or isinstance(v, (bool, int, float, str, complex, type)):
        return v
    if isinstance(v, Tensor):
        pins.append(v)
        return ("T", id(v), v._version)
    if depth < 6 and not isinstance(v, types.ModuleType):
        d = depth + 1
        if isinstance(v, (tuple, list)):
            return (type(v), tuple(_value_key(x, pins, d) for x in v))
        if isinstance(v, dict):
            return ("D", tuple((k, _value_key(x, pins, d)) for k, x in v.items()))
        if isinstance(v, types.MethodType):
            return ("B", _value_key(v.__func__, pins, d), _value_key(v.__self__, pins, d))
        if isinstance(v, types.FunctionType):
            return _function_key(v, pins, d)
        pins.append(v)
        if isinstance(v, nn.Module):
            return ("M", id(v), _module_key(v, pins, d))
        tensors = getattr(v, "_tensors", None)
        if callable(tensors):
            return (type(v), id(v), tuple(_value_key(t, pins, d) for t in tensors()))
    pins.append(v)
    return ("id", id(v))


def _function_key(f: types.FunctionType, pins: list, depth: int) -> tuple:
    """A function's code, defaults, closure cells and named globals (`_value_key`)."""
    cells = []
    for c in f.__closure__ or ():
        try:
            cells.append(_value_key(c.cell_contents, pins, depth))
        except ValueError:  # an empty cell
            cells.append(None)
    g = f.__globals__
    names = tuple((n, _value_key(g[n], pins, depth)) for n in f.__code__.co_names if n in g)
    return ("F", f.__code__, _value_key(f.__defaults__, pins, depth), tuple(cells), names)


def _module_key(module: nn.Module, pins: list, depth: int) -> tuple:
    out = []
    for mod in module.modules():
        pins.append(mod)
        attrs = tuple(
            (k, _value_key(v, pins, depth)) for k, v in vars(mod).items()
            if k not in RUNTIME_ATTRS and k not in ("_parameters", "_buffers", "_modules")
        )
        tensors = []
        for k, t in (*mod._parameters.items(), *mod._buffers.items()):
            if t is not None:
                pins.append(t)
                tensors.append((k, id(t), tuple(t.shape), t.dtype, t.device))
        out.append((type(mod), id(mod), attrs, tuple(tensors)))
    return tuple(out)


def config_key(module: nn.Module, pins: list | None = None) -> tuple:
    """What a captured step depends on besides its inputs, computed once per ``streaming()``
    block: for every submodule its identity, type, attributes (`_value_key`, which
    follows the system's functions into their closures and globals), and its parameters' and
    buffers' identities and metadata.

    Parameters and buffers enter the compiled step as inputs (their values may change in
    place, e.g. by an optimiser); every other tensor the step reads is a constant of the
    graph, so an in-place change of one (its ``_version``) gives a new key. ``pins`` receives
    the objects keyed by identity (keep them with the key)."""
    return _module_key(module, [] if pins is None else pins, 0)


class CaptureError(RuntimeError):
    """The step could not be captured with ``make_fx`` or compiled by Inductor; the filter
    then uses its Dynamo-compiled step for the rest of the ``streaming()`` block."""


def _meta(t: Tensor) -> tuple:
    """Shape, strides (those of size-1 dims do not matter to the compiled code and are left
    out: a ``y[:, k]`` slice of a ``[1, T, m]`` log then keys as any ``[1, m]`` tensor),
    dtype and device."""
    return (t.shape, tuple(s for s, n in zip(t.stride(), t.shape) if n != 1), t.dtype, t.device)


class _Step(nn.Module):
    """The filter's flat step as a module whose parameters and buffers are the filter's, for
    ``torch.func.functional_call``."""

    def __init__(self, filt: nn.Module) -> None:
        super().__init__()
        self.filt = filt

    def forward(self, *flat: Any) -> Any:
        return flat_step(self.filt, *flat)


class DirectSteps:
    """The compiled one-step graphs of a filter for one configuration, called without Dynamo.

    ``steps(fields, consistent, bounded, extras, u, y, set_type)`` takes the flat state of
    `diffsmf.filters.state.flat_args` (fields ``[B, ...]``, ``consistent [B]``,
    ``bounded [B]``, extras ``{name: [B, ...]}``), ``u [B, p]`` or None and ``y [B, m]``, and
    returns the next flat state, like `diffsmf.filters.state.flat_step`. Call it in no-grad mode.
    """

    def __init__(self, filt: nn.Module, options: dict[str, Any]) -> None:
        self._module = _Step(filt)
        self._options = options
        self._entries: OrderedDict[tuple, Callable] = OrderedDict()
        named = [*self._module.named_parameters(), *self._module.named_buffers()]
        self._names = [k for k, _ in named]
        self._tensors = [t for _, t in named]
        # the last call's output tensors and their structure: when they come back as the
        # next state (the online loop), their metadata is known without reading it again
        self._last: tuple = ((), (), ())
        # the last call's (y, u) metadata and compiled step: a call on the last outputs with
        # the same metadata runs that step without building and looking up its key
        self._last_io: tuple = ((), None)

    def __call__(
        self, fields: Sequence[Tensor], consistent: Tensor, bounded: Tensor,
        extras: dict[str, Tensor], u: Tensor | None, y: Tensor, set_type: type,
    ) -> tuple:
        state = [*fields, consistent, bounded, *extras.values()]
        struct = (set_type, len(fields), tuple(extras))
        io = (_meta(y), None if u is None else _meta(u))
        last_struct, last_out, last_meta = self._last
        if struct == last_struct and len(state) == len(last_out) and all(
            map(operator.is_, state, last_out)
        ):
            if io == self._last_io[0]:  # the online loop: the last call's own step
                out, self._last = self._last_io[1](state, u, y)
                return out
            meta = last_meta
        else:
            meta = tuple(map(_meta, state))
        key = (struct, meta, *io)
        entry = self._entries.get(key)
        if entry is None:
            try:
                entry = self._build(state, u, y, key)
            except Exception as err:  # noqa: BLE001 -- any capture failure: the caller falls back
                raise CaptureError(f"{type(err).__name__}: {err}") from err
        else:
            self._entries.move_to_end(key)
        out, self._last = entry(state, u, y)
        self._last_io = (io, entry)  # valid while the next inputs are these outputs
        return out

    def _build(self, state: list[Tensor], u: Tensor | None, y: Tensor, key: tuple) -> Callable:
        """Capture and compile the step for one input structure (seconds, once)."""
        (set_type, n_fields, extra_keys), *_ = key
        n_par = len(self._names)
        out_keys: list[tuple] = []

        def flat_step(*args: Tensor) -> list[Tensor]:
            params = dict(zip(self._names, args[:n_par]))
            ls = args[n_par:]
            fields, consistent, bounded = ls[:n_fields], ls[n_fields], ls[n_fields + 1]
            j = n_fields + 2 + len(extra_keys)
            extras = dict(zip(extra_keys, ls[n_fields + 2:j]))
            u = ls[j + 1] if len(ls) > j + 1 else None
            out = torch.func.functional_call(
                self._module, params, (tuple(fields), consistent, bounded, extras, u, ls[j],
                                       set_type))
            new_fields, new_consistent, new_bounded, new_extras = out
            out_keys.append((len(new_fields), tuple(new_extras)))
            return [*new_fields, new_consistent, new_bounded, *new_extras.values()]

        from torch._inductor import compile as inductor_compile
        from torch.fx.experimental.proxy_tensor import make_fx

        example = [*self._tensors, *state, y, *([] if u is None else [u])]
        with torch.no_grad(), traced():
            gm = make_fx(flat_step, tracing_mode="fake", _allow_non_fake_inputs=True)(*example)
        options = self._options
        stack = options.get("cpp_wrapper") and _intermediate_bytes(gm) <= STACK_BYTES
        small = known_options(SMALL_STEP_OPTIONS) if stack and not _has_sort(gm) else {}
        with warnings.catch_warnings(), _stack_arrays(stack) as on:
            # torch 2.13's lowering calls its own deprecated check
            warnings.filterwarnings("ignore", ".*_prims_common.check", FutureWarning)
            compiled = inductor_compile(gm, example, options={
                **small, **options, **(_STACK_OPTIONS if on else {})})
        (n_out, out_extras), = out_keys
        out_struct = (self._module.filt._runtime.out_type, n_out, out_extras)
        call, head = _entry(compiled, example)
        head = [*head, *self._tensors]
        out_meta: list[tuple] = []

        def run(state: list[Tensor], u: Tensor | None, y: Tensor) -> tuple:
            out = call([*head, *state, y] if u is None else [*head, *state, y, u])
            if not out_meta:
                out_meta.append(tuple(map(_meta, out)))
            flat = (
                tuple(out[:n_out]), out[n_out], out[n_out + 1],
                dict(zip(out_extras, out[n_out + 2:])),
            )
            return flat, (out_struct, out, out_meta[0])

        self._entries[key] = run
        while len(self._entries) > MAX_ENTRIES:
            self._entries.popitem(last=False)
        return run


def _entry(
    compiled: Callable, example: list[Tensor]
) -> tuple[Callable[[list], Sequence[Tensor]], list[Tensor]]:
    """How to call a graph that ``torch._inductor.compile`` compiled: ``(call, head)``, where
    ``call([*head, *inputs])`` returns its outputs (``call`` may clear the list it is given).

    ``torch._inductor.compile`` returns the Inductor graph behind AOTAutograd's wrappers, which
    put the graph module's own constants in front of the inputs, handle input mutations and
    outputs that alias inputs, and disable Dynamo for the call: about 4 of the 20 us of an
    HSNSMF call at B = 1. A graph with none of those has nothing for them to do, so its
    Inductor entry (the ``current_callable`` that the returned function carries) is called
    directly, after the two calls are checked to give the same outputs on ``example`` (the
    inputs of the capture), none of them an input. Where anything differs (another torch, a
    mutated input, an output that is an input), the wrapped function is used.
    """
    public = (lambda args: compiled(*args)), []
    entry = getattr(compiled, "current_callable", None)
    if entry is None or getattr(compiled, "mutated_inputs", None) or not callable(
        getattr(compiled, "named_parameters", None)
    ):
        return public
    try:
        consts = [*dict(compiled.named_parameters(remove_duplicate=False)).values(),
                  *dict(compiled.named_buffers(remove_duplicate=False)).values()]
        with torch.no_grad():
            ref = compiled(*example)
            out = entry([*consts, *example])
    except Exception:  # noqa: BLE001 -- any other calling convention: the wrapped function
        return public
    inputs = {t.untyped_storage().data_ptr() for t in example}
    same = (
        isinstance(ref, (list, tuple)) and isinstance(out, (list, tuple))
        and len(ref) == len(out)
        and all(isinstance(a, Tensor) and isinstance(b, Tensor)
                and a.untyped_storage().data_ptr() not in inputs
                and a.shape == b.shape and a.stride() == b.stride() and a.dtype == b.dtype
                and a.device == b.device
                and (torch.equal(a, b) or (a.is_floating_point() and torch.allclose(
                    a, b, rtol=0.0, atol=0.0, equal_nan=True)))
                for a, b in zip(ref, out))
    )
    return (entry, consts) if same else public


def known_options(options: dict[str, Any]) -> dict[str, Any]:
    """The entries of ``options`` that this torch's Inductor knows (older releases may lack
    one; ``torch._inductor.compile`` and ``torch.compile`` reject an option missing from
    ``get_config_copy()``)."""
    import torch._inductor.config as cfg

    known = cfg.get_config_copy()
    return {k: v for k, v in options.items() if k in known}


def _has_sort(gm: torch.fx.GraphModule) -> bool:
    """Whether ``gm`` calls a sort-like aten op (a library call for which Inductor keeps
    tensor handles instead of stack arrays)."""
    return any(
        n.op == "call_function" and isinstance(n.target, torch._ops.OpOverload)
        and n.target.overloadpacket.__name__ in _SORTS
        for n in gm.graph.nodes
    )


def _intermediate_bytes(gm: torch.fx.GraphModule) -> int:
    """Bytes of every tensor a node of ``gm`` computes, summed (an upper bound of what
    Inductor allocates after fusion); a tensor on an accelerator counts as unbounded (no
    stack arrays there)."""
    total = 0
    for node in gm.graph.nodes:
        vals = node.meta.get("val") if node.op == "call_function" else None
        for v in vals if isinstance(vals, (list, tuple)) else (vals,):
            if isinstance(v, Tensor):
                if v.device.type not in ("cpu", "meta"):
                    return 1 << 62
                total += v.numel() * v.element_size()
    return total


@functools.cache
def _stack_wrapper() -> type:
    """Inductor's C++ wrapper for the CPU that keeps intermediates in stack arrays
    (``CppWrapperCpuArrayRef``), except the graph's outputs: a stack-allocated output would
    be returned in a thread-local buffer that the next call overwrites (a trajectory of
    states, kept step after step, would change under the caller)."""
    from torch._inductor.codegen.cpp_wrapper_cpu_array_ref import CppWrapperCpuArrayRef
    from torch._inductor.virtualized import V

    class _Wrapper(CppWrapperCpuArrayRef):
        @staticmethod
        def create(*args: Any, **kwargs: Any) -> _Wrapper:
            return _Wrapper()

        def can_stack_allocate_buffer(self, buffer: Any) -> bool:
            outputs = V.graph.get_output_names()
            return buffer.get_name() not in outputs and super().can_stack_allocate_buffer(buffer)

    return _Wrapper


@contextlib.contextmanager
def _stack_arrays(enable: bool) -> Iterator[bool]:
    """`_stack_wrapper` as Inductor's C++ wrapper for the CPU (which Inductor otherwise
    selects only when its option is set at its first compile in the process), for this
    compile only: the registration is put back on exit, so other compiles in the process are
    unaffected. Yields whether it is in place (False when not asked, or when this torch
    lacks the wrapper: then the compile proceeds as usual)."""
    entry = old = None
    if enable:
        try:
            from torch._inductor.codegen import common

            wrapper = _stack_wrapper()
            common.init_backend_registration()
            entry = common.device_codegens.get("cpu")
            old = entry.cpp_wrapper_codegen if entry is not None else None
        except (ImportError, AttributeError):
            entry = None
    if entry is None or old is None:
        yield False
        return
    entry.cpp_wrapper_codegen = wrapper
    try:
        yield True
    finally:
        entry.cpp_wrapper_codegen = old
