"""Kalman-type filters at batch 1: diffsmf's EKF and CombinedFilter vs filterpy, same run.

One trajectory of ``spring_damper`` (2 states, 1 output). The peer is filterpy's
``ExtendedKalmanFilter`` with the analytic Jacobian of the model (numpy), stepped online
(``predict`` then ``update``); ours run ``forward`` over the horizon, eager and compiled
(``filt.compile()``, the one-off compile time printed separately; and
``filt.compile(steps_per_call=K)``, K steps per compiled call; with ``--python-wrapper`` each
compiled row again with Inductor's Python wrapper instead of the default C++ one), and the
compiled filter
also online, one ``filt.step`` call per measurement (with Dynamo's guard checks, and inside
``filt.streaming()``, which skips them once checked). The CombinedFilter does a
Kalman step plus the outer Minkowski sums of its mean set, so filterpy's EKF step is the
natural lower reference for it. Median of ``--repeats`` timings; filterpy is timed again
right after each row (its time drifts by up to 1.7x between runs here); one torch thread.

    python benchmarks/kalman_bench.py [--steps 200] [--repeats 5] [--no-compile]
        [--per-call 8] [--python-wrapper]
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


def torch_seconds(filt, y: torch.Tensor, repeats: int) -> float:
    with torch.no_grad():
        filt(y[:, :3])  # warm-up (and compile)
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            filt(y)
            ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def online_seconds(filt, y: torch.Tensor, repeats: int, stream: bool) -> float:
    """Median seconds for ``filt.step`` over ``y [1, T, m]``, one measurement at a time
    (``stream``: inside ``filt.streaming()``, Dynamo's guards skipped once checked)."""
    ts = []
    with torch.no_grad():
        for _ in range(repeats):
            with filt.streaming() if stream else contextlib.nullcontext():
                st = filt.initial_state(batch=1)
                t0 = time.perf_counter()
                for k in range(y.shape[1]):
                    st = filt.step(st, None, y[:, k])
                ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
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
    Q = np.diag(ekf.process_noise.detach().numpy() ** 2 / 3)  # uniform-noise variances
    R = np.diag(ekf.measurement_noise.detach().numpy() ** 2 / 3)

    def reference() -> float:  # filterpy s/step, median of --repeats (timed next to each row)
        runs = [filterpy_seconds(y[0].numpy(), x0, P0, Q, R) for _ in range(args.repeats)]
        return float(np.median(runs)) / args.steps

    print(f"torch {torch.__version__}, 1 thread; spring_damper, B = 1, {args.steps} steps")
    print("\n| filter | mode | ms per step | filterpy EKF ms per step | ratio (ours / filterpy) "
          "| compile s |")
    print("|---|---|---:|---:|---:|---:|")
    for name in ("ekf", "combined"):
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
            t = torch_seconds(filt, y, args.repeats) / args.steps
            ref = reference()
            print(f"| {name} | {mode} | {1e3 * t:.3f} | {1e3 * ref:.3f} | {t / ref:.1f} | "
                  f"{tc:.0f} |", flush=True)
            for stream in (False, True) if comp == 1 else ():  # online, like filterpy's loop
                t = online_seconds(filt, y, args.repeats, stream) / args.steps
                ref = reference()
                how = "in `streaming()`" if stream else "guarded"
                print(f"| {name} | compiled, online `step`, {how} | {1e3 * t:.3f} | "
                      f"{1e3 * ref:.3f} | {t / ref:.1f} | |", flush=True)


if __name__ == "__main__":
    main()
