"""Discrete-time nonlinear system with bounded (and optionally Gaussian) noise.

Model (the convention of every filter in diffsmf, docs/design.md)::

    x_k = f(x_{k-1}, u_{k-1}, theta_{k-1}) + w_{k-1} (+ g_{k-1}),   w in W,  g ~ N(0, Q)
    y_k = h(x_k) + v_k (+ e_k),                                        v in V,  e ~ N(0, R)
    x_0 in X0

``W``, ``V``, ``X0`` are any `diffsmf.sets` set; ``theta`` is an unknown parameter known
only to lie in the `Interval` ``parameters`` (nominal value: its midpoint).

Inputs: a system with ``n_inputs = p > 0`` needs ``u [..., p]`` at every step. They come either
from an ``inputs`` schedule (built-ins such as ``"bilinear"``, ``"vdp"``) or from the caller
(logged data: ``System(..., n_inputs=p)``, then ``filt(y, u=U)`` / ``sys.simulate(..., u=U)``).
`System.check_input` is the one validator every filter and ``simulate`` use.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from diffsmf.convex import ConvexSet, check_nonempty
from diffsmf.interval.engine import StepModel, register_row_model
from diffsmf.linearize.jacobians import jacobian
from diffsmf.systems.checks import trial_enclosure, uncertified_fit
from diffsmf.systems.model import Dynamics, as_dynamics, check_dtype, check_module_dtype
from diffsmf.utils import is_int

__all__ = ["System", "Trajectory", "check_system", "scale_set", "wrap_angle"]


class Trajectory(NamedTuple):
    """A batch of simulated trajectories.

    x: ``[B, T+1, n]`` true states (``x[:, 0]`` in ``x0_set``);
    y: ``[B, T, m]`` measurements, ``y[:, k-1] = h(x_k) + v_k``;
    u: ``[B, T, p]`` inputs (``u[:, k-1]`` drives ``x_{k-1} -> x_k``) or ``None``;
    theta: ``[B, T, q]`` parameters used at each step, or ``None``.
    """

    x: Tensor
    y: Tensor
    u: Tensor | None
    theta: Tensor | None


def _as_schedule(
    name: str, value: Tensor | Callable[[int], Tensor] | None
) -> Callable[[int], Tensor] | None:
    if value is None or callable(value):
        return value
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.dim() < 2:
        raise ValueError(f"{name}: a tensor schedule must have shape [T, dim] or [B, T, dim]")
    return lambda k: t[..., k, :]


class System(nn.Module):
    """Nonlinear system with set-bounded noise, as an ``nn.Module``.

    Args:
        f: ``f(x [..., n], u [..., p] | None, theta [..., q] | None) -> [..., n]``, torch ops.
        h: ``h(x [..., n]) -> [..., m]``, torch ops.
        x0_set: initial set (batch shape ``[]``), dim n.
        process_noise: bounded process noise set W (dim n) or ``None`` (zero).
        measurement_noise: bounded measurement noise set V (dim m) or ``None`` (zero).
        parameters: ``Interval`` of mismatched parameters (dim q) or ``None``.
        inputs: ``u(k) -> [p]`` or ``[B, p]`` (k = 0, 1, ...), or a tensor ``[T, p]``; ``None``
            for an autonomous system or when the inputs come with the data (``n_inputs``).
        n_inputs: input dimension p. Inferred from ``inputs`` when given (and then checked
            against it); default 0 (autonomous) when there is no schedule. Give it for a system
            whose inputs come from logged data: filters and ``simulate`` then require ``u``.
        theta_schedule: the true parameter used by ``simulate`` at step k (``k -> [q]``,
            or a tensor ``[T, q]``); default: the midpoint of ``parameters``.
        process_cov: optional Gaussian process covariance Q ``[n, n]``.
        measurement_cov: optional Gaussian measurement covariance R ``[m, m]``.
        name: a label for tables and figures.
        angle_outputs: indices of the outputs that are angles in radians (bearings,
            headings), e.g. ``[1]`` for ``y = [range, bearing]``. Their measurements are
            compared with the prediction modulo ``2 pi``: every filter builds the strip (or
            the innovation) on the branch that the predicted measurement ``h(c)`` picks,
            ``y' = h(c) + wrap(y - h(c))`` with ``wrap`` into ``[-pi, pi)``
            (`wrap_angle`). Default: none.
    """

    def __init__(
        self,
        f: Callable[..., Tensor],
        h: Callable[[Tensor], Tensor],
        x0_set: ConvexSet,
        process_noise: ConvexSet | None = None,
        measurement_noise: ConvexSet | None = None,
        parameters: ConvexSet | None = None,
        *,
        inputs: Tensor | Callable[[int], Tensor] | None = None,
        n_inputs: int | None = None,
        theta_schedule: Tensor | Callable[[int], Tensor] | None = None,
        process_cov: Tensor | None = None,
        measurement_cov: Tensor | None = None,
        name: str = "system",
        angle_outputs: list[int] | tuple[int, ...] | None = None,
    ) -> None:
        super().__init__()
        if not callable(f) or not callable(h):
            raise ValueError("f, h: must be callables written with torch ops")
        if not isinstance(x0_set, ConvexSet):
            raise ValueError("x0_set: must be a diffsmf set")
        if len(x0_set.batch_shape) != 0:
            raise ValueError("x0_set: must have an empty batch shape")
        check_nonempty("x0_set", x0_set)
        check_module_dtype("f", f)
        check_module_dtype("h", h)
        self.f = as_dynamics(f)
        self.h = h
        self.x0_set = x0_set
        self.n = x0_set.dim
        _check_state_dims(f, x0_set, process_noise)
        self.m = _output_dim(h, x0_set.center)
        self.angle_outputs = _check_angle_outputs(angle_outputs, self.m)
        # [m] bool mask of the angle outputs (a plain tensor, not a buffer: state_dicts unchanged)
        self._angle_mask = torch.zeros(self.m, dtype=torch.bool, device=x0_set.device)
        self._angle_mask[list(self.angle_outputs)] = True
        for label, s, d in (
            ("process_noise", process_noise, self.n),
            ("measurement_noise", measurement_noise, self.m),
        ):
            if s is not None and (not isinstance(s, ConvexSet) or s.dim != d):
                raise ValueError(f"{label}: must be a diffsmf set of dim {d}")
            if s is not None:
                check_nonempty(label, s)
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise
        if parameters is not None:
            if not isinstance(parameters, ConvexSet):
                raise ValueError(
                    "parameters: must be a diffsmf set of parameter vectors (e.g. "
                    f"ds.Interval(lower, upper)), got {type(parameters).__name__}"
                )
            if len(parameters.batch_shape) != 0:
                raise ValueError("parameters: must have an empty batch shape, got "
                                 f"{list(parameters.batch_shape)}")
            check_nonempty("parameters", parameters)
        self.parameters = parameters
        self.inputs = _as_schedule("inputs", inputs)
        self.n_inputs = _infer_n_inputs(self.inputs, n_inputs)
        self._check_f()
        self._check_engine()
        #: True when f is (or calls) a fitted model without its certified error: a filter's
        #: sets then bound the fit, not the plant (filters warn; `diffsmf.pwl.as_system`)
        self.uncertified_fit = uncertified_fit(self.f)
        self.theta_schedule = _as_schedule("theta_schedule", theta_schedule)
        self.process_cov = _check_cov("process_cov", process_cov, self.n)
        self.measurement_cov = _check_cov("measurement_cov", measurement_cov, self.m)
        self.name = name

    def extra_repr(self) -> str:
        """``name, n, m, p`` and the sets, shown by ``print(system)``."""

        def kind(s: ConvexSet | None) -> str:
            return "None" if s is None else f"{type(s).__name__}(dim={s.dim})"

        parts = [
            f"name={self.name!r}", f"n={self.n}", f"m={self.m}", f"n_inputs={self.n_inputs}",
            f"x0_set={kind(self.x0_set)}", f"process_noise={kind(self.process_noise)}",
            f"measurement_noise={kind(self.measurement_noise)}",
        ]
        if self.parameters is not None:
            parts.append(f"parameters={kind(self.parameters)}")
        if self.process_cov is not None or self.measurement_cov is not None:
            parts.append("gaussian=True")
        if self.angle_outputs:
            parts.append(f"angle_outputs={list(self.angle_outputs)}")
        return ", ".join(parts)

    # ------------------------------------------------------------------ helpers
    def _check_f(self) -> None:
        """f on [1, n] (centre of X0, zero input, nominal theta) must give [1, n]."""
        x = self.x0_set.center.detach().unsqueeze(0)
        u = None if self.n_inputs == 0 else torch.zeros(1, self.n_inputs, dtype=x.dtype)
        th = None if self.parameters is None else self.parameters.center.detach().unsqueeze(0)
        try:
            with torch.no_grad():
                out = self.f(x, u, th)
        except Exception as exc:  # the user's function: say which call failed
            raise ValueError(
                f"f: f(x [1, {self.n}], u {'None' if u is None else list(u.shape)}, theta) at the "
                f"centre of x0_set failed ({type(exc).__name__}: {exc})"
                + ("; if f uses u, give n_inputs=p (or an inputs schedule)" if u is None else "")
            ) from exc
        if not isinstance(out, Tensor) or tuple(out.shape) != (1, self.n):
            got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
            raise ValueError(
                f"f: must map x [..., {self.n}] to [..., {self.n}] with torch ops; on x [1, "
                f"{self.n}] it returned {got}"
            )
        _check_model_call("f", lambda z: self.f(z, u, th), x, out)

    def _check_engine(self) -> None:
        """Capture ``f`` and ``h`` with the guarantee engine now, so that a model it cannot
        enclose (an op without a rule, a Python branch on the state, a cast) is reported when
        the system is built, naming the function; and require float64."""
        x = self.x0_set.center.detach().unsqueeze(0)
        u = None if self.n_inputs == 0 else torch.zeros(1, self.n_inputs, dtype=x.dtype)
        th = None if self.parameters is None else self.parameters.center.detach().unsqueeze(0)
        with torch.no_grad():
            check_dtype("f", self.f.fn if isinstance(self.f, Dynamics) else self.f,
                        self.f(x, u, th))
            check_dtype("h", self.h, self.h(x))
        points = _trial_points(self.x0_set)
        trial_enclosure("f", StepModel(self.f, u, th, "f"), points)
        register_row_model(self.h)
        trial_enclosure("h", self.h, points)

    @property
    def angle_mask(self) -> Tensor:
        """``[m]`` bool: True for the angle outputs (`angle_outputs`)."""
        return self._angle_mask

    def innovation(self, y: Tensor, y_pred: Tensor) -> Tensor:
        """``y - y_pred [..., m]`` with the angle outputs' components wrapped into
        ``[-pi, pi)`` (`wrap_angle`): the residual on the branch that the prediction
        picks, ``y' - y_pred`` for ``y' = y_pred + wrap(y - y_pred)``. Without angle outputs it
        is ``y - y_pred`` itself. Branch-free (no host sync)."""
        d = y - y_pred
        if not self.angle_outputs:
            return d
        mask = self._angle_mask.to(device=d.device)
        return torch.where(mask, wrap_angle(d), d)

    @property
    def theta_nominal(self) -> Tensor | None:
        """Midpoint of the parameter interval ``[q]`` (or ``None``)."""
        return None if self.parameters is None else self.parameters.center

    def input_at(self, k: int, batch: int) -> Tensor | None:
        """Input ``u_k`` of the ``inputs`` schedule as ``[batch, p]`` (or ``None``)."""
        if self.inputs is None:
            return None
        u = torch.as_tensor(self.inputs(k), dtype=self.x0_set.dtype, device=self.x0_set.device)
        u = u.reshape(-1) if u.dim() == 0 else u
        return u.expand(batch, u.shape[-1])

    def check_input(self, u: Tensor | None, batch_shape: tuple[int, ...] | torch.Size) -> (
        Tensor | None
    ):
        """Validate inputs against ``n_inputs`` -> ``u`` as a tensor of the system dtype (or None).

        Args:
            u: ``[*batch_shape, p]`` with ``p = n_inputs`` (``[B, p]`` for one step of
                ``predict``, ``[B, T, p]`` for ``forward`` / ``simulate``), or ``None``.
            batch_shape: the leading dims ``u`` must have exactly (no broadcasting).

        Raises:
            ValueError: message starting with ``u:`` when ``u`` is missing for ``p > 0``, given
                for ``p = 0``, has the wrong last dimension (``u[..., :1]`` for ``p = 2`` is
                refused, not broadcast), the wrong batch shape, or holds NaN / inf.
        """
        p = self.n_inputs
        if u is None and p == 0:  # the common case of systems without inputs
            return None
        batch_shape = tuple(int(b) for b in batch_shape)
        want = "[" + ", ".join(str(b) for b in (*batch_shape, p)) + "]"
        if u is None:
            if p > 0:
                raise ValueError(
                    f"u: system {self.name!r} has {p} input(s) (n_inputs={p}) but no u was "
                    f"given; pass u of shape {want}"
                )
            return None
        if p == 0:
            raise ValueError(
                f"u: system {self.name!r} has no inputs (n_inputs=0) but u was given; leave u "
                "out, or build the System with n_inputs=p"
            )
        if isinstance(u, Tensor):
            t = u.to(dtype=self.x0_set.dtype, device=self.x0_set.device)
        else:
            try:
                t = torch.as_tensor(u, dtype=self.x0_set.dtype, device=self.x0_set.device)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise ValueError(f"u: cannot be read as a tensor of numbers ({exc})") from exc
        if t.dim() == 0 or t.shape[-1] != p:
            raise ValueError(
                f"u: expected last dimension {p} (n_inputs of {self.name!r}), got shape "
                f"{tuple(t.shape)}; expected {want}"
            )
        if tuple(t.shape[:-1]) != batch_shape:
            raise ValueError(f"u: expected shape {want}, got {tuple(t.shape)}")
        if not torch.isfinite(t).all():
            bad = (~torch.isfinite(t)).nonzero()[0].tolist()
            raise ValueError(f"u: contains NaN or inf (first at index {tuple(bad)})")
        return t

    def theta_at(self, k: int, batch: int) -> Tensor | None:
        """True parameter at step k for ``simulate``, ``[batch, q]`` (or ``None``)."""
        if self.parameters is None:
            return None
        th = self.theta_nominal if self.theta_schedule is None else self.theta_schedule(k)
        th = torch.as_tensor(th, dtype=self.x0_set.dtype, device=self.x0_set.device)
        return th.expand(batch, th.shape[-1])

    def _check_x0(self, x0: object, batch: int) -> Tensor:
        """``x0`` of ``simulate`` as ``[batch, n]`` (``[n]`` or ``[1, n]`` broadcast)."""
        try:
            t = torch.as_tensor(x0, dtype=self.x0_set.dtype, device=self.x0_set.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ValueError(f"x0: cannot be read as a tensor of states ({exc})") from exc
        if t.dim() == 0 or t.shape[-1] != self.n or t.dim() > 2 or (
            t.dim() == 2 and t.shape[0] not in (1, batch)
        ):
            raise ValueError(f"x0: expected shape [{batch}, {self.n}] or [{self.n}], got "
                             f"{tuple(t.shape)}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError("x0: contains NaN or inf")
        return t.expand(batch, self.n)

    def forward(self, x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
        """One noise-free step ``f(x, u, theta)``; ``theta`` defaults to the nominal value."""
        if theta is None:
            theta = self.theta_nominal
        return self.f(x, u, theta)

    def rescaled(self, scale: Tensor | list[float], name: str | None = None) -> System:
        """The same system in the state coordinates ``x' = D x``, ``D = diag(scale)``.

        ``f'(x', u, theta) = D f(D^-1 x', u, theta)``, ``h'(x') = h(D^-1 x')``; ``x0_set`` and
        the process noise set are mapped by ``D`` (`scale_set`, same set types), the
        process covariance becomes ``D Q D``; the outputs, measurement noise, parameters and
        inputs are unchanged. A change of units (e.g. mol/L to mmol/L is ``scale = 1000`` on
        that state): a scale-invariant filter gives ``D`` times the sets of ``self`` on the
        same measurements (docs/which_filter.md).

        Args:
            scale: ``[n]`` positive finite factors.
            name: the new system's name (default ``self.name + "_rescaled"``).
        """
        d = torch.as_tensor(scale, dtype=self.x0_set.dtype, device=self.x0_set.device)
        if d.shape != (self.n,) or not bool(torch.isfinite(d).all()) or bool((d <= 0).any()):
            raise ValueError(f"scale: expected [{self.n}] positive finite factors, got {scale!r}")
        f, h = self.f, self.h

        def f2(x: Tensor, u: Tensor | None = None, theta: Tensor | None = None) -> Tensor:
            return f(x / d, u, theta) * d

        def h2(x: Tensor) -> Tensor:
            return h(x / d)

        W = None if self.process_noise is None else scale_set(self.process_noise, d)
        Q = None if self.process_cov is None else self.process_cov * d.unsqueeze(-1) * d
        out = System(
            f2, h2, scale_set(self.x0_set, d), W, self.measurement_noise, self.parameters,
            inputs=self.inputs, n_inputs=self.n_inputs, theta_schedule=self.theta_schedule,
            process_cov=Q, measurement_cov=self.measurement_cov,
            name=self.name + "_rescaled" if name is None else name,
            angle_outputs=self.angle_outputs,
        )
        for attr in ("horizon",):
            if hasattr(self, attr):
                setattr(out, attr, getattr(self, attr))
        return out

    # ------------------------------------------------------------------ simulation
    def simulate(
        self,
        steps: int,
        batch: int = 1,
        seed: int | None = 0,
        noise: str = "uniform",
        theta: Tensor | Callable[[int], Tensor] | None = None,
        x0: Tensor | None = None,
        u: Tensor | None = None,
        differentiable: bool = False,
    ) -> Trajectory:
        """Simulate ``batch`` trajectories of ``steps`` steps.

        Args:
            noise: ``"uniform"`` (points drawn inside the noise sets and X0) or ``"vertex"``
                (worst case: vertices / boundary points of the sets, new draw every step).
            theta: parameter schedule overriding ``theta_schedule`` (``k -> [q]`` or
                ``[B, q]``, or a tensor ``[T, q]`` / ``[B, T, q]``).
            x0: initial states ``[B, n]``; default drawn from ``x0_set`` like the noise.
            u: inputs ``[B, T, p]`` (``u[:, k]`` drives ``x_k -> x_{k+1}``), checked by
                `check_input`; overrides the ``inputs`` schedule. Required when
                ``n_inputs > 0`` and the system has no schedule.
            differentiable: ``False`` (default): the trajectory is data, with no autograd
                history, so it can feed any number of training steps even when ``f`` or
                ``h`` has learnable parameters (as ``torch.distributions``' ``sample``).
                ``True``: gradients flow from ``x`` and ``y`` to the model's parameters,
                ``theta``, ``x0`` and ``u`` (as ``rsample``; grad mode must be on).

        Returns:
            `Trajectory` with ``x [B, T+1, n]``, ``y [B, T, m]``, ``u``, ``theta``.
            The angle outputs (``angle_outputs``) of ``y`` are wrapped into ``[-pi, pi)``,
            as a sensor reports them.

        Raises:
            ValueError: a simulated state or measurement is NaN or inf (the model left its
                domain or diverged from this initial state); the message names the function
                (``f`` or ``h``), the first step and the trajectories where it happened.
                A trajectory is never returned with non-finite values.
        """
        if noise not in ("uniform", "vertex"):
            raise ValueError(f"noise: expected 'uniform' or 'vertex', got {noise!r}")
        for label, v in (("steps", steps), ("batch", batch)):
            if not is_int(v) or v < 1:
                raise ValueError(f"{label}: must be an integer >= 1, got {v!r}")
        steps, batch = int(steps), int(batch)
        if u is not None or (self.n_inputs > 0 and self.inputs is None):
            u_given = self.check_input(u, (batch, steps))
        else:
            u_given = None
        gen = torch.Generator(device=self.x0_set.device)
        gen.manual_seed(0 if seed is None else seed)

        def draw(s: ConvexSet | None, dim: int) -> Tensor:
            if s is None:
                return torch.zeros(batch, dim, dtype=self.x0_set.dtype, device=self.x0_set.device)
            pts = s.sample_extreme(batch, gen) if noise == "vertex" else s.sample(batch, gen)
            return pts.reshape(batch, dim)

        def gauss(cov: Tensor | None, dim: int) -> Tensor | float:
            if cov is None:
                return 0.0
            evals, evecs = torch.linalg.eigh(cov)  # PSD square root (Q may be singular)
            root = evecs * evals.clamp_min(0).sqrt().unsqueeze(-2)
            z = torch.randn(batch, dim, generator=gen, dtype=cov.dtype, device=cov.device)
            return z @ root.mT

        with torch.set_grad_enabled(differentiable and torch.is_grad_enabled()):
            schedule = _as_schedule("theta", theta) or self.theta_schedule
            x = draw(self.x0_set, self.n) if x0 is None else self._check_x0(x0, batch)
            xs, ys, us, ths = [x], [], [], []
            for k in range(steps):
                u = self.input_at(k, batch) if u_given is None else u_given[:, k]
                th = None
                if self.parameters is not None:
                    th = self.theta_nominal if schedule is None else schedule(k)
                    th = torch.as_tensor(th, dtype=x.dtype, device=x.device)
                    th = th.expand(batch, th.shape[-1])
                w = draw(self.process_noise, self.n) + gauss(self.process_cov, self.n)
                x = self.f(x, u, th) + w
                v = draw(self.measurement_noise, self.m) + gauss(self.measurement_cov, self.m)
                y = self.h(x) + v
                if self.angle_outputs:  # reported as a sensor does: wrapped into [-pi, pi)
                    y = torch.where(self._angle_mask, wrap_angle(y), y)
                xs.append(x)
                ys.append(y)
                us.append(u)
                ths.append(th)
            X, Y = torch.stack(xs, 1), torch.stack(ys, 1)
            _check_finite_trajectory(X, Y)
            return Trajectory(
                x=X,
                y=Y,
                u=None if self.n_inputs == 0 else torch.stack(us, 1),
                theta=None if self.parameters is None else torch.stack(ths, 1),
            )


def scale_set(S: ConvexSet, d: Tensor) -> ConvexSet:
    """``D S = {D x : x in S}`` for ``D = diag(d)``, ``d [n] > 0``, as the same set type.

    Interval, Ellipsoid, Zonotope, Parallelotope and ConstrainedZonotope are mapped exactly
    (bounds, shape ``D S D``, generators ``D G``); another set by ``S.linear_map(diag(d))``.
    """
    from diffsmf.sets import ConstrainedZonotope, Ellipsoid, Interval, Parallelotope, Zonotope

    d = torch.as_tensor(d, dtype=S.dtype, device=S.device)
    col = d.unsqueeze(-1)
    if isinstance(S, Interval):
        return Interval(S.lower * d, S.upper * d)
    if isinstance(S, Ellipsoid):
        return Ellipsoid(S.center * d, S.shape * col * d)
    if isinstance(S, Parallelotope):
        return Parallelotope(S.center * d, S.T * col)
    if isinstance(S, ConstrainedZonotope):
        return ConstrainedZonotope(S.center * d, S.generators * col, S.A, S.b)
    if isinstance(S, Zonotope):
        return Zonotope(S.center * d, S.generators * col)
    return S.linear_map(torch.diag(d))


def wrap_angle(a: Tensor) -> Tensor:
    """``a`` wrapped into ``[-pi, pi)`` (elementwise, differentiable almost everywhere)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def _check_angle_outputs(idx: object, m: int) -> tuple[int, ...]:
    """``angle_outputs`` as a sorted tuple of distinct output indices in ``[0, m)``."""
    if idx is None:
        return ()
    try:
        items = list(idx)  # type: ignore[call-overload]
    except TypeError:
        raise ValueError(
            f"angle_outputs: expected a list of output indices, got {idx!r}"
        ) from None
    for i in items:
        if not is_int(i) or not 0 <= int(i) < m:
            raise ValueError(
                f"angle_outputs: {i!r} is not an output index in [0, {m}) (h has m = {m} outputs)"
            )
    out = tuple(sorted(int(i) for i in items))
    if len(set(out)) != len(out):
        raise ValueError(f"angle_outputs: repeated index in {items}")
    return out


def _check_state_dims(f: Callable[..., Tensor], x0_set: ConvexSet, W: ConvexSet | None) -> None:
    """``x0_set`` and ``process_noise`` must have the same dimension; when they differ, the
    one that does not match ``f`` is named (``f`` is tried on a point of W's dimension)."""
    if not isinstance(W, ConvexSet) or W.dim == x0_set.dim:
        return
    n, nw = x0_set.dim, W.dim
    try:
        with torch.no_grad():
            out = f(torch.zeros(1, nw, dtype=x0_set.dtype), None, None)
        f_fits_w = isinstance(out, Tensor) and tuple(out.shape) == (1, nw)
    except Exception:  # f does not take the noise's dimension (or needs u / theta)
        f_fits_w = False
    if f_fits_w:
        raise ValueError(
            f"x0_set: has dim {n}, but process_noise has dim {nw} and f maps [1, {nw}] to "
            f"[1, {nw}]; give an initial set of dim {nw}"
        )
    raise ValueError(
        f"process_noise: must be a diffsmf set of dim {n} (the dim of x0_set), got dim {nw}"
    )


def _check_finite_trajectory(X: Tensor, Y: Tensor) -> None:
    """Raise a ``ValueError`` naming ``f`` / ``h``, the first step and the trajectories where
    the simulated states ``X [B, T+1, n]`` or measurements ``Y [B, T, m]`` are not finite."""
    badx = ~torch.isfinite(X).all(-1)  # [B, T+1]
    bady = ~torch.isfinite(Y).all(-1)  # [B, T]
    if not bool(badx.any() or bady.any()):
        return
    kx = int(badx.any(0).nonzero()[0]) if bool(badx.any()) else X.shape[1]
    ky = int(bady.any(0).nonzero()[0]) + 1 if bool(bady.any()) else X.shape[1]
    if kx <= ky:
        name, k, rows = "f", kx, badx[:, kx]
        what = f"the state x_{k} (f(x_{k - 1}) + w)"
    else:
        name, k, rows = "h", ky, bady[:, ky - 1]
        what = f"the measurement y_{k} (h(x_{k}) + v)"
    traj = rows.nonzero().reshape(-1).tolist()
    shown = ", ".join(map(str, traj[:10])) + (", ..." if len(traj) > 10 else "")
    raise ValueError(
        f"{name}: {what} is NaN or inf at step {k} in trajectory(ies) {shown} of {X.shape[0]}: "
        "the model left its domain or diverged; simulate never returns non-finite values "
        "(shrink x0_set or the noise bounds, or pass x0)"
    )


def _output_dim(h: Callable[[Tensor], Tensor], c: Tensor) -> int:
    """m from ``h`` on ``[1, n]`` (must return ``[1, m]``, m >= 1)."""
    try:
        with torch.no_grad():
            y = h(c.detach().unsqueeze(0))
    except Exception as exc:  # the user's function: say which call failed
        raise ValueError(
            f"h: h(x [1, {c.shape[-1]}]) at the centre of x0_set failed "
            f"({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(y, Tensor) or y.dim() != 2 or y.shape[0] != 1 or y.shape[1] < 1:
        got = tuple(y.shape) if isinstance(y, Tensor) else type(y).__name__
        raise ValueError(
            f"h: must map x [..., n] to [..., m] (keep the last dim, e.g. x[..., :1] rather than "
            f"x[..., 0]); on x [1, {c.shape[-1]}] it returned {got}"
        )
    _check_model_call("h", h, c.detach().unsqueeze(0), y)
    return int(y.shape[-1])


def _trial_points(x0_set: ConvexSet) -> list[Tensor]:
    """Points ``[1, n]`` where `trial_enclosure` runs the engine: the centre of ``x0_set``
    and an off-centre point of its hull (a numpy part of the model, recorded as the constant
    it had at the capture's example, shows where the state is not that example)."""
    c = x0_set.center.detach().reshape(1, -1)
    hull = x0_set.interval_hull()
    r = ((hull.upper - hull.lower).detach().reshape(1, -1) / 2).nan_to_num(0.0, 0.0, 0.0)
    n = c.shape[-1]
    pattern = torch.linspace(0.37, -0.29, n, dtype=c.dtype, device=c.device) if n > 1 else (
        torch.full((1,), 0.37, dtype=c.dtype, device=c.device))
    step = torch.where(r > 0, r, 1e-3 * (1.0 + c.abs())) * pattern
    return [c, c + step]


def _check_model_call(name: str, fn: Callable[[Tensor], Tensor], x: Tensor, out: Tensor) -> None:
    """``fn(x)`` (``out``, ``[1, k]``) must be finite and differentiable by autograd at ``x``.

    Every filter linearises ``f`` and ``h`` with autograd (`jacobian`),
    so a model written with numpy, ``.item()`` or ``.tolist()`` fails there; say so once, when
    the system is built, naming the function.
    """
    where = f"at the centre of x0_set ({name}(c) = {out.detach().reshape(-1).tolist()})"
    if not bool(torch.isfinite(out).all()):
        raise ValueError(f"{name}: returned NaN or inf {where}")
    try:
        with warnings.catch_warnings():  # a model that reads the state in Python (float(x))
            # is reported by the engine's own check, in one line, not by torch's warning
            warnings.filterwarnings("ignore", "Converting a tensor with requires_grad=True")
            J = jacobian(fn, x)
    except Exception as exc:  # the user's function: say which call failed
        raise ValueError(
            f"{name}: autograd cannot differentiate {name} {where} ({type(exc).__name__}: {exc});"
            " the filters linearise the model with autograd, so write it with torch operations"
            " (no numpy, .item() or .tolist())"
        ) from exc
    if not bool(torch.isfinite(J).all()):
        raise ValueError(f"{name}: its Jacobian is NaN or inf {where}")


def _infer_n_inputs(schedule: Callable[[int], Tensor] | None, n_inputs: int | None) -> int:
    """Input dimension from the ``inputs`` schedule (its value at k = 0) and/or ``n_inputs``."""
    if n_inputs is not None:
        if isinstance(n_inputs, bool) or not isinstance(n_inputs, int) or n_inputs < 0:
            raise ValueError(f"n_inputs: must be an integer >= 0, got {n_inputs!r}")
    if schedule is None:
        return 0 if n_inputs is None else n_inputs
    try:
        u0 = torch.as_tensor(schedule(0))
    except Exception as exc:  # a user callable: report which argument failed
        raise ValueError(f"inputs: calling inputs(0) failed ({type(exc).__name__}: {exc})") from exc
    p = 1 if u0.dim() == 0 else int(u0.shape[-1])
    if n_inputs is not None and n_inputs != p:
        raise ValueError(f"n_inputs: {n_inputs} does not match the inputs schedule (p = {p})")
    return p


def _check_cov(name: str, cov: Tensor | None, dim: int) -> Tensor | None:
    if cov is None:
        return None
    c = torch.as_tensor(cov, dtype=torch.float64)
    if c.shape != (dim, dim):
        raise ValueError(f"{name}: expected shape ({dim}, {dim}), got {tuple(c.shape)}")
    if not torch.allclose(c, c.mT) or torch.linalg.eigvalsh(c).min() < 0:
        raise ValueError(f"{name}: must be symmetric positive semidefinite")
    return c


def check_system(name: str, system: object) -> System:
    """``system`` itself, or a ``ValueError`` naming ``name`` when it is not a `System`
    (a `Trajectory` passed in its place, e.g. by swapped arguments, says so)."""
    if not isinstance(system, System):
        hint = (" (a Trajectory: pass the System it comes from, and the trajectory where a "
                "trajectory is asked for)") if isinstance(system, Trajectory) else ""
        raise ValueError(
            f"{name}: must be a diffsmf.System, got {type(system).__name__}{hint}"
        )
    return system
