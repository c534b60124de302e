"""Training losses for tuning set-membership filters.

Three terms, each a mean over trajectories and time steps so that weights do not depend on the
batch size or horizon:

* `log_volume_loss` -- mean ``log vol(X_{k|k})`` of the posterior sets (the quantity to
  shrink; log so that steps with tiny and large sets count alike).
* `containment_loss` -- hinge on the normalised distance of the true state outside the
  posterior set (needs ground truth ``x``).
* `consistency_loss` -- hinge on the normalised distance of each measurement outside the
  *predicted output set* ``h(X_{k|k-1}) (+) V`` (no ground truth needed): a measurement outside
  it means the noise bounds are too small (the filter then reports ``consistent=False``).
* `prediction_loss` -- the mean squared one-step output prediction error from the filter's
  centres, in measurement-noise units: for learning a model (a network inside ``f``) through
  the filter, `fit_loss`.

`filter_with_predictions` runs a filter through its public online API
(``initial_state``/``predict``/``update``/``collect``) and returns the result together with the
consistency excess of every measurement, so all three losses come from one pass.
"""

from __future__ import annotations

import contextlib
import warnings
import weakref
from dataclasses import asdict, dataclass

import torch
from torch import Tensor
from torch._dynamo.exc import TorchDynamoException

from diffsmf.convex import ConvexSet, where
from diffsmf.filters.base import FilterResult, FilterState, SetFilter
from diffsmf.filters.runtime import compiled_loop
from diffsmf.filters.state import flat_state, state_from_flat
from diffsmf.linearize import jacobian
from diffsmf.sets.constrained_zonotope import ConstrainedZonotope
from diffsmf.utils import tracing

__all__ = [
    "LossWeights",
    "PassOutput",
    "consistency_excess",
    "consistency_loss",
    "containment_loss",
    "filter_with_predictions",
    "fit_loss",
    "log_volume_loss",
    "normalised_outside",
    "prediction_loss",
    "total_loss",
]

_TINY = 1e-300


@dataclass(frozen=True)
class LossWeights:
    """Weights of the tuning loss ``volume * L_vol + containment * L_cont + consistency * L_cons``.

    Defaults (docs/training.md): ``volume=1``; ``containment=1000`` and ``consistency=1000``:
    the hinges are means over all steps, so at equilibrium with the volume gradient only about
    0.1 % of the steps may sit in the penalised band (a weight of 100 let about 1 % of the
    training measurements go inconsistent in the toy test). ``margin=0.1``: a measurement
    less than 0.1 noise units (`consistency_excess`) inside the edge of the predicted
    output set is already penalised, a safety buffer because outer-bounding filters detect
    inconsistency late (their predicted sets are larger than the true feasible sets).
    ``skip`` initial steps are left out of the volume term (the initial set is not tunable).
    ``prediction``: weight of `prediction_loss` in `fit_loss` (learning a model; the tuning
    loop leaves it out).
    """

    volume: float = 1.0
    containment: float = 1000.0
    consistency: float = 1000.0
    margin: float = 0.1
    skip: int = 1
    prediction: float = 1.0

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass
class PassOutput:
    """One filter pass: the result, the consistency excess ``[B, T, m]`` of every y_k and the
    state after the last step (``final``, to continue a pass: windowed tuning)."""

    result: FilterResult
    excess: Tensor
    final: FilterState | None = None


def log_volume_loss(result: FilterResult, skip: int = 1) -> Tensor:
    """Mean of ``log vol(X_{k|k})`` over batch and steps ``k >= skip``: scalar.

    Volumes are clamped at 1e-300 (a degenerate set gives a large negative log, not -inf).
    """
    vol = result.volume[:, skip:]
    return torch.log(vol.clamp_min(_TINY)).mean()


def _directions(s: ConvexSet, x: Tensor, extra: int = 8) -> Tensor:
    """Probe directions ``[D, *batch, n]``: +-axes, ``x - center`` and ``extra`` fixed ones."""
    n = s.dim
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    g = torch.Generator().manual_seed(1234)
    fixed = torch.randn(extra, n, generator=g, dtype=x.dtype).to(x.device)
    fixed = fixed / fixed.norm(dim=-1, keepdim=True)
    base = torch.cat([eye, -eye, fixed], 0)  # [D0, n]
    bshape = torch.broadcast_shapes(s.batch_shape, x.shape[:-1])
    base = base.reshape((base.shape[0],) + (1,) * len(bshape) + (n,)).expand(
        (base.shape[0],) + tuple(bshape) + (n,)
    )
    r = (x - s.center).expand(tuple(bshape) + (n,))
    nr = r.norm(dim=-1, keepdim=True)
    radial = torch.where(nr > 0, r / nr.clamp_min(_TINY), eye[0].expand_as(r))
    return torch.cat([base, radial.unsqueeze(0)], 0)


def normalised_outside(s: ConvexSet, x: Tensor) -> Tensor:
    """Normalised distance of ``x [..., n]`` outside the set ``s``: ``[...]``, 0 inside.

    ``max_d (d.x - h(d)) / (h(d) + h(-d))`` over probe directions d (the coordinate axes,
    the direction from the centre to x and 8 fixed directions), h the support function:
    positive only if x is outside (a separating direction proves it), differentiable in the
    set's fields, and in units of the set's width along d.
    """
    d = _directions(s, x)
    hp = s.support(d)
    hm = s.support(-d)
    width = (hp + hm).clamp_min(1e-12)
    excess = ((d * x).sum(-1) - hp) / width
    return excess.amax(0).clamp_min(0.0)


def containment_loss(result: FilterResult, x: Tensor) -> Tensor:
    """Mean hinge on the normalised distance of the true states ``x [B, T+1, n]`` outside."""
    if x.shape[:-1] != result.volume.shape:
        raise ValueError(
            f"x: expected shape {tuple(result.volume.shape) + (x.shape[-1],)}, got {tuple(x.shape)}"
        )
    return normalised_outside(result.sets, x).mean()


def consistency_excess(filt: SetFilter, predicted: ConvexSet, y: Tensor) -> Tensor:
    """Excess of ``y [B, m]`` outside the predicted output set, in noise units: ``[B, m]``.

    Output set ``h(X_{k|k-1}) (+) V`` to first order: with J the Jacobian of h at the centre
    c, component i is the interval ``h_i(c) + cV_i +- (r_i + rV_i)`` with
    ``r_i = h(J_i) - J_i.c`` (support function; exact for linear h, where a positive excess
    is exactly an empty strip intersection). Excess
    ``(|y_i - h_i(c) - cV_i| - r_i - rV_i) / s_i``: <= 0 consistent, > 0 not, where
    ``s_i = rV_i + |J_i| rW`` is one step of noise seen at the output (the scale that the
    tuned bounds change; normalising by the whole half-width would let the initial set, not
    the noise, set the units). A constrained zonotope is not symmetric about its centre: its
    range ``[-h(-J_i), h(J_i)]`` is taken from both support values.
    """
    c = predicted.center
    h = filt.system.h
    J = jacobian(h, c.detach())  # [B, m, n]; a direction only, so no gradient through it
    Jm = J.movedim(-2, 0)  # [m, B, n]
    Jc = (Jm * c).sum(-1)  # [m, B]
    hi = predicted.support(Jm)
    mid = h(c) + filt.measurement_noise_center
    if isinstance(predicted, ConstrainedZonotope):
        # not symmetric about its centre c: J.x ranges over [-h(-J), h(J)], whose midpoint
        # need not be J.c (the symmetric formula below would cut the range and report a
        # consistent measurement as outside)
        lo = -predicted.support(-Jm)
        r = 0.5 * (hi - lo)
        mid = mid + (0.5 * (hi + lo) - Jc).movedim(0, -1)
    else:
        r = hi - Jc  # [m, B]; the set is symmetric about c
    r = r.movedim(0, -1)  # [B, m]
    rv = filt.measurement_half_widths
    scale = (rv + (J.abs() * filt.process_half_widths).sum(-1)).clamp_min(1e-12)
    return ((y - mid).abs() - r - rv) / scale


def filter_with_predictions(
    filt: SetFilter,
    y: Tensor,
    u: Tensor | None = None,
    *,
    guard_empty: bool = True,
    state: FilterState | None = None,
) -> PassOutput:
    """Run ``filt`` on ``y [B, T, m]`` (``u [B, T, p]``) step by step through its public API.

    Same sets as ``filt(y, u)`` (forward is exactly predict then update), plus the consistency
    excess ``[B, T, m]`` of each measurement against the predicted set.

    ``guard_empty``: a measurement with excess > -1e-9 (outside, or within 1e-9 noise units of
    the edge of, the predicted output set) is not passed to ``update``; that element keeps its
    predicted set and is flagged inconsistent -- the filter contract's own rule for an empty
    intersection, applied a hair earlier (a superset, so still guaranteed). Reason: the strip
    intersections compute their unused non-empty branch on empty input and its backward gives
    0 * inf = NaN gradients (seen in ``Parallelotope.intersect_strip``); the guard keeps the
    gradients finite. With nonlinear h the excess is first order, so the guard is a heuristic.

    ``state``: start from this state (batch ``[B]``) instead of ``filt.initial_state``.
    """
    if y.dim() != 3 or y.shape[-1] != filt.system.m:
        raise ValueError(f"y: expected shape [B, T, {filt.system.m}], got {tuple(y.shape)}")
    B, T, _ = y.shape
    state = filt.initial_state(batch=B) if state is None else state
    if state.set.batch_shape != (B,):
        raise ValueError(f"state: expected batch shape [{B}], got {list(state.set.batch_shape)}")
    states = [state]
    excess = []
    with _compiled_guarded_steps(filt) as run:
        for k in range(T):
            uk = None if u is None else u[:, k]
            out = None
            if run is not None:
                try:
                    out = run(state, uk, y[:, k], guard_empty)
                except TorchDynamoException as err:  # no C++ compiler, a graph break, ...
                    _stop_compiling(filt, err)
                    run = None
            if out is None:
                out = _guarded_step(filt, state, uk, y[:, k], guard_empty)
            state, e = out
            excess.append(e)
            states.append(state)
    return PassOutput(result=filt.collect(states), excess=torch.stack(excess, 1), final=state)


def _guarded_step(
    filt: SetFilter, state: FilterState, u: Tensor | None, yk: Tensor, guard_empty: bool
) -> tuple[FilterState, Tensor]:
    """One step of `filter_with_predictions` -> ``(state, excess [B, m])``.

    Eagerly the guard runs only when some element needs it (one host sync); while tracing
    (`SetFilter.compile`) it always runs, branch-free: for an element that is not
    guarded it selects the unguarded update, so the values are the same bits either way.
    """
    pred = filt.predict(state, u)
    nan = torch.isnan(yk)
    e = consistency_excess(filt, pred.set, torch.nan_to_num(yk))
    excess = torch.where(nan, torch.full_like(e, -1.0), e)
    if not guard_empty:
        return filt.update(pred, yk), excess
    bad = ((e > -1e-9) & ~nan).any(-1)
    if not tracing() and not bool(bad.any()):
        return filt.update(pred, yk), excess
    safe = torch.where(bad.unsqueeze(-1), _output_centre(filt, pred.set), yk)
    new = filt.update(pred, safe)
    guarded = new.replace(set=where(bad, pred.set, new.set), consistent=new.consistent & ~bad)
    return guarded, excess


def _flat_guarded_step(
    filt: SetFilter,
    fields: tuple[Tensor, ...],
    consistent: Tensor,
    bounded: Tensor,
    extras: dict[str, Tensor],
    set_type: type,
    u: Tensor | None,
    y: Tensor,
    guard_empty: bool,
) -> tuple[tuple, Tensor]:
    """`_guarded_step` on flat tensors (what ``filt.compile()`` traces for tuning, through
    `diffsmf.filters.runtime.compiled_loop`) -> ``(flat state, excess)``."""
    state = state_from_flat(fields, consistent, bounded, extras, set_type)
    new, excess = _guarded_step(filt, state, u, y, guard_empty)
    return flat_state(new), excess


_STEP_NAME = "guarded_step"
#: Filters whose compiled tuning step failed, with the compiled function that failed: they
#: tune eagerly until their next ``compile()`` (which makes a new compiled function).
_FAILED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _stop_compiling(filt: SetFilter, err: Exception) -> None:
    """The compiled tuning step failed to compile: warn once and tune this filter eagerly
    (same sets and gradients, only slower) until its next ``compile()``."""
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    warnings.warn(
        f"compile: the tuning step of {type(filt).__name__} could not be compiled ({first}); "
        "tuning eagerly", RuntimeWarning, stacklevel=4,
    )
    _FAILED[filt] = filt.compiled_function(_STEP_NAME, _flat_guarded_step)


def _compiled_guarded_steps(filt: SetFilter) -> contextlib.AbstractContextManager:
    """`compiled_loop` over `_flat_guarded_step`; it yields None (tune eagerly) before
    ``filt.compile()``, after the compiled step failed, and for filters whose guarded set
    would change size (CZSMF's predicted set has more generators than its capped update, so
    the branch-free guard would pad every state)."""
    if tracing() or not getattr(filt, "_constant_set_size", True):
        return contextlib.nullcontext()
    fn = filt.compiled_function(_STEP_NAME, _flat_guarded_step)
    if fn is None or (filt in _FAILED and _FAILED[filt] is fn):
        return contextlib.nullcontext()
    return compiled_loop(filt, _STEP_NAME, _flat_guarded_step)


def _output_centre(filt: SetFilter, predicted: ConvexSet) -> Tensor:
    """``h(c) + cV`` of the predicted set (inside the predicted output set), detached."""
    return (filt.system.h(predicted.center) + filt.measurement_noise_center).detach()


def consistency_loss(excess: Tensor, margin: float = 0.1) -> Tensor:
    """Mean hinge ``relu(excess + margin)`` over ``[B, T, m]`` (see `consistency_excess`)."""
    return torch.relu(excess + margin).mean()


def total_loss(
    out: PassOutput,
    x: Tensor | None,
    weights: LossWeights,
    *,
    use_containment: bool,
    use_consistency: bool,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Weighted sum of the three terms; returns ``(loss, {term: value})`` (values detached)."""
    terms = {"log_volume": log_volume_loss(out.result, weights.skip)}
    loss = weights.volume * terms["log_volume"]
    if use_containment:
        if x is None:
            raise ValueError("x: containment loss needs ground-truth states")
        terms["containment"] = containment_loss(out.result, x)
        loss = loss + weights.containment * terms["containment"]
    if use_consistency:
        terms["consistency"] = consistency_loss(out.excess, weights.margin)
        loss = loss + weights.consistency * terms["consistency"]
    return loss, {k: v.detach() for k, v in terms.items()}


def prediction_loss(filt: SetFilter, result: FilterResult, y: Tensor, u: Tensor | None = None
                    ) -> Tensor:
    """Mean squared one-step output prediction error, in measurement-noise units: scalar.

    ``mean(((y_k - h(f(c_{k-1}, u_{k-1})) - cV) / rV)^2)`` over ``[B, T, m]``, with ``c_{k-1}``
    the centre of the filter's set after ``y_{k-1}`` (``result.center [B, T+1, n]``), the
    nominal parameter, ``cV`` / ``rV`` the measurement-noise centre and half-widths (the
    half-widths without gradient: the term must not widen the bounds to shrink itself), and
    angle outputs wrapped (``System.innovation``). The prediction-error criterion of system
    identification, through the filter's estimates; it pulls a learnable model towards the
    data where every measurement is already consistent.
    """
    system = filt.system
    x_pred = system(result.center[:, :-1], u)  # [B, T, n]
    y_pred = system.h(x_pred) + filt.measurement_noise_center
    e = system.innovation(y, y_pred) / filt.measurement_half_widths.detach().clamp_min(1e-300)
    return (e * e).mean()


def fit_loss(
    filt: SetFilter,
    y: Tensor,
    u: Tensor | None = None,
    x: Tensor | None = None,
    weights: LossWeights | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss for learning a model (e.g. a network inside ``f``) and the bounds jointly
    through a guaranteed filter, from logged measurements ``y [B, T, m]`` (inputs ``u [B,
    T, p]``; true states ``x [B, T+1, n]`` when known): one pass of `filter_with_predictions`,
    then ``volume * L_vol + consistency * L_cons + prediction * L_pred (+ containment *
    L_cont with x)``. Returns ``(loss, {term: value})`` (values detached).

    Tight sets (`log_volume_loss`) that no measurement refutes (`consistency_loss`), from a
    model whose one-step predictions fit the data (`prediction_loss`). Call
    ``loss.backward()`` and step an optimiser over the model's and the filter's parameters.
    The sets bound the learned model: they contain the plant's states only as far as the
    model and the bounds hold, which the data can refute but not prove (docs/training.md).
    """
    weights = weights or LossWeights()
    out = filter_with_predictions(filt, y, u)
    loss, terms = total_loss(out, x, weights, use_containment=x is not None,
                             use_consistency=True)
    if weights.prediction:
        pred = prediction_loss(filt, out.result, y, u)
        terms["prediction"] = pred.detach()
        loss = loss + weights.prediction * pred
    return loss, terms
