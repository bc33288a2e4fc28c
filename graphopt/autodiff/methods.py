"""``ndarray`` methods of :class:`~graphopt.autodiff.jet.Jet` (``x.reshape``, ``x.sum``, …),
each through the NumPy function, so that the jet rules apply."""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.autodiff.errors import JetError

__all__ = ["ArrayMethods"]


class ArrayMethods:
    """The methods; the class using it has ``value``, ``tangent``, ``lo`` and ``n``."""

    __slots__ = ()
    value: np.ndarray
    tangent: np.ndarray
    lo: int
    n: int


    def reshape(self, *shape: Any, order: str = "C") -> Any:
        """As ``ndarray.reshape``."""
        s = shape[0] if len(shape) == 1 and not isinstance(shape[0], int) else shape
        return np.reshape(self, s, order=order)  # type: ignore[call-overload]

    def transpose(self, *axes: Any) -> Any:
        """As ``ndarray.transpose``."""
        a = axes[0] if len(axes) == 1 and not isinstance(axes[0], int) else (axes or None)
        return np.transpose(self, a)  # type: ignore[return-value]

    def swapaxes(self, a: int, b: int) -> Any:
        """As ``ndarray.swapaxes``."""
        return np.swapaxes(self, a, b)  # type: ignore[return-value]

    def squeeze(self, axis: Any = None) -> Any:
        """As ``ndarray.squeeze``."""
        return np.squeeze(self, axis)  # type: ignore[return-value]

    def ravel(self) -> Any:
        """As ``ndarray.ravel``."""
        return np.ravel(self)  # type: ignore[return-value]

    def flatten(self) -> Any:
        """As ``ndarray.flatten`` (a copy)."""
        return np.ravel(self).copy()  # type: ignore[union-attr]

    def copy(self) -> Any:
        """A copy of value and derivatives."""
        return type(self)(self.value.copy(), self.tangent.copy(), self.lo, self.n)  # type: ignore[call-arg]

    def astype(self, dtype: Any, copy: bool = True) -> Any:
        """Floating dtypes keep the derivatives; others are refused (they would drop them)."""
        if np.dtype(dtype).kind != "f":
            raise JetError(f"astype({np.dtype(dtype).name})", "an integer or boolean copy of a "
                           "jet has no derivative; use its .value explicitly")
        return self.copy() if copy else self

    def sum(self, axis: Any = None, keepdims: bool = False, **kw: Any) -> Any:
        """As ``ndarray.sum``."""
        return np.sum(self, axis=axis, keepdims=keepdims, **kw)

    def mean(self, axis: Any = None, keepdims: bool = False, **kw: Any) -> Any:
        """As ``ndarray.mean``."""
        return np.mean(self, axis=axis, keepdims=keepdims, **kw)

    def prod(self, axis: Any = None, keepdims: bool = False, **kw: Any) -> Any:
        """As ``ndarray.prod``."""
        return np.prod(self, axis=axis, keepdims=keepdims, **kw)

    def max(self, axis: Any = None, keepdims: bool = False) -> Any:
        """As ``ndarray.max``."""
        return np.max(self, axis=axis, keepdims=keepdims)

    def min(self, axis: Any = None, keepdims: bool = False) -> Any:
        """As ``ndarray.min``."""
        return np.min(self, axis=axis, keepdims=keepdims)

    def dot(self, other: Any) -> Any:
        """As ``ndarray.dot``."""
        return np.dot(self, other)

    def clip(self, lo: Any = None, hi: Any = None) -> Any:
        """As ``ndarray.clip``."""
        return np.clip(self, lo, hi)

    def take(self, indices: Any, axis: Any = None) -> Any:
        """As ``ndarray.take``."""
        return np.take(self, indices, axis=axis)

    def diagonal(self, offset: int = 0, axis1: int = 0, axis2: int = 1) -> Any:
        """As ``ndarray.diagonal``."""
        return np.diagonal(self, offset, axis1, axis2)

    def trace(self, offset: int = 0, axis1: int = 0, axis2: int = 1) -> Any:
        """As ``ndarray.trace``."""
        return np.trace(self, offset, axis1, axis2)

    def all(self, *a: Any, **k: Any) -> Any:
        """Of the values."""
        return self.value.all(*a, **k)

    def any(self, *a: Any, **k: Any) -> Any:
        """Of the values."""
        return self.value.any(*a, **k)

    def argmax(self, *a: Any, **k: Any) -> Any:
        """Of the values."""
        return self.value.argmax(*a, **k)

    def argmin(self, *a: Any, **k: Any) -> Any:
        """Of the values."""
        return self.value.argmin(*a, **k)
