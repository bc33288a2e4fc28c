"""The batched jet: an array of values with a first-order derivative part per tangent direction.

A :class:`Jet` holds ``value`` ``(m, …)`` — any shape, the edges' arrays run over ``m`` — and
``tangent`` ``(k, m, …)``: the derivatives of every value w.r.t. ``k`` of the ``n`` tangent
directions of one edge (``Σ dᵢ`` over its vertex positions), the directions ``lo … lo+k−1``.
The others are known to be zero (a rotation built from a pose's increment depends on 3
directions, not on the point's), so operations only touch the directions that can be non-zero:
the *support*.

Layout: the tangent axis is **first**. An elementwise rule such as ``t_a · v_b`` is then one
NumPy broadcast of a contiguous ``(k, m, …)`` block against ``(m, …)`` (trailing axes align),
where a last tangent axis ``(m, …, k)`` would need ``v[..., None]`` on every operand and a
strided inner loop of length ``k`` (``docs/autodiff.md`` has the measurements).

The NumPy protocols live in :mod:`graphopt.autodiff.ufuncs` (``__array_ufunc__``) and
:mod:`graphopt.autodiff.functions` (``__array_function__``); this module holds the class, its
indexing and the helpers both use. A NumPy function without a derivative rule raises
:class:`JetError` naming it — never a dropped derivative, never an object array.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.lib.mixins import NDArrayOperatorsMixin

from graphopt.autodiff.errors import JetError
from graphopt.autodiff.methods import ArrayMethods
from graphopt.autodiff.replay import forward_rule

__all__ = ["HOOKS", "Jet", "JetError", "is_jet", "parts"]

#: The NumPy protocol handlers, registered by :mod:`graphopt.autodiff.ufuncs` (``"ufunc"``)
#: and :mod:`graphopt.autodiff.functions` (``"function"``) when the package is imported.
HOOKS: dict[str, Callable[..., Any]] = {}


class Tape:
    """Whether jet operations are recorded for reverse accumulation
    (:mod:`graphopt.autodiff.tape`) instead of carrying their tangents forward."""

    active = False


_ONES: dict[int, np.ndarray] = {}


def unit_row(m: int) -> np.ndarray:
    """``(1, m)`` ones, read-only (the derivative of a unit column), one array per ``m``."""
    t = _ONES.get(m)
    if t is None:
        if len(_ONES) > 16:
            _ONES.clear()
        t = _ONES[m] = np.broadcast_to(np.ones(1), (1, m))
    return t


_EYES: dict[tuple[int, int], np.ndarray] = {}


def _identity(d: int, m: int) -> np.ndarray:
    """The identity ``(d, m, d)`` broadcast over ``m`` edges, read-only, one array per shape
    (a seed's tangent; made once, not per block)."""
    t = _EYES.get((d, m))
    if t is None:
        if len(_EYES) > 16:
            _EYES.clear()
        t = _EYES[d, m] = np.broadcast_to(np.eye(d)[:, None, :], (d, m, d))
    return t


def is_jet(a: object) -> bool:
    """True for a :class:`Jet`."""
    return type(a) is Jet


def parts(a: Any) -> tuple[np.ndarray, np.ndarray | None, int]:
    """``(value, tangent or None, lo)`` of a jet or a constant (converted with ``asarray``)."""
    if type(a) is Jet:
        return a.value, a.tangent, a.lo
    return np.asarray(a), None, 0


def expand(t: np.ndarray, ndim: int) -> np.ndarray:
    """A tangent ``(k, *s)`` with unit axes after ``k`` so that its value part has ``ndim``
    axes (NumPy aligns trailing axes, the tangent axis must stay first)."""
    extra = ndim - (t.ndim - 1)
    if extra <= 0:
        return t
    return t.reshape((t.shape[0],) + (1,) * extra + t.shape[1:])


def full(t: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``t`` broadcast to ``(k, *shape)`` (a view when it is smaller)."""
    t = expand(t, len(shape))
    target = (t.shape[0],) + tuple(shape)
    return t if t.shape == target else np.broadcast_to(t, target)


def combine(shape: tuple[int, ...], n: int, terms: list[tuple[int, np.ndarray, bool]]) -> Any:
    """Sum of tangent terms over their supports, as a :class:`Jet` of a value set later.

    Args:
        shape: The result's value shape.
        n: Total tangent directions.
        terms: ``(lo, tangent (k, …), fresh)``; ``fresh`` terms are temporaries that may be
            written into.

    Returns:
        ``(tangent (k, *shape), lo)``, or ``None`` when there is no term.
    """
    if not terms:
        return None
    if len(terms) == 1:
        lo, t, fresh = terms[0]
        out = full(t, shape)
        if not fresh and out.flags.writeable:  # p + 1 is a new array: writing p must not
            out = out.copy()                   # change its derivatives
        return out, lo
    lo = min(t[0] for t in terms)
    hi = max(t[0] + t[1].shape[0] for t in terms)
    same = all(t[0] == lo and t[1].shape[0] == hi - lo for t in terms)
    target = (hi - lo,) + tuple(shape)
    if same:
        first = next((i for i, t in enumerate(terms) if t[2] and t[1].shape == target), None)
        if first is None:
            acc = expand(terms[0][1], len(shape)) + expand(terms[1][1], len(shape))
            rest = terms[2:]
        else:
            acc = terms[first][1]
            rest = terms[:first] + terms[first + 1:]
        for _, t, _ in rest:
            acc += expand(t, len(shape))
        return full(acc, shape), lo
    # Different supports: start from a term that covers the union if there is one (written
    # into if it is a temporary, else copied), not from zeros, and add the others into it.
    cover = next((i for i, t in enumerate(terms)
                  if t[0] == lo and t[1].shape[0] == hi - lo), None)
    if cover is None:
        acc = np.zeros(target)
        rest = terms
    else:
        _, t0, fresh0 = terms[cover]
        acc = t0 if fresh0 and t0.shape == target and t0.flags.writeable else \
            np.array(np.broadcast_to(expand(t0, len(shape)), target))
        rest = terms[:cover] + terms[cover + 1:]
    for tlo, t, _ in rest:
        acc[tlo - lo: tlo - lo + t.shape[0]] += expand(t, len(shape))
    return acc, lo


def make(value: np.ndarray, tan: tuple[np.ndarray, int] | None, n: int) -> Any:
    """A :class:`Jet`, or the plain ``value`` when there is no tangent."""
    if tan is None:
        return value
    return Jet(value, tan[0], tan[1], n)


def _expand_key(key: Any, ndim: int) -> tuple[Any, ...]:
    """An index as a tuple without ``Ellipsis`` (spelled out as slices), for ``ndim`` axes."""
    if not isinstance(key, tuple):
        key = (key,)
    used = 0
    for k in key:
        if k is None or k is Ellipsis:
            continue
        if isinstance(k, np.ndarray) and k.dtype == bool:
            used += k.ndim
        elif type(k) is Jet:
            raise JetError("indexing with a jet", "index with integers, slices or plain arrays")
        else:
            used += 1
    if any(k is Ellipsis for k in key):
        i = next(i for i, k in enumerate(key) if k is Ellipsis)
        key = key[:i] + (slice(None),) * (ndim - used) + key[i + 1:]
    return key


def _advanced_first(key: tuple[Any, ...]) -> int:
    """Number of leading axes NumPy puts first for non-adjacent advanced indices (``0`` if the
    advanced indices are adjacent, or absent): the tangent axis then comes after them."""
    adv = [i for i, k in enumerate(key)
           if isinstance(k, np.ndarray | list) or (np.ndim(k) > 0 and not isinstance(k, slice))]
    if not adv:
        return 0
    ints = [i for i, k in enumerate(key) if isinstance(k, int | np.integer)]
    pos = sorted(adv + ints)
    if pos[-1] - pos[0] + 1 == len(pos):
        return 0
    shapes = [np.shape(key[i]) if not (isinstance(key[i], np.ndarray) and key[i].dtype == bool)
              else (int(np.count_nonzero(key[i])),) for i in adv]
    return len(np.broadcast_shapes(*shapes))


def _rows_after(rows: tuple[int, int], key: tuple[Any, ...],
               value: np.ndarray) -> tuple[int, int] | None:
    """The edges of axis 0 after a value index (``None`` when axis 0 is no longer a range of
    them): a unit-step slice of axis 0 keeps a sub-range."""
    k0 = key[0] if key else slice(None)
    if not isinstance(k0, slice) or k0.step not in (None, 1) or value.ndim == 0:
        return None
    a, b, _ = k0.indices(rows[1] - rows[0])
    return (rows[0] + a, rows[0] + b) if value.shape[0] == b - a else None


def _is_basic(key: tuple[Any, ...]) -> bool:
    return all(k is None or isinstance(k, slice | int | np.integer) for k in key)


def _operator(uf: np.ufunc, reflected: bool = False) -> Callable[[Any, Any], Any]:
    """An arithmetic operator: recorded directly while recording (the ufunc protocol costs
    more than the arithmetic on a block of edges), else through the ufunc."""
    def op(self: Jet, other: Any) -> Any:
        a, b = (other, self) if reflected else (self, other)
        if Tape.active:
            out = HOOKS["binary"](uf, a, b)
            if out is not None:
                return out
        return uf(a, b)
    return op


class Jet(ArrayMethods, NDArrayOperatorsMixin):
    """Values ``(m, …)`` with derivatives ``(k, m, …)`` w.r.t. tangent directions ``lo…lo+k−1``
    of ``n``.

    Args:
        value: The values.
        tangent: The derivatives, the tangent axis first; shape ``(k, *value.shape)``.
        lo: First tangent direction the derivatives cover.
        n: Total number of tangent directions (of the edge being differentiated).
    """

    __slots__ = ("value", "_tangent", "_lo", "n", "_base", "_key", "seed", "columns", "rows",
                 "_tape")
    # Above ndarray's: mixed operations dispatch to the jet.
    __array_priority__ = 1000.0

    def __init__(self, value: np.ndarray, tangent: np.ndarray | None, lo: int, n: int) -> None:
        self.value = value
        self._tangent = tangent
        self._lo = lo
        self.n = n
        # Recorded, not yet computed (graphopt.autodiff.tape): the derivatives are formed on
        # first use of .tangent/.lo, or never (reverse accumulation from the result).
        self._tape: Any = None
        # (a, b): axis 0 holds edges a…b−1 of the block being differentiated; None: unknown.
        self.rows: tuple[int, int] | None = None
        self._base: Jet | None = None  # for a view: the jet it indexes, with self._key
        self._key: tuple[Any, ...] = ()
        # For (m, d) values: each column's support (lo, hi), so that x[:, j] covers only its
        # own directions (see __getitem__); a seed's tangent is the identity over the columns.
        self.columns: list[tuple[int, int]] | None = None
        self.seed = False

    @property
    def tangent(self) -> np.ndarray:
        """The derivatives ``(k, *value.shape)`` (formed now if they were only recorded)."""
        if self._tape is not None:
            HOOKS["materialise"](self)
        return self._tangent  # type: ignore[return-value]

    @tangent.setter
    def tangent(self, t: np.ndarray) -> None:
        self._tangent = t

    @property
    def lo(self) -> int:
        """The first direction the derivatives cover."""
        if self._tape is not None:
            HOOKS["materialise"](self)
        return self._lo

    @lo.setter
    def lo(self, lo: int) -> None:
        self._lo = lo

    # --- array-like attributes ---------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, ...]:
        """The value's shape."""
        return self.value.shape

    @property
    def ndim(self) -> int:
        """The value's number of axes."""
        return self.value.ndim

    @property
    def size(self) -> int:
        """The value's number of entries."""
        return self.value.size

    @property
    def dtype(self) -> np.dtype:
        """The value's dtype."""
        return self.value.dtype

    @property
    def T(self) -> Jet:  # noqa: N802 - ndarray's name
        """The transpose (all axes reversed)."""
        return np.transpose(self)  # type: ignore[return-value]

    def __iter__(self) -> Any:
        for i in range(len(self.value)):
            yield self[i]

    def __len__(self) -> int:
        return len(self.value)

    def __repr__(self) -> str:
        return (f"Jet(shape={self.shape}, directions={self.lo}..{self.lo + len(self.tangent)}"
                f" of {self.n})")

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        raise JetError("converting a jet to a plain array (np.asarray, np.array, float, an "
                       "assignment into an array not made with np.*_like(x) or like=x)",
                       "the derivatives would be lost")

    def __float__(self) -> float:
        self.__array__()
        return 0.0

    def __int__(self) -> int:
        self.__array__()
        return 0

    __index__ = __int__

    def __bool__(self) -> bool:
        return bool(self.value)

    # --- NumPy protocols (rules in ufuncs.py and functions.py) --------------------------------

    __add__, __radd__ = _operator(np.add), _operator(np.add, True)
    __sub__, __rsub__ = _operator(np.subtract), _operator(np.subtract, True)
    __mul__, __rmul__ = _operator(np.multiply), _operator(np.multiply, True)
    __truediv__, __rtruediv__ = _operator(np.divide), _operator(np.divide, True)

    def __array_ufunc__(self, ufunc: np.ufunc, method: str, *inputs: Any, **kwargs: Any) -> Any:
        return HOOKS["ufunc"](ufunc, method, inputs, kwargs)

    def __array_function__(self, func: Any, types: Any, args: Any, kwargs: Any) -> Any:
        return HOOKS["function"](func, types, args, kwargs, like=self)

    # --- indexing ----------------------------------------------------------------------------

    def tangent_key(self, key: Any) -> tuple[tuple[Any, ...], int]:
        """The tangent's index for a value index, and the number of leading axes NumPy puts
        before the tangent axis (non-adjacent advanced indices)."""
        k = _expand_key(key, self.value.ndim)
        k = tuple(np.asarray(a) if isinstance(a, list) else a for a in k)
        return (slice(None),) + k, _advanced_first(k)

    @classmethod
    def seeded(cls, value: np.ndarray, lo: int, n: int) -> Jet:
        """``(m, d)`` values with derivative the identity: direction ``lo + j`` of column ``j``.

        Args:
            value: The values.
            lo: The first column's direction.
            n: Total directions.
        """
        m, d = value.shape
        out = cls(value, _identity(d, m), lo, n)
        out.seed = True
        out.columns = [(lo + j, lo + j + 1) for j in range(d)]
        return out

    def _column_view(self, key: Any) -> Jet | None:
        """``x[:, j]`` or ``x[:, a:b]`` of a 2-D jet whose columns' supports are known
        (:attr:`columns`): the result covers only those columns' directions."""
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None)):
            return None
        c = key[1]
        cols = self.columns
        assert cols is not None
        d = self.value.shape[1]
        one = isinstance(c, int | np.integer)
        if one:
            a, b = int(c) % d, int(c) % d + 1
        elif isinstance(c, slice) and c.step in (None, 1):
            a, b, _ = c.indices(d)
            if b <= a:
                return None
        else:
            return None
        lo, hi = min(x[0] for x in cols[a:b]), max(x[1] for x in cols[a:b])
        m = len(self.value)
        if self.seed or (one and len(cols[a]) > 2 and cols[a][2]):  # unit: derivative 1
            k = hi - lo
            t = unit_row(m) if one else _identity(k, m)
        else:
            t = self.tangent[lo - self.lo: hi - self.lo, :, a if one else slice(a, b)]
        out = Jet(self.value[:, a] if one else self.value[:, a:b], t, lo, self.n)
        out.rows = self.rows
        if not one:
            out.seed, out.columns = self.seed, cols[a:b]
        return out

    def __getitem__(self, key: Any) -> Jet:
        if self._tape is not None or Tape.active:
            lazy = HOOKS["getitem"](self, key)
            if lazy is not None:
                return lazy
        if self.columns is not None:
            narrow = self._column_view(key)
            if narrow is not None:
                return narrow
        tkey, first = self.tangent_key(key)
        value = self.value[tkey[1:]]
        tangent = self.tangent[tkey]
        if first:
            tangent = np.moveaxis(tangent, first, 0)
        out = Jet(value, tangent, self.lo, self.n)
        if _is_basic(tkey[1:]):
            out._base, out._key = self, tkey[1:]
        if self.rows is not None and not first:
            out.rows = _rows_after(self.rows, tkey[1:], value)
            if out.rows is not None and len(tkey) == 2 and self.columns is not None:
                out.columns, out.seed = self.columns, self.seed  # rows only: same columns
        return out

    def __setitem__(self, key: Any, item: Any) -> None:
        if Tape.active and HOOKS["setitem"](self, key, item):
            return
        forward_rule("writing into a jet")
        v, t, lo = parts(item)
        tkey, first = self.tangent_key(key)
        if t is not None:
            self.widen(lo, lo + len(t))
        sub = self.value[tkey[1:]].shape
        self.value[tkey[1:]] = v
        k = len(self.tangent)
        if t is None:
            self.tangent[tkey] = 0.0
            return
        src = np.zeros((k,) + tuple(sub)) if (lo != self.lo or len(t) != k) else None
        if src is None:
            src = full(t, tuple(sub))
        else:
            src[lo - self.lo: lo - self.lo + len(t)] = expand(t, len(sub))
        if first:
            src = np.moveaxis(src, 0, first)
        self.tangent[tkey] = src

    def widen(self, lo: int, hi: int) -> None:
        """Make the tangent cover directions ``lo…hi−1`` too (zeros), through a view's base.

        Args:
            lo: First direction to cover.
            hi: One past the last.
        """
        if not self.tangent.flags.writeable:
            self.tangent = self.tangent.copy()
        nlo, nhi = min(lo, self.lo), max(hi, self.lo + len(self.tangent))
        if nlo == self.lo and nhi == self.lo + len(self.tangent):
            return
        if self._base is not None:
            self._base.widen(nlo, nhi)
            self.tangent = self._base.tangent[(slice(None),) + self._key]
            self.lo = self._base.lo
            return
        t = np.zeros((nhi - nlo,) + self.value.shape)
        t[self.lo - nlo: self.lo - nlo + len(self.tangent)] = self.tangent
        self.tangent, self.lo = t, nlo
