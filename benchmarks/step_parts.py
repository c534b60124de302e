"""Where a compiled filter step goes: each part compiled on its own, ms per call.

The parts of one step of HSNSMF or MSZM (Wang et al. 2022), each traced with ``torch.compile`` and
the filters' own Inductor options (``SetFilter.compile``: no SIMD, C++ wrapper), timed on a state
reached after a few eager steps (median of ``--repeats`` calls after two warm-up calls):

* ``hull``: the set's interval hull;
* ``jacobian``: the Stirling slopes at the centre (Wang et al. 2022, eq. 12);
* ``remainder``: the guaranteed prediction remainder over the region the filter uses (HSNSMF
  the parallelotope, MSZM its interval hull; Wang et al. 2022, eq. 14-18);
* ``predict``, ``update``: the filter's two halves (MSZM's include its reduction);
* ``step``: predict + update, what ``filt.compile()`` runs per step.

Parts traced separately do not share buffers, so their sum need not equal ``step``. The
figures in docs/results/speed.md (where the time goes) come from this breakdown. Each part
compiles once (tens of seconds each on a 2-core CPU; an Inductor cache makes later runs fast).

    python benchmarks/step_parts.py --filter mszm --batch 10000 [--system spring_damper]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

from diffsmf import filters, systems
from diffsmf.filters.prediction import prediction_remainder, step_function
from diffsmf.filters.runtime import compile_options
from diffsmf.linearize import stirling_jacobian

FILTERS = ("hsnsmf", "mszm")


def _parts(filt, state, u, y) -> dict[str, Callable[..., tuple]]:
    """Functions of the set's tensor fields -> tensors, one per part (input ``u [B, p]`` or
    None, measurement ``y [B, m]`` of the timed step)."""
    set_type = type(state.set)
    system = filt.system
    fn = step_function(system, u)

    def rebuild(fields: tuple) -> object:
        return state.replace(set=set_type._from_tensors(fields))

    def hull(*fields):
        box = set_type._from_tensors(fields).interval_hull()
        return box.lower, box.upper

    def jacobian(*fields):
        return (stirling_jacobian(fn, set_type._from_tensors(fields).center, filt.stirling_step),)

    def remainder(*fields):
        S = set_type._from_tensors(fields)
        region = S if isinstance(filt, filters.HSNSMF) else S.interval_hull()
        F = stirling_jacobian(fn, S.center, filt.stirling_step)
        E, _ = prediction_remainder(
            system, filt.remainder_fn, fn, region, S.center, F, u, filt.remainder_margin
        )
        return E.lower, E.upper

    def predict(*fields):
        return tuple(filt.predict(rebuild(fields), u).set._tensors())

    def update(*fields):
        return tuple(filt._update(rebuild(fields), y).set._tensors())

    def step(*fields):
        return tuple(filt._eager_step(rebuild(fields), u, y).set._tensors())

    return dict(hull=hull, jacobian=jacobian, remainder=remainder, predict=predict,
                update=update, step=step)


def _time(fn: Callable[..., tuple], args: tuple, repeats: int) -> float:
    """Median ms per call of ``fn`` compiled with the filters' options."""
    cf = torch.compile(fn, fullgraph=True, dynamic=False, options=compile_options())
    cf(*args)
    cf(*args)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cf(*args)
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--filter", choices=FILTERS, default="mszm")
    ap.add_argument("--system", default="spring_damper")
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--parts", nargs="+", default=None, help="subset of the parts")
    args = ap.parse_args()
    if args.batch < 1 or args.repeats < 1 or args.threads < 1:
        ap.error("--batch, --repeats and --threads must be >= 1")
    torch.set_num_threads(args.threads)
    torch.set_default_dtype(torch.float64)
    try:
        system = systems.get(args.system)
    except (KeyError, ValueError) as e:
        ap.error(str(e))
    if system.n != 2:
        ap.error(f"--system: a built-in with 2 states (the Wang et al. 2022 examples), "
                 f"got n = {system.n}")
    filt = filters.by_name(args.filter)(system)
    tr = system.simulate(steps=4, batch=args.batch, seed=0, noise="uniform")
    with torch.no_grad():
        state = filt.initial_state(batch=args.batch)
        for k in range(3):  # MSZM's sets reach their generator count
            state = filt.step(state, None if tr.u is None else tr.u[:, k], tr.y[:, k])
        parts = _parts(filt, state, None if tr.u is None else tr.u[:, 3], tr.y[:, 3])
        names = args.parts or list(parts)
        bad = [p for p in names if p not in parts]
        if bad:
            ap.error(f"--parts: unknown {bad}; choose from {list(parts)}")
        fields = tuple(state.set._tensors())
        print(f"{args.filter.upper()} on {args.system}, B = {args.batch}, "
              f"{args.threads} thread(s), median of {args.repeats}\n")
        print("| part | ms per call |\n|---|---:|")
        for name in names:
            print(f"| {name} | {_time(parts[name], fields, args.repeats):.2f} |", flush=True)


if __name__ == "__main__":
    main()
