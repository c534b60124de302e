"""Windowed tuning: truncated back-propagation through time with carried filter states.

A filter is a recursion, so one tuning pass over ``T`` steps is ``T`` sequential steps whatever
the batch size; on a CPU the cost of a step is dominated by the number of tensor operations,
not by the batch (64 or 256 trajectories cost about the same). ``tune(..., window=L)`` cuts
every trajectory into ``ceil(T / L)`` windows of ``L`` steps and runs *all windows of a
mini-batch side by side* as one batch: ``L`` sequential steps per pass instead of ``T``.

Window ``w > 0`` starts from the filter state reached at its first step in the previous pass
(detached: the gradient is truncated at window boundaries, as in stateful truncated BPTT for
recurrent networks); the states of every trajectory are initialised by one gradient-free pass
and refreshed by each training pass (the end state of window ``w`` becomes the start of window
``w + 1``), so they lag the parameters by one epoch. Window 0 starts from the filter's initial
state as usual. Every step ``k >= 1`` of every trajectory enters the loss exactly once.

What this changes: only the training gradient (an approximation: the influence of a
parameter on the sets through more than ``L`` steps is dropped, and the start states are one
epoch old). The filter itself, and everything evaluated on it (validation, held-out audits),
is the exact full-length recursion; nothing about the guarantee depends on the window.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from diffsmf.convex import ConvexSet, align, cat
from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.tuning import ddp
from diffsmf.tuning.losses import LossWeights, filter_with_predictions, total_loss

__all__ = ["WindowCache", "windowed_loss"]


def _fields(S: ConvexSet) -> tuple[Tensor, ...]:
    return S._tensors()


def _shape_key(st: FilterState) -> tuple:
    """States that can be concatenated along the batch share this key."""
    fields = tuple(tuple(t.shape[1:]) for t in _fields(st.set))
    extras = tuple(sorted((k, tuple(v.shape[1:])) for k, v in st.extras.items()))
    return type(st.set), fields, extras


def cat_states(states: Sequence[FilterState]) -> FilterState:
    """Concatenate states with batch shape ``[B_i]`` into one of ``[sum B_i]``."""
    keys = set(states[0].extras)
    if any(set(s.extras) != keys for s in states):
        raise ValueError("states: extras differ, cannot concatenate")
    return FilterState(
        set=cat([s.set for s in states]),
        consistent=torch.cat([s.consistent for s in states], 0),
        extras={k: torch.cat([s.extras[k] for s in states], 0) for k in keys},
    )


def take_state(st: FilterState, idx: Tensor | slice) -> FilterState:
    """Batch elements ``idx`` of a state with batch shape ``[B]``."""
    return FilterState(
        set=st.set[idx],
        consistent=st.consistent[idx],
        extras={k: v[idx] for k, v in st.extras.items()},
    )


def _detach(st: FilterState) -> FilterState:
    return FilterState(
        set=st.set.detach(),
        consistent=st.consistent.detach(),
        extras={k: v.detach() for k, v in st.extras.items()},
    )


def put_state(st: FilterState, idx: Tensor, new: FilterState) -> FilterState:
    """``st`` with batch elements ``idx`` replaced by ``new`` (detached; out of place)."""
    a, b = align([st.set, new.set])
    fields = [t.index_copy(0, idx, v.detach()) for t, v in zip(_fields(a), _fields(b))]
    return FilterState(
        set=a._rebuild(fields),
        consistent=st.consistent.index_copy(0, idx, new.consistent.detach()),
        extras={k: v.index_copy(0, idx, new.extras[k].detach()) for k, v in st.extras.items()},
    )


class WindowCache:
    """Start states of windows ``1 .. W-1`` for every trajectory (detached).

    Args:
        filt: the filter being tuned.
        data: the training trajectories (``y [N, T, m]``, optional ``u``).
        length: window length ``L >= 1`` in steps.
        chunk: trajectories per gradient-free pass when initialising.
    """

    def __init__(self, filt: SetFilter, data: Any, length: int, chunk: int = 256) -> None:
        if not isinstance(length, int) or isinstance(length, bool) or length < 1:
            raise ValueError(f"window: expected a positive number of steps, got {length!r}")
        T = data.y.shape[1]
        self.length = length
        self.bounds = [(s, min(s + length, T)) for s in range(0, T, length)]
        self.starts: list[FilterState | None] = [None] * len(self.bounds)
        if len(self.bounds) == 1:
            return
        parts: list[list[FilterState]] = [[] for _ in self.bounds]
        with torch.no_grad():
            for c0 in range(0, len(data), chunk):
                y = data.y[c0 : c0 + chunk]
                u = None if data.u is None else data.u[c0 : c0 + chunk]
                state = filt.initial_state(batch=y.shape[0])
                for w, (s, e) in enumerate(self.bounds[:-1]):
                    uw = None if u is None else u[:, s:e]
                    state = filter_with_predictions(filt, y[:, s:e], uw, state=state).final
                    parts[w + 1].append(_detach(state))
        for w in range(1, len(self.bounds)):
            self.starts[w] = cat_states(parts[w])

    def start(self, filt: SetFilter, w: int, idx: Tensor) -> FilterState:
        """Start state of window ``w`` for trajectories ``idx``."""
        if w == 0:
            return filt.initial_state(batch=len(idx))
        st = self.starts[w]
        assert st is not None
        return take_state(st, idx)

    def sync(self, glob: Tensor) -> None:
        """Under ``torch.distributed``: give every process the start states that each one
        stored for its round-robin shard (`diffsmf.tuning.ddp.shard`) of the global
        mini-batch ``glob``, so all processes keep the same cache (a no-op otherwise).

        Each row comes from exactly one process and the others add zeros, so the all-reduced
        sum is exact. Zonotopes are first padded to the largest generator count of any process.
        """
        if not ddp.is_distributed():
            return
        import torch.distributed as dist

        pos = torch.arange(ddp.rank(), len(glob), ddp.world_size(), device=glob.device)
        mine = glob[pos]

        def share(t: Tensor) -> Tensor:
            buf = torch.zeros((len(glob), *t.shape[1:]), dtype=t.dtype, device=t.device)
            buf[pos] = t[mine]
            return t.index_copy(0, glob, ddp.all_reduce_sum(buf))

        for w in range(1, len(self.starts)):
            st = self.starts[w]
            assert st is not None
            S = st.set
            if hasattr(S, "pad_generators"):  # equal generator counts on every process
                m = torch.tensor(float(S.generators.shape[-1]), dtype=torch.float64)
                dist.all_reduce(m, op=dist.ReduceOp.MAX)
                (S,) = align([S], count=int(m))
            cons = share(st.consistent.to(torch.float64)) > 0.5
            self.starts[w] = FilterState(
                set=S._rebuild([share(t) for t in _fields(S)]),
                consistent=cons,
                extras={k: share(v) for k, v in st.extras.items()},
            )

    def store(self, w: int, idx: Tensor, state: FilterState) -> None:
        """Record the state reached at the end of window ``w - 1`` as the start of ``w``."""
        if 0 < w < len(self.bounds):
            cur = self.starts[w]
            assert cur is not None
            self.starts[w] = put_state(cur, idx, state)


def windowed_loss(
    filt: SetFilter,
    part: Any,
    idx: Tensor,
    cache: WindowCache,
    weights: LossWeights,
    *,
    use_containment: bool,
    use_consistency: bool,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Loss of trajectories ``idx`` (data ``part``) with all their windows run side by side.

    Windows whose start states share field shapes (and length) form one batch; the loss is the
    step-weighted mean over the groups, the same weighting as one full-length pass.
    Updates ``cache`` with the end state of every window. -> ``(loss, {term: value})``.
    """
    groups: dict[tuple, list[tuple[int, FilterState]]] = defaultdict(list)
    for w, (s, e) in enumerate(cache.bounds):
        st = cache.start(filt, w, idx)
        groups[(e - s, *_shape_key(st))].append((w, st))
    total_steps = sum(e - s for s, e in cache.bounds)
    loss: Tensor | int = 0
    terms: dict[str, Tensor] = {}
    B = len(idx)
    for members in groups.values():
        ws = [w for w, _ in members]
        state = cat_states([st for _, st in members])
        sl = [slice(*cache.bounds[w]) for w in ws]
        y = torch.cat([part.y[:, s] for s in sl], 0)
        u = None if part.u is None else torch.cat([part.u[:, s] for s in sl], 0)
        x = None
        if part.x is not None:
            x = torch.cat([part.x[:, s.start : s.stop + 1] for s in sl], 0)
        out = filter_with_predictions(filt, y, u, state=state)
        lg, tg = total_loss(
            out, x, weights, use_containment=use_containment, use_consistency=use_consistency
        )
        share = len(ws) * (sl[0].stop - sl[0].start) / total_steps
        loss = loss + lg * share
        for k, v in tg.items():
            terms[k] = terms.get(k, 0) + v * share
        assert out.final is not None
        for j, w in enumerate(ws):
            cache.store(w + 1, idx, take_state(out.final, slice(j * B, (j + 1) * B)))
    assert isinstance(loss, Tensor)
    return loss, terms
