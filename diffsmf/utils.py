"""Small shared utilities: learnable positive hyperparameters (GPyTorch style)."""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import inspect
import math
import numbers
import sys
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "HIGHS_OPTIONS",
    "RANK_ORDER_MAX",
    "is_int",
    "Positive",
    "StrictlyPositive",
    "check_half_widths",
    "check_strictly_positive",
    "descending_order",
    "eager_constant",
    "fix_dynamo_matmul",
    "inv_softplus",
    "load_object",
    "materialize",
    "progress_bar",
    "register_positive",
    "retain_freed_memory",
    "traced",
    "tracing",
    "user_stacklevel",
]

#: the folder of the diffsmf package (frames there are not the user's, `user_stacklevel`)
_PACKAGE_ROOT = str(Path(__file__).resolve().parent)
#: torch's folder: its frames between the user and diffsmf (``nn.Module.__call__``,
#: ``__setattr__``) are not the user's either
_TORCH_ROOT = str(Path(torch.__file__).resolve().parent)


def progress_bar(progress: Any, total: int, desc: str, unit: str) -> Any:
    """A progress bar over ``total`` units, or None when ``progress`` is falsy.

    ``progress``: ``True`` (a `tqdm.auto.tqdm` bar that disappears when done), or a factory
    called as ``progress(total=total, desc=desc, unit=unit)`` that returns an object with
    ``update(n)`` and ``close()`` (e.g. ``functools.partial(tqdm, position=1)``, or your own
    logger).
    """
    if progress is None or progress is False:
        return None
    if progress is True:
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, unit=unit, leave=False)
    if not callable(progress):
        raise ValueError(f"progress: expected True, False or a callable that makes a bar "
                         f"(e.g. tqdm), got {type(progress).__name__}")
    return progress(total=total, desc=desc, unit=unit)


def user_stacklevel() -> int:
    """The ``stacklevel`` for ``warnings.warn`` called by the caller of this function that
    points at the first frame outside the diffsmf and torch packages (the user's line, also
    when torch's ``Module.__call__`` or ``__setattr__`` stands between)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(
            (_PACKAGE_ROOT, _TORCH_ROOT)):
        frame, level = frame.f_back, level + 1
    return level


#: scipy HiGHS options of the reference LPs (audits, exact-geometry fallbacks): feasibility to
#: 1e-10, HiGHS's tightest, instead of its default 1e-7, so that a reported distance of 0 cannot
#: hide a constraint violated by more than 1e-10 (the audits' tolerance is 1e-9).
HIGHS_OPTIONS = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}


def is_int(value: object) -> bool:
    """``value`` is an integer (a Python ``int`` or a numpy integer: ``numbers.Integral``) and
    not a ``bool`` (``True`` is not a count or a size)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def broadcast_shapes(*shapes: tuple[int, ...]) -> torch.Size:
    """``torch.broadcast_shapes`` of shapes (not tensors) in plain Python: the same result
    and a ``RuntimeError`` on shapes that do not broadcast, in 1-2 us instead of 14 us
    (it is called by the set constructors and linearisations of every eager step)."""
    first = shapes[0]
    if all(s == first for s in shapes):
        return torch.Size(first)
    n = max(map(len, shapes))
    out = [1] * n
    for k, s in enumerate(shapes):
        off = n - len(s)
        for i, d in enumerate(s):
            o = out[off + i]
            if d != o:
                if o == 1:
                    out[off + i] = d
                elif d != 1:
                    raise RuntimeError(
                        "Shape mismatch: objects cannot be broadcast to a single shape. "
                        f"Mismatch is between arg {k} {list(s)} and the broadcast of the "
                        f"earlier shapes {out}.")
    return torch.Size(out)


def tracing() -> bool:
    """True while ``torch.compile`` (or `traced`) traces the code: then host-syncing
    checks are skipped and data-dependent branches take their general, branch-free form."""
    return _TRACED or bool(torch.compiler.is_compiling())


_TRACED = False  # set by traced()
_T = TypeVar("_T")


def eager_constant(cache: dict, key: Hashable, make: Callable[[], _T]) -> _T:
    """``make()`` kept in ``cache`` under ``key`` in eager mode (a constant tensor made once,
    not ops per call); while traced, made afresh (a graph constant: no lookup of host state
    for ``torch.compile`` to guard on)."""
    if tracing():
        return make()
    value = cache.get(key)
    if value is None:
        value = cache[key] = make()
    return value
_EVENTS = 0  # depth of numerical_events() blocks


def checking() -> bool:
    """True where value checks (NaN, inf, a domain, a singular or indefinite matrix) raise a
    ``ValueError``: not while traced (`tracing`) and not inside `numerical_events`
    (a filter step), where such a value is a per-element event that the filter flags."""
    return not _EVENTS and not tracing()


@contextlib.contextmanager
def numerical_events() -> Iterator[None]:
    """Inside the block, value checks of the sets and interval functions do not raise
    (`checking` is False, as in a compiled step): an interval function outside its
    domain (sqrt / log / power of an interval below 0, log1p below -1) returns NaN bounds for
    the offending elements, and sets are built from non-finite or degenerate fields as they
    are. The filters run their predict / update steps inside it and flag those elements
    (``FilterResult.events``); the other elements are unaffected. Shape and type errors
    still raise."""
    global _EVENTS
    _EVENTS += 1
    try:
        yield
    finally:
        _EVENTS -= 1


#: glibc ``mallopt`` parameters set by `retain_freed_memory`.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_RETAINED = False


def retain_freed_memory(trim: int = 512 << 20, mmap: int = 64 << 20) -> bool:
    """Keep freed heap memory in the process instead of returning it to the OS (glibc only).

    A compiled filter step at a large batch allocates its buffers afresh on every call
    (megabytes at B = 10,000). glibc serves blocks above its mmap threshold with fresh pages and
    trims freed memory above its trim threshold, so every call page-faults its buffers in again,
    and the kernel zeroes each page: about 6,500 faults per step and 10.5 % of the profile in
    the page zeroing alone (HSNSMF, B = 10,000, one thread). This raises the mmap threshold to
    ``mmap`` bytes and the trim threshold to ``trim`` bytes (``mallopt``, the same as the
    environment variables ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``),
    process-wide: the process keeps up to ``trim`` bytes of freed memory for reuse. Called by
    ``SetFilter.compile()`` (``retain_memory=False`` skips it). Idempotent; returns True if the
    settings are in effect (False on a C library without ``mallopt``, e.g. macOS or musl).
    """
    global _RETAINED
    if _RETAINED:
        return True
    if sys.platform != "linux":
        return False
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    ok = libc.mallopt(_M_MMAP_THRESHOLD, int(mmap)) == 1
    ok = libc.mallopt(_M_TRIM_THRESHOLD, int(trim)) == 1 and ok
    _RETAINED = ok
    return ok


_MATMUL_FIXED = False


def fix_dynamo_matmul() -> bool:
    """Make ``torch.compile`` trace ``x @ A`` correctly for an Interval or a Jet ``x``.

    Dynamo (torch 2.13) sends a binary operator whose left operand is a non-tensor object with
    ``__torch_function__`` to the tensor's *reflected* method with the operands swapped, and its
    table of reflected methods leaves out ``@``: ``x @ A`` reached ``__torch_function__`` as
    ``Tensor.__matmul__(A, x)``, i.e. ``A @ x``. That failed for jets and could silently compute
    ``A @ x`` for intervals of matching shapes. This adds the missing ``Tensor.__rmatmul__``
    entry. Called by ``SetFilter.compile()``; call it before ``torch.compile`` of your own code
    that multiplies intervals or jets with ``@``. Idempotent; False if this torch has no such
    table (then there is nothing to fix or it cannot be fixed here).
    """
    global _MATMUL_FIXED
    if _MATMUL_FIXED:
        return True
    import operator

    try:
        from torch._dynamo.variables import builtin
    except ImportError:
        return False
    populate = getattr(builtin, "populate_builtin_to_tensor_fn_map", None)
    table = getattr(builtin, "BUILTIN_TO_TENSOR_RFN_MAP", None)
    if populate is None or not isinstance(table, dict):
        return False
    populate()
    table.setdefault(operator.matmul, torch.Tensor.__rmatmul__)
    _MATMUL_FIXED = True
    return True


def materialize(x: Tensor) -> Tensor:
    """``x`` itself; while traced for Inductor, a hint to compute it once into a buffer.

    Inductor inlines a cheap elementwise producer into every consumer, and a consumer that
    broadcasts it (a ``[p, v]`` table built from ``[p]`` and ``[v]`` factors) then recomputes it
    for every element of the table. Forcing the stride order realises the buffer (no copy if
    the strides already match). Applied only without autograd recording on ``x`` (the prim has
    no derivative); in eager mode it returns ``x`` unchanged.
    """
    if not tracing() or x.requires_grad:
        return x
    import torch._inductor.inductor_prims  # noqa: F401  (registers the prim)

    return torch.ops.prims.inductor_force_stride_order(x, x.stride())


#: Comparisons (batch x m x m) up to which a traced `descending_order` ranks instead of sorting.
RANK_ORDER_MAX = 1 << 16


def descending_order(score: Tensor) -> Tensor:
    """The permutation ``[..., m]`` that sorts ``score [..., m]`` in descending order along
    the last dim, stable (equal scores keep their order; NaN counts as the largest, as in
    ``torch.sort``): ``torch.sort(score, descending=True, stable=True).indices``.

    While traced, with at most `RANK_ORDER_MAX` comparisons, the same permutation by ranks:
    element j goes to position ``#{i : s_i > s_j} + #{i < j : s_i = s_j}``, one ``m x m``
    table of comparisons. Inductor fuses it with the rest of a small step, where a library
    sort is a separate call that keeps tensor handles (and the small-step compile options
    off, `diffsmf.filters.streaming`). For a large batch the table costs more than the sort
    (``m^2`` against ``m log m`` per element: MSZM at B = 10,000, m = 26), so it sorts.
    """
    m = score.shape[-1]
    if not tracing() or score.numel() * m > RANK_ORDER_MAX:
        return torch.sort(score, dim=-1, descending=True, stable=True).indices
    score = materialize(score)  # read m times per element below: computed once
    nan = score.isnan()
    si, sj = score.unsqueeze(-1), score.unsqueeze(-2)  # [..., i, 1], [..., 1, j]
    ni, nj = nan.unsqueeze(-1), nan.unsqueeze(-2)
    idx = torch.arange(m, device=score.device)
    earlier = idx.unsqueeze(-1) < idx  # [i, j]: i < j
    ahead = (si > sj) | (ni & ~nj) | (((si == sj) | (ni & nj)) & earlier)  # i before j
    # both stored once (`materialize`): inlined, each index read would redo the table
    rank = materialize(ahead.sum(-2))  # [..., j]: the position of element j
    hit = rank.unsqueeze(-2) == idx.unsqueeze(-1)  # [..., r, j]: element j at position r
    return materialize((hit * idx).sum(-1))  # [..., r]


@contextlib.contextmanager
def traced() -> Iterator[None]:
    """Make `tracing` true inside the block: for graph capture without Dynamo
    (``make_fx`` in `diffsmf.filters.streaming`), which must see the same branch-free
    code as ``torch.compile``."""
    global _TRACED
    old, _TRACED = _TRACED, True
    try:
        yield
    finally:
        _TRACED = old

_SOFTPLUS_ONE = math.log(math.expm1(1.0))  # inv_softplus(1)


def inv_softplus(x: Tensor) -> Tensor:
    """Inverse of ``softplus`` for ``x > 0`` (stable for large x)."""
    return torch.where(x > 20, x, torch.log(torch.expm1(x.clamp_min(1e-30))))


def register_positive(module: nn.Module, name: str, value: Any, learnable: bool = True) -> None:
    """Create the positive hyperparameter ``name`` on ``module``.

    Stored as ``raw_<name>`` (an ``nn.Parameter``, or a buffer when not learnable) and a buffer
    ``<name>_scale`` equal to the initial value, with ``value = scale * softplus(raw)`` and
    ``raw`` initialised to ``inv_softplus(1)``: gradient steps are relative to the initial
    magnitude, so bounds of 1e-3 and 1e3 train alike. Components equal to 0 stay exactly 0.
    Pair it with a `Positive` descriptor on the class to read and write ``module.name``.
    """
    v = torch.as_tensor(value, dtype=torch.float64).detach()
    v = check_half_widths(name, v.reshape(-1), v.numel(), v.dtype).reshape(v.shape)
    raw = torch.full_like(v, _SOFTPLUS_ONE)
    if learnable:
        module.register_parameter(f"raw_{name}", nn.Parameter(raw))
    else:
        module.register_buffer(f"raw_{name}", raw)
    # a scalar's scale is stored with shape [1]: torch.compile reads a 0-d buffer of a module
    # as a Python float, then restarts its trace to specialise it (ESMF: 16 s of a 66 s compile)
    module.register_buffer(f"{name}_scale", v.clone().reshape(v.shape or (1,)))
    if v.dim() == 0:
        module._register_load_state_dict_pre_hook(
            functools.partial(_scalar_scale_hook, key=f"{name}_scale")
        )


def _scalar_scale_hook(state_dict: dict, prefix: str, *args: Any, key: str) -> None:
    """Load a scalar hyperparameter's 0-d scale (saved before it was stored as ``[1]``)."""
    v = state_dict.get(prefix + key)
    if isinstance(v, Tensor) and v.dim() == 0:
        state_dict[prefix + key] = v.reshape(1)


class Positive:
    """Descriptor for a hyperparameter created by `register_positive`.

    ``obj.name`` returns ``scale * softplus(raw_name)`` (differentiable in ``raw_name``);
    ``obj.name = value`` resets ``scale`` to ``value`` and ``raw`` to ``inv_softplus(1)``.
    ``storage``: the name the hyperparameter was registered under, when the attribute has
    another (``process_half_widths = Positive(storage="process_noise")`` reads
    ``raw_process_noise``).
    """

    def __init__(self, storage: str | None = None) -> None:
        self.storage = storage

    def __set_name__(self, owner: type, name: str) -> None:
        self.attr = name
        self.name = self.storage or name

    def __get__(self, obj: Any, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        raw = getattr(obj, f"raw_{self.name}")
        scale = getattr(obj, f"{self.name}_scale")
        if torch.is_grad_enabled() and raw.requires_grad or not _cacheable(raw, scale):
            return _positive_value(raw, scale)
        # without a graph to record the value is a constant of (raw, scale): computed once and
        # reused until either changes (an optimiser step, a setter, load_state_dict, .to())
        key = (raw._version, scale._version, raw.untyped_storage(), scale.untyped_storage())
        cache = obj.__dict__.setdefault("_positive_cache", {})
        hit = cache.get(self.name)
        if hit is not None and _same_key(hit[0], key):
            return hit[1]
        with torch.no_grad():
            value = _positive_value(raw, scale)
        cache[self.name] = (key, value)
        return value

    def __set__(self, obj: Any, value: Any) -> None:
        scale = getattr(obj, f"{self.name}_scale")
        v = check_half_widths(self.attr, value, scale.numel(), scale.dtype).to(scale.device)
        with torch.no_grad():
            scale.copy_(v.expand_as(scale))
            getattr(obj, f"raw_{self.name}").fill_(_SOFTPLUS_ONE)


def _positive_value(raw: Tensor, scale: Tensor) -> Tensor:
    """``scale * softplus(raw)`` with the shape of ``raw`` (a scalar's scale is ``[1]``)."""
    if scale.shape != raw.shape:
        scale = scale.reshape(raw.shape)
    return scale * F.softplus(raw)


def _cacheable(raw: Tensor, scale: Tensor) -> bool:
    """Whether a `Positive` value may be reused: plain eager tensors (not while traced,
    not inside ``inference_mode`` or a ``torch.func`` transform)."""
    return (
        not tracing()
        and not torch.is_inference_mode_enabled()
        and type(raw) in (Tensor, nn.Parameter)
        and type(scale) is Tensor
        and not torch._C._functorch.is_functorch_wrapped_tensor(raw)
    )


def _same_key(a: tuple, b: tuple) -> bool:
    """Equal version counters and the same storages (held by the key, so never reused)."""
    return a[0] == b[0] and a[1] == b[1] and a[2]._cdata == b[2]._cdata and (
        a[3]._cdata == b[3]._cdata
    )


class StrictlyPositive(Positive):
    """`Positive` whose setter also rejects 0 and infinity (a
    multiplicative factor such as ``minkowski_scale`` must be finite and > 0)."""

    def __set__(self, obj: Any, value: Any) -> None:
        check_strictly_positive(self.name, value)
        super().__set__(obj, value)


def check_half_widths(
    name: str, value: Any, dim: int, dtype: torch.dtype = torch.float64, *, positive: bool = False
) -> Tensor:
    """Half-widths or steps (a noise box, a remainder margin, a Stirling step) -> ``[dim]`` of
    ``dtype``; ``ValueError`` naming ``name`` for a wrong length (a scalar or ``[1]``
    broadcasts), NaN, inf, negative values (with ``positive``: also 0) or non-numbers. The one
    validator of such values (pair it with `register_positive`)."""
    try:
        v = torch.as_tensor(value, dtype=dtype).detach()
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{name}: expected a number or a [{dim}] tensor, got {value!r}") from exc
    if v.dim() > 1 or (v.dim() == 1 and v.shape[0] not in (1, dim)):
        raise ValueError(
            f"{name}: expected a scalar or a [{dim}] tensor (one half-width per component), "
            f"got shape {tuple(v.shape)}"
        )
    low = bool((v <= 0).any()) if positive else bool((v < 0).any())
    if not bool(torch.isfinite(v).all()) or low:
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name}: must be finite and {bound}, got {v.tolist()}")
    return v.expand(dim).clone()


def check_strictly_positive(name: str, value: Any) -> Tensor:
    """``value`` as a finite scalar float64 tensor > 0, else ``ValueError`` naming ``name``."""
    try:
        v = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"{name}: expected a positive number, got {value!r}") from e
    if v.numel() != 1 or v.dim() > 1:
        raise ValueError(f"{name}: must be a scalar, got shape {tuple(v.shape)}")
    if not bool(torch.isfinite(v).all()) or bool((v <= 0).any()):
        raise ValueError(f"{name}: must be finite and > 0, got {v.reshape(-1).tolist()[0]}")
    return v.reshape(())


def load_object(spec: str, what: str = "--model") -> object:
    """``"path/to/file.py:FUNCTION"`` -> whatever ``FUNCTION()`` returns (no arguments).

    Raises ``ValueError`` / ``FileNotFoundError`` naming ``what`` for a malformed spec, a missing
    file, an import failure, a missing function, or an exception raised by the function. Shared
    by the commands that take a user's model file (``diffsmf filter --model``,
    ``diffsmf design-observer --model``).
    """
    path_s, sep, func = spec.rpartition(":")
    if not sep or not path_s or not func or not func.isidentifier():
        raise ValueError(f"{what}: expected FILE.py:FUNCTION (e.g. my_model.py:make_system), "
                         f"got {spec!r}")
    path = Path(path_s)
    if not path.is_file():
        raise FileNotFoundError(2, f"{what}: no such model file", str(path))
    if path.suffix != ".py":
        raise ValueError(f"{what}: {str(path)!r} is not a Python file (.py)")
    mod_name = f"_diffsmf_user_model_{abs(hash(str(path.resolve())))}"
    loader_spec = importlib.util.spec_from_file_location(mod_name, path)
    if loader_spec is None or loader_spec.loader is None:  # pragma: no cover
        raise ValueError(f"{what}: cannot import {str(path)!r}")
    module = importlib.util.module_from_spec(loader_spec)
    sys.modules[mod_name] = module
    try:
        loader_spec.loader.exec_module(module)
    except Exception as exc:  # the user's file: report where, keep it one line
        raise ValueError(f"{what}: importing {str(path)!r} failed: {type(exc).__name__}: {exc}"
                         ) from exc
    factory = getattr(module, func, None)
    if factory is None or not callable(factory):
        found = sorted(k for k, v in vars(module).items()
                       if callable(v) and not k.startswith("_") and
                       getattr(v, "__module__", None) == mod_name)
        raise ValueError(f"{what}: {str(path)!r} has no function {func!r} (functions there: "
                         f"{found})")
    needs = _required_parameters(factory)
    if needs:  # e.g. the dynamics f(x) itself instead of a function that builds the model
        raise ValueError(f"{what}: {func} must take no arguments and return the model, but it "
                         f"takes {', '.join(needs)}; write a function without arguments that "
                         f"builds it (e.g. make_system() returning diffsmf.System(f, h, ...))")
    try:
        return factory()
    except Exception as exc:
        raise ValueError(f"{what}: {func}() failed: {type(exc).__name__}: {exc}") from exc


def _required_parameters(fn: Callable[..., object]) -> list[str]:
    """Names of the parameters of ``fn`` without a default (``*args`` / ``**kwargs`` do not
    count); empty where the signature cannot be read."""
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return []
    return [p.name for p in params if p.default is inspect.Parameter.empty
            and p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)]
