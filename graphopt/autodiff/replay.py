"""A block's linearisation as a program of NumPy calls: traced once, replayed per block.

The tape (:mod:`graphopt.autodiff.tape`) costs Python per recorded operation: on 100,000
BAL edges in blocks of 12,500, the recording and the reverse pass spend ~0.3 ms of Python per
block on ~140 NumPy calls whose arithmetic takes about as long. The operations are the same in
every block (the error's code, the vertices' structure and the shapes do not change), so one
block is *traced*: its inputs (the block's estimates, derived values, measurements, the
per-vertex jets, the Jacobian rows) are viewed as :class:`Traced` arrays, which record every
NumPy call made on them — by the error, the tape and the reverse pass alike — as a step of a
:class:`Program`. Later blocks run the steps on their own inputs (no jets, no tape, each
intermediate dropped after its last use).

A trace is kept only if it is closed: block data read into Python (a truth value, a float, an
index: a data-dependent branch) raises :class:`Poisoned`, and so does an operand that is a
view of traced data made without the tracer (``np.asarray``), an unrecorded traced array or a
write into a plain array. A copy made outside NumPy's dispatch (``np.array`` of a traced
array, then assigned into a plain array) cannot be seen; the caller therefore checks each new
program once against the tape on a block other than the traced one (bit for bit) before
trusting it (:mod:`graphopt.autodiff.jacobians`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from contextlib import contextmanager
from typing import Any

import numpy as np

__all__ = ["Poisoned", "Program", "Traced", "Tracer", "active", "forward_rule", "tracing"]

_LOCAL = threading.local()
_view = np.ndarray.view


class Poisoned(Exception):
    """The traced computation depends on block data in a way a program cannot replay."""


def active() -> Tracer | None:
    """The tracer recording in this thread, if any."""
    return getattr(_LOCAL, "tracer", None)


def forward_rule(what: str) -> None:
    """Called where the jets compute derivatives forward (or fill containers): there plain
    arrays (``np.zeros``) receive block data by assignment, which a trace cannot see."""
    if getattr(_LOCAL, "tracer", None) is not None:
        raise Poisoned(what)


def _tracer() -> Tracer:
    t = active()
    if t is None:  # a traced array used after its trace (kept by a cache): not replayable
        raise Poisoned("a traced array outside its trace")
    return t


class Traced(np.ndarray):
    """An array whose NumPy operations the active :class:`Tracer` records."""

    # Another type's protocol (a jet's) goes first: it computes on the traced values itself.
    def __array_ufunc__(self, ufunc: np.ufunc, method: str, *inputs: Any, **kw: Any) -> Any:
        for a in inputs + tuple(kw.get("out", ())):
            if hasattr(a, "__array_ufunc__") and not isinstance(a, np.ndarray):
                return NotImplemented
        return _tracer().ufunc(ufunc, method, inputs, kw)

    def __array_function__(self, func: Any, types: Any, args: Any, kwargs: Any) -> Any:
        if not all(issubclass(t, np.ndarray) for t in types):
            return NotImplemented
        return _tracer().function(func, args, kwargs)

    def __getitem__(self, key: Any) -> Any:
        return _tracer().getitem(self, key)

    def __setitem__(self, key: Any, value: Any) -> None:
        _tracer().setitem(self, key, value)

    def _escape(self, *args: Any, **kwargs: Any) -> Any:
        raise Poisoned("block data read into Python (a data-dependent branch or scalar)")

    __bool__ = __float__ = __int__ = __index__ = __complex__ = _escape
    item = tolist = tobytes = __iter__ = _escape

    @property
    def T(self) -> Any:  # noqa: N802 - ndarray's name
        return _tracer().method(self, "transpose", (), {})


def _method(name: str) -> Callable[..., Any]:
    def call(self: Traced, *args: Any, **kwargs: Any) -> Any:
        return _tracer().method(self, name, args, kwargs)
    call.__name__ = name
    return call


for _name in ("reshape", "transpose", "swapaxes", "copy", "ravel", "flatten", "squeeze",
              "astype", "sum", "mean", "prod", "max", "min", "any", "all", "dot", "take",
              "clip"):
    setattr(Traced, _name, _method(_name))

#: Functions of the shapes only (their results are not data).
_METADATA = {np.shape, np.ndim, np.size, np.result_type, np.may_share_memory,
             np.shares_memory}

# A reference to a step's operand: (0, slot) a traced array, (1, type, [refs]) a list or
# tuple, (2, {key: ref}) a dict, (3, value) a constant.
Ref = tuple[Any, ...]


class Tracer:
    """Records the NumPy calls on :class:`Traced` arrays as steps over numbered slots."""

    def __init__(self) -> None:
        self.steps: list[tuple[Any, ...]] = []
        self.slots: dict[int, int] = {}
        self.keep: list[np.ndarray] = []  # (ids stay unique while the trace lives)
        self.inputs = 0

    def input(self, a: np.ndarray) -> Traced:
        """Slot ``inputs`` (in call order): ``a`` as a traced array."""
        if self.steps or self.inputs != len(self.keep):
            raise RuntimeError("inputs come before the first step")
        self.inputs += 1
        return self._new(a)

    def slot(self, a: Any) -> int:
        """The slot of a traced array (:class:`Poisoned` for one made without the tracer)."""
        s = self.slots.get(id(a)) if type(a) is Traced else None
        if s is None:
            raise Poisoned("an array made from traced data without the tracer")
        return s

    def _new(self, a: np.ndarray) -> Traced:
        t = _view(a, Traced)
        self.slots[id(t)] = len(self.keep)
        self.keep.append(t)
        return t

    def _ref(self, x: Any) -> Ref:
        if isinstance(x, np.ndarray):
            if type(x) is Traced:
                return (0, self.slot(x))
            b = x.base  # a plain view of traced data (np.asarray): its contents would go stale
            while b is not None:
                if type(b) is Traced:
                    raise Poisoned("a plain view of traced data")
                b = getattr(b, "base", None)
            return (3, x)
        if type(x) in (list, tuple):
            return (1, type(x), [self._ref(e) for e in x])
        if type(x) is dict:
            return (2, {k: self._ref(v) for k, v in x.items()})
        return (3, x)

    def _raw(self, x: Any) -> Any:
        if type(x) is Traced:
            return _view(x, np.ndarray)
        if type(x) in (list, tuple):
            return type(x)(self._raw(e) for e in x)
        if type(x) is dict:
            return {k: self._raw(v) for k, v in x.items()}
        return x

    def _result(self, r: Any) -> tuple[Any, int | None]:
        if isinstance(r, np.ndarray | np.generic):  # (a 0-d result stays traced: no escape)
            t = self._new(np.asarray(r) if isinstance(r, np.generic) else r)
            return t, self.slots[id(t)]
        if isinstance(r, tuple | list) and any(isinstance(e, np.ndarray) for e in r):
            raise Poisoned("a NumPy call returning several arrays")
        return r, None  # shapes and other metadata

    def ufunc(self, uf: np.ufunc, method: str, inputs: tuple[Any, ...],
              kw: dict[str, Any]) -> Any:
        """A ufunc call on traced operands (``out=``: written in place, as recorded)."""
        f = uf if method == "__call__" else getattr(uf, method)
        refs = self._ref(inputs), self._ref(kw)
        out = kw.get("out")
        res = f(*self._raw(inputs), **self._raw(kw))
        if out is not None:
            o = out[0] if type(out) is tuple else out
            if len(out if type(out) is tuple else (o,)) != 1 or type(o) is not Traced:
                raise Poisoned("a ufunc writing into a plain array")
            self.steps.append(("call", f, refs[0], refs[1], None))
            return o
        t, s = self._result(res)
        self.steps.append(("call", f, refs[0], refs[1], s))
        return t

    def function(self, func: Any, args: tuple[Any, ...], kwargs: dict[str, Any]) -> Any:
        """A NumPy function (``__array_function__``) with traced arguments."""
        if "out" in kwargs:
            raise Poisoned(f"np.{func.__name__}(out=...) on traced data")
        refs = self._ref(args), self._ref(kwargs)
        r = func(*self._raw(args), **self._raw(kwargs))
        if func in _METADATA:
            return r
        t, s = self._result(r)
        if s is None:  # (a count, a list of indices: numbers from the data)
            raise Poisoned(f"np.{func.__name__} returned no array")
        self.steps.append(("call", func, refs[0], refs[1], s))
        return t

    def getitem(self, a: Traced, key: Any) -> Any:
        """``a[key]`` (a view or a gather)."""
        src, k = self.slot(a), self._ref(key)
        t, s = self._result(_view(a, np.ndarray)[self._raw(key)])
        self.steps.append(("get", src, k, s))
        return t

    def setitem(self, a: Traced, key: Any, value: Any) -> None:
        """``a[key] = value``."""
        step = ("set", self.slot(a), self._ref(key), self._ref(value))
        _view(a, np.ndarray)[self._raw(key)] = self._raw(value)
        self.steps.append(step)

    def method(self, a: Traced, name: str, args: tuple[Any, ...], kw: dict[str, Any]) -> Any:
        """An ndarray method without NumPy dispatch (``reshape``, ``copy``, …)."""
        step = (self.slot(a), self._ref(args), self._ref(kw))
        t, s = self._result(getattr(_view(a, np.ndarray), name)(*self._raw(args),
                                                                  **self._raw(kw)))
        if s is None:
            raise Poisoned(f"ndarray.{name} returned no array")
        self.steps.append(("method", name, *step, s))
        return t


@contextmanager
def tracing(tracer: Tracer) -> Any:
    """Make ``tracer`` the one :class:`Traced` arrays report to (this thread)."""
    before = active()
    _LOCAL.tracer = tracer
    try:
        yield tracer
    finally:
        _LOCAL.tracer = before


# --- the program ------------------------------------------------------------------------------

def _getter(r: Ref) -> Callable[[list[Any]], Any]:
    kind = r[0]
    if kind == 0:
        s = r[1]
        return lambda S: S[s]
    if kind == 3:
        c = r[1]
        return lambda S: c
    if kind == 1:
        typ, parts = r[1], [_getter(p) for p in r[2]]
        return lambda S: typ(p(S) for p in parts)
    items = [(k, _getter(v)) for k, v in r[1].items()]
    return lambda S: {k: p(S) for k, p in items}


def _slots(r: Ref, acc: list[int]) -> None:
    if r[0] == 0:
        acc.append(r[1])
    elif r[0] == 1:
        for p in r[2]:
            _slots(p, acc)
    elif r[0] == 2:
        for p in r[1].values():
            _slots(p, acc)


def _compile(step: tuple[Any, ...]) -> tuple[Callable[[list[Any]], None], list[int]]:
    """One step as a call on the slot list, and the slots it reads or writes."""
    used: list[int] = []
    kind = step[0]
    if kind == "call":
        _, f, a, k, o = step
        _slots(a, used)
        _slots(k, used)
        parts = a[2]
        if not k[1] and len(parts) == 2 and o is not None and parts[0][0] == 0:
            i, (kb, b) = parts[0][1], parts[1]  # f(slot, slot | constant): the common case
            run = ((lambda S: S.__setitem__(o, f(S[i], S[b]))) if kb == 0 else
                   (lambda S: S.__setitem__(o, f(S[i], b))) if kb == 3 else None)
            if run is not None:
                return run, used + [o]
        A, K = _getter(a), _getter(k)
        if o is None:
            return (lambda S: f(*A(S), **K(S))), used
        return (lambda S: S.__setitem__(o, f(*A(S), **K(S)))), used + [o]
    if kind == "get":
        _, s, k, o = step
        _slots(k, used)
        if k[0] == 3:
            key = k[1]
            return (lambda S: S.__setitem__(o, S[s][key])), used + [s, o]
        K = _getter(k)
        return (lambda S: S.__setitem__(o, S[s][K(S)])), used + [s, o]
    if kind == "set":
        _, s, k, v = step
        _slots(k, used)
        _slots(v, used)
        K, V = _getter(k), _getter(v)
        return (lambda S: S[s].__setitem__(K(S), V(S))), used + [s]
    _, name, s, a, k, o = step
    _slots(a, used)
    _slots(k, used)
    A, K = _getter(a), _getter(k)
    return (lambda S: S.__setitem__(o, getattr(S[s], name)(*A(S), **K(S)))), used + [s, o]


class Program:
    """A trace's steps as calls on a list of slots, each slot dropped after its last use
    (the block's temporaries are freed as the tape's are: a block's memory stays in the CPU
    caches).

    Args:
        tracer: The finished trace.
        outputs: Slots to return (kept to the end).
    """

    def __init__(self, tracer: Tracer, outputs: list[int]) -> None:
        self.inputs, self.size, self.outputs = tracer.inputs, len(tracer.keep), outputs
        compiled = [_compile(s) for s in tracer.steps]
        last: dict[int, int] = {}
        for i, (_, used) in enumerate(compiled):
            for s in used:
                last[s] = i
        drops: list[list[int]] = [[] for _ in compiled]
        for s, i in last.items():
            if s >= self.inputs and s not in outputs:
                drops[i].append(s)
        self.calls: list[Callable[[list[Any]], None]] = []
        for (run, _), d in zip(compiled, drops, strict=True):
            self.calls.append(run)
            if d:
                self.calls.append(_dropper(tuple(d)))
        self.steps = len(compiled)

    def run(self, inputs: list[Any]) -> list[Any]:
        """The output slots' arrays for a block's ``inputs`` (as traced, in order)."""
        S: list[Any] = list(inputs) + [None] * (self.size - self.inputs)
        with np.errstate(all="ignore"):  # (as the traced block: its warnings were seen once)
            for call in self.calls:
                call(S)
        return [S[o] for o in self.outputs]


def _dropper(slots: tuple[int, ...]) -> Callable[[list[Any]], None]:
    def drop(S: list[Any]) -> None:
        for s in slots:
            S[s] = None
    return drop
