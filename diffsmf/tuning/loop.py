"""The tuning loop: gradient descent on set volume with held-out validation.

    report, filt = tune(filt, traj, epochs=200, batch_size=64, validation=0.25, seed=0)

Runs data-parallel when ``torch.distributed`` is initialised (see `diffsmf.tuning.ddp`).
"""

from __future__ import annotations

import copy
import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.filters.base import NOISE_HALF_WIDTHS, SetFilter, check_filter
from diffsmf.systems import Trajectory
from diffsmf.tuning import ddp
from diffsmf.tuning.losses import LossWeights, filter_with_predictions, total_loss
from diffsmf.tuning.windows import WindowCache, windowed_loss
from diffsmf.utils import is_int, progress_bar

__all__ = [
    "Data", "TuneReport", "as_data", "evaluate", "resolve_params", "simulate_finite", "tune",
]

DEFAULT_PARAMS = ("process_noise", "measurement_noise", "stirling_step")
# Hyperparameters of the diffsmf filters that are not tuned by default; like the default trio,
# a name here that a filter lacks (EKF, CombinedFilter: no remainder margin; only CDSMF and
# ESMF have a Minkowski-weight scale) is skipped.
OPTIONAL_PARAMS = ("remainder_margin", "minkowski_scale")
KNOWN_PARAMS = DEFAULT_PARAMS + OPTIONAL_PARAMS
#: The filter's names of the noise half-widths -> their tuning (stored) names; both are
#: accepted (`diffsmf.filters.base.NOISE_HALF_WIDTHS`).
_STORED = {v: k for k, v in NOISE_HALF_WIDTHS.items()}
LOSS_MODES = ("auto", "consistency", "containment", "both")


@dataclass
class Data:
    """Trajectories: ``y [N, T, m]``, optional true states ``x [N, T+1, n]``, inputs ``u``."""

    y: Tensor
    x: Tensor | None = None
    u: Tensor | None = None

    def __len__(self) -> int:
        return self.y.shape[0]

    def take(self, idx: Tensor) -> Data:
        return Data(
            self.y[idx],
            None if self.x is None else self.x[idx],
            None if self.u is None else self.u[idx],
        )


@dataclass
class TuneReport:
    """What `tune` did.

    history: one dict per epoch (``epoch``, ``loss``, loss terms, ``val_*`` when validated,
        and each tuned value after the epoch as ``name[i]``, e.g. ``process_noise[0]``);
    initial / final: hyperparameter values before and after (final = best validation epoch);
    validation_before / validation_after: `evaluate` metrics on the validation set;
    nonfinite_steps: optimiser steps skipped because a gradient was not finite.
    """

    params: list[str]
    skipped_params: list[str]
    initial: dict[str, list[float]]
    final: dict[str, list[float]]
    history: list[dict[str, float]] = field(default_factory=list)
    best_epoch: int = 0
    stopped_early: bool = False
    validation_before: dict[str, float] | None = None
    validation_after: dict[str, float] | None = None
    nonfinite_steps: int = 0
    seconds: float = 0.0
    loss_mode: str = "auto"
    weights: dict[str, float] = field(default_factory=dict)
    world_size: int = 1
    tied: list[list[str]] = field(default_factory=list)
    window: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# ---------------------------------------------------------------------------- helpers
def as_data(trajectories: Any) -> Data:
    """Accept a `diffsmf.Trajectory` (or anything with ``y``/``x``/``u``) or a tensor y."""
    if isinstance(trajectories, Data):
        return trajectories
    if isinstance(trajectories, Tensor):
        return Data(y=trajectories)
    y = getattr(trajectories, "y", None)
    if not isinstance(y, Tensor) or y.dim() != 3:
        raise ValueError("trajectories: expected a Trajectory with y [N, T, m] (or a tensor y)")
    x = getattr(trajectories, "x", None)
    u = getattr(trajectories, "u", None)
    if x is not None and x.shape[:2] != (y.shape[0], y.shape[1] + 1):
        raise ValueError(f"trajectories: x must be [N, T+1, n], got {tuple(x.shape)}")
    return Data(y=y, x=x, u=u)


def resolve_params(
    filt: nn.Module, names: Sequence[str] | str
) -> tuple[dict[str, nn.Parameter], list[str]]:
    """Map hyperparameter names to the ``nn.Parameter`` to optimise.

    ``name`` selects ``raw_name`` (softplus-positive hyperparameters) or the parameter ``name``
    itself; ``"all"`` selects every parameter. Names of `KNOWN_PARAMS` (the default
    trio, ``remainder_margin`` and ``minkowski_scale``) that the filter lacks are skipped
    (returned second); any other unknown name raises ``ValueError``. A softplus-positive
    hyperparameter whose scale is 0 everywhere (e.g. the default ``remainder_margin=0``)
    cannot move: a warning says so.
    """
    named = dict(filt.named_parameters())
    if names == "all":
        return {k[4:] if k.startswith("raw_") else k: p for k, p in named.items()}, []
    if isinstance(names, str):
        names = [names]
    out, skipped = {}, []
    for n in names:
        attr = _STORED.get(n, n)
        if f"raw_{attr}" in named:
            out[n] = named[f"raw_{attr}"]
            scale = getattr(filt, f"{attr}_scale", None)
            if isinstance(scale, Tensor) and not bool((scale != 0).any()):
                warnings.warn(
                    f"params: {n!r} is 0 (scale * softplus(raw) with scale 0) and stays 0 "
                    f"while tuning; start it from a positive value to tune it",
                    stacklevel=3,
                )
        elif n in named:
            out[n] = named[n]
        elif n in KNOWN_PARAMS:
            skipped.append(n)
        else:
            raise ValueError(f"params: filter {type(filt).__name__} has no parameter {n!r}")
    if not out:
        raise ValueError(f"params: none of {list(names)} is a parameter of this filter")
    return out, skipped


def hyperparameter_values(filt: nn.Module, names: Sequence[str]) -> dict[str, list[float]]:
    """Constrained values (``filter.name``, e.g. the softplus-positive bound) as lists."""
    named = dict(filt.named_parameters())
    out = {}
    for n in names:
        v = getattr(filt, NOISE_HALF_WIDTHS.get(n, n), None) if "." not in n else None
        if not isinstance(v, Tensor):
            v = named[n]
        out[n] = torch.as_tensor(v).detach().reshape(-1).tolist()
    return out


def _loss_flags(mode: str, has_x: bool) -> tuple[bool, bool]:
    if mode not in LOSS_MODES:
        raise ValueError(f"loss: expected one of {LOSS_MODES}, got {mode!r}")
    if mode == "auto":
        mode = "containment" if has_x else "consistency"
    cont = mode in ("containment", "both")
    if cont and not has_x:
        raise ValueError(f"loss: {mode!r} needs ground-truth states (trajectories.x)")
    return cont, mode in ("consistency", "both")


def _make_optimizer(name: str, params: list[nn.Parameter], lr: float) -> torch.optim.Optimizer:
    """Adam/AdamW with ``betas=(0.9, 0.99)``: the consistency hinge gives huge gradients while
    bounds are far too small and tiny ones near the boundary; the default beta2 = 0.999
    remembers the huge ones for ~1000 steps and stalls the approach (toy test)."""
    if name in ("adam", "adamw"):
        cls = torch.optim.Adam if name == "adam" else torch.optim.AdamW
        return cls(params, lr=lr, betas=(0.9, 0.99))
    if name == "sgd":
        return torch.optim.SGD(params, lr=lr)
    raise ValueError(f"optimizer: expected one of ['adam', 'adamw', 'sgd'], got {name!r}")


@torch.no_grad()
def evaluate(
    filt: SetFilter,
    data: Any,
    weights: LossWeights | None = None,
    *,
    loss: str = "auto",
    chunk: int = 256,
    atol: float = 1e-9,
) -> dict[str, float]:
    """Metrics of ``filt`` on trajectories (sharded and summed over processes under DDP).

    No gradients, so the filter runs unguarded (its own consistency flags and sets).

    Returns ``loss``, ``log_volume`` (mean log-volume, steps >= skip), ``mean_volume``,
    ``consistent_frac`` (fraction of steps the filter flagged consistent), ``max_excess``
    (largest normalised consistency excess), and with true states ``violations`` (number of
    (trajectory, step) pairs outside the set, ``contains`` with ``atol``) and
    ``violating_trajectories``.
    """
    check_filter("filt", filt)
    data = as_data(data)
    weights = weights or LossWeights()
    cont, cons = _loss_flags(loss, data.x is not None)
    idx = ddp.shard(torch.arange(len(data)))
    dev = data.y.device
    acc = torch.zeros(7, dtype=torch.float64, device=dev)
    max_excess = torch.full((), -math.inf, dtype=torch.float64, device=dev)
    for s in range(0, len(idx), chunk):
        part = data.take(idx[s : s + chunk])
        out = filter_with_predictions(filt, part.y, part.u, guard_empty=False)
        lval, terms = total_loss(out, part.x, weights, use_containment=cont, use_consistency=cons)
        b = part.y.shape[0]
        vol = out.result.volume[:, weights.skip :]
        acc[0] += lval * b
        acc[1] += terms["log_volume"] * b
        acc[2] += vol.mean() * b
        acc[3] += out.result.consistent[:, 1:].double().mean() * b
        acc[4] += b
        if part.x is not None:
            inside = out.result.sets.contains(part.x, atol=atol)
            acc[5] += (~inside).sum()
            acc[6] += (~inside).any(-1).sum()
        max_excess = torch.maximum(max_excess, out.excess.max())
    acc = ddp.all_reduce_sum(acc)
    if ddp.is_distributed():
        import torch.distributed as dist

        dist.all_reduce(max_excess, op=dist.ReduceOp.MAX)
    n = acc[4].clamp_min(1)
    res = {
        "loss": float(acc[0] / n),
        "log_volume": float(acc[1] / n),
        "mean_volume": float(acc[2] / n),
        "consistent_frac": float(acc[3] / n),
        "max_excess": float(max_excess),
        "trajectories": int(acc[4]),
    }
    if data.x is not None:
        res["violations"] = int(acc[5])
        res["violating_trajectories"] = int(acc[6])
    return res


def _tie_groups(
    tie: Sequence[Sequence[str]] | str | None, chosen: dict[str, nn.Parameter]
) -> dict[tuple[str, ...], list[nn.Parameter]]:
    """Validate ``tie`` and make each group's raw values equal (their mean) to start."""
    if tie is None:
        return {}
    if tie == "noise":
        tie = [[n for n in (*NOISE_HALF_WIDTHS, *NOISE_HALF_WIDTHS.values()) if n in chosen]]
    if isinstance(tie, str):
        raise ValueError(f"tie: expected 'noise', None or groups of names, got {tie!r}")
    out = {}
    for g in tie:
        missing = [n for n in g if n not in chosen]
        if missing:
            raise ValueError(f"tie: {missing} are not tuned parameters ({list(chosen)})")
        ps = [chosen[n] for n in g]
        with torch.no_grad():
            mean = torch.cat([p.reshape(-1) for p in ps]).mean()
            for p in ps:
                p.fill_(mean)
        out[tuple(g)] = ps
    return out


def _tie_grads(groups: dict[tuple[str, ...], list[nn.Parameter]]) -> None:
    """Gradient of a shared factor: every element of a group gets the group's summed grad.

    With equal starting values and equal gradients, Adam/SGD keep the elements equal.
    """
    for ps in groups.values():
        grads = [p.grad for p in ps if p.grad is not None]
        if not grads:
            continue
        total = sum(g.sum() for g in grads)
        for p in ps:
            p.grad = total.expand_as(p).clone()


def _nonempty(label: str, data: Data) -> Data:
    """``data`` with at least one trajectory of at least one step (else a ValueError)."""
    if data.y.dim() != 3 or data.y.shape[0] == 0 or data.y.shape[1] == 0:
        raise ValueError(f"{label}: no data (y [N, T, m] = {list(data.y.shape)}; need N, T >= 1)")
    return data


def _split(data: Data, validation: Any, seed: int) -> tuple[Data, Data | None]:
    if validation is None:
        return data, None
    if isinstance(validation, float):
        if not 0.0 < validation < 1.0:
            raise ValueError(f"validation: a fraction must be in (0, 1), got {validation}")
        g = torch.Generator().manual_seed(seed)
        perm = torch.randperm(len(data), generator=g).to(data.y.device)
        nv = max(1, int(round(validation * len(data))))
        if nv >= len(data):
            raise ValueError("validation: leaves no training trajectories")
        return data.take(perm[nv:]), data.take(perm[:nv])
    return data, as_data(validation)


def _save(path: Path, payload: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


# ---------------------------------------------------------------------------- the loop
def tune(
    filt: SetFilter,
    trajectories: Any,
    *,
    params: Sequence[str] | str = DEFAULT_PARAMS,
    optimizer: str = "adam",
    lr: float = 0.05,
    epochs: int = 100,
    batch_size: int = 64,
    validation: Any = None,
    loss: str = "auto",
    weights: LossWeights | None = None,
    val_every: int = 5,
    patience: int = 10,
    checkpoint_dir: str | Path | None = None,
    checkpoint_every: int = 20,
    resume: str | Path | None = None,
    seed: int = 0,
    progress: Any = False,
    tie: Sequence[Sequence[str]] | str | None = None,
    window: int | None = None,
    compile: bool = False,
) -> tuple[TuneReport, SetFilter]:
    """Tune ``filt``'s hyperparameters in place; returns ``(report, filt)``.

    Args:
        trajectories: `diffsmf.Trajectory` (``x`` may be ``None``: no ground truth).
        params: hyperparameter names (``raw_<name>`` or parameter ``<name>``) or ``"all"``;
            besides the default trio the filters have ``remainder_margin`` (HSNSMF, MSZM,
            CDSMF, ESMF; start it from a positive value, a 0 margin stays 0) and
            ``minkowski_scale`` (CDSMF, ESMF: factor on the rule's Minkowski weight, 1 = the
            rule; any value keeps the guarantee). Known names a filter lacks are skipped.
        validation: ``None``, a fraction of ``trajectories`` held out, or a Trajectory.
        loss: ``"auto"`` (containment if ``x`` is given, else consistency), ``"consistency"``
            (no ground truth), ``"containment"`` or ``"both"``; always plus log-volume.
        val_every, patience: validate every ``val_every`` epochs; stop after ``patience``
            validations without improvement; the best validated parameters are restored at
            the end (without validation: those with the best training loss, at the start of
            that epoch, when the loss was computed).
        checkpoint_dir: write ``last.pt`` every ``checkpoint_every`` epochs and ``best.pt``.
        resume: a ``last.pt`` to continue from.
        seed: seeds the mini-batch order (deterministic; identical across DDP processes).
        tie: groups of hyperparameters that share ONE multiplicative factor, e.g.
            ``[("process_noise", "measurement_noise")]`` or the shorthand ``"noise"``: only the
            overall scale of the bounds is learned. Without ground truth the split between
            process and measurement noise is not identifiable (docs/training.md): use the
            consistency loss with ``tie="noise"``.
        window: ``None`` (default: back-propagate through the whole horizon) or ``L``:
            truncated back-propagation over windows of ``L`` steps run side by side, with
            carried states (`diffsmf.tuning.windows`; about ``T / L`` times faster on a CPU;
            validation and the returned filter are exact). ``LossWeights.skip`` applies per
            window.
        progress: ``True`` for a progress bar over the epochs (tqdm), or a bar factory
            (`diffsmf.utils.progress_bar`); off by default (``diffsmf tune`` shows it).
        compile: tune through the compiled step (``filt.compile()``, in place; a filter
            compiled before is used as it is): the same sets and gradients up to rounding,
            a one-off compile per batch size and grad mode, then 5-8x faster per epoch
            (docs/training.md). CZSMF tunes eagerly.

    Under ``torch.distributed`` each global mini-batch is sharded over the processes and the
    gradients are summed, so K processes follow the single-process trajectory.
    """
    check_filter("filt", filt)
    _check_counts(epochs=epochs, batch_size=batch_size, val_every=val_every, patience=patience)
    if not isinstance(compile, bool):
        raise ValueError(f"compile: expected True or False, got {compile!r}")
    t0 = time.perf_counter()
    if compile and not filt.compiled:
        filt.compile(progress=bool(progress) and ddp.rank() == 0)
    weights = weights or LossWeights()
    data, val, cont, cons = _tuning_data(trajectories, validation, seed, loss)
    chosen, skipped = resolve_params(filt, params)
    groups = _tie_groups(tie, chosen)
    names, tuned = list(chosen), list(chosen.values())
    restore = _train_only(filt, tuned)
    ddp.broadcast_parameters(filt)
    run = _Run(filt, data, weights, cont, cons, tuned, groups,
               _make_optimizer(optimizer, tuned, lr), batch_size, seed,
               WindowCache(filt, data, window) if window is not None else None)
    report = TuneReport(
        params=names, skipped_params=skipped, initial=hyperparameter_values(filt, names),
        final={}, loss_mode=loss, weights=weights.to_dict(), world_size=ddp.world_size(),
        tied=[list(g) for g in groups], window=window,
    )
    start_epoch, best = run.resume(resume, report)
    if val is not None:
        report.validation_before = evaluate(filt, val, weights, loss=loss)
    bar = progress_bar(progress if ddp.rank() == 0 else False, epochs - start_epoch, "tune",
                       "epoch")
    best = run.train(report, range(start_epoch, epochs), best, val, loss, val_every, patience,
                     checkpoint_dir, checkpoint_every, bar)
    if best[2] > 0:
        filt.load_state_dict(best[1])
    report.best_epoch = best[2]
    restore()
    report.final = hyperparameter_values(filt, names)
    if val is not None:
        report.validation_after = evaluate(filt, val, weights, loss=loss)
    report.seconds = time.perf_counter() - t0
    return report, filt


def _tuning_data(trajectories: Any, validation: Any, seed: int, loss: str
                 ) -> tuple[Any, Any, bool, bool]:
    """The training and validation data of `tune` and which loss terms it uses."""
    data, val = _split(_nonempty("trajectories", as_data(trajectories)), validation, seed)
    if val is not None:
        _nonempty("validation", val)
    cont, cons = _loss_flags(loss, data.x is not None)
    return data, val, cont, cons


def _check_counts(**counts: Any) -> None:
    """Every count a positive integer (the error names it)."""
    for label, v in counts.items():
        if not is_int(v) or v < 1:
            raise ValueError(f"{label}: must be a positive integer, got {v!r}")


def _train_only(filt: nn.Module, tuned: list[Tensor]) -> Any:
    """Gradients for the ``tuned`` parameters of ``filt`` only -> a function that restores the
    others' ``requires_grad`` flags."""
    frozen = [p for p in filt.parameters() if all(p is not q for q in tuned)]
    saved = [p.requires_grad for p in frozen]
    for p in frozen:
        p.requires_grad_(False)
    for p in tuned:
        p.requires_grad_(True)

    def restore() -> None:
        for p, f in zip(frozen, saved):
            p.requires_grad_(f)

    return restore


def _advance(bar: Any, loss: float, best: float) -> None:
    """One epoch on the progress bar (if any), with the epoch's loss and the best so far."""
    if bar is None:
        return
    if hasattr(bar, "set_postfix"):
        bar.set_postfix(loss=f"{loss:.4g}", best=f"{best:.4g}", refresh=False)
    bar.update(1)


@dataclass
class _Run:
    """What one `tune` run trains with: the filter, the data, the loss, the tuned parameters and
    their tie groups, the optimiser and the window cache (``None``: whole horizons)."""

    filt: SetFilter
    data: Any
    weights: LossWeights
    cont: bool
    cons: bool
    tuned: list[Tensor]
    groups: list[Any]
    opt: torch.optim.Optimizer
    batch_size: int
    seed: int
    cache: WindowCache | None

    @property
    def keys(self) -> list[str]:
        return ["loss", "log_volume"] + ["containment"] * self.cont + ["consistency"] * self.cons

    def epoch(self, epoch: int) -> tuple[dict[str, float], int]:
        """One pass over the data in seeded mini-batches -> (the epoch's mean loss terms, the
        number of optimiser steps skipped for a non-finite gradient)."""
        n = len(self.data)
        g = torch.Generator().manual_seed(self.seed * 100_003 + epoch)
        perm = torch.randperm(n, generator=g).to(self.data.y.device)
        sums: dict[str, float] = {}
        skipped = 0
        for s in range(0, n, self.batch_size):
            glob = perm[s : s + self.batch_size]
            stats = self._batch(glob)
            w = len(glob) / n
            for k, v in zip(self.keys, stats.tolist()):
                sums[k] = sums.get(k, 0.0) + v * w
            if all(torch.isfinite(p.grad).all() for p in self.tuned if p.grad is not None):
                self.opt.step()
            else:
                skipped += 1
        return sums, skipped

    def _batch(self, glob: Tensor) -> Tensor:
        """Gradients of one global mini-batch (sharded over the processes, summed) -> its
        loss terms ``[len(keys)]``, summed over the processes."""
        local = ddp.shard(glob)
        self.opt.zero_grad(set_to_none=True)
        keys = self.keys
        stats = torch.zeros(len(keys), dtype=torch.float64)
        if len(local):
            frac = len(local) / len(glob)  # local mean -> share of the global mean
            part = self.data.take(local)
            if self.cache is not None:
                lval, terms = windowed_loss(
                    self.filt, part, local, self.cache, self.weights,
                    use_containment=self.cont, use_consistency=self.cons,
                )
            else:
                out = filter_with_predictions(self.filt, part.y, part.u)
                lval, terms = total_loss(
                    out, part.x, self.weights, use_containment=self.cont,
                    use_consistency=self.cons,
                )
            (lval * frac).backward()
            stats = torch.stack([lval.detach()] + [terms[k] for k in keys[1:]]).cpu() * frac
        ddp.all_reduce_grads(self.tuned)
        if self.cache is not None:
            self.cache.sync(glob)  # every process keeps every trajectory's window states
        _tie_grads(self.groups)
        return ddp.all_reduce_sum(stats)

    def resume(self, path: str | Path | None, report: TuneReport) -> tuple[int, tuple]:
        """Continue from the checkpoint ``path`` (``None``: start afresh) -> (the first epoch,
        ``best``: the best score, its state dict and its epoch)."""
        if path is None:
            return 0, (math.inf, copy.deepcopy(self.filt.state_dict()), 0)
        ck = torch.load(path, weights_only=False)
        self.filt.load_state_dict(ck["filter"])
        self.opt.load_state_dict(ck["optimizer"])
        report.history = ck["history"]
        return ck["epoch"], (ck["best_loss"], ck["best_state"], ck["best_epoch"])

    def train(self, report: TuneReport, epochs: range, best: tuple, val: Any, loss: str,
              val_every: int, patience: int, checkpoint_dir: str | Path | None,
              checkpoint_every: int, bar: Any) -> tuple:
        """The epochs of `tune`: train, score (validation loss every ``val_every`` epochs, or
        the training loss), checkpoint, stop after ``patience`` validations without
        improvement -> ``best``. Closes ``bar`` (if any) at the end."""
        is_main = ddp.rank() == 0
        bad_vals = 0
        for epoch in epochs:
            # without validation an epoch is scored by its training loss, which was computed
            # with the values at the epoch's start: those are the ones to keep if it is best
            start = copy.deepcopy(self.filt.state_dict()) if val is None else None
            sums, nonfinite = self.epoch(epoch)
            report.nonfinite_steps += nonfinite
            row: dict[str, float] = {"epoch": epoch + 1, **sums}
            for name, vals in hyperparameter_values(self.filt, report.params).items():
                row.update({f"{name}[{i}]": v for i, v in enumerate(vals)})  # for the figures
            score = sums["loss"] if val is None else None
            if val is not None and ((epoch + 1) % val_every == 0 or epoch + 1 == epochs.stop):
                m = evaluate(self.filt, val, self.weights, loss=loss)
                row.update({f"val_{k}": v for k, v in m.items()})
                score = m["loss"]
            if score is not None and score < best[0] - 1e-12:
                best = (score, start if start is not None else
                        copy.deepcopy(self.filt.state_dict()), epoch + 1)
                bad_vals = 0
                if checkpoint_dir is not None and is_main:
                    _save(Path(checkpoint_dir) / "best.pt", {"filter": best[1], "epoch": epoch + 1})
            elif score is not None:
                bad_vals += 1
            report.history.append(row)
            _advance(bar, sums["loss"], best[0])
            if checkpoint_dir is not None and is_main and (epoch + 1) % checkpoint_every == 0:
                self.save_last(Path(checkpoint_dir) / "last.pt", epoch + 1, report.history, best)
            if val is not None and bad_vals >= patience:
                report.stopped_early = True
                break
        if bar is not None:
            bar.close()
        return best

    def save_last(self, path: Path, epoch: int, history: list, best: tuple) -> None:
        """The checkpoint to resume from (``resume=path``)."""
        _save(path, {
            "filter": self.filt.state_dict(), "optimizer": self.opt.state_dict(),
            "epoch": epoch, "history": history, "best_loss": best[0], "best_state": best[1],
            "best_epoch": best[2],
        })


def simulate_finite(system: Any, steps: int, batch: int, seed: int, noise: str) -> Any:
    """``system.simulate`` keeping only trajectories that stay finite (first ``batch`` of them).

    Some built-in models leave their domain from parts of the initial set (``spring_damper``
    with vertex noise diverges from about 25 % of the corners of X0: a softening spring); a
    filter cannot be tuned or audited on inf. Draws 2x, 4x, ... until enough are finite.
    """
    draw = batch
    for _ in range(6):
        tr = system.simulate(steps, batch=draw, seed=seed, noise=noise)
        ok = torch.isfinite(tr.x).all(-1).all(-1) & torch.isfinite(tr.y).all(-1).all(-1)
        if int(ok.sum()) >= batch:
            idx = ok.nonzero().squeeze(-1)[:batch]
            return Trajectory(
                x=tr.x[idx],
                y=tr.y[idx],
                u=None if tr.u is None else tr.u[idx],
                theta=None if tr.theta is None else tr.theta[idx],
            )
        draw *= 2
    raise ValueError(f"system: fewer than {batch} finite trajectories out of {draw}")
