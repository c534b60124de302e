"""The systems of the reference toolbox's observer tests, with their recorded data, and the
tank cascade of any size (registered in `diffsmf.systems.registry`).

* ``"linear_2d"``: the two-dimensional linear example of Alamo, Bravo & Camacho (2005,
  sec. 7.1), as CORA's observer unit test ``test_linearSysDT_observe_02_2dim`` states it.
* ``"tank6"``: CORA's nonlinear six-tank observer test (``test_nonlinearSysDT_observe_01_tank``,
  model ``tank6EqDT_inflow4``): six tanks in a row, square-root outflows, Euler step 0.5, three
  inflows, levels 2, 4 and 5 measured.
* ``"tank_cascade"``: ``n`` tanks in a row (any ``n``, ``"tank_cascade:30"``), every second
  level measured: the large plant of ``benchmarks/large_plants.py``.

`recorded` returns the measurements (and inputs) that the toolbox's tests store, so that a
filter's final set can be compared with the toolbox's saved results.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.sets import Zonotope
from diffsmf.systems.library import box, positive, sym_box
from diffsmf.systems.system import System

__all__ = ["linear_2d", "recorded", "tank6", "tank_cascade"]

_F64 = torch.float64
_G = 9.81

_Y_2D = [[0.0234670727523143], [-4.3282364718962034], [-4.1973096745991345],
         [-1.9546081148402012], [0.0983604258227819], [1.1666132024783362],
         [1.1073176387179109], [0.4263920687095986], [-0.0092682185713610],
         [-0.3069527304071071], [-0.1292621672249405], [-0.0195793311301101],
         [-0.0751745657276915], [0.0774426557519688], [0.2618198630568284],
         [-0.0222441951122745], [0.0464232298590576], [-0.1385809053684645],
         [0.0876767710448164], [-0.1094667337318030]]

_U_TANK = [
    [0.1, 0.1, 0.1],
    [0.1, 0.1, 0.1],
    [0.1, 0.1, 0.1],
    [0.1025, 0.1025, 0.105],
    [0.105, 0.105, 0.11],
    [0.1075, 0.1075, 0.115],
    [0.11, 0.11, 0.12],
    [0.1125, 0.1125, 0.125],
    [0.115, 0.115, 0.13],
    [0.1175, 0.1175, 0.135],
    [0.12, 0.12, 0.14],
    [0.1225, 0.1225, 0.145],
    [0.125, 0.125, 0.15],
    [0.1275, 0.1275, 0.155],
    [0.13, 0.13, 0.16],
    [0.1325, 0.1325, 0.165],
    [0.135, 0.135, 0.17],
    [0.1375, 0.1375, 0.175],
    [0.14, 0.14, 0.18],
    [0.1425, 0.1425, 0.185],
]

_Y_TANK = [
    [18.587107801413037, 20.225990245627816, 19.112251238495777],
    [19.284508642234258, 20.158180661305583, 18.973762663726877],
    [19.804172917266072, 20.171464843998834, 18.94817082410438],
    [19.984844940204784, 20.327437617339143, 18.992192949983256],
    [20.2789535501327, 20.153618747112297, 19.00188195851898],
    [20.483743290472002, 20.38006872027638, 19.150117548502443],
    [20.674406205375988, 20.376688700844845, 18.975701530881086],
    [20.564287471887262, 20.299247293957542, 19.08828348979567],
    [20.524616208625844, 20.24341925375551, 18.99187188370038],
    [20.39085890953035, 20.277306209637565, 19.066458349897363],
    [20.579505841851283, 20.2900717556372, 18.943805866972866],
    [20.499347774002867, 20.468834597540557, 19.214278885933556],
    [20.334643962630423, 20.2707835532585, 18.957978956507624],
    [20.272233256206864, 20.22339446570158, 19.084269923675965],
    [20.16774332661966, 20.46714845771351, 19.183361721875762],
    [20.169739624168546, 20.201977670029528, 19.08104150630512],
    [20.10446158056945, 20.43160725296825, 19.11824420633317],
    [20.06090052728117, 20.48113524801599, 19.284683679863136],
    [19.93755470645448, 20.48740510369765, 19.15650310633674],
    [19.834875810069285, 20.410091165821306, 19.215720898675404],
]


def linear_2d(horizon: int = 20) -> System:
    """Alamo, Bravo & Camacho 2005, sec. 7.1: ``x+ = [[0, -0.5], [1, 1]] x + w``,
    ``y = [-2, 1] x + v``; ``X0 = 3 [-1, 1]^2``, ``w`` on the segment ``[-0.12, 0.02]' [-1, 1]``
    (a zonotope with one generator), ``|v| <= 0.2``."""
    A = torch.tensor([[0.0, -0.5], [1.0, 1.0]], dtype=_F64)
    C = torch.tensor([[-2.0, 1.0]], dtype=_F64)

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        return x @ A.T

    def h(x: Tensor) -> Tensor:
        return x @ C.T

    X0 = Zonotope(torch.zeros(2, dtype=_F64), 3.0 * torch.eye(2, dtype=_F64))
    W = Zonotope(torch.zeros(2, dtype=_F64), torch.tensor([[-0.12], [0.02]], dtype=_F64))
    s = System(f, h, X0, W, sym_box(1, 0.2, "v"), name="linear_2d")
    s.horizon, s.paper_x0 = horizon, None
    return s


def _tank6_inputs(k: int) -> Tensor:
    """CORA's recorded inflows ``[3]`` at step k (held at the last one after 20 steps)."""
    return torch.tensor(_U_TANK[min(k, len(_U_TANK) - 1)], dtype=_F64)


def tank6(dt: float = 0.5, w: float = 0.001, v: float = 0.2, horizon: int = 20) -> System:
    """CORA's ``tank6EqDT_inflow4`` (Euler step ``dt``), as its observer test uses it.

    ``x_i+ = x_i + dt (outflow terms)`` with ``k = 0.015``, ``g = 9.81``: tank 1 drains by
    ``k sqrt(2 g x_1)`` and takes ``u_1``; tank 2 takes ``sqrt(2 g) (sqrt x_1 - sqrt x_2)``
    (without the factor ``k``, as in CORA's model); tanks 3-6 take ``k sqrt(2 g) (sqrt x_{i-1}
    - sqrt x_i)``, with ``u_2`` and ``u_3`` inside that bracket for tanks 4 and 5. Levels 2, 4
    and 5 measured, ``|v| <= 0.2``, ``|w| <= 0.001``, ``X0 = 20 +- 4``. The inputs are the
    test's recorded inflows (`recorded`).
    """
    dt, k = positive("dt", dt), 0.015
    s2g = (2 * _G) ** 0.5

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        r = torch.sqrt(x)
        u = torch.zeros_like(x[..., :3]) if u is None else u
        d = [
            -k * s2g * r[..., 0] + u[..., 0],
            s2g * (r[..., 0] - r[..., 1]),
            k * s2g * (r[..., 1] - r[..., 2]),
            k * s2g * (r[..., 2] - r[..., 3] + u[..., 1]),
            k * s2g * (r[..., 3] - r[..., 4] + u[..., 2]),
            k * s2g * (r[..., 4] - r[..., 5]),
        ]
        return x + dt * torch.stack(d, -1)

    def h(x: Tensor) -> Tensor:
        return x[..., [1, 3, 4]]

    x0 = box(torch.full((6,), 20.0, dtype=_F64), 4.0)
    s = System(f, h, x0, sym_box(6, w, "w"), sym_box(3, v, "v"), inputs=_tank6_inputs,
               name="tank6")
    s.horizon, s.paper_x0 = horizon, None
    return s


def tank_cascade(n: int = 6, dt: float = 1.0, w: float = 0.01, v: float = 0.2,
                 horizon: int = 100) -> System:
    """``n`` tanks in a row with square-root outflows ``k sqrt(2 g x_i)`` (``k = 0.015``), each
    feeding the next, a constant inflow 0.1 to the first; levels 2, 4, ... measured
    (``|v| <= 0.2``), ``|w| <= 0.01``, ``X0 = 20 +- 4`` in every level."""
    if not isinstance(n, int) or n < 2:
        raise ValueError(f"n: the number of tanks must be an integer >= 2, got {n!r}")
    dt, k = positive("dt", dt), 0.015
    idx = list(range(1, n, 2))

    def f(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        q = k * torch.sqrt(2 * _G * x)
        inflow = torch.cat([torch.full_like(x[..., :1], 0.1), q[..., :-1]], -1)
        return x + dt * (inflow - q)

    def h(x: Tensor) -> Tensor:
        return x[..., idx]

    x0 = box(torch.full((n,), 20.0, dtype=_F64), 4.0)
    s = System(f, h, x0, sym_box(n, w, "w"), sym_box(len(idx), v, "v"),
               name=f"tank_cascade:{n}")
    s.horizon, s.paper_x0 = horizon, None
    return s


def recorded(name: str) -> tuple[Tensor, Tensor | None]:
    """The measurements ``y [1, T, m]`` and inputs ``u [1, T, p]`` (or None) that the reference
    toolbox's observer test of ``name`` (``"linear_2d"`` | ``"tank6"``) records; its first
    measurement is of the initial state (update before the first prediction).

    Raises:
        ValueError: starting with ``name:`` for a system without recorded data.
    """
    if name == "linear_2d":
        return torch.tensor(_Y_2D, dtype=_F64).unsqueeze(0), None
    if name == "tank6":
        return (torch.tensor(_Y_TANK, dtype=_F64).unsqueeze(0),
                torch.tensor(_U_TANK, dtype=_F64).unsqueeze(0))
    raise ValueError(f"name: no recorded data for {name!r}; choose from ['linear_2d', 'tank6']")

