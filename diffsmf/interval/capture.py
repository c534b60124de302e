"""Capture a torch model once as an ATen graph, then evaluate it in interval-jet arithmetic.

`capture` traces a model function with torch's own graph capture (``make_fx`` with
functionalisation and the core-ATen decompositions, so in-place ops, views and composite ops
such as ``einsum``, ``roll`` or ``nn.Linear`` reach the engine as a handful of core ops). The
graph is captured on inputs with one batch row (``x [1, n]``) and evaluated on any batch: a
`Program` maps every node to its rule in `diffsmf.interval.rules` and runs the
rules on enclosures whose extra leading dims (batch, tangents) the graph never sees. Nodes that
depend on constants only are evaluated once, at capture.

The capture reports, naming the model, what the engine cannot enclose: a Python branch on the
state (``if x > 0``), a cast of the state to another dtype, ``.detach()``, ``.item()`` or an
op without a rule. A model that needs an op the engine lacks, or a function the user can
enclose better by hand, registers an inclusion rule (`inclusion`), or, for an
``nn.Module``, defines ``interval_enclosure(lo, hi) -> (value_lo, value_hi, jac_lo, jac_hi)``.
"""

from __future__ import annotations

import functools
import itertools
import operator
import types
import weakref
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor, nn

from diffsmf.interval.arith import Stacked, deferred_checks, products_ok, stacking, tensor_of
from diffsmf.interval.box import Interval
from diffsmf.interval.errors import EngineError
from diffsmf.interval.jet import Jet, lead, move, point, register_seed
from diffsmf.interval.rounding import traced_program
from diffsmf.interval.rules import RULES, BoolBox, Ctx, register
from diffsmf.utils import tracing

__all__ = ["EngineError", "Program", "capture", "inclusion", "reachable_modules"]

aten = torch.ops.aten




# ----------------------------------------------------------------------------- leaves
_LEAVES: dict[int, Any] = {}
_LEAF_KEYS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_COUNTER = itertools.count()


def _leaf_key(obj: Any) -> int:
    try:
        key = _LEAF_KEYS.get(obj)
    except TypeError:
        key = None
    if key is None:
        key = next(_COUNTER)
        _LEAVES[key] = obj
        try:
            _LEAF_KEYS[obj] = key
        except TypeError:
            pass
    return key


@torch.library.custom_op("diffsmf::inclusion_leaf", mutates_args=())
def _leaf_op(x: Tensor, key: int) -> Tensor:
    return _call_leaf(_LEAVES[key], x).clone()


@_leaf_op.register_fake
def _leaf_fake(x: Tensor, key: int) -> Tensor:  # pragma: no cover - real-mode capture
    return _call_leaf(_LEAVES[key], torch.zeros_like(x, device="meta"))


def _call_leaf(obj: Any, x: Tensor) -> Tensor:
    fn = getattr(obj, "_diffsmf_raw", None)
    if fn is not None:
        return fn(x)
    for cls in type(obj).__mro__:  # a class patched while capturing: its own forward
        if cls in _CLASS_FORWARD:
            return _CLASS_FORWARD[cls](obj, x)
    return obj(x)


def inclusion(rule: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor, Tensor]]) -> Callable:
    """Decorator: give a function of ``x [..., d] -> [..., k]`` a hand-written inclusion rule.

    ``rule(lo, hi)`` takes a box ``lo, hi [..., d]`` and returns ``(value_lo, value_hi [..., k],
    jac_lo, jac_hi [..., k, d])``: an enclosure of the function's values over the box and of its
    (generalised) Jacobians. The engine then treats the function as one opaque operation with a
    first-order (mean-value) remainder. Outside the engine the function runs unchanged::

        def my_rule(lo, hi):
            ...
            return vlo, vhi, jlo, jhi

        @ds.interval.inclusion(my_rule)
        def saturate(x):
            return torch.tanh(x) * 2.0
    """

    if not callable(rule):
        raise ValueError(f"rule: must be a function (lo, hi) -> (value_lo, value_hi, jac_lo, "
                         f"jac_hi), got {type(rule).__name__}")

    def deco(fn: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
        if not callable(fn):
            raise ValueError(f"inclusion: decorates a function, got {type(fn).__name__}")

        class _Leaf:
            def __init__(self) -> None:
                self._diffsmf_raw = fn

            def interval_enclosure(self, lo: Tensor, hi: Tensor) -> tuple[Tensor, ...]:
                return rule(lo, hi)

        leaf = _Leaf()
        key = _leaf_key(leaf)

        def wrapper(x: Tensor) -> Tensor:
            if _CAPTURING:
                return _leaf_op(x, key)
            return fn(x)

        wrapper.__wrapped__ = fn  # type: ignore[attr-defined]
        wrapper.__name__ = getattr(fn, "__name__", "leaf")
        return wrapper

    return deco


_CAPTURING = False


def reachable_modules(fn: Any, depth: int = 3) -> list[nn.Module]:
    """nn.Modules reachable from ``fn``: itself, its submodules, closure cells and globals."""
    found: list[nn.Module] = []
    seen: set[int] = set()

    def visit(obj: Any, d: int) -> None:
        if id(obj) in seen or d < 0:
            return
        seen.add(id(obj))
        if isinstance(obj, nn.Module):
            found.extend(m for m in obj.modules() if id(m) not in {id(f) for f in found})
            return
        if isinstance(obj, types.MethodType):
            visit(obj.__self__, d - 1)
            visit(obj.__func__, d - 1)
            return
        if isinstance(obj, types.FunctionType):
            for cell in obj.__closure__ or ():
                try:
                    visit(cell.cell_contents, d - 1)
                except ValueError:
                    pass
            g = obj.__globals__
            for name in obj.__code__.co_names:
                if name in g and isinstance(g[name], (nn.Module, types.FunctionType)):
                    visit(g[name], d - 1)
            return
        if isinstance(obj, (list, tuple)):
            for o in obj:
                visit(o, d - 1)
        elif callable(obj) and hasattr(obj, "__dict__"):
            for o in vars(obj).values():
                if isinstance(o, (nn.Module, types.FunctionType, types.MethodType)):
                    visit(o, d - 1)

    visit(fn, depth)
    return found


#: while capturing: the original ``forward`` of every module class with ``interval_enclosure``
_CLASS_FORWARD: dict[type, Callable[..., Tensor]] = {}


def _leaf_classes() -> list[tuple[type, Callable[..., Tensor], bool]]:
    """``(class, its forward, whether the class defines it itself)`` for the loaded
    ``nn.Module`` subclasses with ``interval_enclosure`` whose ``forward`` is their own or
    inherited from a class without one (``class MyLinear(nn.Linear)`` with a rule); a
    subclass that inherits both from a patched class is served by that class's patch."""
    found = []
    todo = list(nn.Module.__subclasses__())
    seen: set[type] = set()
    while todo:
        cls = todo.pop()
        if cls in seen:
            continue
        seen.add(cls)
        todo.extend(cls.__subclasses__())
        if not callable(getattr(cls, "interval_enclosure", None)):
            continue
        owner = next(k for k in cls.__mro__ if "forward" in vars(k))
        if owner is cls or not callable(getattr(owner, "interval_enclosure", None)):
            found.append((cls, vars(owner)["forward"], owner is cls))
    return found


@contextmanager
def _patched_leaves(fn: Any):
    """While capturing, modules with ``interval_enclosure`` become one opaque leaf op:
    those reachable from ``fn`` (instances, also with an ``interval_enclosure`` of their
    own), and every instance of a module class that defines one, wherever the model keeps
    it (a dict, a list, an attribute of a plain object, a function that ``f`` calls)."""
    global _CAPTURING
    patched = []
    inner: set[int] = set()  # submodules of a leaf run inside it, unpatched
    for m in reachable_modules(fn):
        if hasattr(m, "interval_enclosure") and id(m) not in inner:
            inner.update(id(s) for s in m.modules())
            key = _leaf_key(m)
            raw = m.forward
            m._diffsmf_raw = raw  # type: ignore[attr-defined]
            m.forward = _leaf_forward(key)  # type: ignore[method-assign]
            patched.append((m, raw))
    classes = _leaf_classes()
    for cls, forward, _own in classes:
        _CLASS_FORWARD[cls] = forward
        cls.forward = _class_leaf_forward  # type: ignore[method-assign]
    _CAPTURING = True
    try:
        yield
    finally:
        _CAPTURING = False
        for cls, forward, own in classes:
            _CLASS_FORWARD.pop(cls)
            if own:
                cls.forward = forward  # type: ignore[method-assign]
            else:
                del cls.forward
        for m, _raw in patched:
            del m.forward
            del m._diffsmf_raw


def _class_leaf_forward(self: nn.Module, x: Tensor, *rest: Any, **kwargs: Any) -> Tensor:
    """``forward`` of a module class with ``interval_enclosure`` while capturing: one leaf op
    for a call on the state alone; a call with other arguments (an input) is traced
    through its own ``forward``, as outside the capture."""
    if any(r is not None for r in (*rest, *kwargs.values())):
        for cls in type(self).__mro__:
            if cls in _CLASS_FORWARD:
                return _CLASS_FORWARD[cls](self, x, *rest, **kwargs)
    return _leaf_forward(_leaf_key(self))(x)


def _leaf_forward(key: int) -> Callable[..., Tensor]:
    def forward(x: Tensor, *rest: Any, **kwargs: Any) -> Tensor:
        if any(r is not None for r in (*rest, *kwargs.values())):
            raise EngineError("a module with interval_enclosure is enclosed in its first "
                              "argument only; its other arguments (inputs, parameters) must be "
                              "None")
        return _leaf_op(x, key)

    return forward


@register(torch.ops.diffsmf.inclusion_leaf, category="extension")
def _leaf_rule(ctx: Ctx, x: Any, key: int) -> Any:
    obj = _LEAVES[key]
    if not isinstance(x, Jet):
        return _call_leaf(obj, x)
    vlo, vhi, jlo, jhi = obj.interval_enclosure(x.val.lower, x.val.upper)
    val = Interval._make(vlo, vhi)
    grad = hess = None
    if x.order >= 1 and x.grad is not None:
        J = Interval._make(jlo.unsqueeze(0), jhi.unsqueeze(0))  # [1, ..., k, d]
        g = Interval._make(x.grad.lower.unsqueeze(-1), x.grad.upper.unsqueeze(-1))
        grad = J.__matmul__(g)  # [n, ..., k, 1]
        grad = Interval._make(grad.lower.squeeze(-1), grad.upper.squeeze(-1))
    if x.order >= 2 and grad is not None:
        # affine over the box where the Jacobian enclosure is a point (one linear piece)
        flat = ((jlo == jhi).all(-1)) & _affine_input(x)
        inf = torch.full((x.n, x.n, *vlo.shape), torch.inf, dtype=vlo.dtype, device=vlo.device)
        z = torch.zeros_like(inf)
        hess = Interval._make(torch.where(flat, z, -inf), torch.where(flat, z, inf))
    return x.like(val, grad, hess)


def _affine_input(x: Jet) -> Tensor | bool:
    """True where the leaf's input is affine in the variables (its Hessian is 0)."""
    if x.hess is None:
        return True
    z = (x.hess.lower == 0) & (x.hess.upper == 0)
    return z.flatten(0, 1).all(0).all(-1, keepdim=True)


# ----------------------------------------------------------------------------- capture
@functools.lru_cache(maxsize=1)
def _decompositions() -> dict[Any, Callable]:
    from torch._decomp import core_aten_decompositions

    table = dict(core_aten_decompositions())
    keep = {op for op in table if op.overloadpacket in RULES}  # ops with a rule of their own
    keep |= {op for op in table if str(op.overloadpacket) in ("aten.softplus",)}
    for op in keep:
        table.pop(op, None)
    return table


def capture(fn: Callable[..., Tensor], example: Sequence[Tensor], name: str) -> Program:
    """Capture ``fn(*example)`` (one batch row each, e.g. ``x [1, n]``) as a `Program`.

    Raises:
        EngineError: naming ``name``, the op and what to do, when the model branches on the
            state in Python, casts it, calls ``.item()``, or uses an op without a rule.
    """
    from torch.func import functionalize
    from torch.fx.experimental.proxy_tensor import make_fx

    ex = [e.detach() for e in example]
    try:
        with _patched_leaves(fn):
            gm = make_fx(functionalize(fn, remove="mutations_and_views"),
                         decomposition_table=_decompositions(), tracing_mode="real",
                         _allow_non_fake_inputs=True)(*ex)
    except RuntimeError as exc:
        msg = str(exc)
        if "_local_scalar_dense" in msg or "data-dependent" in msg:
            raise EngineError(
                f"{name}: the model reads a value of the state in Python (an `if` on the state, "
                "`.item()`, `.tolist()` or `float(x)`); write branches with torch.where, "
                "torch.clamp, torch.maximum or relu so the engine can enclose them"
            ) from exc
        raise EngineError(f"{name}: the model could not be captured ({msg.splitlines()[0]})") \
            from exc
    gm.graph.eliminate_dead_code()
    return Program(gm, name)


class _Slot:
    """A reference to the value of an earlier node (a slot of the evaluation list)."""

    __slots__ = ("i",)

    def __init__(self, i: int) -> None:
        self.i = i


def _template(a: Any, slot: dict) -> Any:
    """Node arguments with every fx Node replaced by its `_Slot` (so that evaluation
    touches no fx object: it traces under torch.compile)."""
    if isinstance(a, torch.fx.Node):
        return _Slot(slot[a])
    if isinstance(a, (list, tuple)):
        return type(a)(_template(b, slot) for b in a)
    return a


def _fill(a: Any, env: list) -> Any:
    if isinstance(a, _Slot):
        return env[a.i]
    if isinstance(a, (list, tuple)):
        return type(a)(_fill(b, env) for b in a)
    return a


class Program:
    """A captured model graph, evaluated on enclosures by the per-op rules."""

    def __init__(self, gm: torch.fx.GraphModule, name: str) -> None:
        self.name = name
        self.ops: list[str] = []
        self._slot: dict[torch.fx.Node, int] = {}
        self._init: list[Any] = []  # constants, None for computed slots
        self._inputs: list[int] = []
        #: (slot, rule, ctx, args template, kwargs template)
        self.steps: list[tuple[int, Callable, Ctx, Any, dict]] = []
        const: set[torch.fx.Node] = set()
        for node in gm.graph.nodes:
            if node.op == "placeholder":
                self._inputs.append(self._new(node, None))
            elif node.op == "get_attr":
                t = getattr(gm, node.target)
                self._new(node, t)
                if not (isinstance(t, Tensor) and t.requires_grad):
                    const.add(node)
            elif node.op == "call_function":
                self._add(node, const)
            elif node.op == "output":
                self._output = _template(node.args[0], self._slot)
                self.out_rank = _rank(node.args[0])
        del self._slot

    def _new(self, node: torch.fx.Node, value: Any) -> int:
        self._slot[node] = len(self._init)
        self._init.append(value)
        return self._slot[node]

    def _add(self, node: torch.fx.Node, const: set) -> None:
        is_const = all(d in const for d in node.all_input_nodes)
        if node.target is operator.getitem:
            rule: Callable = _getitem
            ctx = Ctx((None,), 0, "getitem")
        else:
            packet = getattr(node.target, "overloadpacket", node.target)
            opname = str(packet).removeprefix("aten.")
            rule = RULES.get(packet)
            for suffix in ("_copy", "_"):  # functionalised view ops, in-place variants
                if rule is None and opname.endswith(suffix):
                    rule = RULES.get(getattr(aten, opname.removesuffix(suffix), None))
            if rule is None and is_const:
                rule = _no_rule
            if rule is None:
                raise EngineError(
                    f"{self.name}: the operation {opname} has no inclusion rule; rewrite that "
                    "part of the model with supported torch ops (see the 'Writing models' docs "
                    "page) or register a rule with diffsmf.interval.inclusion"
                )
            self.ops.append(opname)
            ranks = tuple(_rank(a) if isinstance(a, torch.fx.Node) else None for a in node.args)
            shapes = tuple(_shape(a) for a in node.args)
            ctx = Ctx(ranks, _rank(node), opname, shapes)
        args = _template(node.args, self._slot)
        kwargs = {k: _template(v, self._slot) for k, v in node.kwargs.items()}
        if is_const:  # constant subgraph: evaluate once now
            try:
                value = node.target(*_fill(args, self._init), **_fill(kwargs, self._init))
                self._new(node, value)
                const.add(node)
                return
            except Exception:  # noqa: BLE001 - evaluate it per call instead
                pass
        self.steps.append((self._new(node, None), rule, ctx, args, kwargs))

    def _steps(self, env: list) -> None:
        for slot, rule, ctx, args, kwargs in self.steps:
            env[slot] = rule(ctx, *_fill(args, env), **_fill(kwargs, env))

    def run(self, inputs: Sequence[Any]) -> Any:
        """Evaluate on ``inputs`` (one per placeholder: a Jet, a Tensor, in capture order)."""
        env = list(self._init)
        for i, value in zip(self._inputs, inputs, strict=True):
            env[i] = value
        if tracing() and TRACED_STACKING:  # stacked; each product with its own NaN rule
            prev = stacking(True)
            try:
                with traced_program():
                    self._steps(env)
            finally:
                stacking(prev)
        elif tracing() or not _small(inputs):
            self._steps(env)
        else:  # both bounds of an enclosure in one tensor, one NaN check for all products
            prev = stacking(True)
            checks: list[Tensor] = []
            try:
                with deferred_checks(checks):
                    self._steps(env)
            finally:
                stacking(prev)
            if not products_ok(checks):  # 0 * inf met: again, each product checked
                env = list(self._init)
                for i, value in zip(self._inputs, inputs, strict=True):
                    env[i] = value
                self._steps(env)
        out = _fill(self._output, env)
        if isinstance(out, BoolBox):
            raise EngineError(f"{self.name}: the model returns a comparison")
        return out


#: while traced, programs are evaluated in stacked mode at every size: both bounds of an
#: enclosure in one tensor, so that a jet's graph holds about 40 % fewer operations
#: (spring_damper's HSNSMF step: the interval jet of its model 481 -> 300 of 1,457 -> 1,282
#: traced operations; cstr's MSZM step 6,399 -> 4,584), with the same bounds (the products
#: take their branch-free rule for 0 * inf and NaN operands, `arith._mul_stacked_general`)
TRACED_STACKING = True

#: boxes of at most this many elements are evaluated in stacked mode (fewer ops; for larger
#: ones separate bounds are faster: no stacking copies)
STACKED_MAX = 2048


def stacks(lo: Tensor, hi: Tensor) -> bool:
    """Whether an input box with these bounds is evaluated stacked: while traced, always
    (`TRACED_STACKING`); eagerly, small boxes on the CPU (the deferred product check reads the
    host once per evaluation)."""
    if tracing():
        return TRACED_STACKING and lo.shape == hi.shape and hi is not lo
    return (lo.shape == hi.shape and hi is not lo
            and lo.numel() <= STACKED_MAX and lo.device.type == "cpu")


def _small(inputs: Sequence[Any]) -> bool:
    for j in inputs:
        if isinstance(j, Jet):
            v = j.val
            if (v.both if isinstance(v, Stacked) else v.lower).numel() > 2 * STACKED_MAX:
                return False
    return True


def _getitem(ctx: Ctx, seq: Any, i: int) -> Any:
    return seq[i]


def _no_rule(ctx: Ctx, *args: Any, **kwargs: Any) -> Any:
    raise EngineError(f"the constant operation {ctx.name} could not be evaluated at capture")


def _shape(node: Any) -> tuple[int, ...] | None:
    if isinstance(node, torch.fx.Node):
        v = node.meta.get("val")
        if isinstance(v, Tensor):
            return tuple(int(d) for d in v.shape)
    return None


def _rank(node: Any) -> int:
    if isinstance(node, torch.fx.Node):
        v = node.meta.get("val")
        if isinstance(v, Tensor):
            return v.dim()
        if isinstance(v, (int, float, bool)):
            return 0
    return 0


# ----------------------------------------------------------------------------- evaluation
def seed(box: Interval, order: int, n_total: int, offset: int) -> Jet:
    """The jet of an input box ``[*E, 1, d]`` whose variables are ``offset .. offset + d``."""
    if not isinstance(box, Stacked) and stacks(box.lower, box.upper):
        box = Interval._pair(torch.stack([box.lower, box.upper]))  # both bounds in one op
    lo = tensor_of(box)
    rank = lo.dim() - isinstance(box, Stacked)
    d = lo.shape[-1]
    if order == 0:
        return Jet(box, None, None, 0, n_total)
    key = (n_total, d, offset, rank, lo.dtype, lo.device)
    g = _SEEDS.get(key)
    if g is None:
        eye = torch.zeros(n_total, d, dtype=lo.dtype, device=lo.device)
        eye[offset:offset + d] = torch.eye(d, dtype=lo.dtype, device=lo.device)
        g = eye.reshape(n_total, *([1] * (rank - 1)), d)
        if not tracing():
            _SEEDS[key] = g
            register_seed(g)
    return Jet(box, point(g), None, order, n_total)


#: seed gradients (constants, made once per shape eagerly)
_SEEDS: dict = {}


def to_trailing(out: Any, order: int, like: Tensor, n: int, row: bool) -> Jet:
    """The program's result (leading tangents; a batch row dim when ``row``) -> value ``[*E, k]``,
    gradient ``[*E, k, n]``, Hessian ``[*E, k, n, n]`` (None when structurally zero)."""
    if not isinstance(out, Jet):
        t = torch.as_tensor(out, dtype=like.dtype, device=like.device)
        out = Jet(point(t), None, None, order, n)

    def sq(t: Interval | None) -> Interval | None:
        if t is None or not row:
            return t
        return move(t, lambda x: x.squeeze(-2))

    val, grad, hess = sq(out.val), sq(out.grad), sq(out.hess)
    if grad is not None:
        grad = lead(grad, lambda x, k: x.movedim(k, -1))
    if hess is not None:
        hess = lead(hess, lambda x, k: x.movedim((k, k + 1), (-2, -1)))
    return Jet(val, grad, hess, order, n)
