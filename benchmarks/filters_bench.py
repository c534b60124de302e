"""Filter speed: trajectory-steps per second on ``spring_damper`` at batch 1, 100 and 10,000.

Each diffsmf filter runs batched (one tensor op per step for the whole batch). The reference
is a straightforward numpy HS-NSMF that loops over trajectories (same algorithm: Stirling
slopes, DC remainder at the parallelotope vertices with alpha from the exact Hessian bound of
the spring-damper model, Theorem 2 box sum, Chisci minimal outer parallelotope over the
generator bases, Wang et al. 2022, eq. 30-41 strip update).

Runtime is capped: each (filter, batch) cell runs ``--steps`` steps (default 10; a fifth of
them for the eager filters above batch 1,000) and the per-trajectory numpy loop runs at most
``--max-numpy`` trajectories, its rate at larger batches being extrapolated (it is linear in
the batch; stated in the table). The compiled rows always run all ``--steps`` steps: a
compiled ``forward`` checks Dynamo's guards in full on its first two steps only (see
``SetFilter.forward``), and over two steps that start-up weighed on the rate at batch
10,000 (HSNSMF, one thread, two audits on the machine: 165,892 trajectory-steps/s over 2
steps, 191,406 over 20).

    python benchmarks/filters_bench.py [--steps 10] [--batches 1 100 10000] [--compiled]
    python benchmarks/filters_bench.py --scaling [--dims 2 4 8 16 32]

``--compiled`` adds rows for ``filt.compile()`` (the fullgraph step; its one-off compile time
is printed separately) and, at batch 1, for the compiled filter used online (one
``filt.step`` call per measurement inside ``filt.streaming()``, as the numpy loop steps).
``--scaling`` prints time per step vs the state dimension on the ``oscillator_chain`` system
(remainder ``"auto"``: vertices up to n = 8, then vertex-free) with the fitted growth exponent
(least squares of log time on log n).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import time

import numpy as np
import torch

from diffsmf import filters, systems

# ---------------------------------------------------------------------- numpy reference
DT, K0, KD, CD = 0.1, 1.5, 3.0, 1.24


def _f(x: np.ndarray) -> np.ndarray:
    x1, x2 = x[..., 0], x[..., 1]
    return np.stack([x1 + DT * x2, x2 + DT * (-K0 * x1 * (1 - KD * x1**2) - CD * x2)], -1)


def _grad_f(x: np.ndarray) -> np.ndarray:
    """Exact Jacobian of the spring-damper step at x [2] -> [2, 2]."""
    x1 = x[0]
    return np.array([[1.0, DT], [DT * (-K0 + 3 * K0 * KD * x1**2), 1 - DT * CD]])


def _alpha(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """DC parameter per output: Hessian of f2 is diag(6 dt k0 kd x1, 0); f1 is linear."""
    h11 = 6 * DT * K0 * KD * np.array([lo[0], hi[0]])
    return np.array([0.0, max(0.0, -h11.min() / 2)])


def _dc_box(c: np.ndarray, T: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wang et al. 2022, eq. 15-16 at the 4 vertices of c + T[-1,1]^2 -> (lower, upper)."""
    V = c + np.array(list(itertools.product([-1, 1], repeat=2))) @ T.T
    r = np.abs(T).sum(1)
    a = _alpha(c - r, c + r)
    d = V - c
    sq = (d * d).sum(1)[:, None]
    rv = _f(V) - _f(c) - d @ J.T
    upper = (rv + a * sq).max(0)
    lower = (d @ (_grad_f(c) - J).T - a * sq).min(0)
    return lower, upper


def _chisci(G: np.ndarray) -> np.ndarray:
    """Minimal-volume outer parallelotope over generator bases (Chisci 1996) -> T."""
    n, m = G.shape
    best, bestT = np.inf, None
    for idx in itertools.combinations(range(m), n):
        B = G[:, idx]
        if abs(np.linalg.det(B)) < 1e-14:
            continue
        T = B * np.abs(np.linalg.solve(B, G)).sum(1)
        v = abs(np.linalg.det(T))
        if v < best:
            best, bestT = v, T
    return bestT


def _strip(xc: np.ndarray, T: np.ndarray, p: np.ndarray, cs: float):
    """Wang et al. 2022, eq. 30-41 for the strip |p x - cs| <= 1 -> (xc, T, consistent)."""
    T = T.copy()
    pt = p @ T
    e_p = p @ xc - cs + np.abs(pt).sum()
    e_m = p @ xc - cs - np.abs(pt).sum()
    if e_p < -1 or e_m > 1:
        return xc, T, False
    T = T * np.where(pt < 0, -1.0, 1.0)
    pt = np.abs(pt)
    rp, rm = min(1, e_p), min(1, -e_m)
    pb = 2 / (rp + rm) * p
    cb = 2 / (rp + rm) * (cs + (rp - rm) / 2)
    xb, Tb = xc.copy(), T.copy()
    for i in range(T.shape[1]):
        if pt[i] != 0:
            ri_p = min(1, (1 - e_m) / pt[i] - 1)
            ri_m = min(1, (1 + e_p) / pt[i] - 1)
            Tb[:, i] = (ri_p + ri_m) / 2 * T[:, i]
            xb = xb + (ri_p - ri_m) / 2 * T[:, i]
    pbt = pb @ Tb
    i_star = int(np.argmax(np.append(pbt, 1.0)))
    if i_star == T.shape[1]:
        return xb, Tb, True
    Ts = Tb - np.outer(Tb[:, i_star], pbt / pbt[i_star])
    Ts[:, i_star] = Tb[:, i_star] / pbt[i_star]
    xs = xb + Tb[:, i_star] * (cb - pb @ xb) / pbt[i_star]
    return xs, Ts, True


def numpy_hsnsmf(y: np.ndarray, c0, r0, w: float, v: float, h: float = 0.1) -> np.ndarray:
    """HS-NSMF on one spring-damper trajectory ``y [T, 1]`` -> centres ``[T+1, 2]``."""
    c, T = np.asarray(c0, float), np.diag(r0)
    out = [c]
    H = np.array([1.0, 0.0])
    for k in range(y.shape[0]):
        J = np.stack([(_f(c + h * e) - _f(c - h * e)) / (2 * h) for e in np.eye(2)], 1)
        lo, hi = _dc_box(c, T, J)
        rad = (hi - lo) / 2 + w
        Z = np.hstack([J @ T, np.diag(rad)])
        c = _f(c) + (hi + lo) / 2
        T = _chisci(Z)
        c, T, _ = _strip(c, T, H / v, y[k, 0] / v)  # linear h: no remainder
        out.append(c)
    return np.stack(out)


# ---------------------------------------------------------------------- timing
def _time_torch(
    name: str, system, batch: int, steps: int, compiled: bool = False, repeats: int = 3,
    online: bool = False,
) -> tuple[float, float]:
    """(median trajectory-steps/s over ``repeats`` runs, one-off compile seconds or 0).

    ``online``: one ``filt.step`` call per measurement inside ``filt.streaming()`` instead of
    ``forward`` over the horizon (after ``compile()`` that is the Dynamo-free compiled step on
    validated inputs, captured at the warm-up)."""
    traj = system.simulate(steps=steps, batch=batch, seed=0, noise="uniform")
    filt = filters.by_name(name)(system)
    t_compile = 0.0
    if compiled:
        filt.compile(retain_memory=True)  # the benchmark opts in (process-wide setting)
    def run_online(T: int) -> None:
        st = filt.initial_state(batch=batch)
        for k in range(T):
            st = filt.step(st, None if traj.u is None else traj.u[:, k], traj.y[:, k])

    with torch.no_grad(), filt.streaming() if online else contextlib.nullcontext():
        t0 = time.perf_counter()
        # warm-up / compile: 3 steps (CZSMF's growth phase runs eagerly; every other filter
        # compiles its step graph at the first)
        w = min(3, steps)
        if online:
            run_online(w)
        else:
            filt(traj.y[:, :w], u=None if traj.u is None else traj.u[:, :w])
        t_compile = time.perf_counter() - t0 if compiled else 0.0
        rates = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            if online:
                run_online(steps)
            else:
                filt(traj.y, u=traj.u)
            rates.append(batch * steps / (time.perf_counter() - t0))
    return float(np.median(rates)), t_compile


def scaling(dims: list[int], names: list[str], batch: int, steps: int) -> None:
    """Time per step vs n on ``oscillator_chain`` and the fitted growth exponent."""
    print(f"\n| filter | remainder | {' | '.join(f'n={n}' for n in dims)} | exponent |")
    print("|---|---|" + "---:|" * (len(dims) + 1))
    for name in names:
        ms, rem = [], set()
        for n in dims:
            system = systems.get("oscillator_chain", n=n)
            rem.add(getattr(filters.by_name(name)(system), "remainder", "-"))
            rate, _ = _time_torch(name, system, batch, steps, repeats=1)
            ms.append(1e3 * batch / rate)
        slope = float(np.polyfit(np.log(dims), np.log(ms), 1)[0])
        cells = " | ".join(f"{t:.1f}" for t in ms)
        print(f"| {name} | {'/'.join(sorted(rem))} | {cells} | {slope:.2f} |", flush=True)
    print(f"\nms per step (B = {batch}, {steps} steps, median of 1 run per cell); "
          "exponent: slope of log(ms) on log(n).")


def _time_numpy(
    system, batch: int, steps: int, max_traj: int, repeats: int = 5
) -> tuple[float, bool]:
    """(median trajectory-steps/s of the numpy loop over ``repeats`` passes, extrapolated?)."""
    b = min(batch, max_traj)
    traj = system.simulate(steps=steps, batch=b, seed=0, noise="uniform")
    y = traj.y.numpy()
    numpy_hsnsmf(y[0, :1], [0.2, 0.3], [0.15, 0.15], 2e-3, 1e-3)  # warm-up (first-call costs)
    rates = []
    for _ in range(repeats):  # median: one pass over 100 short trajectories is a fraction of
        t0 = time.perf_counter()  # a second, and its rate drifted 2x between runs here
        for i in range(b):
            numpy_hsnsmf(y[i], [0.2, 0.3], [0.15, 0.15], 2e-3, 1e-3)
        rates.append(b * steps / (time.perf_counter() - t0))
    return float(np.median(rates)), b < batch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 100, 10000])
    ap.add_argument("--filters", nargs="+", default=["hsnsmf", "mszm", "cdsmf", "esmf", "ekf"])
    ap.add_argument("--max-numpy", type=int, default=100)
    ap.add_argument("--compiled", action="store_true", help="add filt.compile() rows")
    ap.add_argument("--compiled-filters", nargs="+", default=["hsnsmf"])
    ap.add_argument("--scaling", action="store_true", help="time per step vs n instead")
    ap.add_argument("--dims", type=int, nargs="+", default=[2, 4, 8, 16, 32])
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op thread(s)")
    if args.scaling:
        scaling(args.dims, [f for f in args.filters if f != "ekf"], 10, max(2, args.steps // 2))
        return
    system = systems.get("spring_damper")
    rows = []
    for batch in args.batches:
        steps = args.steps if batch <= 1000 else max(2, args.steps // 5)  # eager rows
        ref, extrap = _time_numpy(system, batch, steps, args.max_numpy)
        variants = [(n, False, False) for n in args.filters]
        if args.compiled:
            variants += [(n, True, False) for n in args.compiled_filters]
            if batch == 1:  # the online fast path: one filt.step call per measurement
                variants += [(n, True, True) for n in args.compiled_filters]
        for name, comp, online in variants:
            T = args.steps if comp else steps
            rate, tc = _time_torch(name, system, batch, T, compiled=comp, online=online)
            mode = ", online streaming step" if online else ""
            label = f"{name} (compiled{mode})" if comp else name
            rows.append((label, batch, T, rate, ref, extrap))
            print(
                f"{label:<30} B={batch:<6} {rate:12.0f} traj-steps/s   numpy HSNSMF {ref:10.0f}"
                f"{' (extrapolated)' if extrap else ''}   ratio {rate / ref:8.2f}"
                + (f"   compile {tc:.0f} s" if comp else ""),
                flush=True,
            )
    print("\n| filter | batch | steps | diffsmf traj-steps/s | numpy HSNSMF traj-steps/s | ratio |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, batch, steps, rate, ref, extrap in rows:
        star = "*" if extrap else ""
        print(f"| {name} | {batch} | {steps} | {rate:.0f} | {ref:.0f}{star} | {rate / ref:.2f} |")
    print("\n* numpy loop timed on at most --max-numpy trajectories; its rate per")
    print("  trajectory-step does not depend on the batch (a Python loop), so it is carried over.")


if __name__ == "__main__":
    main()
