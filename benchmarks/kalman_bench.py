"""Kalman-type filters at batch 1: diffsmf's EKF and CombinedFilter vs filterpy, same run.

One trajectory of ``spring_damper`` (2 states, 1 output). The peer is filterpy's
``ExtendedKalmanFilter`` with the analytic Jacobian of the model (numpy), stepped online
(``predict`` then ``update``); ours run ``forward`` over the horizon, eager and compiled
(``filt.compile()``, the one-off compile time printed separately; and
``filt.compile(steps_per_call=K)``, K steps per compiled call; with ``--python-wrapper`` each
compiled row again with Inductor's Python wrapper instead of the default C++ one), and the
compiled filter
also online, one ``filt.step`` call per measurement (through Dynamo with its guard checks, and
inside ``filt.streaming()``, where the step captured with ``make_fx`` is called without
Dynamo; its one-off capture runs in the untimed warm-up). The CombinedFilter does a
Kalman step plus the outer Minkowski sums of its mean set, so filterpy's EKF step is the
natural lower reference for it. Median of ``--repeats`` timings; filterpy is timed again
right after each timed run of ours (A B A B), and the ratio is the median of the per-pair
ratios (filterpy's own time drifts by 2x within a run on this loaded machine); one torch
thread.

    python benchmarks/kalman_bench.py [--steps 200] [--repeats 9] [--no-compile]
        [--per-call 8] [--python-wrapper] [--filters ekf combined]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np
import torch

from diffsmf import filters, systems

DT, K0, KD, CD = 0.1, 1.5, 3.0, 1.24


def _f(x: np.ndarray) -> np.ndarray:
    x1, x2 = x
    return np.array([x1 + DT * x2, x2 + DT * (-K0 * x1 * (1 - KD * x1**2) - CD * x2)])


def _F(x: np.ndarray) -> np.ndarray:
    return np.array([[1.0, DT], [DT * (-K0 + 3 * K0 * KD * x[0] ** 2), 1 - DT * CD]])


def filterpy_seconds(y: np.ndarray, x0: np.ndarray, P0: np.ndarray, Q: np.ndarray,
                     R: np.ndarray) -> float:
    """Seconds for filterpy's EKF over ``y [T, 1]``."""
    from filterpy.kalman import ExtendedKalmanFilter

    ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    ekf.x, ekf.P, ekf.Q, ekf.R = x0.copy(), P0.copy(), Q, R
    H = np.array([[1.0, 0.0]])
    t0 = time.perf_counter()
    for k in range(y.shape[0]):
        ekf.F = _F(ekf.x)
        ekf.x = _f(ekf.x)
        ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
        ekf.update(y[k], lambda x: H, lambda x: H @ x)
    return time.perf_counter() - t0


def torch_seconds(filt, y: torch.Tensor) -> float:
    """Seconds for ``filt``'s ``forward`` over ``y [1, T, m]``."""
    with torch.no_grad():
        t0 = time.perf_counter()
        filt(y)
        return time.perf_counter() - t0


def online_seconds(filt, y: torch.Tensor, stream: bool) -> float:
    """Seconds for ``filt.step`` over ``y [1, T, m]``, one measurement at a time
    (``stream``: inside ``filt.streaming()``, the Dynamo-free captured step)."""
    with torch.no_grad(), filt.streaming() if stream else contextlib.nullcontext():
        st = filt.initial_state(batch=1)
        t0 = time.perf_counter()
        for k in range(y.shape[1]):
            st = filt.step(st, None, y[:, k])
        return time.perf_counter() - t0


def paired(ours, ref, repeats: int) -> tuple[float, float, float]:
    """``repeats`` timings of ``ours()`` each followed by one of ``ref()`` (A B A B: both see
    the same machine load) -> medians of ours, of ref, and of the per-pair ratios."""
    ours()  # warm-up (and compile)
    pairs = [(ours(), ref()) for _ in range(repeats)]
    a, b = np.array(pairs).T
    return float(np.median(a)), float(np.median(b)), float(np.median(a / b))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=9,
                    help="timed runs of each row, each followed by a filterpy run")
    ap.add_argument("--filters", nargs="*", default=["ekf", "combined"],
                    choices=["ekf", "combined"])
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--per-call", type=int, nargs="*", default=[8],
                    help="steps_per_call values of the extra compiled rows (none: no rows)")
    ap.add_argument("--python-wrapper", action="store_true",
                    help="also each compiled row with Inductor's Python wrapper "
                    "(options={'cpp_wrapper': False}; the default is the C++ wrapper)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    system = systems.get("spring_damper")
    traj = system.simulate(steps=args.steps, batch=1, seed=0)
    y = traj.y
    ekf = filters.EKF(system)
    st = ekf.initial_state(batch=1)
    x0 = st.set.center[0].numpy()
    P0 = st.extras["covariance"][0].numpy()
    Q = np.diag(ekf.process_half_widths.detach().numpy() ** 2 / 3)  # uniform-noise variances
    R = np.diag(ekf.measurement_half_widths.detach().numpy() ** 2 / 3)

    def reference() -> float:  # filterpy seconds for the horizon
        return filterpy_seconds(y[0].numpy(), x0, P0, Q, R)

    print(f"torch {torch.__version__}, 1 thread; spring_damper, B = 1, {args.steps} steps")
    print("\n| filter | mode | ms per step | filterpy EKF ms per step | ratio (ours / filterpy) "
          "| compile s |")
    print("|---|---|---:|---:|---:|---:|")
    for name in args.filters:
        modes = [("eager", 0, False)]
        if not args.no_compile:
            for cw in (True, False) if args.python_wrapper else (True,):
                tag = "" if cw else ", Python wrapper"
                modes += [(f"compiled{tag}", 1, cw)] + [
                    (f"compiled, {k} steps per call{tag}", k, cw) for k in args.per_call
                ]
        for mode, comp, cw in modes:
            filt = filters.by_name(name)(system)
            tc = 0.0
            if comp:
                filt.compile(steps_per_call=comp, options=None if cw else {"cpp_wrapper": False})
                t0 = time.perf_counter()
                with torch.no_grad():
                    filt(y[:, :2])
                tc = time.perf_counter() - t0
            t, ref, ratio = paired(lambda f=filt: torch_seconds(f, y), reference, args.repeats)
            ms = 1e3 / args.steps
            print(f"| {name} | {mode} | {ms * t:.3f} | {ms * ref:.3f} | {ratio:.1f} | "
                  f"{tc:.0f} |", flush=True)
            for stream in (False, True) if comp == 1 else ():  # online, like filterpy's loop
                t, ref, ratio = paired(
                    lambda f=filt, s=stream: online_seconds(f, y, s), reference, args.repeats
                )
                how = "in `streaming()`" if stream else "guarded"
                print(f"| {name} | compiled, online `step`, {how} | {ms * t:.3f} | "
                      f"{ms * ref:.3f} | {ratio:.1f} | |", flush=True)


if __name__ == "__main__":
    main()
