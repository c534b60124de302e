"""The filter state and result, and the flat form in which a compiled step takes a state.

`FilterState` is what one filter step maps to the next, `FilterResult` what ``forward``
returns. A compiled step (`diffsmf.filters.runtime`) takes a state as flat tensors: the set's
fields, ``consistent``, ``bounded`` and the extras (`flat_args` / `flat_state`), and
`state_from_flat` rebuilds it; `flat_step` is the step on that form (what is traced).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, align, check_count, check_nonempty, stack
from diffsmf.filters.events import LOSES_BOUND, FilterEvent, mark_unbounded
from diffsmf.utils import tracing

__all__ = [
    "FilterResult",
    "FilterState",
    "bounded_result",
    "carry",
    "check_initial_set",
    "expand_state_set",
    "flat_args",
    "flat_state",
    "flat_step",
    "flat_steps",
    "measurement_events",
    "pad_and_stack",
    "predicted_state",
    "state_batch",
    "state_from_flat",
    "updated_state",
    "with_events",
]


#: `measurement_events` of every code ``0 .. 2 MAX - 1`` (eager lookup tables, per device).
_MEASUREMENT_TABLES: dict[torch.device, Tensor] = {}


def measurement_events(ev: Tensor) -> Tensor:
    """`FilterEvent` codes ``ev [B]`` (int64) of a measurement update as the state records
    them: the bits that would lose the bound (``LOSES_BOUND``) become ``MEASUREMENT_SKIPPED``
    (the update was skipped; the set keeps its guarantee), the others stay. Eagerly one
    lookup in a table of all codes, while traced the same bit arithmetic."""
    from diffsmf.utils import tracing

    if tracing():
        skipped = ((ev & LOSES_BOUND) != 0) * int(FilterEvent.MEASUREMENT_SKIPPED)
        return (ev & ~LOSES_BOUND) | skipped
    table = _MEASUREMENT_TABLES.get(ev.device)
    if table is None:
        codes = torch.arange(2 * max(FilterEvent), dtype=torch.int64, device=ev.device)
        skipped = ((codes & LOSES_BOUND) != 0) * int(FilterEvent.MEASUREMENT_SKIPPED)
        table = _MEASUREMENT_TABLES[ev.device] = (codes & ~LOSES_BOUND) | skipped
    return table[ev]


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
            ev = measurement_events(ev)
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



def predicted_state(state: FilterState, S: ConvexSet, ev: Tensor) -> FilterState:
    """The state a ``_predict`` hook returns: set ``S``, events ``ev [B]`` (int64 remainder
    codes, `checked_remainder`: ``DOMAIN`` / ``DIVERGED``, each of which loses the bound) and
    ``bounded = (ev == 0)`` of this step alone. `SetFilter.predict` then ORs in the
    events and ANDs in ``bounded`` that ``state`` had met (`carry`): the same state as
    ``state.replace(set=S).flag(ev)`` after that, in fewer ops."""
    return state.replace(set=S, extras={**state.extras, "events": ev}, bounded=ev == 0)


def updated_state(state: FilterState, S: ConvexSet, ok: Tensor, ev: Tensor) -> FilterState:
    """The state an ``_update`` hook returns: set ``S``, ``consistent = ok [B]`` and the
    measurement events ``ev [B]`` of this step alone (`measurement_events`; ``bounded`` is
    ``state``'s). `SetFilter.update` then ORs in the events ``state`` had met (`carry`): the
    same state as ``state.replace(set=S, consistent=ok).flag(ev, unbounded=False)``."""
    events = measurement_events(ev.to(torch.int64))
    return state.replace(set=S, consistent=ok, extras={**state.extras, "events": events})


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



def _contiguous(v: Any) -> Any:
    """A tensor made contiguous (one compiled graph for expanded and dense inputs); other
    extras (e.g. the ellipsoidal filters' initial box, an Interval) as they are."""
    return v.contiguous() if isinstance(v, Tensor) else v



def flat_args(state: FilterState, grad_leaves: bool = False) -> tuple:
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
    (``bounded`` all True for None); `diffsmf.filters.runtime.unflatten` rebuilds it."""
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



def flat_step(
    filt: Any,
    fields: tuple[Tensor, ...],
    consistent: Tensor,
    bounded: Tensor,
    extras: dict[str, Tensor],
    u: Tensor | None,
    y: Tensor,
    set_type: type,
) -> tuple[tuple[Tensor, ...], Tensor, Tensor, dict[str, Tensor]]:
    """The step of the filter ``filt`` on flat tensors (the function that ``compile`` traces):
    its eager ``update(predict(state, u), y)`` between `state_from_flat` and `flat_state`."""
    state = state_from_flat(fields, consistent, bounded, extras, set_type)
    return flat_state(filt._eager_step(state, u, y))


def flat_steps(
    filt: Any,
    fields: tuple[Tensor, ...],
    consistent: Tensor,
    bounded: Tensor,
    extras: dict[str, Tensor],
    us: Tensor | None,
    ys: Tensor,
    set_type: type,
) -> tuple[tuple, ...]:
    """``K = ys.shape[1]`` steps of `flat_step` (``us [B, K, p]``, ``ys [B, K, m]``)
    -> the K flat states (the function that ``compile(steps_per_call=K)`` traces)."""
    out = []
    flat = (fields, consistent, bounded, extras)
    for j in range(ys.shape[1]):
        u = None if us is None else us[:, j]
        flat = flat_step(filt, *flat, u, ys[:, j], set_type)
        out.append(flat)
    return tuple(out)


def check_initial_set(name: str, S: ConvexSet | None, n: int) -> None:
    """Validate an ``initial_set`` override (a non-empty set of dim ``n``, batch shape ``[]``)."""
    if S is not None and (not isinstance(S, ConvexSet) or S.dim != n or S.batch_shape != ()):
        raise ValueError(f"{name}: must be a diffsmf set of dim {n} with empty batch shape")
    if S is not None:
        check_nonempty(name, S)


def expand_state_set(S: ConvexSet, batch: int | None) -> ConvexSet:
    """``S`` (batch shape ``[]``) broadcast to ``[batch]`` (default 1)."""
    return S.expand(state_batch(batch))


def state_batch(batch: Any) -> int:
    """The ``batch`` argument of ``initial_state``: ``None`` -> 1, else an ``int >= 0`` (not
    a ``bool``); anything else raises ``ValueError`` naming ``batch``."""
    return 1 if batch is None else check_count("batch", batch)


def carry(prev: FilterState, new: FilterState, update: bool = False) -> FilterState:
    """``new`` with what ``prev`` had met: ``bounded`` stays False once False and the event
    bits accumulate (a filter's step may build its state afresh); after an update, a
    measurement is never inconsistent against an unbounded set (``consistent |= ~bounded``)."""
    b = new.bounded
    if prev.bounded is not None and b is not prev.bounded:  # (b & b is b)
        b = prev.bounded if b is None else prev.bounded & b
    ev = prev.extras.get("events")
    extras = new.extras
    if ev is not None:
        now = extras.get("events")
        if now is not ev:
            extras = {**extras, "events": ev if now is None else ev | now}
    consistent = new.consistent
    if update and b is not None:
        consistent = b <= consistent  # consistent | ~b, one op on bools
    return FilterState(new.set, consistent, extras, b)


def with_events(state: FilterState) -> FilterState:
    """``state`` with ``extras["events"]`` (zeros ``[B]`` int64) when it has none, so that
    every state of a run has the same structure (one compiled graph)."""
    if "events" in state.extras:
        return state
    ev = torch.zeros(state.consistent.shape, dtype=torch.int64, device=state.consistent.device)
    return state.replace(extras={**state.extras, "events": ev})


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


def pad_and_stack(sets: list[ConvexSet]) -> ConvexSet:
    """Stack along a new dim 1; zonotopes with differing generator counts are zero-padded."""
    return stack(align(sets), dim=1)
