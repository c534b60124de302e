"""Filter contract shared by every filter: state, result and the predict/update loop.

``forward(y, u)`` is exactly: for each k, ``predict(state, u[:, k-1])`` then
``update(state, y[:, k-1])`` (docs/design.md). A subclass implements the hooks
``_predict(state, u)`` and ``_update(state, y)`` (and ``_initial_state(batch)`` when its start
is not the system's initial set); the public ``predict``, ``update`` and ``initial_state``
validate the inputs, record the events and call them. NaN handling, the boundedness guard
and result assembly live here once (the guard's tests of a set are in
`diffsmf.filters.events`; ``carry`` and ``bounded_result``, which combine states, in
`diffsmf.filters.state`). The compiled runtime (``compile``, ``step``, ``streaming``, the
compiled time loop of ``forward``) is `diffsmf.filters.runtime`; the state and its flat form
are `diffsmf.filters.state`.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.convex import ConvexSet, align, family, where
from diffsmf.filters import measurements, runtime
from diffsmf.filters.events import (
    MAX_SET_RADIUS,
    FilterEvent,
    all_small,
    finite_fields,
    hull_radius,
)
from diffsmf.filters.params import register_minkowski_scale, scaled_minkowski_sum
from diffsmf.filters.runtime import COMPILE_OPTIONS, compiled_loop
from diffsmf.filters.state import (
    FilterResult,
    FilterState,
    bounded_result,
    carry,
    flat_state,
    pad_and_stack,
    state_batch,
    state_from_flat,
    with_events,
)
from diffsmf.sets.interval import Interval
from diffsmf.systems.system import System, check_system
from diffsmf.utils import (
    Positive,
    StrictlyPositive,
    check_half_widths,
    numerical_events,
    register_positive,
    tracing,
    user_stacklevel,
)

__all__ = [
    "COMPILE_OPTIONS",
    "MAX_SET_RADIUS",
    "FilterResult",
    "bounded_result",
    "check_filter",
    "compiled_loop",
    "flat_state",
    "FilterState",
    "SetFilter",
    "StrictlyPositive",
    "register_minkowski_scale",
    "scaled_minkowski_sum",
    "state_batch",
    "state_from_flat",
]


def _noise_box(filt: nn.Module, name: str, c: Tensor, r: Tensor) -> Interval:
    """``Interval(c - r, c + r)``; without autograd recording, eagerly, the box of the last call
    again while ``r`` is the same tensor (`Positive` reuses its value) and ``c`` unchanged."""
    if r.requires_grad or tracing() or torch.is_inference_mode_enabled():
        return Interval(c - r, c + r)
    cache = filt.__dict__.setdefault("_noise_box_cache", {})
    key = (r, c._version, c.untyped_storage())
    hit = cache.get(name)
    if hit is not None and hit[0][0] is r and hit[0][1] == key[1] and (
        hit[0][2]._cdata == key[2]._cdata
    ):
        return hit[1]
    box = Interval(c - r, c + r)
    cache[name] = (key, box)
    return box


def _flagging(fn: Callable[..., FilterState], *args: Any) -> FilterState:
    """``fn(*args)`` inside `diffsmf.utils.numerical_events` (a numerical event is
    flagged per element, never raised); traced code has no value checks anyway."""
    if tracing():
        return fn(*args)
    with numerical_events():
        return fn(*args)


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


def warn_uncertified_fit(system: System, filter_name: str) -> None:
    """Warn, at the user's line, when ``system``'s dynamics are a fitted model (an SCPLNN)
    without its certified error (``System.uncertified_fit``): the filter's sets then bound
    the fitted model, not the plant it approximates."""
    if getattr(system, "uncertified_fit", False):
        warnings.warn(
            f"system {system.name!r}: f is a fitted SCPLNN without a certified error, so "
            f"{filter_name}'s sets bound the fitted model, not the plant it approximates; "
            "build the system with ds.pwl.as_system(model, h, x0_set, W, V, "
            "certificate=ds.pwl.certify_error(model, g)), which adds the model's error to the "
            "process noise",
            UserWarning, stacklevel=user_stacklevel())


#: The noise bounds by their stored and tuning names (``raw_process_noise``, ``params=
#: ["process_noise"]``, bounds files, the command line) -> the filter's attributes.
NOISE_HALF_WIDTHS = {"process_noise": "process_half_widths",
                     "measurement_noise": "measurement_half_widths"}


class _Renamed:
    """A deprecated attribute name that reads and writes the attribute ``new`` (a
    `DeprecationWarning` at the user's line)."""

    def __init__(self, new: str) -> None:
        self.new = new

    def __set_name__(self, owner: type, name: str) -> None:
        self.old = name
        self.__doc__ = f"Deprecated name of `{self.new}`."

    def __get__(self, obj: Any, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        self._warn()
        return getattr(obj, self.new)

    def __set__(self, obj: Any, value: Any) -> None:
        self._warn()
        setattr(obj, self.new, value)

    def _warn(self) -> None:
        warnings.warn(f"{self.old}: the filter's noise half-widths are now {self.new} (the "
                      f"system's {self.old} is a set)", DeprecationWarning,
                      stacklevel=user_stacklevel())


def _renamed(old: str, old_value: Any, new: str, new_value: Any) -> tuple[Any, str]:
    """``(value, name)`` of the argument ``new`` or of its deprecated name ``old``, the name
    the caller used (for the errors); both given: an error naming them."""
    if old_value is None:
        return new_value, new
    if new_value is not None:
        raise ValueError(f"{new}: give it or its deprecated name {old}, not both")
    warnings.warn(f"{old}: renamed {new} (the system's {old} is a set)", DeprecationWarning,
                  stacklevel=user_stacklevel())
    return old_value, old

class SetFilter(nn.Module):
    """Base class of every filter (set-membership or Kalman).

    Learnable hyperparameters shared by all filters: ``process_half_widths [n]`` and
    ``measurement_half_widths [m]``, the half-widths of the noise bounds, per component
    (default: the half-widths of the interval hulls of the system's noise sets, so the
    system's sets themselves; `process_noise_set` scales the system's set to them). The
    system's ``process_noise`` is a set; ``filt.process_noise`` is a deprecated name of
    ``filt.process_half_widths``.

    A subclass implements ``_predict(state, u)`` (time update on a validated ``u``) and
    ``_update(state, y)`` (measurement update on a finite ``y``), and ``_initial_state(batch)``
    when it does not start from the system's initial set. The public ``predict``, ``update``
    and ``initial_state`` call these hooks: they validate ``u`` / ``y``, keep the event bits
    and the ``bounded`` flags from step to step and end an update with `guard`. (A subclass
    that overrides ``predict`` or ``initial_state`` itself, as before these hooks, still runs,
    without the check of ``u`` and the zero event bits of the first state.)

    Args:
        system: the `System` to filter.
        process_half_widths: process noise half-widths ``[n]`` instead of the system's.
        measurement_half_widths: measurement noise half-widths ``[m]`` instead of the
            system's.
        process_noise, measurement_noise: deprecated names of the two above.
        skip_nan: skip the update of a batch element whose measurement has NaN (else raise).
    """

    process_half_widths = Positive(storage="process_noise")  # see NOISE_HALF_WIDTHS
    measurement_half_widths = Positive(storage="measurement_noise")

    process_noise = _Renamed(NOISE_HALF_WIDTHS["process_noise"])
    measurement_noise = _Renamed(NOISE_HALF_WIDTHS["measurement_noise"])

    #: Whether ``predict`` and ``update`` give sets of the same field shapes (False for CZSMF,
    #: whose predicted set is larger than its capped update); tuning compiles its guarded step
    #: (`diffsmf.tuning.losses.filter_with_predictions`) only for such filters.
    _constant_set_size: bool = True

    def __init__(
        self,
        system: System,
        *,
        process_half_widths: Tensor | None = None,
        measurement_half_widths: Tensor | None = None,
        skip_nan: bool = False,
        learn_noise: bool = True,
        process_noise: Tensor | None = None,
        measurement_noise: Tensor | None = None,
    ) -> None:
        super().__init__()
        check_system("system", system)
        warn_uncertified_fit(system, type(self).__name__)
        self.system = system
        self.skip_nan = skip_nan
        n, m = system.n, system.m
        dt = system.x0_set.dtype
        for noise, s, dim, override, label in (
            ("process", system.process_noise, n,
             *_renamed("process_noise", process_noise, "process_half_widths",
                       process_half_widths)),
            ("measurement", system.measurement_noise, m,
             *_renamed("measurement_noise", measurement_noise, "measurement_half_widths",
                       measurement_half_widths)),
        ):
            if s is None:
                c, r = torch.zeros(dim, dtype=dt), torch.zeros(dim, dtype=dt)
            else:
                hull = s.interval_hull()
                c, r = hull.center.detach(), hull.radius.detach()
            if override is not None:
                r = check_half_widths(label, override, dim, dt)
            # stored as raw_process_noise / process_noise_scale (the tuning names)
            register_positive(self, f"{noise}_noise", r, learnable=learn_noise)
            self.register_buffer(f"{noise}_noise_center", c.clone())
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
        """Current process-noise box W ``[n]`` (differentiable in ``process_half_widths``)."""
        return _noise_box(self, "process_noise", self.process_noise_center,
                          self.process_half_widths)

    def process_noise_set(self) -> ConvexSet:
        """The process-noise set W as given by the system, scaled per component, ``[n]``.

        ``W_s = c + diag(s) (W - c)`` with ``s = process_half_widths / (half-width of W's interval
        hull)``: for a box this is exactly `process_noise_box`; a ``Zonotope`` /
        ``Parallelotope`` keeps its generators (``diag(s) G``) and an ``Ellipsoid`` its shape
        (``diag(s) S diag(s)``), so no filter pays for the interval hull of a non-box W.
        ``s = 1`` (the default) is the system's set. Differentiable in
        ``process_half_widths``. A component with a zero hull half-width stays zero.
        """
        return self._scaled_noise_set(
            self.system.process_noise, self.process_noise_box(), self.process_half_widths,
            self.process_noise_hull_radius, self.process_noise_center,
        )

    def measurement_noise_set(self) -> ConvexSet:
        """The measurement-noise set V as given by the system, scaled per component, ``[m]``
        (as `process_noise_set`; a box V is exactly `measurement_noise_box`)."""
        return self._scaled_noise_set(
            self.system.measurement_noise, self.measurement_noise_box(),
            self.measurement_half_widths, self.measurement_noise_hull_radius,
            self.measurement_noise_center,
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
        """Current measurement-noise box V ``[m]`` (differentiable in
        ``measurement_half_widths``)."""
        return _noise_box(
            self, "measurement_noise", self.measurement_noise_center,
            self.measurement_half_widths,
        )


    # ------------------------------------------------------------------ contract
    def initial_state(self, batch: int | None = None) -> FilterState:
        """State at k = 0, batch shape ``[batch]``: the subclass's `_initial_state` with
        ``extras["events"]`` (zeros) so that every state of a run has one structure."""
        return with_events(self._initial_state(batch))

    def _initial_state(self, batch: int | None) -> FilterState:
        """Hook: the state at k = 0 (default: the system's initial set)."""
        x0 = self.system.x0_set
        b = state_batch(batch)
        return FilterState(
            set=x0.expand(b), consistent=torch.ones(b, dtype=torch.bool, device=x0.device)
        )

    def predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        """Time update with input ``u [B, p]`` (the input that drives x_{k-1} -> x_k).

        ``u`` is validated by the system first (`System.check_input`: missing, wrong width
        or NaN raise); then the subclass's `_predict`, whose numerical events are flagged per
        element (never raised), and whose state keeps what ``state`` had met."""
        u = self._check_u(u, state)
        return carry(state, _flagging(self._predict, state, u))

    def _predict(self, state: FilterState, u: Tensor | None) -> FilterState:
        """Hook: time update with a validated input ``u [B, p]`` (or None)."""
        raise NotImplementedError

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        """Hook: measurement update with finite ``y [B, m]``; sets ``consistent``."""
        raise NotImplementedError

    def update(self, state: FilterState, y: Tensor) -> FilterState:
        """Measurement update with ``y [B, m]``; NaN rows raise or (``skip_nan``) are skipped.

        ``y`` is validated first (`_check_update_y`: exactly ``[B, m]``, no inf). Ends
        with the boundedness guard (`guard`)."""
        y = self._check_update_y(y, state)
        cls = type(self)
        if not self.skip_nan and cls._guarded_update is SetFilter._guarded_update and (
            cls._check_update_y is SetFilter._check_update_y
        ):  # a NaN row raised in `_check_update_y` already (eager): no rows to skip
            return _flagging(cls._guarded_update, self, state, y, None)
        bad = torch.isnan(y).any(-1)
        if not tracing() and bool(bad.any()) and not self.skip_nan:
            raise ValueError("y: contains NaN (pass skip_nan=True to skip those updates)")
        return _flagging(cls._guarded_update, self, state, y, bad)

    def _guarded_update(self, state: FilterState, y: Tensor, bad: Tensor | None) -> FilterState:
        """`update` on a validated ``y`` (``bad [B]``: its NaN rows; None without
        ``skip_nan``)."""
        if not self.skip_nan or bad is None or (not tracing() and not bool(bad.any())):
            return self.guard(carry(state, self._update(state, y)))
        new = carry(state, self._update(
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
        Branch-free while traced; eagerly, a batch that is all bounded skips the replacement.
        """
        S = state.set
        r = hull_radius(S)
        was = state.bounded
        if not tracing() and type(S) in (family("Zonotope"), family("Parallelotope")) and (
            r.numel() > 0 and all_small(r, S.center)
        ):  # eager, every element finite and small: nothing to flag or replace
            b = torch.ones_like(state.consistent) if was is None else was
            new = with_events(state).replace(bounded=b)
            # consistent | ~b, one op on bools
            return new if was is None else new.replace(consistent=b <= state.consistent)
        finite = finite_fields(S)
        small = (r <= MAX_SET_RADIUS).all(-1)  # NaN: False
        ok = finite & small
        lost = ~ok if was is None else was & ~ok
        # NON_FINITE (8) where a field is not finite, else DIVERGED (1), where the bound is lost
        ev = (int(FilterEvent.NON_FINITE) - 7 * finite) * lost
        b = ok if was is None else was & ok
        old = state.extras.get("events")
        extras = {**state.extras, "events": ev if old is None else old | ev}
        new = FilterState(S, state.consistent | ~b, extras, b)  # nothing contradicts R^n
        if not tracing() and bool(b.all()):
            return new
        init = self.initial_state(batch=int(finite.shape[0]) if finite.dim() else None)
        ref = init.set
        same = type(ref) is type(S) and ref.batch_shape == S.batch_shape
        if same:
            S_a, ref_a = align([S, ref])
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
        dtype = self.system.x0_set.dtype
        return measurements.check_step_y(y, state, self.system.m, dtype, self.skip_nan)

    def _check_u(self, u: Tensor | None, state: FilterState) -> Tensor | None:
        """``u [B, p]`` validated by the system (skipped while tracing for torch.compile)."""
        if tracing():
            return u
        return self.system.check_input(u, state.set.batch_shape)

    def _eager_step(self, state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
        """``update(predict(state, u), y)``, eagerly (what `compile` traces)."""
        return self.update(self.predict(state, u), y)

    def _compile_ready(self, state: FilterState) -> bool:
        """Whether the compiled graph serves ``state`` (else its step runs eagerly): every
        extra is a tensor (a state built by hand with another object in its extras runs
        eagerly)."""
        return all(isinstance(v, Tensor) for v in state.extras.values())

    def forward(self, y: Tensor, u: Tensor | None = None, *, progress: Any = False
                ) -> FilterResult:
        """Filter measurements ``y [B, T, m]`` (inputs ``u [B, T, p]``) -> `FilterResult`.

        ``progress``: ``True`` shows a progress bar over the T steps (tqdm), or pass a bar
        factory such as ``tqdm`` itself (`diffsmf.utils.progress_bar`); off by default.
        """
        y = measurements.measurements(y, self.system.m, self.system.x0_set.dtype, self.skip_nan)
        B, T, _ = y.shape
        if not tracing():
            measurements.check_log(y, u)
            u = self.system.check_input(u, (B, T))
        states = runtime.run_steps(self, self.initial_state(batch=B), y, u, progress)
        return self.collect(states)

    def collect(self, states: list[FilterState]) -> FilterResult:
        """Assemble a `FilterResult` from the per-step states."""
        sets = pad_and_stack([s.set for s in states])
        hull = runtime.compiled_hull_and_volume(self, sets)
        if hull is None:
            box = sets.interval_hull()
            hull = box.lower, box.upper, sets.volume()
        extras = {
            k: torch.stack([s.extras[k] for s in states], 1)
            for k in states[-1].extras
            if not k.startswith("_") and all(k in s.extras for s in states)
        }
        return bounded_result(FilterResult, states, sets, sets.center, *hull, extras)

    # ------------------------------------------------------------------ compiled runtime
    def step(self, state: FilterState, u: Tensor | None, y: Tensor) -> FilterState:
        """One step: ``update(predict(state, u), y)`` (``u [B, p]`` or None, ``y [B, m]``).

        The online fast path: after `compile` this runs the compiled step (the same
        graph as ``forward``'s loop, `diffsmf.filters.runtime.online_step`) on validated
        inputs, so a measurement that arrives on its own costs one compiled call instead of
        hundreds of eager operations. ``y`` must be ``[B, m]`` with the state's batch ``B``
        (inf raises; NaN raises unless ``skip_nan``), ``u`` as in `predict`. Without
        ``compile()`` (or while tracing) it is the eager ``update(predict(state, u), y)``.
        See also `streaming`.
        """
        if not self.compiled or tracing():
            return self._eager_step(state, u, y)
        return runtime.online_step(self, state, u, y)

    @property
    def compiled(self) -> bool:
        """Whether the step is compiled (after ``compile()``, outside an ``eager()`` block)."""
        return runtime.runtime_of(self).step is not None

    def compile(  # type: ignore[override]
        self, steps_per_call: int = 1, *, retain_memory: bool = False, progress: bool = False,
        **compile_kwargs: Any,
    ) -> SetFilter:
        """The fast path: compile one filter step with ``torch.compile(fullgraph=True)``.

        ``forward`` then runs the compiled step in its time loop and `step` is the online
        fast path; ``predict`` / ``update`` stay eager. Returns ``self``. The arguments
        (``steps_per_call``: steps per compiled call; ``retain_memory``: opt in to
        `diffsmf.utils.retain_freed_memory`; ``progress``: a line on stderr while a new
        batch size compiles, and how long it took; ``compile_kwargs`` for `torch.compile`)
        are documented at `diffsmf.filters.runtime.compile_filter`.
        """
        runtime.compile_filter(
            self, steps_per_call, retain_memory=retain_memory, progress=progress,
            **compile_kwargs,
        )
        return self

    def eager(self) -> contextlib.AbstractContextManager[SetFilter]:
        """``with filt.eager():`` -- inside the block a compiled filter runs eagerly
        (``forward``, ``step`` and `compiled_function`), e.g. for a one-off pass on a
        batch size that would otherwise compile a new graph; the compiled graphs are kept for
        after the block. Without `compile` it changes nothing."""
        return runtime.eager(self)

    def compiled_function(
        self, name: str, fn: Callable[..., Any], **overrides: Any
    ) -> Callable[..., Any] | None:
        """``fn(self, *args)`` compiled with this filter's `compile` arguments (updated by
        ``overrides``), cached under ``name``, or None when the filter is not compiled
        (`diffsmf.filters.runtime.compiled_function`)."""
        return runtime.compiled_function(self, name, fn, **overrides)

    def streaming(self) -> contextlib.AbstractContextManager[SetFilter]:
        """Online use of the compiled step without Dynamo: ``with filt.streaming(): state =
        filt.step(state, u, y)`` -- inside the block, after `compile` with Inductor and in
        no-grad mode, ``step`` (and ``forward``) call Inductor's compiled code directly,
        without Dynamo's frame and guards. Do not change the filter or its system inside the
        block; the contract and the details are at `diffsmf.filters.runtime.streaming`.
        Without `compile` it changes nothing."""
        return runtime.streaming(self)
