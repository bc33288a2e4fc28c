"""NumPy functions on :class:`~graphopt.autodiff.jet.Jet` (``__array_function__``).

Each function in :data:`HANDLED` maps the value's operation to the tangent's: the same call with
every axis argument shifted by one (the tangent axis is first), or, for the bilinear ones
(``einsum``, ``dot``, ``tensordot``, ``cross``), one call per jet operand with its tangent in
place of its value. Functions that only read values (``argmax``, ``shape``, ``isclose``, …)
return the plain result. A function not listed raises :class:`~graphopt.autodiff.jet.JetError`
naming it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

import graphopt.autodiff.tape as tape
import graphopt.autodiff.tape_ops as tape_ops
from graphopt.autodiff.jet import HOOKS, Jet, JetError, Tape, full, parts
from graphopt.autodiff.replay import forward_rule
from graphopt.autodiff.ufuncs import write_out

__all__ = ["HANDLED", "apply_function"]

HANDLED: dict[Any, Callable[..., Any]] = {}


def _fname(func: Any) -> str:
    mod = getattr(func, "__module__", "numpy") or "numpy"
    prefix = "np.linalg." if "linalg" in mod else "np."
    return prefix + getattr(func, "__name__", str(func))


def apply_function(func: Any, types: Any, args: tuple[Any, ...], kwargs: dict[str, Any],
                   like: Jet | None = None) -> Any:
    """Dispatch ``func(*args, **kwargs)`` to its jet implementation.

    Args:
        func: The NumPy function.
        types: The argument types NumPy found.
        args: Positional arguments.
        kwargs: Keyword arguments.
        like: The jet of a ``like=`` argument (array creation), if any.

    Raises:
        JetError: a function without a derivative rule, naming it.
    """
    if not all(issubclass(t, Jet | np.ndarray) for t in types):
        return NotImplemented
    impl = HANDLED.get(func)
    if impl is None:
        raise JetError(_fname(func))
    out = impl(like, *args, **kwargs) if func in _CREATION else impl(*args, **kwargs)
    if type(out) is Jet and out._tape is None:  # derivatives formed forward
        forward_rule(_fname(func))
    return out


def _implements(*funcs: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    def deco(f: Callable[..., Any]) -> Callable[..., Any]:
        for fn in funcs:
            HANDLED[fn] = f
        return f
    return deco


def _n(*arrays: Any) -> int:
    return max(a.n for a in arrays if type(a) is Jet)


def _pos(axis: int, ndim: int) -> int:
    """A non-negative axis (NumPy's range check)."""
    if not -ndim <= axis < ndim:
        raise np.exceptions.AxisError(axis, ndim)
    return axis % ndim


def _taxis(axis: Any, ndim: int) -> Any:
    """The tangent's axis (or axes) for a value axis: non-negative ones shift by one."""
    if axis is None:
        return tuple(range(1, ndim + 1))
    if isinstance(axis, Sequence):
        return tuple(_pos(a, ndim) + 1 for a in axis)
    return _pos(axis, ndim) + 1


def _linear(fn: Callable[..., Any], a: Any, axis_kw: dict[str, Any] | None = None,
            **kw: Any) -> Any:
    """``fn`` applied to value and tangent alike (a linear map), axes shifted for the
    tangent."""
    v, t, lo = parts(a)
    y = fn(v, **(axis_kw or {}), **kw)
    if t is None:
        return y
    tkw = {k: _taxis(x, v.ndim) for k, x in (axis_kw or {}).items()}
    return Jet(y, fn(t, **tkw, **kw), lo, a.n)


# --- values only ------------------------------------------------------------------------------

_VALUE_ONLY = (np.argmax, np.argmin, np.argsort, np.nonzero, np.flatnonzero, np.count_nonzero,
               np.any, np.all, np.shape, np.ndim, np.size, np.isclose, np.allclose,
               np.array_equal, np.searchsorted, np.round, np.around, np.iscomplexobj,
               np.isrealobj, np.result_type)


def _value_only(func: Any) -> Callable[..., Any]:
    def impl(*args: Any, **kwargs: Any) -> Any:
        args = tuple(a.value if type(a) is Jet else a for a in args)
        kwargs = {k: (a.value if type(a) is Jet else a) for k, a in kwargs.items()}
        return func(*args, **kwargs)
    return impl


for _f in _VALUE_ONLY:
    HANDLED[_f] = _value_only(_f)


# --- creation ---------------------------------------------------------------------------------

def _container(value: np.ndarray, like: Jet) -> Any:
    """A jet with zero derivatives over ``like``'s directions (an output to fill: assigning
    a jet of other directions widens it), or the plain value for a non-float dtype."""
    if value.dtype.kind != "f":
        return value
    if Tape.active:
        return tape.container(value, like)
    return Jet(value, np.zeros((len(like.tangent),) + value.shape), like.lo, like.n)


def _make_like(func: Any, fill: Any) -> Callable[..., Any]:
    def impl(a: Any, *args: Any, dtype: Any = None, shape: Any = None, **kw: Any) -> Any:
        v = a.value
        s = v.shape if shape is None else shape
        dt = v.dtype if dtype is None else np.dtype(dtype)
        # (like=v: a traced block's container is traced too, graphopt.autodiff.replay)
        if func is np.full_like:
            value = np.full(s, args[0] if args else kw["fill_value"], dtype=dt, like=v)
        else:
            value = (np.full(s, fill, dtype=dt, like=v) if fill is not None
                     else np.empty(s, dtype=dt, like=v))
        return _container(value, a)
    return impl


HANDLED[np.zeros_like] = _make_like(np.zeros_like, 0.0)
HANDLED[np.ones_like] = _make_like(np.ones_like, 1.0)
HANDLED[np.empty_like] = _make_like(np.empty_like, None)
HANDLED[np.full_like] = _make_like(np.full_like, None)


def _create(func: Any) -> Callable[..., Any]:
    def impl(like: Jet, *args: Any, **kwargs: Any) -> Any:
        kwargs.pop("like", None)
        out = func(*args, like=like.value, **kwargs)  # (traced if the jet's value is)
        return _container(out if isinstance(out, np.ndarray) else np.asarray(out), like)
    return impl


_CREATION = (np.zeros, np.empty, np.ones, np.full)
for _f in _CREATION:
    HANDLED[_f] = _create(_f)


@_implements(np.asarray, np.array, np.asanyarray, np.ascontiguousarray)
def _asarray(a: Any, *args: Any, **kw: Any) -> Any:
    if type(a) is Jet:
        return a
    if isinstance(a, list | tuple) and any(type(x) is Jet for x in a):
        raise JetError("np.array of a list of jets", "use np.stack")
    return np.asarray(a)


@_implements(np.copy)
def _copy(a: Any, *args: Any, **kw: Any) -> Any:
    return a.copy()


@_implements(np.copyto)
def _copyto(dst: Any, src: Any, casting: str = "same_kind", where: Any = True) -> None:
    if where is not True:
        raise JetError("np.copyto(..., where=...)")
    write_out(src, dst, "np.copyto")


# --- reductions -------------------------------------------------------------------------------

def _reduction(fn: Any) -> Callable[..., Any]:
    def impl(a: Any, axis: Any = None, dtype: Any = None, out: Any = None,
             keepdims: bool = False, **kw: Any) -> Any:
        if kw.get("where", True) is not True:
            raise JetError(f"{_fname(fn)}(..., where=...)")
        kw.pop("where", None)
        if Tape.active and type(a) is Jet and out is None and not kw and axis is not None:
            rec = tape_ops.reduce(fn, a, axis, keepdims, lambda: impl(a, axis, keepdims=keepdims))
            if rec is not None:
                return rec
        r = _linear(fn, a, {"axis": axis}, keepdims=keepdims, **kw)
        return r if out is None else write_out(r, out, _fname(fn))
    return impl


HANDLED[np.sum] = _reduction(np.sum)
HANDLED[np.mean] = _reduction(np.mean)


@_implements(np.cumsum)
def _cumsum(a: Any, axis: Any = None, dtype: Any = None, out: Any = None) -> Any:
    if axis is None:
        a, axis = np.ravel(a), 0
    return _linear(np.cumsum, a, {"axis": axis})


@_implements(np.diff)
def _diff(a: Any, n: int = 1, axis: int = -1, **kw: Any) -> Any:
    if kw:
        raise JetError("np.diff with prepend/append")
    return _linear(np.diff, a, {"axis": axis}, n=n)


@_implements(np.prod)
def _prod(a: Any, axis: Any = None, dtype: Any = None, out: Any = None,
          keepdims: bool = False, **kw: Any) -> Any:
    if kw or out is not None:
        raise JetError("np.prod with out/initial/where")
    v, t, lo = parts(a)
    y = np.prod(v, axis=axis, keepdims=keepdims)
    if t is None:
        return y
    if axis is None:
        v, t, ax = v.reshape(-1), t.reshape(len(t), -1), 0
    elif isinstance(axis, Sequence):
        raise JetError("np.prod over several axes")
    else:
        ax = _pos(axis, v.ndim)
    vm = np.moveaxis(v, ax, -1)
    tm = np.moveaxis(t, ax + 1, -1)
    # ∂/∂v_i ∏ v = ∏_{j≠i} v_j, from prefix and suffix products (no division by zero).
    left = np.ones_like(vm)
    right = np.ones_like(vm)
    left[..., 1:] = np.cumprod(vm[..., :-1], axis=-1)
    right[..., :-1] = np.cumprod(vm[..., :0:-1], axis=-1)[..., ::-1]
    tan = np.sum(tm * (left * right), axis=-1)
    if keepdims:
        tan = np.expand_dims(tan, _taxis(axis, v.ndim) if axis is not None else
                             tuple(range(1, np.ndim(y) + 1)))
    return Jet(y, tan.reshape((len(t),) + np.shape(y)), lo, a.n)


def _extremum(fn: Any, arg: Any) -> Callable[..., Any]:
    def impl(a: Any, axis: Any = None, out: Any = None, keepdims: bool = False,
             **kw: Any) -> Any:
        if kw or out is not None:
            raise JetError(f"{_fname(fn)} with out/initial/where")
        if type(a) is not Jet:
            return fn(a, axis=axis, keepdims=keepdims)
        if axis is None:
            flat = np.ravel(a)
            i = int(arg(flat.value))
            r = flat[i]
            return np.reshape(r, (1,) * a.ndim) if keepdims else r
        if isinstance(axis, Sequence):  # move the axes last and merge them
            axes = sorted(_pos(i, a.ndim) for i in axis)
            moved = np.moveaxis(a, axes, list(range(a.ndim - len(axes), a.ndim)))
            merged = np.reshape(moved, moved.shape[:a.ndim - len(axes)] + (-1,))
            r = impl(merged, axis=-1)
            return np.expand_dims(r, tuple(axes)) if keepdims else r
        idx = np.expand_dims(arg(a.value, axis=axis), axis)
        r = np.take_along_axis(a, idx, axis=axis)
        return r if keepdims else np.squeeze(r, axis=axis)
    return impl


HANDLED[np.max] = HANDLED[np.amax] = _extremum(np.max, np.argmax)
HANDLED[np.min] = HANDLED[np.amin] = _extremum(np.min, np.argmin)


# --- shape ------------------------------------------------------------------------------------

@_implements(np.reshape)
def _reshape(a: Any, shape: Any = None, order: str = "C", **kw: Any) -> Any:
    if shape is None:
        shape = kw.pop("newshape")
    if order != "C":
        raise JetError(f"np.reshape(..., order={order!r})")
    v, t, lo = parts(a)
    y = v.reshape(shape)
    return y if t is None else Jet(y, t.reshape((len(t),) + y.shape), lo, a.n)


@_implements(np.ravel)
def _ravel(a: Any, order: str = "C") -> Any:
    return _reshape(a, -1, order)


@_implements(np.transpose)
def _transpose(a: Any, axes: Any = None) -> Any:
    v, t, lo = parts(a)
    ax = tuple(range(v.ndim))[::-1] if axes is None else tuple(_pos(i, v.ndim) for i in axes)
    y = v.transpose(ax)
    return y if t is None else Jet(y, t.transpose((0,) + tuple(i + 1 for i in ax)), lo, a.n)


@_implements(np.swapaxes)
def _swapaxes(a: Any, axis1: int, axis2: int) -> Any:
    v, t, lo = parts(a)
    y = np.swapaxes(v, axis1, axis2)
    if t is None:
        return y
    return Jet(y, np.swapaxes(t, _pos(axis1, v.ndim) + 1, _pos(axis2, v.ndim) + 1), lo, a.n)


@_implements(np.moveaxis)
def _moveaxis(a: Any, source: Any, destination: Any) -> Any:
    v, t, lo = parts(a)
    y = np.moveaxis(v, source, destination)
    if t is None:
        return y
    s = [_pos(i, v.ndim) + 1 for i in np.atleast_1d(source)]
    d = [_pos(i, v.ndim) + 1 for i in np.atleast_1d(destination)]
    return Jet(y, np.moveaxis(t, s, d), lo, a.n)


@_implements(np.squeeze)
def _squeeze(a: Any, axis: Any = None) -> Any:
    v, t, lo = parts(a)
    if axis is None:
        axis = tuple(i for i, s in enumerate(v.shape) if s == 1)
    return _linear(np.squeeze, a, {"axis": axis}) if t is not None else np.squeeze(v, axis)


@_implements(np.expand_dims)
def _expand_dims(a: Any, axis: Any) -> Any:
    v, t, lo = parts(a)
    y = np.expand_dims(v, axis)
    if t is None:
        return y
    axes = axis if isinstance(axis, Sequence) else (axis,)
    taxes = tuple(_pos(i, y.ndim) + 1 for i in axes)
    return Jet(y, np.expand_dims(t, taxes), lo, a.n)


@_implements(np.broadcast_to)
def _broadcast_to(a: Any, shape: Any, subok: bool = False) -> Any:
    v, t, lo = parts(a)
    y = np.broadcast_to(v, shape)
    return y if t is None else Jet(y, full(t, y.shape), lo, a.n)


@_implements(np.broadcast_arrays)
def _broadcast_arrays(*args: Any, subok: bool = False) -> list[Any]:
    shape = np.broadcast_shapes(*(np.shape(a) for a in args))
    return [_broadcast_to(a, shape) for a in args]


@_implements(np.atleast_1d)
def _atleast_1d(*arys: Any) -> Any:
    r = [np.reshape(a, (1,)) if np.ndim(a) == 0 else a for a in arys]
    return r[0] if len(r) == 1 else r


@_implements(np.atleast_2d)
def _atleast_2d(*arys: Any) -> Any:
    r = [np.reshape(a, (1, -1)) if np.ndim(a) < 2 else a for a in arys]
    return r[0] if len(r) == 1 else r


@_implements(np.flip)
def _flip(a: Any, axis: Any = None) -> Any:
    return _linear(np.flip, a, {"axis": axis})


@_implements(np.roll)
def _roll(a: Any, shift: Any, axis: Any = None) -> Any:
    if axis is None:
        raise JetError("np.roll without axis")
    return _linear(np.roll, a, {"axis": axis}, shift=shift)


@_implements(np.repeat)
def _repeat(a: Any, repeats: Any, axis: Any = None) -> Any:
    if axis is None:
        a, axis = np.ravel(a), 0
    return _linear(np.repeat, a, {"axis": axis}, repeats=repeats)


@_implements(np.diagonal)
def _diagonal(a: Any, offset: int = 0, axis1: int = 0, axis2: int = 1) -> Any:
    v, t, lo = parts(a)
    y = np.diagonal(v, offset, axis1, axis2)
    return Jet(y, np.diagonal(t, offset, _pos(axis1, v.ndim) + 1, _pos(axis2, v.ndim) + 1),
               lo, a.n)


@_implements(np.trace)
def _trace(a: Any, offset: int = 0, axis1: int = 0, axis2: int = 1, **kw: Any) -> Any:
    return np.sum(_diagonal(a, offset, axis1, axis2), axis=-1)


# --- joining ----------------------------------------------------------------------------------

@_implements(np.concatenate)
def _concatenate(arrays: Sequence[Any], axis: Any = 0, out: Any = None, **kw: Any) -> Any:
    if kw:
        raise JetError(f"np.concatenate with {sorted(kw)}")
    if axis is None:
        arrays, axis = [np.ravel(a) for a in arrays], 0
    if Tape.active and out is None and any(type(a) is Jet for a in arrays):
        return tape_ops.concatenate(list(arrays), axis, False,
                                lambda: _concatenate(arrays, axis))
    ps = [parts(a) for a in arrays]
    y = np.concatenate([p[0] for p in ps], axis=axis)
    jets = [a for a in arrays if type(a) is Jet]
    if not jets:
        return y if out is None else write_out(y, out, "np.concatenate")
    n = _n(*jets)
    ax = _pos(axis, y.ndim) + 1
    lo = min(j.lo for j in jets)
    hi = max(j.lo + len(j.tangent) for j in jets)
    if len(jets) == len(arrays) and all(j.lo == lo and len(j.tangent) == hi - lo for j in jets):
        tan = np.concatenate([j.tangent for j in jets], axis=ax)
    else:
        tan = np.zeros((hi - lo,) + y.shape)
        start = 0
        for v, t, tlo in ps:
            stop = start + v.shape[ax - 1]
            if t is not None:
                sl = [slice(tlo - lo, tlo - lo + len(t))] + [slice(None)] * y.ndim
                sl[ax] = slice(start, stop)
                tan[tuple(sl)] = t
            start = stop
    r = Jet(y, tan, lo, n)
    return r if out is None else write_out(r, out, "np.concatenate")


@_implements(np.stack)
def _stack(arrays: Sequence[Any], axis: int = 0, out: Any = None, **kw: Any) -> Any:
    arrays = list(arrays)
    a0 = arrays[0]  # (a jet's own ndim: np.ndim would dispatch through the protocol again)
    nd = (a0.value.ndim if type(a0) is Jet else np.ndim(a0)) + 1
    ax = _pos(axis, nd)
    if Tape.active and out is None and not kw and any(type(a) is Jet for a in arrays):
        return tape_ops.concatenate(arrays, ax, True, lambda: _stack(arrays, ax))
    return _concatenate([np.expand_dims(a, ax) for a in arrays], axis=ax, out=out, **kw)


@_implements(np.hstack)
def _hstack(tup: Sequence[Any], **kw: Any) -> Any:
    arrs = [a if np.ndim(a) else np.reshape(a, (1,)) for a in tup]
    return _concatenate(arrs, axis=0 if np.ndim(arrs[0]) == 1 else 1, **kw)


@_implements(np.vstack)
def _vstack(tup: Sequence[Any], **kw: Any) -> Any:
    arrs = [np.reshape(a, (1, -1)) if np.ndim(a) < 2 else a for a in tup]
    return _concatenate(arrs, axis=0, **kw)


@_implements(np.column_stack)
def _column_stack(tup: Sequence[Any]) -> Any:
    arrs = [np.reshape(a, (-1, 1)) if np.ndim(a) < 2 else a for a in tup]
    return _concatenate(arrs, axis=1)


@_implements(np.split, np.array_split)
def _split(a: Any, indices_or_sections: Any, axis: int = 0) -> list[Any]:
    v, t, lo = parts(a)
    vs = np.array_split(v, indices_or_sections, axis=axis)
    ts = np.array_split(t, indices_or_sections, axis=_pos(axis, v.ndim) + 1)
    return [Jet(x, y, lo, a.n) for x, y in zip(vs, ts, strict=True)]


HOOKS["function"] = apply_function
