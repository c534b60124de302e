"""Enclosures of a model over a box: the engine's entry points.

`enclose` evaluates a model ``fn(x [..., n]) -> [..., k]`` over a box ``[..., n]`` and
returns guaranteed enclosures of its value ``[..., k]``, Jacobian ``[..., k, n]`` and Hessians
``[..., k, n, n]``. The model is captured once (per function object) and evaluated by the
per-op rules. The filters pass a `StepModel` (the system's ``f`` with this step's input
and parameter), whose program is captured once per system.
"""

from __future__ import annotations

import types
import weakref
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.interval.arith import shape_of, tensor_of
from diffsmf.interval.box import Interval
from diffsmf.interval.capture import EngineError, Program, capture, seed, stacks, to_trailing
from diffsmf.interval.jet import Jet, point
from diffsmf.utils import eager_constant

__all__ = ["Enclosure", "StepModel", "enclose", "enclose_dynamics", "program_for",
           "register_row_model"]

_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def register_row_model(fn: Callable[..., Tensor]) -> None:
    """Declare ``fn(x [..., n]) -> [..., k]`` batch-elementwise (no batched closures): one
    program, captured on a batch row, then serves every batch shape."""
    if _is_row_model(fn):
        return

    def call(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        return fn(x)

    call.__name__ = getattr(fn, "__name__", "h")
    try:
        if isinstance(fn, nn.Module):
            object.__setattr__(fn, "_diffsmf_row_call", call)
        else:
            fn._diffsmf_row_call = call  # type: ignore[attr-defined]
    except (AttributeError, TypeError):  # cannot carry it: the shape-specific path is taken
        pass
_BY_ID: dict[tuple, Program] = {}


class Enclosure:
    """Enclosures of a model over a box: ``val [..., k]``, ``grad [..., k, n]`` (order >= 1),
    ``hess [..., k, n, n]`` (order 2; zeros when structurally zero, see ``hess_is_zero``)."""

    __slots__ = ("_hess", "grad", "n", "order", "val")

    def __init__(self, jet: Jet) -> None:
        self.val = jet.val
        self.n = jet.n
        self.order = jet.order
        like, vshape = tensor_of(jet.val), shape_of(jet.val)  # (no views of stacked bounds)
        if jet.order >= 1 and jet.grad is None:
            z = torch.zeros((*vshape, jet.n), dtype=like.dtype, device=like.device)
            self.grad = point(z)
        else:
            self.grad = jet.grad
            if self.grad is not None and shape_of(self.grad)[:-1] != vshape:
                shape = (*torch.broadcast_shapes(shape_of(self.grad)[:-1], vshape), jet.n)
                self.grad = Interval._make(self.grad.lower.expand(shape),
                                           self.grad.upper.expand(shape))
        self._hess = jet.hess

    @property
    def hess_is_zero(self) -> bool:
        """True when the Hessian is structurally zero (the model is affine)."""
        return self.order >= 2 and self._hess is None

    @property
    def hess(self) -> Interval | None:
        if self.order < 2:
            return None
        like = tensor_of(self.val)
        shape = (*shape_of(self.val), self.n, self.n)
        if self._hess is None:
            z = torch.zeros(shape, dtype=like.dtype, device=like.device)
            return point(z)
        h = self._hess
        if shape_of(h) != shape:
            shape = torch.broadcast_shapes(shape_of(h), shape)
            h = Interval._make(h.lower.expand(shape), h.upper.expand(shape))
        return h

    @property
    def shape(self) -> torch.Size:
        return self.val.lower.shape


class StepModel:
    """``x -> f(x, u, theta)``: a system's dynamics for one step, with a stable program.

    Args:
        f: the system's ``f(x, u, theta)`` (a stable object: its program is cached on it).
        u: input ``[..., p]`` or ``None``.
        theta: parameter ``[..., q]`` or ``None``.
    """

    def __init__(self, f: Callable[..., Tensor], u: Tensor | None, theta: Tensor | None,
                 name: str = "f") -> None:
        self.f = f
        self.u = u
        self.theta = theta
        self.name = name

    def __call__(self, x: Tensor) -> Tensor:
        return self.f(x, self.u, self.theta)

    def points(self) -> list[Tensor]:
        return [t for t in (self.u, self.theta) if t is not None]

    def program(self, x: Tensor) -> Program:
        u_ex = None if self.u is None else self.u.detach().reshape(-1, self.u.shape[-1])[:1]
        th_ex = None if self.theta is None else self.theta.detach().reshape(
            -1, self.theta.shape[-1])[:1]
        has = (u_ex is not None, th_ex is not None)

        def g(x_: Tensor, *rest: Tensor) -> Tensor:
            it = iter(rest)
            u_ = next(it) if has[0] else None
            th_ = next(it) if has[1] else None
            return self.f(x_, u_, th_)

        ex = [x] + [t for t in (u_ex, th_ex) if t is not None]
        return program_for(self.f, g, ex, self.name, key=has)


def program_for(owner: Any, fn: Callable[..., Tensor], example: list[Tensor], name: str,
                key: Any = None) -> Program:
    """The program of ``fn`` captured on ``example`` (cached on ``owner`` and ``key``)."""
    shapes = tuple((tuple(e.shape), e.dtype, e.device.type) for e in example)
    k = (key, shapes)
    cache = _cache_of(owner)
    prog = cache.get(k)
    if prog is None:
        fp = fingerprint(owner)
        shared = None if fp is None else (fp, k, name)
        prog = _SHARED.get(shared) if shared is not None else None
        if prog is None:
            prog = capture(fn, example, name)
            if shared is not None:
                if len(_SHARED) >= _SHARED_MAX:
                    _SHARED.pop(next(iter(_SHARED)))
                _SHARED[shared] = prog
        cache[k] = prog
    return prog


#: Programs shared between model objects with the same fingerprint (a built-in system made
#: twice: new closures, the same code and constants), oldest dropped first.
_SHARED: dict = {}
_SHARED_MAX = 256
_SMALL = 4096  # tensors of at most this many elements are fingerprinted by value


def fingerprint(fn: Any, depth: int = 4) -> Any:
    """A hashable key that determines what ``fn`` computes, or None when unknown.

    Functions: their code, defaults, closure values and the globals they name (numbers,
    strings, small tensors by value, other functions recursively; modules by identity). A
    wrapper declares ``engine_wraps = (tag, wrapped function)``: its key is the tag and the
    wrapped function's key.
    Anything else (nn.Modules, whose parameters may change, large tensors, other objects):
    None, and ``fn``'s program is not shared.
    """
    if depth < 0:
        return None
    wraps = getattr(fn, "engine_wraps", None)  # e.g. `diffsmf.systems.model.Dynamics`
    if wraps is not None:
        tag, inner_fn = wraps
        inner = fingerprint(inner_fn, depth - 1)
        return None if inner is None else (tag, inner)
    if not isinstance(fn, types.FunctionType):
        return None
    parts: list[Any] = [fn.__code__]
    for v in (fn.__defaults__ or ()):
        parts.append(_value_print(v, depth - 1))
    for c in fn.__closure__ or ():
        try:
            parts.append(_value_print(c.cell_contents, depth - 1))
        except ValueError:  # an empty cell
            parts.append(("empty",))
    g = fn.__globals__
    for name in fn.__code__.co_names:
        if name in g:
            v = g[name]
            parts.append((name, id(v)) if isinstance(v, types.ModuleType) else
                         (name, _value_print(v, depth - 1)))
    if any(p is _UNKNOWN for p in parts) or any(
            isinstance(p, tuple) and len(p) == 2 and p[1] is _UNKNOWN for p in parts):
        return None
    return tuple(parts)


_UNKNOWN = object()


def _value_print(v: Any, depth: int) -> Any:
    if v is None or isinstance(v, (bool, int, float, complex, str, torch.dtype)):
        return (type(v).__name__, v)
    if isinstance(v, (tuple, list)):
        items = tuple(_value_print(x, depth - 1) for x in v)
        return _UNKNOWN if any(i is _UNKNOWN for i in items) else (type(v).__name__, items)
    if isinstance(v, dict):
        items = tuple((k, _value_print(x, depth - 1)) for k, x in sorted(v.items(), key=str))
        return _UNKNOWN if any(i[1] is _UNKNOWN for i in items) else ("dict", items)
    if isinstance(v, Tensor):
        if v.requires_grad or v.numel() > _SMALL or v.is_sparse:
            return _UNKNOWN
        t = v.detach().cpu().contiguous()
        return ("tensor", t.dtype, tuple(t.shape), str(v.device), t.numpy().tobytes()
                if t.dtype != torch.bfloat16 else t.float().numpy().tobytes())
    if isinstance(v, types.FunctionType) or type(v).__name__ == "Dynamics":
        fp = fingerprint(v, depth)
        return _UNKNOWN if fp is None else ("fn", fp)
    if isinstance(v, types.ModuleType):
        return ("module", id(v))
    return _UNKNOWN


def enclose(fn: Callable[..., Tensor], box: Interval, order: int = 2,
            name: str = "fn") -> Enclosure:
    """Enclosures of ``fn`` over ``box [..., n]`` -> `Enclosure` (``[..., k]`` value,
    ``[..., k, n]`` Jacobian, ``[..., k, n, n]`` Hessians, as ``order`` asks).

    ``fn`` maps ``x [..., n]`` to ``[..., k]`` with torch ops (leading dims are batch dims).
    Raises `EngineError` naming ``name`` for a model the engine cannot enclose.
    """
    if not isinstance(box, Interval) or box.lower.dim() < 1:
        raise ValueError("box: expected an Interval of shape [..., n]")
    if order not in (0, 1, 2):
        raise ValueError(f"order: expected 0, 1 or 2, got {order}")
    lo = box.lower
    n = lo.shape[-1]
    if isinstance(fn, StepModel):  # one program for every batch shape: a batch row in front
        prog = fn.program(_example(n, lo))
        if prog.out_rank != 2:
            raise EngineError(f"{prog.name}: must map x [..., n] to [..., k] (keep the batch "
                              "dims)")
        out = prog.run([seed(_row(box), order, n, 0), *[t.unsqueeze(-2) for t in fn.points()]])
        return Enclosure(to_trailing(out, order, lo, n, row=True))
    if _is_row_model(fn):
        return enclose(StepModel(_RowCall(fn), None, None, name), box, order, name)
    # any function (it may close over batched tensors): captured at this box's shape
    prog = program_for(fn, fn, [torch.zeros_like(lo)], getattr(fn, "__name__", name))
    if prog.out_rank < 1:
        raise EngineError(f"{prog.name}: must map x [..., n] to [..., k] (keep the batch dims)")
    out = prog.run([seed(box, order, n, 0)])
    return Enclosure(to_trailing(out, order, lo, n, row=False))


def enclose_dynamics(
    f: Callable[..., Tensor],
    box: Interval,
    theta: Interval,
    u: Tensor | None,
    order: int = 1,
) -> Enclosure:
    """Enclose ``f(x, u, theta)`` jointly over ``x`` in ``box [..., n]`` and ``theta`` in
    ``theta [..., q]`` -> value ``[..., n]`` and (order 1) the Jacobian w.r.t. ``(x, theta)``
    ``[..., n, n + q]`` (used for the parameter deviation, Song et al. 2017, eq. 18-21).
    A point ``theta`` (``lower == upper``) is enclosed the same way."""
    lo = box.lower
    n, q = lo.shape[-1], theta.lower.shape[-1]
    sm = StepModel(f, u, theta.lower)
    prog = sm.program(_example(n, lo))
    th = Interval._make(theta.lower.unsqueeze(-2), theta.upper.unsqueeze(-2))
    inputs = [seed(_row(box), order, n + q, 0)]
    if u is not None:
        inputs.append(u.unsqueeze(-2))
    inputs.append(seed(th, order, n + q, n))
    out = prog.run(inputs)
    return Enclosure(to_trailing(out, order, lo, n + q, row=True))


_EXAMPLES: dict = {}


def _example(n: int, like: Tensor) -> Tensor:
    """Zeros ``[1, n]`` like ``like``: the example input that keys a step model's program
    (cached eagerly: a constant, not an op per call)."""
    return eager_constant(_EXAMPLES, (n, like.dtype, like.device),
                          lambda: torch.zeros(1, n, dtype=like.dtype, device=like.device))


def _row(box: Interval) -> Interval:
    """The box ``[..., n]`` with a batch row dim ``[..., 1, n]`` (stacked where the program
    will run stacked: one op less)."""
    lo, hi = box.lower, box.upper
    if stacks(lo, hi):
        return Interval._pair(torch.stack([lo, hi]).unsqueeze(-2))
    return Interval._make(lo.unsqueeze(-2), hi.unsqueeze(-2))


def _cache_of(owner: Any) -> dict:
    """The program cache of ``owner``, an attribute of the object itself where possible (a
    lookup torch.compile traces without guards on a global weak dictionary)."""
    cache = getattr(owner, "_diffsmf_programs", None)
    if cache is not None:
        return cache
    cache = {}
    try:
        object.__setattr__(owner, "_diffsmf_programs", cache) if isinstance(owner, nn.Module) \
            else setattr(owner, "_diffsmf_programs", cache)
        return cache
    except (AttributeError, TypeError):
        pass
    try:
        return _PROGRAMS.setdefault(owner, cache)
    except TypeError:  # not weak-referenceable
        return _BY_ID.setdefault((id(owner),), cache)


def _is_row_model(fn: Any) -> bool:
    return getattr(fn, "_diffsmf_row_call", None) is not None


def _RowCall(fn: Callable[..., Tensor]) -> Callable[..., Tensor]:  # noqa: N802 - a factory
    """``fn(x)`` as ``f(x, u, theta)``, one stable object per ``fn`` (its program's owner)."""
    return fn._diffsmf_row_call  # type: ignore[attr-defined]
