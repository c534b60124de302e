"""Checks of a user's model run where the ``System`` is built: the guarantee engine on ``f``
and ``h`` (`trial_enclosure`) and fitted models without a certified error
(`uncertified_fit`)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from diffsmf.interval.capture import EngineError, reachable_modules
from diffsmf.interval.engine import enclose
from diffsmf.sets.interval import Interval
from diffsmf.systems.model import Dynamics

__all__ = ["trial_enclosure", "uncertified_fit"]


def trial_enclosure(name: str, model: Callable[[Tensor], Tensor], points: list[Tensor]) -> None:
    """Run the guarantee engine once on ``model`` (``x [1, n] -> [1, k]``) where the filters
    will: its value and Jacobian enclosures at the first point ``[1, n]``, its value at the
    others, and each value against the model itself there. (Every rule refuses what it
    cannot enclose whatever the order, so the Hessians, whose cost grows as n^3, are left to
    the filters.)

    What only shows when the captured program runs (``.detach()``, a cast of the state, an
    op without a rule) and what the capture cannot see (numpy, ``math`` or a tensor rebuilt
    from the state's numbers: the engine records such a part as a constant, and its sets
    would be wrong) are reported now, when the ``System`` is built, naming ``name``.

    Raises:
        ValueError: (an `EngineError` for an unsupported operation) starting with ``name:``.
    """
    for i, x in enumerate(points):
        try:
            enc = enclose(model, Interval(x, x), 1 if i == 0 else 0, name)
        except EngineError as exc:
            msg = str(exc)
            if msg.startswith(f"{name}:"):
                raise
            raise EngineError(f"{name}: {msg}; write that part of {name} with torch operations "
                              "on the state (see the 'Writing models' docs page)") from exc
        try:
            with torch.no_grad():
                value = model(x)
        except Exception as exc:  # the user's function: say which call failed
            raise ValueError(f"{name}: {name}(x) at x = {x.reshape(-1).tolist()}, a point of "
                             f"x0_set, failed ({type(exc).__name__}: {exc})") from exc
        lo, hi = enc.val.lower.detach(), enc.val.upper.detach()
        finite = torch.isfinite(value) & torch.isfinite(lo) & torch.isfinite(hi)
        # the enclosure holds the exact value; the float one may differ by its rounding (a
        # part recorded as a constant from another point differs by far more)
        tol = 1e-7 * (1.0 + value.abs())
        off = finite & ((value < lo - tol) | (value > hi + tol))
        if bool(off.any()):
            raise ValueError(
                f"{name}: at x = {x.reshape(-1).tolist()} it returns "
                f"{value.reshape(-1).tolist()}, but the engine's capture of {name} gives "
                f"{((lo + hi) / 2).reshape(-1).tolist()}: part of {name} is computed outside "
                "torch (numpy, math, or a tensor made from the state's numbers, e.g. "
                "torch.tensor(x.numpy())), which the capture records as a constant; write that "
                "part with torch operations"
            )


def uncertified_fit(f: Callable[..., Tensor]) -> bool:
    """Whether the dynamics ``f`` use a model fitted to samples (a module with
    ``fitted_model = True``, e.g. an SCPLNN) whose certified error was not added: ``f`` is the
    fit, or calls it, and no ``certificate`` marks it (`diffsmf.pwl.as_system` sets one).

    A filter on such a system bounds the fitted model, not the plant it approximates.
    """
    mods = reachable_modules(f.fn if isinstance(f, Dynamics) else f)
    if any(getattr(m, "certificate", None) is not None for m in mods):
        return False
    return any(getattr(m, "fitted_model", False) is True for m in mods)
