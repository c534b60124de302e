"""Filter contract shared by every filter: state, result and the predict/update loop.

``forward(y, u)`` is exactly: for each k, ``predict(state, u[:, k-1])`` then
``update(state, y[:, k-1])`` (docs/design.md). Subclasses implement ``initial_state``,
``predict`` and ``_update``; NaN handling and result assembly live here once.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import math
import types
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.filters._direct import CaptureError, DirectSteps, config_key
from diffsmf.filters.events import LOSES_BOUND, FilterEvent, mark_unbounded
from diffsmf.sets.base import ConvexSet, align, check_count, stack, where
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System, check_system
from diffsmf.utils import (
    Positive,
    StrictlyPositive,
    check_strictly_positive,
    numerical_events,
    register_positive,
    retain_freed_memory,
    tracing,
)

__all__ = [
    "MAX_SET_RADIUS",
    "FilterResult",
    "bounded_result",
    "check_filter",
    "FilterState",
    "SetFilter",
    "StrictlyPositive",
    "register_minkowski_scale",
    "scaled_minkowski_sum",
]


#: A set whose interval hull has a half-width above this (or any non-finite field) is
#: *unbounded*: flagged ``bounded=False`` from then on, its bounds reported as +-inf.
MAX_SET_RADIUS = 1e100


@dataclass(frozen=True)
class FilterState:
    """Online filter state.

    set: current set, batch shape ``[B]``; consistent: ``[B]`` bool (False when the last
    measurement did not meet the predicted set); extras: filter-specific tensors
    (e.g. ``"covariance" [B, n, n]``); bounded: ``[B]`` bool or ``None`` (= all True): False
    from the step where the set stopped being finite (a remainder became unbounded, e.g. at a
    singularity of the model, or the set outgrew `MAX_SET_RADIUS`). Such an element's
    guaranteed set is all of R^n; ``set`` then holds a finite placeholder (the initial set)
    so that the batch carries on, and must not be read as an estimate: read
    ``guaranteed_set`` (R^n there). ``extras["events"]`` ``[B]`` int64: the `FilterEvent`
    bits met so far (sticky; see `diffsmf.filters.events`).
    """

    set: ConvexSet
    consistent: Tensor
    extras: dict[str, Tensor] = field(default_factory=dict)
    bounded: Tensor | None = None

    def replace(self, **kw: Any) -> FilterState:
        d = {
            "set": self.set,
            "consistent": self.consistent,
            "extras": self.extras,
            "bounded": self.bounded,
        }
        d.update(kw)
        return FilterState(**d)

    def and_bounded(self, ok: Tensor) -> FilterState:
        """This state with ``bounded &= ok`` (``ok [B]`` bool)."""
        b = ok if self.bounded is None else self.bounded & ok
        return self.replace(bounded=b)

    def flag(self, events: Tensor, unbounded: bool = True) -> FilterState:
        """This state with the `FilterEvent` bits ``events [B]`` (int) recorded: OR-ed into
        ``extras["events"]``; with ``unbounded`` (events of the set itself, e.g. its
        prediction remainder), ``bounded`` is False where one of them loses the bound
        (``LOSES_BOUND``: diverged, domain, non-finite). ``unbounded=False`` for events of a
        measurement update, which keep the guarantee: a lost bound there is recorded as
        ``MEASUREMENT_SKIPPED`` (the update was skipped). Branch-free."""
        ev = events.to(torch.int64)
        if not unbounded:  # a measurement that could not be bounded: skipped, not a lost bound
            skipped = (ev & LOSES_BOUND) != 0
            ev = (ev & ~LOSES_BOUND) | torch.where(skipped, int(FilterEvent.MEASUREMENT_SKIPPED), 0)
        old = self.extras.get("events")
        new = self.replace(extras={**self.extras, "events": ev if old is None else old | ev})
        return new.and_bounded((ev & LOSES_BOUND) == 0) if unbounded else new

    @property
    def events(self) -> Tensor:
        """``[B]`` int64 `FilterEvent` bits met so far (0 = none)."""
        ev = self.extras.get("events")
        return torch.zeros_like(self.consistent, dtype=torch.int64) if ev is None else ev

    @property
    def guaranteed_set(self) -> ConvexSet:
        """The set to read as the estimate: ``set`` where ``bounded``, all of R^n where not
        (`diffsmf.filters.events.mark_unbounded`: ``contains`` True, ``interval_hull``
        -inf / +inf, ``volume`` inf there)."""
        return mark_unbounded(self.set, self.bounded)


def _carry(prev: FilterState, new: FilterState, update: bool = False) -> FilterState:
    """``new`` with what ``prev`` had met: ``bounded`` stays False once False and the event
    bits accumulate (a filter's step may build its state afresh); after an update, a
    measurement is never inconsistent against an unbounded set (``consistent |= ~bounded``)."""
    b = new.bounded
    if prev.bounded is not None:
        b = prev.bounded if b is None else prev.bounded & b
    ev = prev.extras.get("events")
    extras = new.extras
    if ev is not None:
        now = extras.get("events")
        extras = {**extras, "events": ev if now is None else ev | now}
    consistent = new.consistent
    if update and b is not None:
        consistent = consistent | ~b
    return FilterState(new.set, consistent, extras, b)


def _flagging(fn: Callable[..., FilterState], *args: Any) -> FilterState:
    """``fn(*args)`` inside `diffsmf.utils.numerical_events` (a numerical event is
    flagged per element, never raised); traced code has no value checks anyway."""
    if tracing():
        return fn(*args)
    with numerical_events():
        return fn(*args)


def _with_events(state: FilterState) -> FilterState:
    """``state`` with ``extras["events"]`` (zeros ``[B]`` int64) when it has none, so that
    every state of a run has the same structure (one compiled graph)."""
    if "events" in state.extras:
        return state
    ev = torch.zeros(state.consistent.shape, dtype=torch.int64, device=state.consistent.device)
    return state.replace(extras={**state.extras, "events": ev})


@dataclass(frozen=True)
class FilterResult:
    """Sets over time.

    sets: batch shape ``[B, T+1]`` (index 0 = initial set, k = after ``y_k``);
    center, lower, upper: ``[B, T+1, n]``; volume: ``[B, T+1]``; consistent: ``[B, T+1]``
    bool; extras: stacked filter-specific tensors, e.g. ``"covariance" [B, T+1, n, n]``;
    bounded: ``[B, T+1]`` bool, False where the set stopped being finite (see
    `FilterState`): there ``lower = -inf``, ``upper = +inf``, ``volume = inf``,
    ``center`` is NaN (never a plausible-looking number), ``consistent`` is True (no
    measurement contradicts an unbounded prediction) and ``sets`` is all of R^n
    (`diffsmf.filters.events.mark_unbounded`: ``sets.contains(x)`` True, its hull +-inf).
    events (property): ``[B, T+1]`` int64 `FilterEvent` bits met at or before each step
    (``describe_events(res.events)`` says what happened where).
    """

    sets: ConvexSet
    center: Tensor
    lower: Tensor
    upper: Tensor
    volume: Tensor
    consistent: Tensor
    extras: dict[str, Tensor] = field(default_factory=dict)
    bounded: Tensor | None = None

    @property
    def covariance(self) -> Tensor | None:
        return self.extras.get("covariance")

    @property
    def events(self) -> Tensor:
        """``[B, T+1]`` int64: the `FilterEvent` bits met by each trajectory at or before
        each step (0 = none; zeros for a result without events)."""
        ev = self.extras.get("events")
        if ev is None:
            return torch.zeros(self.consistent.shape, dtype=torch.int64,
                               device=self.consistent.device)
        return ev


def state_batch(batch: Any) -> int:
    """The ``batch`` argument of ``initial_state``: ``None`` -> 1, else an ``int >= 0`` (not
    a ``bool``); anything else raises ``ValueError`` naming ``batch``."""
    return 1 if batch is None else check_count("batch", batch)


def _check_half_widths(name: str, value: Any, dim: int, dtype: torch.dtype) -> Tensor:
    """Noise half-width override -> ``[dim]``; ``ValueError`` naming ``name`` for a wrong
    length (a scalar or ``[1]`` broadcasts), NaN, inf, negative values or non-numbers."""
    try:
        v = torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{name}: expected a number or a [{dim}] tensor, got {value!r}") from exc
    if v.dim() > 1 or (v.dim() == 1 and v.shape[0] not in (1, dim)):
        raise ValueError(
            f"{name}: expected a scalar or a [{dim}] tensor (one half-width per component), "
            f"got shape {tuple(v.shape)}"
        )
    if not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
        raise ValueError(f"{name}: half-widths must be finite and >= 0, got {v.tolist()}")
    return v.expand(dim).clone()


def check_filter(name: str, filt: Any, system: System | None = None) -> Any:
    """``filt`` itself, or a ``ValueError`` naming ``name`` when it is not a filter instance
    built on a `System` (any ``nn.Module`` with a ``system``: the set
    filters, the EKF, the CombinedFilter, a user's own), e.g. a filter class not instantiated.
    With ``system`` (to run the filter on data of that system): its ``n`` and ``m`` must be
    the filter's, else the ``ValueError`` names ``system``."""
    built = isinstance(getattr(filt, "system", None), System)
    if not (isinstance(filt, torch.nn.Module) and built):
        what = f"the class {filt.__name__}" if isinstance(filt, type) else type(filt).__name__
        raise ValueError(
            f"{name}: must be a filter built on a System (e.g. ds.filters.HSNSMF(system)), "
            f"got {what}"
        )
    own = filt.system
    if system is not None and (system.n, system.m) != (own.n, own.m):
        raise ValueError(
            f"system: n = {system.n}, m = {system.m}, but {name}'s system has n = {own.n}, "
            f"m = {own.m}"
        )
    return filt


def bounded_result(
    cls: type,
    states: list[FilterState],
    sets: ConvexSet,
    center: Tensor,
    lower: Tensor,
    upper: Tensor,
    volume: Tensor,
    extras: dict[str, Tensor],
) -> FilterResult:
    """A ``cls`` (`FilterResult` or a subclass) from stacked per-step quantities, with
    the ``bounded [B, T+1]`` flags of ``states`` applied: where a set stopped being finite,
    ``lower = -inf``, ``upper = +inf``, ``volume = inf`` and ``center`` is NaN (one home for
    that rule, used by every filter's ``collect``)."""
    bounded = torch.stack(
        [torch.ones_like(s.consistent) if s.bounded is None else s.bounded for s in states], 1
    )
    b = bounded.unsqueeze(-1)
    inf = torch.full_like(lower, torch.inf)
    if "events" not in extras and all("events" in s.extras for s in states):
        extras = {**extras, "events": torch.stack([s.extras["events"] for s in states], 1)}
    return cls(
        sets=sets if tracing() or bool(bounded.all()) else mark_unbounded(sets, bounded),
        center=torch.where(b, center, torch.full_like(center, torch.nan)),
        lower=torch.where(b, lower, -inf),
        upper=torch.where(b, upper, inf),
        volume=torch.where(bounded, volume, torch.full_like(volume, torch.inf)),
        consistent=torch.stack([s.consistent for s in states], 1) | ~bounded,
        extras=extras,
        bounded=bounded,
    )


def _contiguous(v: Any) -> Any:
    """A tensor made contiguous (one compiled graph for expanded and dense inputs); other
    extras (e.g. the ellipsoidal filters' initial box, an Interval) as they are."""
    return v.contiguous() if isinstance(v, Tensor) else v


#: Compiled steps of a ``forward`` call that run Dynamo's full guard check (counted per call of
#: the compiled function, so eager steps such as CZSMF's growth phase do not count). From then
#: on the step's inputs are the previous compiled step's outputs and same-shaped slices of
#: ``y`` / ``u`` (the same tensor metadata as the step before, and the module does not change
#: inside the loop), so the guards are known to pass and only those that
#: tell cached graphs apart are run (``torch.compiler.set_stance(skip_guard_eval_unsafe=True)``;
#: about a third of a compiled B = 1 step was guard evaluation). ``forward`` resets the count.
_GUARDED_STEPS = 2


#: Filter configurations whose Dynamo-free compiled steps are kept (see ``_direct_steps``).
_DIRECT_CONFIGS = 4


#: Measurements with at most this many entries are checked for inf / NaN in Python (an
#: online step's ``y [1, m]``: 1 us instead of two tensor ops and a sync, about 11 us here).
_SMALL_Y = 64


#: Inductor options of `SetFilter.compile`. A filter step is hundreds of operations on
#: ``[B, n, n]`` tensors with n = 1-32: Inductor vectorises along the innermost dimension, so
#: for small n its SIMD code is mostly tails and remainders, and g++ takes twice as long to build
#: it. Measured on spring_damper (HSNSMF, 1 thread, cold cache, one run each): no-grad compile
#: 46 -> 33 s at B = 1 and 59 -> 30 s at B = 10,000 (run time 2,275 -> 3,194 and 205k -> 214k
#: trajectory-steps/s); the B = 64 gradient graphs 145 -> 78 s, run time 18k -> 33k
#: trajectory-steps/s. The sets are the same (the same operations in scalar code).
#: ``cpp_wrapper``: Inductor writes the code that calls the kernels (buffer allocations, size
#: and stride checks, library calls) in C++ instead of Python; at B = 1 that code was most of
#: a compiled step. Same sets and gradients; A/B in one process, 8 interleaved runs each
#: (spring_damper, B = 1, 1 thread): HSNSMF 0.749 -> 0.421 ms per step, ESMF 1.707 -> 0.973,
#: EKF 0.104 -> 0.095; cold compile times within 25 %.
#: ``memory_planning``: the intermediate buffers of a call come from one planned pool instead
#: of one allocation each (a 4-step CombinedFilter graph allocated 236 tensors per call). Same
#: sets and gradients (bit for bit in the checks); A/B in one process, interleaved runs
#: (spring_damper, 1 thread, a quiet machine): CombinedFilter B = 1, 4 steps per call, 0.116 ->
#: 0.102 ms per step; HSNSMF B = 1 0.239 -> 0.218; HSNSMF B = 10,000 and the EKF unchanged.
COMPILE_OPTIONS: dict[str, Any] = {
    "cpp.vec_isa_ok": False, "cpp_wrapper": True, "memory_planning": True,
}


def _compile_options() -> dict[str, Any]:
    """`COMPILE_OPTIONS` that this torch's Inductor knows (older releases may lack one;
    ``torch.compile`` rejects an option missing from ``get_config_copy()``, as checked here)."""
    import torch._inductor.config as cfg

    known = cfg.get_config_copy()
    return {k: v for k, v in COMPILE_OPTIONS.items() if k in known}


def _check_options(options: Any) -> dict[str, Any]:
    """``options`` of `SetFilter.compile` as a dict, with a one-line ``ValueError``
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


def _y_tensor(y: Any, dtype: torch.dtype, device: torch.device | None) -> Tensor:
    """``y`` as a tensor; ``ValueError`` naming ``y`` when it is None or not numeric (NaN is
    left to the callers, which honour ``skip_nan``)."""
    try:
        return torch.as_tensor(y, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"y: cannot convert {type(y).__name__} to measurements ({exc})") from exc


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


def _skip_guards() -> contextlib.AbstractContextManager:
    """Context that skips Dynamo's guard evaluation (see `_GUARDED_STEPS`); a no-op on
    torch versions without ``set_stance(skip_guard_eval_unsafe=...)`` (before 2.6)."""
    set_stance = getattr(torch.compiler, "set_stance", None)
    if set_stance is None:
        return contextlib.nullcontext()
    try:
        return set_stance("default", skip_guard_eval_unsafe=True)
    except TypeError:  # a set_stance without the keyword
        return contextlib.nullcontext()


def _signature(state: FilterState, u: Tensor | None, y: Tensor) -> tuple:
    """What tells compiled step graphs apart, for `SetFilter.streaming`: the set type,
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


def _flat_args(state: FilterState, grad_leaves: bool = False) -> tuple:
    """``state`` as the flat, contiguous tensors that the compiled step takes: fields,
    consistent, bounded (all True for None), extras (contiguous: the expanded initial set
    would otherwise be a second graph). ``grad_leaves``: every floating field and extra that
    does not require grad becomes a leaf that does (`_grad_leaf`)."""
    S, b = state.set, state.bounded
    if b is None:
        b = torch.ones_like(state.consistent)
    leaf = _grad_leaf if grad_leaves else _identity
    return (
        tuple(leaf(t.contiguous()) for t in S._tensors()), state.consistent.contiguous(),
        b.contiguous(), {k: leaf(_contiguous(v)) for k, v in state.extras.items()},
    )


def state_from_flat(
    fields: tuple[Tensor, ...], consistent: Tensor, bounded: Tensor, extras: dict[str, Tensor],
    set_type: type,
) -> FilterState:
    """The `FilterState` of a compiled step's flat inputs (see `flat_state`)."""
    return FilterState(set_type._from_tensors(fields), consistent, extras, bounded)


def flat_state(state: FilterState) -> tuple[tuple[Tensor, ...], Tensor, Tensor, dict[str, Tensor]]:
    """``state`` as a compiled step returns it: ``(fields, consistent, bounded, extras)``
    (``bounded`` all True for None); `SetFilter._unflatten` rebuilds it."""
    nb = torch.ones_like(state.consistent) if state.bounded is None else state.bounded
    return state.set._tensors(), state.consistent, nb, dict(state.extras)


def _identity(t: Any) -> Any:
    return t


def _grad_leaf(t: Any) -> Any:
    """A floating tensor that does not require grad as a leaf that does (else ``t``).

    Dynamo guards on ``requires_grad``: while training, the initial state (constant) and the
    later states (functions of the parameters) would otherwise compile two graph pairs,
    forward and backward, for the same step (about 40 s each for HSNSMF at B = 64). As
    leaves, the initial state's tensors take the graph of the later steps; the gradient they
    receive is not used, and the parameters' gradients are unchanged."""
    if isinstance(t, Tensor) and t.is_floating_point() and not t.requires_grad:
        return t.detach().requires_grad_()
    return t


def _pad_horizon(x: Tensor, K: int) -> Tensor:
    """``x [B, T, d]`` padded along T to a multiple of ``K`` by repeating its last step."""
    pad = -x.shape[1] % K
    if pad == 0:
        return x
    return torch.cat([x, x[:, -1:].expand(x.shape[0], pad, x.shape[2])], 1)


def _flat_hull(self: SetFilter, *fields: Tensor, set_type: type) -> tuple[Tensor, Tensor]:
    """Interval hull bounds ``[N, n]`` of the set of type ``set_type`` with ``fields``
    (batch ``[N]``); compiled by `SetFilter._hull_and_volume`."""
    hull = set_type._from_tensors(fields).interval_hull()
    return hull.lower, hull.upper


def _flat_volume(self: SetFilter, *fields: Tensor, set_type: type) -> Tensor:
    """Volume ``[N]`` of the set of type ``set_type`` with ``fields`` (batch ``[N]``);
    compiled by `SetFilter._hull_and_volume`."""
    return set_type._from_tensors(fields).volume()


def _pad_and_stack(sets: list[ConvexSet]) -> ConvexSet:
    """Stack along a new dim 1; zonotopes with differing generator counts are zero-padded."""
    return stack(align(sets), dim=1)


class SetFilter(nn.Module):
    """Base class of every filter (set-membership or Kalman).

    Learnable hyperparameters shared by all filters: ``process_noise [n]`` and
    ``measurement_noise [m]``, the half-widths of box noise bounds centred at the system's
    noise centres (default: the half-widths of the interval hulls of the system's noise sets).

    Args:
        system: the `System` to filter.
        process_noise: process noise half-width override ``[n]``.
        measurement_noise: measurement noise half-width override ``[m]``.
        skip_nan: skip the update of a batch element whose measurement has NaN (else raise).
    """

    process_noise = Positive()
    measurement_noise = Positive()
    #: Whether ``predict`` and ``update`` give sets of the same field shapes (False for CZSMF,
    #: whose predicted set is larger than its capped update); tuning compiles its guarded step
    #: (`training.losses.filter_with_predictions`) only for such filters.
    _constant_set_size: bool = True

    def __init_subclass__(cls, **kw: Any) -> None:
        """Every subclass's ``predict`` validates ``u`` against the system first
        (`check_input`: missing, wrong width, NaN raise), and a
        subclass's own ``update`` validates ``y`` (`_check_update_y`), as the base
        ``update`` does."""
        super().__init_subclass__(**kw)
        raw = cls.__dict__.get("predict")
        if raw is not None and not getattr(raw, "_checks_u", False):

            @functools.wraps(raw)
            def predict(
                self: SetFilter, state: FilterState, u: Tensor | None = None
            ) -> FilterState:
                u = self._check_u(u, state)
                return _carry(state, _flagging(raw, self, state, u))

            predict._checks_u = True  # type: ignore[attr-defined]
            cls.predict = predict  # type: ignore[method-assign]
        raw_update = cls.__dict__.get("update")
        if raw_update is not None and not getattr(raw_update, "_checks_y", False):

            @functools.wraps(raw_update)
            def update(self: SetFilter, state: FilterState, y: Tensor) -> FilterState:
                y = self._check_update_y(y, state)
                return _carry(state, _flagging(raw_update, self, state, y), update=True)

            update._checks_y = True  # type: ignore[attr-defined]
            cls.update = update  # type: ignore[method-assign]
        raw_init = cls.__dict__.get("initial_state")
        if raw_init is not None and not getattr(raw_init, "_adds_events", False):

            @functools.wraps(raw_init)
            def initial_state(self: SetFilter, batch: int | None = None) -> FilterState:
                return _with_events(raw_init(self, batch))

            initial_state._adds_events = True  # type: ignore[attr-defined]
            cls.initial_state = initial_state  # type: ignore[method-assign]

    def __init__(
        self,
        system: System,
        *,
        process_noise: Tensor | None = None,
        measurement_noise: Tensor | None = None,
        skip_nan: bool = False,
        learn_noise: bool = True,
    ) -> None:
        super().__init__()
        check_system("system", system)
        self.system = system
        self.skip_nan = skip_nan
        n, m = system.n, system.m
        dt = system.x0_set.dtype
        for name, s, dim, override in (
            ("process_noise", system.process_noise, n, process_noise),
            ("measurement_noise", system.measurement_noise, m, measurement_noise),
        ):
            if s is None:
                c, r = torch.zeros(dim, dtype=dt), torch.zeros(dim, dtype=dt)
            else:
                hull = s.interval_hull()
                c, r = hull.center.detach(), hull.radius.detach()
            if override is not None:
                r = _check_half_widths(name, override, dim, dt)
            register_positive(self, name, r, learnable=learn_noise)
            self.register_buffer(f"{name}_center", c.clone())
        # the hull half-widths of the system's W and V: process_noise_set / measurement_noise_set
        # scale the set per component by the half-width / these (scale 1 is the system's set,
        # for any set type)
        for name, S, dim in (
            ("process_noise", system.process_noise, n),
            ("measurement_noise", system.measurement_noise, m),
        ):
            r0 = torch.zeros(dim, dtype=dt) if S is None else S.interval_hull().radius.detach()
            self.register_buffer(f"{name}_hull_radius", r0.clone(), persistent=False)

    # ------------------------------------------------------------------ noise sets
    def process_noise_box(self) -> Interval:
        """Current process-noise box W ``[n]`` (differentiable in ``process_noise``)."""
        c, r = self.process_noise_center, self.process_noise
        return Interval(c - r, c + r)

    def process_noise_set(self) -> ConvexSet:
        """The process-noise set W as given by the system, scaled per component, ``[n]``.

        ``W_s = c + diag(s) (W - c)`` with ``s = process_noise / (half-width of W's interval
        hull)``: for a box this is exactly `process_noise_box`; a ``Zonotope`` /
        ``Parallelotope`` keeps its generators (``diag(s) G``) and an ``Ellipsoid`` its shape
        (``diag(s) S diag(s)``), so no filter pays for the interval hull of a non-box W.
        ``s = 1`` (the default) is the system's set. Differentiable in
        ``process_noise``. A component with a zero hull half-width stays zero.
        """
        return self._scaled_noise_set(
            self.system.process_noise, self.process_noise_box(), self.process_noise,
            self.process_noise_hull_radius, self.process_noise_center,
        )

    def measurement_noise_set(self) -> ConvexSet:
        """The measurement-noise set V as given by the system, scaled per component, ``[m]``
        (as `process_noise_set`; a box V is exactly `measurement_noise_box`)."""
        return self._scaled_noise_set(
            self.system.measurement_noise, self.measurement_noise_box(), self.measurement_noise,
            self.measurement_noise_hull_radius, self.measurement_noise_center,
        )

    @staticmethod
    def _scaled_noise_set(
        S: ConvexSet | None, box: Interval, r: Tensor, r0: Tensor, c: Tensor
    ) -> ConvexSet:
        """``c + diag(r / r0) (S - c)``: ``S`` keeps its type (``box`` for a box or no set)."""
        from diffsmf.sets.ellipsoid import Ellipsoid
        from diffsmf.sets.parallelotope import Parallelotope
        from diffsmf.sets.zonotope import Zonotope

        if S is None or isinstance(S, Interval):
            return box
        pos = r0 > 0
        scale = torch.where(pos, r / torch.where(pos, r0, 1.0), 0.0)
        if isinstance(S, (Zonotope, Parallelotope)):
            G = S.generators.to(dtype=c.dtype, device=c.device)  # follows filt.to(device)
            return Zonotope(c, scale.unsqueeze(-1) * G)
        if isinstance(S, Ellipsoid):
            M = S.shape.to(dtype=c.dtype, device=c.device)
            return Ellipsoid._make(c, scale.unsqueeze(-1) * M * scale.unsqueeze(-2))
        return box

    def measurement_noise_box(self) -> Interval:
        """Current measurement-noise box V ``[m]`` (differentiable in ``measurement_noise``)."""
        c, r = self.measurement_noise_center, self.measurement_noise
        return Interval(c - r, c + r)

    # ------------------------------------------------------------------ contract
    def initial_state(self, batch: int | None = None) -> FilterState:
        """State at k = 0 (the system's initial set), batch shape ``[batch]``."""
        x0 = self.system.x0_set
        b = state_batch(batch)
        return _with_events(FilterState(
            set=x0.expand(b), consistent=torch.ones(b, dtype=torch.bool, device=x0.device)
        ))

    def predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Time update with input ``u [B, p]`` (the input that drives x_{k-1} -> x_k)."""
        raise NotImplementedError

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Measurement update with finite ``y [B, m]``; sets ``consistent``."""
        raise NotImplementedError

    def update(self, state: FilterState, y: Tensor) -> FilterState:
        """Measurement update with ``y [B, m]``; NaN rows raise or (``skip_nan``) are skipped.

        ``y`` is validated first (`_check_update_y`: exactly ``[B, m]``, no inf). Ends
        with the boundedness guard (`guard`)."""
        y = self._check_update_y(y, state)
        bad = torch.isnan(y).any(-1)
        if not tracing() and bool(bad.any()) and not self.skip_nan:
            raise ValueError("y: contains NaN (pass skip_nan=True to skip those updates)")
        return _flagging(type(self)._guarded_update, self, state, y, bad)

    def _guarded_update(self, state: FilterState, y: Tensor, bad: Tensor) -> FilterState:
        """`update` on a validated ``y`` (``bad [B]``: its NaN rows)."""
        if not self.skip_nan or (not tracing() and not bool(bad.any())):
            return self.guard(_carry(state, self._update(state, y)))
        new = _carry(state, self._update(
            state, torch.where(bad.unsqueeze(-1), torch.zeros_like(y), y)
        ))
        keep = ~bad
        extras = {
            k: torch.where(keep.reshape(keep.shape + (1,) * (v.dim() - 1)), v, state.extras[k])
            for k, v in new.extras.items()
            if k in state.extras
        }
        return self.guard(FilterState(
            set=where(keep, new.set, state.set),
            consistent=torch.where(keep, new.consistent, state.consistent),
            extras={**new.extras, **extras},
            bounded=new.bounded,
        ))

    def guard(self, state: FilterState) -> FilterState:
        """Flag and replace sets that stopped being finite (``bounded``, see FilterState).

        An element is unbounded when a step flagged it (a remainder bound was not finite) or
        its set has a non-finite field (event ``NON_FINITE``) or an interval-hull half-width
        above `MAX_SET_RADIUS` (event ``DIVERGED``). Its set is replaced by the initial
        set (a finite placeholder, so that no NaN reaches the rest of the batch), it stays
        flagged, and its ``consistent`` is True (no measurement contradicts R^n).
        Branch-free.
        """
        S = state.set
        finite = torch.ones(S.batch_shape, dtype=torch.bool, device=S.device)
        for t in S._tensors():
            finite = finite & torch.isfinite(t.detach()).flatten(len(S.batch_shape)).all(-1)
        init = self.initial_state(batch=int(finite.shape[0]) if finite.dim() else None)
        ref = init.set
        same = type(ref) is type(S) and ref.batch_shape == S.batch_shape
        if same:
            S_a, ref_a = align([S, ref])
        # eager hulls check their fields, so take the hull of a NaN set's placeholder (the
        # element is flagged by ``finite`` already); traced code has no checks and keeps S
        hull = (where(finite, S_a, ref_a) if same and not tracing() else S).interval_hull()
        small = (hull.radius.detach() <= MAX_SET_RADIUS).all(-1)
        was = torch.ones_like(finite) if state.bounded is None else state.bounded
        ev = torch.where(was & ~finite, int(FilterEvent.NON_FINITE), 0)
        ev = ev | torch.where(was & finite & ~small, int(FilterEvent.DIVERGED), 0)
        new = _with_events(state).flag(ev).and_bounded(finite & small)
        b = new.bounded
        new = new.replace(consistent=new.consistent | ~b)  # nothing contradicts R^n
        if not same:
            return new
        safe = where(b, S_a, ref_a)
        extras = dict(new.extras)
        for k, v in new.extras.items():
            if k != "events" and k in init.extras and init.extras[k].shape == v.shape:
                keep = b.reshape(b.shape + (1,) * (v.dim() - b.dim()))
                extras[k] = torch.where(keep, v, init.extras[k])
        return new.replace(set=safe, extras=extras)

    def _check_update_y(self, y: Any, state: FilterState) -> Tensor:
        """``y`` of an eager `update` as a tensor of the system's dtype on the state's
        device, of shape exactly ``[*B, m]`` (``B`` the state's batch shape: a ``[1, m]`` or
        ``[B]`` measurement is refused, not broadcast); inf raises, NaN raises unless
        ``skip_nan``. Skipped while tracing (``forward`` and `step` check ``y`` before
        a compiled call)."""
        if tracing():
            return y
        return self._check_step_y(y, state, self.system.m, self.system.x0_set.dtype)

    def _check_u(self, u: Tensor | None, state: FilterState) -> Tensor | None:
        """``u [B, p]`` validated by the system (skipped while tracing for torch.compile)."""
        if tracing():
            return u
        return self.system.check_input(u, state.set.batch_shape)

    def forward(self, y: Tensor, u: Tensor | None = None) -> FilterResult:
        """Filter measurements ``y [B, T, m]`` (inputs ``u [B, T, p]``) -> `FilterResult`."""
        y = self._check_y(y)
        B, T, _ = y.shape
        if not tracing():
            u = self.system.check_input(u, (B, T))
        state = self.initial_state(batch=B)
        states = [state]
        ys = y.unbind(1)
        us = [None] * T if u is None else u.unbind(1)
        if getattr(self, "_compiled_step", None) is None or tracing():
            with _gc_paused():
                for k in range(T):
                    state = self._eager_step(state, us[k], ys[k])
                    states.append(state)
            return self.collect(states)
        stream = getattr(self, "_stream", None)
        if stream is not None and stream["direct"] is not None and not torch.is_grad_enabled():
            try:
                with _gc_paused():
                    for k in range(T):  # inside streaming(): the Dynamo-free compiled steps
                        state = self._direct_call(stream["direct"], state, us[k], ys[k])
                        states.append(state)
                return self.collect(states)
            except CaptureError as err:  # the whole horizon again, with Dynamo's step
                self._drop_direct(stream, err)
                state, states = states[0], states[:1]
        self._guarded_calls = 0  # compiled calls of this forward with Dynamo's full guard check
        K = getattr(self, "_steps_per_call", 1)
        ys_pad = _pad_horizon(y, K)
        us_pad = None if u is None else _pad_horizon(u, K)
        with contextlib.ExitStack() as stack:
            stack.enter_context(_gc_paused())
            skipping, k = False, 0
            while k < T:
                if K == 1 or not self._compile_ready(state):
                    state = self._compiled_step(state, us[k], ys[k])  # eager when not ready
                    states.append(state)
                    k += 1
                else:  # K steps in one graph; a last part past T runs on repeated y / u
                    chunk = slice(k, k + K)
                    uk = None if us_pad is None else us_pad[:, chunk].contiguous()
                    new = self._compiled_steps(state, uk, ys_pad[:, chunk].contiguous())
                    states.extend(new[: T - k])
                    state = states[-1]
                    k += K
                if not skipping and self._guarded_calls >= _GUARDED_STEPS:
                    stack.enter_context(_skip_guards())  # once, for the rest of the loop
                    skipping = True
        return self.collect(states)

    def step(self, state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
        """One step: ``update(predict(state, u), y)`` (``u [B, p]`` or None, ``y [B, m]``).

        The online fast path: after `compile` this runs the compiled step (the same
        graph as ``forward``'s loop) on validated inputs, so a measurement that arrives on its
        own costs one compiled call instead of hundreds of eager operations. ``y`` must be
        ``[B, m]`` with the state's batch ``B`` (inf raises; NaN raises unless ``skip_nan``),
        ``u`` as in `predict`. Without ``compile()`` (or while tracing) it is the eager
        ``update(predict(state, u), y)``. See also `streaming`.
        """
        compiled = getattr(self, "_compiled_step", None)
        if compiled is None or tracing():
            return self._eager_step(state, u, y)
        stream = getattr(self, "_stream", None)
        if stream is not None and stream["direct"] is not None and not torch.is_grad_enabled():
            return self._direct_step(stream, state, u, y)
        u = self._check_u(u, state)
        y = self._check_step_y(y, state, self.system.m, self.system.x0_set.dtype)
        if stream is None:
            return compiled(state, u, y)
        sig = _signature(state, u, y)
        if sig != stream["sig"]:  # new input structure: full guard checks again
            stream.update(sig=sig, guarded=0)
        if stream["guarded"] >= _GUARDED_STEPS:
            with _skip_guards():
                return compiled(state, u, y)
        before = getattr(self, "_guarded_calls", 0)
        new = compiled(state, u, y)
        stream["guarded"] += getattr(self, "_guarded_calls", 0) > before  # a compiled call
        return new

    @contextlib.contextmanager
    def streaming(self) -> Iterator[SetFilter]:
        """Online use of the compiled step without Dynamo.

        ``with filt.streaming(): state = filt.step(state, u, y)`` -- inside the block, after
        `compile` with Inductor and in no-grad mode (``torch.no_grad()``), ``step``
        calls Inductor's compiled code directly, without Dynamo's frame and guards
        (`diffsmf.filters._direct`): the step is captured once per input structure (set
        type, tensor shapes, strides, dtypes, devices, ``u`` given or not) with ``make_fx``,
        from the same branch-free code that ``torch.compile`` traces, and compiled by Inductor
        (seconds, once; reused by later blocks of the same configuration). The EKF's online
        step at B = 1 went from 0.25 to 0.06 ms (docs/filter_core.md). The inputs are still
        validated (``y`` shape, inf / NaN; ``u`` by the system). ``forward`` called inside
        the block runs the same captured step in its loop. While autograd records (or
        with another backend) a call runs the Dynamo-compiled step and skips its guard checks
        once two guarded calls have seen the same input structure.

        The contract: inside the block, do not change the filter or its system (attributes,
        submodules, which tensors are its parameters and buffers, what its functions read).
        Between blocks such changes are allowed: on entry, the filter's configuration
        (`config_key`: attributes of every submodule, identity
        and in-place version of every tensor, the system functions' code, closures and the
        globals they name) selects the compiled steps, so a changed one is compiled anew.
        Parameters and buffers are inputs of the compiled step (their current values are
        used at every call, e.g. after an optimiser step). Without `compile` it changes
        nothing.
        """
        old = getattr(self, "_stream", None)
        self._stream = {
            "sig": None, "guarded": 0, "direct": self._direct_steps(),
            "n_inputs": self.system.n_inputs, "m": self.system.m,
            "dtype": self.system.x0_set.dtype,
        }
        try:
            yield self
        finally:
            self._stream = old

    def _direct_step(
        self, stream: dict, state: FilterState, u: Tensor | None, y: Tensor
    ) -> FilterState:
        """`step` inside `streaming` in no-grad mode: the inputs validated as in
        `step` (the system's dimensions read once per block), then the Dynamo-free
        compiled step (`DirectSteps`)."""
        if u is not None or stream["n_inputs"]:
            u = self._check_u(u, state)
        y = self._check_step_y(y, state, stream["m"], stream["dtype"])
        try:
            return self._direct_call(stream["direct"], state, u, y)
        except CaptureError as err:
            self._drop_direct(stream, err)
        return self._compiled_step(state, u, y)

    @staticmethod
    def _drop_direct(stream: dict, err: CaptureError) -> None:
        """A step that ``make_fx`` / Inductor could not capture: warn once and use the
        Dynamo-compiled step for the rest of the ``streaming()`` block."""
        warnings.warn(
            f"streaming(): the step could not be captured without Dynamo ({err}); the "
            "Dynamo-compiled step is used for the rest of this block", RuntimeWarning,
            stacklevel=4,
        )
        stream["direct"] = None

    def _direct_call(
        self, direct: DirectSteps, state: FilterState, u: Tensor | None, y: Tensor
    ) -> FilterState:
        """One step of the Dynamo-free compiled graph on validated ``u``, ``y`` (eager for a
        state that the graph does not serve, see `_compile_ready`)."""
        if not self._compile_ready(state):
            return self._eager_step(state, u, y)
        y = y.contiguous()  # one compiled step for every slice y[:, k] of a log
        u = None if u is None else u.contiguous()
        fields, consistent, bounded, extras = _flat_args(state)
        return self._unflatten(direct(fields, consistent, bounded, extras, u, y, type(state.set)))

    def _direct_steps(self) -> DirectSteps | None:
        """The Dynamo-free compiled steps (`diffsmf.filters._direct`) for the filter's
        current configuration, or None when it is not compiled with Inductor."""
        options = getattr(self, "_direct_options", None)
        if options is None or getattr(self, "_compiled_step", None) is None:
            return None
        pins: list = []
        key = config_key(self, pins)
        cache = self.__dict__.setdefault("_direct_cache", {})
        if key not in cache:
            if len(cache) >= _DIRECT_CONFIGS:
                cache.pop(next(iter(cache)))
            # the pinned objects live as long as the key: no other can take their identity
            cache[key] = (DirectSteps(self, options), pins)
        return cache[key][0]

    def _eager_step(self, state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
        """``update(predict(state, u), y)``, eagerly (what `compile` traces)."""
        return self.update(self.predict(state, u), y)

    def _check_step_y(self, y: Any, state: FilterState, m: int, dtype: torch.dtype) -> Tensor:
        """``y [B, m]`` for one compiled step, as a ``dtype`` tensor on the state's device:
        shape (``B`` from ``state.consistent [B]``; the system's ``m``), inf / NaN. ``m`` and
        ``dtype`` are passed in so that `streaming` reads them once per block."""
        c = state.consistent
        if not isinstance(y, Tensor) or y.dtype != dtype or y.device != c.device:
            y = _y_tensor(y, dtype, c.device)
        if y.shape != (*c.shape, m):
            expected = [*c.shape, m]
            raise ValueError(f"y: expected shape {expected} for this state, got {list(y.shape)}")
        return self._check_finite_y(y)

    def _check_finite_y(self, y: Tensor) -> Tensor:
        """``y`` unchanged; inf raises, NaN raises unless ``skip_nan`` (host syncs)."""
        if y.numel() <= _SMALL_Y and y.device.type == "cpu":  # online B = 1: no tensor ops
            if all(map(math.isfinite, y.reshape(-1).tolist())):
                return y
        elif bool(torch.isfinite(y).all()):  # the common case: one check
            return y
        if torch.isinf(y).any():
            raise ValueError("y: contains inf")
        if not self.skip_nan:
            raise ValueError("y: contains NaN (pass skip_nan=True to skip those updates)")
        return y

    def compile(  # type: ignore[override]
        self, steps_per_call: int = 1, *, retain_memory: bool = False, **compile_kwargs: Any
    ) -> SetFilter:
        """The fast path: compile one filter step with ``torch.compile(fullgraph=True)``.

        The step (predict + update, the guard included) is traced once per state structure
        (set type and field shapes, batch size, input / measurement shapes) into a single
        graph without host syncs: in the traced code the argument checks that would
        synchronise are skipped (``forward`` still validates ``y`` and ``u`` once for the
        whole horizon, eagerly) and data-dependent branches take their branch-free general
        form (same sets up to rounding; every bound stays guaranteed). ``forward`` then runs
        the compiled step in its time loop, and `step` is the online fast path;
        ``predict`` / ``update`` stay eager. Returns ``self``.

        Args:
            steps_per_call: ``K >= 1``, the steps of ``forward``'s loop that one compiled call
                runs (one graph of K unrolled steps). Each call of a compiled graph costs a
                fixed framework overhead (about 85 us on this 2-core CPU: Dynamo's frame,
                AOTAutograd's and Inductor's wrappers), which dominates small filters at
                batch 1 (the EKF's step is about 0.13 ms); ``K`` steps share it, at the
                price of a graph (and a compile time) about ``K`` times larger. A last part
                shorter than ``K`` runs the same graph on the last ``y`` / ``u`` repeated and
                its extra states are dropped (steps are causal: the kept states are
                unchanged). The online `step` always uses the one-step graph.
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
                defaults).

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
        self._direct_options = None  # streaming() calls Inductor's graphs directly
        if kw.get("backend", "inductor") == "inductor" and "mode" not in kw:
            kw["options"] = {**_compile_options(), **_check_options(kw.get("options"))}
            if set(kw) <= {"fullgraph", "dynamic", "options", "backend"} and not kw["dynamic"]:
                self._direct_options = kw["options"]
        self.__dict__.pop("_direct_cache", None)
        self.__dict__.pop("_compiled_functions", None)
        self.__dict__.pop("_guarded_step_failed", None)
        self._compile_kwargs = kw
        # each its own code object (own recompile budget, see _own_code); compiled lazily
        flat = torch.compile(_own_code(type(self)._flat_step).__get__(self), **kw)
        multi = torch.compile(_own_code(type(self)._flat_steps).__get__(self), **kw)

        def compiled(state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
            if not self._compile_ready(state):
                return self._eager_step(state, u, y)
            self._guarded_calls = getattr(self, "_guarded_calls", 0) + 1  # see forward
            return self._unflatten(flat(*self._step_args(state), u, y, type(state.set)))

        def compiled_steps(state: FilterState, us: Tensor | None, ys: Tensor) -> list[FilterState]:
            self._guarded_calls = getattr(self, "_guarded_calls", 0) + 1
            outs = multi(*self._step_args(state), us, ys, type(state.set))
            return [self._unflatten(o) for o in outs]

        self._out_type = type(self.initial_state(batch=1).set)
        self._steps_per_call = steps_per_call
        self._compiled_step = compiled
        self._compiled_steps = compiled_steps
        return self

    @contextlib.contextmanager
    def eager(self) -> Iterator[SetFilter]:
        """``with filt.eager():`` -- inside the block a compiled filter runs eagerly
        (``forward``, ``step`` and `compiled_function`), e.g. for a one-off pass on a
        batch size that would otherwise compile a new graph; the compiled graphs are kept for
        after the block. Without `compile` it changes nothing."""
        keys = ("_compiled_step", "_compile_kwargs")
        saved = {k: self.__dict__.pop(k) for k in keys if k in self.__dict__}
        try:
            yield self
        finally:
            self.__dict__.update(saved)

    def compiled_function(
        self, name: str, fn: Callable[..., Any], **overrides: Any
    ) -> Callable[..., Any] | None:
        """``fn(self, *args)`` compiled with this filter's `compile` arguments (updated
        by ``overrides``, e.g. ``dynamic=None``), or None when the filter is not compiled.

        For steps that wrap the filter's own step (e.g. the tuning step of
        `training.losses.filter_with_predictions`, which adds the consistency excess):
        ``fn`` gets a code object of its own (its own recompile budget) and is bound to the
        filter; the compiled function is cached under ``name`` until the next ``compile()``.
        Call it on `_step_args` and rebuild the state with `_unflatten`, as the
        compiled step does.
        """
        kw = getattr(self, "_compile_kwargs", None)
        if kw is None:
            return None
        cache = self.__dict__.setdefault("_compiled_functions", {})
        if name not in cache:
            cache[name] = torch.compile(_own_code(fn).__get__(self), **{**kw, **overrides})
        return cache[name]

    def _step_args(self, state: FilterState) -> tuple:
        """`_flat_args` for a compiled call; while a gradient is recorded for a
        trainable parameter (of the filter or its system), the state's floating tensors enter
        as grad leaves, so that every step of a training forward has one signature."""
        trains = torch.is_grad_enabled() and any(p.requires_grad for p in self.parameters())
        return _flat_args(state, grad_leaves=trains)

    def _compile_ready(self, state: FilterState) -> bool:
        """Whether the compiled graph serves ``state`` (else its step runs eagerly): every
        extra is a tensor (a state built by hand with another object in its extras runs
        eagerly)."""
        return all(isinstance(v, Tensor) for v in state.extras.values())

    def _unflatten(self, out: tuple) -> FilterState:
        fields, consistent, bounded, extras = out
        return FilterState(self._out_type._from_tensors(fields), consistent, extras, bounded)

    def _flat_step(
        self,
        fields: tuple[Tensor, ...],
        consistent: Tensor,
        bounded: Tensor,
        extras: dict[str, Tensor],
        u: Tensor | None,
        y: Tensor,
        set_type: type,
    ) -> tuple[tuple[Tensor, ...], Tensor, Tensor, dict[str, Tensor]]:
        """`step` on flat tensors (the function that ``compile`` traces)."""
        state = state_from_flat(fields, consistent, bounded, extras, set_type)
        return flat_state(self._eager_step(state, u, y))

    def _flat_steps(
        self,
        fields: tuple[Tensor, ...],
        consistent: Tensor,
        bounded: Tensor,
        extras: dict[str, Tensor],
        us: Tensor | None,
        ys: Tensor,
        set_type: type,
    ) -> tuple[tuple, ...]:
        """``K = ys.shape[1]`` steps of `_flat_step` (``us [B, K, p]``, ``ys [B, K, m]``)
        -> the K flat states (the function that ``compile(steps_per_call=K)`` traces)."""
        out = []
        flat = (fields, consistent, bounded, extras)
        for j in range(ys.shape[1]):
            u = None if us is None else us[:, j]
            flat = self._flat_step(*flat, u, ys[:, j], set_type)
            out.append(flat)
        return tuple(out)

    def collect(self, states: list[FilterState]) -> FilterResult:
        """Assemble a `FilterResult` from the per-step states."""
        sets = _pad_and_stack([s.set for s in states])
        lower, upper, volume = self._hull_and_volume(sets)
        extras = {
            k: torch.stack([s.extras[k] for s in states], 1)
            for k in states[-1].extras
            if not k.startswith("_") and all(k in s.extras for s in states)
        }
        return bounded_result(FilterResult, states, sets, sets.center, lower, upper, volume, extras)

    def _hull_and_volume(self, sets: ConvexSet) -> tuple[Tensor, Tensor, Tensor]:
        """``(lower, upper, volume)`` of the stacked ``sets`` (batch ``[B, T+1]``):
        ``[B, T+1, n]`` twice and ``[B, T+1]``.

        After `compile`, in no-grad mode, a zonotope's hull and volume run as two
        compiled graphs with a dynamic batch dimension (one each whatever B and T): in 2-D the
        traced volume sums the generator-pair table in one fused loop
        (`PAIR_TABLE_MAX_M`) instead of the eager angle sort, which
        was about a quarter of a compiled MSZM ``forward`` at B = 10,000. The two
        volumes agree to a few ``m eps`` relative; the sets are untouched. Other set types
        (one batched determinant for their volume) and recorded gradients stay eager.
        """
        from diffsmf.sets.zonotope import Zonotope

        batch = sets.batch_shape
        if (
            type(sets) is Zonotope and batch.numel() > 1
            and not torch.is_grad_enabled() and not tracing()
        ):
            # two graphs: fused into one, the two reductions ran at 54 ms instead of 12 + 12
            # (B = 110,000, m = 24, 1 thread, the filter's scalar-code options)
            hull_fn = self.compiled_function("hull", _flat_hull, dynamic=None)
            volume_fn = self.compiled_function("volume", _flat_volume, dynamic=None)
            if hull_fn is not None:  # both None when the filter is not compiled
                fields = [t.reshape(-1, *t.shape[len(batch):]) for t in sets._tensors()]
                for t in fields:
                    torch._dynamo.maybe_mark_dynamic(t, 0)
                lo, hi = hull_fn(*fields, set_type=type(sets))
                vol = volume_fn(*fields, set_type=type(sets))
                return lo.reshape(*batch, -1), hi.reshape(*batch, -1), vol.reshape(batch)
        hull = sets.interval_hull()
        return hull.lower, hull.upper, sets.volume()

    def _check_y(self, y: Tensor) -> Tensor:
        dt = self.system.x0_set.dtype
        y = _y_tensor(y, dt, None) if not isinstance(y, Tensor) else y
        if y.dim() == 2:
            y = y.unsqueeze(0)
        if y.dim() != 3 or y.shape[-1] != self.system.m:
            raise ValueError(f"y: expected shape [B, T, {self.system.m}], got {tuple(y.shape)}")
        if tracing():  # value checks would sync with the host (torch.compile of forward)
            return y
        return self._check_finite_y(y)


# ---------------------------------------------------------------------------- Minkowski weights
def register_minkowski_scale(module: nn.Module, value: Any) -> None:
    """Validate and register the learnable scalar ``minkowski_scale`` (> 0, finite).

    ``minkowski_scale = scale * softplus(raw)`` (`register_positive`):
    positive whatever the raw value, and exactly the given value at construction (softplus of
    the initial raw is exactly 1 in float32 and float64). Used by the ellipsoidal filters
    (CDSMF, ESMF) through `scaled_minkowski_sum`. Raises ``ValueError`` naming
    ``minkowski_scale`` for 0, negative, NaN, infinite or non-scalar values.
    """
    v = check_strictly_positive("minkowski_scale", value)
    register_positive(module, "minkowski_scale", v.clone())


def scaled_minkowski_sum(E1: Any, E2: Any, method: str, scale: Tensor) -> Any:
    """``E1 (+) E2`` with the weight ``p = rule_p * scale`` of ``S(p) = (1 + 1/p) S1 + (1 + p) S2``.

    ``rule_p = minkowski_weight(S1, S2, method)`` is the per-step rule (``"trace"`` or
    ``"volume"``); every ``p > 0`` gives an outer bound, so the factor ``scale > 0`` never
    costs the guarantee. ``scale == 1`` reproduces ``E1.minkowski_sum(E2, method)`` bit for bit
    (``x * 1.0 == x`` in IEEE arithmetic). Both operands are ellipsoids (positive definite).
    A weight that is not finite and positive (shapes that overflowed) is replaced by 1.
    """
    from diffsmf.sets.ellipsoid import minkowski_weight

    rule_p = minkowski_weight(E1.shape, E2.shape, method)
    p = rule_p * scale
    # an overflowed / underflowed rule (shapes beyond 1e150: the set is diverging) gives
    # p = 0, inf or NaN; any p > 0 is an outer bound, and the guard flags the set
    p = torch.where(torch.isfinite(p) & (p > 0), p, torch.ones_like(p))
    return E1.minkowski_sum(E2, p=p)


# =============================================================================================
# Public entry point to the compiled step for time loops other than `SetFilter.forward`
# (the tuning pass of `diffsmf.tuning.losses`): the loop of `forward`, with a wrapped step.
# =============================================================================================
__all__.append("compiled_loop")


@contextlib.contextmanager
def compiled_loop(
    filt: SetFilter, name: str, fn: Callable[..., Any]
) -> Iterator[Callable[..., tuple[FilterState, Any] | None] | None]:
    """A time loop over a compiled wrapper ``fn`` of the filter's step, as in ``forward``.

    ``fn(filt, fields, consistent, bounded, extras, set_type, *args) -> (flat, out)`` takes a
    state as flat tensors (`state_from_flat` rebuilds it) and returns the new state as
    `flat_state` gives it, and any output ``out``. It is compiled with the filter's
    `SetFilter.compile` settings (`SetFilter.compiled_function`, cached under ``name``).

    Yields None when the filter is not compiled (or while tracing): run the loop eagerly.
    Otherwise yields ``run(state, *args)`` -> ``(new state, out)``, or None for a state that
    the compiled graph does not serve (run that step eagerly). As in ``forward``, after the
    first `_GUARDED_STEPS` compiled calls inside the block Dynamo's guard evaluation is
    skipped for the rest of the block, so call ``run`` inside one block on inputs of one
    structure (one batch size, the states that ``run`` returned, same-shaped ``args``).
    """
    compiled = None if tracing() else filt.compiled_function(name, fn)
    if compiled is None:
        yield None
        return
    with contextlib.ExitStack() as stack:
        calls = 0

        def run(state: FilterState, *args: Any) -> tuple[FilterState, Any] | None:
            nonlocal calls
            if not filt._compile_ready(state):
                return None
            flat, out = compiled(*filt._step_args(state), type(state.set), *args)
            calls += 1
            if calls == _GUARDED_STEPS:
                stack.enter_context(_skip_guards())
            return filt._unflatten(flat), out

        yield run
