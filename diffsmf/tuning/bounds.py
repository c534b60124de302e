"""Tuned noise bounds as a file that ``diffsmf filter --bounds`` and ``System`` accept.

    write_bounds("run/bounds.json", filt, safety=1.25)          # after tune(...)
    diffsmf filter --model m.py:make_system --data log.csv --outputs y --bounds run/bounds.json
    system = ds.System(f, h, X0, **ds.tuning.bound_sets("run/bounds.json"))

The file holds, per noise (``process_noise [n]``, ``measurement_noise [m]``), the centre of
the system's noise box and the half-widths to use: the tuned ones times ``safety``. Tuned
bounds are the smallest the data do not refute, not a proof (they can lie below the true
ones), so the file keeps the factor it applied and the tuned values beside it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.filters.base import NOISE_HALF_WIDTHS
from diffsmf.sets.interval import Interval

__all__ = ["FORMAT", "NOISES", "bound_sets", "consistent_scale", "read_bounds", "write_bounds"]

#: the ``format`` entry of a bounds file
FORMAT = "diffsmf-bounds-1"
#: the noises a bounds file holds
NOISES = ("process_noise", "measurement_noise")


def write_bounds(
    path: str | Path, filt: nn.Module, safety: float = 1.0, initial: dict | None = None,
    **record: Any,
) -> dict[str, Any]:
    """Write the noise bounds of ``filt`` (its half-widths times ``safety``) to ``path``
    (JSON) and return what was written.

    Args:
        path: the file to write.
        filt: a filter with ``process_half_widths [n]`` and ``measurement_half_widths [m]``
            and the noise centres (``*_noise_center``), e.g. the filter `tune` returned.
        safety: factor >= 1 on the tuned half-widths (your engineering margin).
        initial: optional half-widths before tuning, kept in the file for the record.
        record: more entries for the record (JSON values), e.g. ``consistency_scale``.
    """
    if isinstance(safety, bool) or not isinstance(safety, (int, float)) or not (
        math.isfinite(safety) and safety >= 1
    ):
        raise ValueError(f"safety: must be a number >= 1, got {safety!r}")
    doc: dict[str, Any] = {"format": FORMAT, "filter": type(filt).__name__,
                           "system": getattr(getattr(filt, "system", None), "name", None),
                           "safety": float(safety), "tuned": {}}
    for name in NOISES:
        half = getattr(filt, NOISE_HALF_WIDTHS[name], None)
        if not isinstance(half, Tensor):
            raise ValueError(f"filt: {type(filt).__name__} has no {name} half-widths to write")
        center = getattr(filt, f"{name}_center", torch.zeros_like(half))
        doc[name] = {"center": center.detach().tolist(),
                     "half_widths": (half.detach() * safety).tolist()}
        doc["tuned"][name] = half.detach().tolist()
    if initial is not None:
        doc["initial"] = {k: list(v) for k, v in initial.items() if k in NOISES}
    doc.update(record)
    doc["options"] = " ".join(
        f"--{k.replace('_', '-')} " + ",".join(f"{v:.10g}" for v in doc[k]["half_widths"])
        for k in NOISES
    )
    Path(path).write_text(json.dumps(doc, indent=2))
    return doc


def read_bounds(path: str | Path, n: int | None = None, m: int | None = None,
                what: str = "path") -> dict[str, Tensor]:
    """Half-widths of a bounds file: ``{"process_noise": [n], "measurement_noise": [m]}``
    (float64), checked against the state and output dimensions when given.

    Raises:
        ValueError: starting with ``what`` (the argument's name; ``diffsmf filter`` passes
            ``--bounds``), naming the file and what is wrong.
    """
    doc = _load(path, what)
    out = {}
    for name, dim in zip(NOISES, (n, m)):
        half = torch.tensor(doc[name]["half_widths"], dtype=torch.float64)
        if dim is not None and half.shape != (dim,):
            raise ValueError(f"{what}: {str(path)!r} has {name} of {half.numel()} value(s), "
                             f"the model needs {dim}")
        out[name] = half
    return out


def bound_sets(path: str | Path, what: str = "path") -> dict[str, Interval]:
    """The bounds of a file as the sets a ``System`` takes: ``{"process_noise":
    Interval [n], "measurement_noise": Interval [m]}`` (centre +- half-widths), e.g.
    ``ds.System(f, h, X0, **bound_sets(path))``; errors start with ``what``, as in
    `read_bounds`."""
    doc = _load(path, what)
    sets = {}
    for name in NOISES:
        c = torch.tensor(doc[name]["center"], dtype=torch.float64)
        r = torch.tensor(doc[name]["half_widths"], dtype=torch.float64)
        sets[name] = Interval(c - r, c + r)
    return sets


def consistent_scale(filt: nn.Module, y: Tensor, u: Tensor | None = None, rtol: float = 0.01,
                     max_doublings: int = 12) -> float:
    """Scale ``filt``'s noise half-widths (both, by one factor ``c >= 1``, in place) up to
    the smallest ``c`` (to ``rtol``) at which every measurement of ``y [B, T, m]`` (inputs
    ``u [B, T, p]``) is consistent with the predicted set; returns ``c`` (1 when they
    already are).

    Tuning by gradient descent can stop a little below the smallest bounds the data do not
    refute (the consistency loss trades a few slightly inconsistent steps for volume); after
    this, no logged measurement refutes the bounds. That is still not a proof that they
    hold: keep a safety factor (`write_bounds`).

    Raises:
        ValueError: naming ``y`` when no factor up to ``2 ** max_doublings`` makes every
            measurement consistent (the model, not the bounds, disagrees with the data).
    """
    base = {k: getattr(filt, k).detach().clone() for k in NOISES}

    def ok(c: float) -> bool:
        for k in NOISES:
            setattr(filt, k, base[k] * c)
        with torch.no_grad():
            res = filt(y, u=u)
        flagged = res.consistent if res.bounded is None else res.consistent | ~res.bounded
        return bool(flagged.all())

    lo, hi = 1.0, 1.0
    if ok(1.0):
        return 1.0
    for _ in range(max_doublings):
        lo, hi = hi, hi * 2
        if ok(hi):
            break
    else:
        for k in NOISES:
            setattr(filt, k, base[k])
        raise ValueError(f"y: measurements stay inconsistent with the model even with the "
                         f"noise bounds {2 ** max_doublings}x the tuned ones: check the model, "
                         "the columns and the units of the data")
    while hi / lo > 1 + rtol:
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    for k in NOISES:
        setattr(filt, k, base[k] * hi)
    return hi


def _load(path: str | Path, what: str) -> dict[str, Any]:
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{what}: no such file {str(p)!r} (diffsmf tune writes bounds.json)")
    try:
        doc = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{what}: {str(p)!r} is not a JSON file ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"{what}: {str(p)!r} is not a diffsmf bounds file (format "
                         f"{FORMAT!r}, written by diffsmf tune)")
    for name in NOISES:
        entry = doc.get(name)
        ok = isinstance(entry, dict) and all(
            isinstance(entry.get(k), list) and entry[k] and all(
                isinstance(v, (int, float)) and math.isfinite(v) for v in entry[k])
            for k in ("center", "half_widths"))
        if not ok or len(entry["center"]) != len(entry["half_widths"]) or min(
                entry["half_widths"]) <= 0:
            raise ValueError(f"{what}: {str(p)!r}: {name} must hold 'center' and "
                             "'half_widths', lists of the same length of finite numbers "
                             "(half-widths > 0)")
    return doc
