"""Wang et al. 2009 example (eq. 23): LMI observer with a PWL model of f(X) = -x1^2 x2.

Prints the paper-comparison table and the pipeline results for three eps values, and writes
docs/figures/observer_vdp.png (eps = 0.05). Run: python examples/observer_vdp.py [--fast]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from diffsmf.observers import (
    analyze_observer_gain,
    design_lipschitz_observer,
    design_observer_pipeline,
    plot_pipeline,
)

A = np.array([[0.0, 1.0], [-1.0, 1.0]])
C = np.array([[1.0, 0.0]])
STRUCT = (np.array([[0.0], [1.0]]), np.eye(2))


def paper_table() -> None:
    print("== Wang et al. 2009 setting: Lipschitz 1, models with eps = 3 and 1.5 ==")
    print(f"{'design':<34}{'gain':>8}{'bound eps=3':>13}{'bound eps=1.5':>15}")
    print(f"{'paper (Theorem 1, eq. 20-22)':<34}{0.2027:>8.4f}{0.6080:>13.4f}{0.3040:>15.4f}")
    for mg in (211.46, 1000.0):
        d = design_lipschitz_observer(A, C, 1.0, 3.0, structure=STRUCT, max_gain=mg)
        print(f"{f'ours, structured, |L| <= {mg:g}':<34}{d.gain:>8.4f}{d.bound:>13.4f}"
              f"{d.gain * 1.5:>15.4f}   L = {np.round(d.L.ravel(), 2).tolist()} ({d.status})")
    g = design_lipschitz_observer(A, C, 1.0, 3.0, max_gain=1000.0)
    print(f"{'ours, general |f(x)-f(x̂)|<=|e|':<34} {g.status}: {g.message[:70]}...")
    p = analyze_observer_gain(A, C, np.array([[7.0], [211.46]]), 1.0, 3.0, structure=STRUCT)
    print(f"{'paper gain L=[7, 211.46] analysed':<34}{p.gain:>8.4f}{p.bound:>13.4f}"
          f"{p.gain * 1.5:>15.4f}   ({p.status})")


def pipeline(fast: bool) -> None:
    print("\n== pipeline: samples -> SCPLNN (certified eps) -> LMI -> simulation ==")
    for eps in (0.2, 0.1, 0.05):
        t0 = time.perf_counter()
        res = design_observer_pipeline("vdp", eps, method="grid", T=20.0 if not fast else 5.0)
        print(f"-- eps target {eps} ({time.perf_counter() - t0:.1f} s)")
        print(res.summary())
        if eps == 0.05:
            plot_pipeline(res, "docs/figures/observer_vdp.png")
    print("\n== fit_scplnn (adaptive splitting, Wang et al. 2009, sec. 3.1.2) as the model ==")
    res = design_observer_pipeline("vdp", 0.2, method="scplnn", simulate_system=False)
    print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.fit.items()})
    print("structured design:", res.design.status, f"bound {res.design.bound:.4g}")


if __name__ == "__main__":
    paper_table()
    pipeline("--fast" in sys.argv)
