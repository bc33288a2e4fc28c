"""What edge types return, checked: shapes and kinds once per group and call, reduced
linearisations, and the edge to name when an error or Jacobian is not finite."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from graphopt.edge import Linearization
from graphopt.errors import GraphError
from graphopt.storage import EdgeGroup


def where(g: EdgeGroup) -> str:
    """The group, named for messages: its size and its first edge's vertices.

    Args:
        g: The group.
    """
    ids = g.vertex_ids[0].tolist() if g.size else []
    return f"{g.size} edges of the group, the first on vertices {ids}"


def checked_output(g: EdgeGroup, out: object, method: str, m: int) -> Linearization:
    """``out`` as a :class:`Linearization` whose arrays have the documented shapes.

    Shape and dtype comparisons only, once per group and call. An error that is not an
    ndarray (a list) is converted with ``np.asarray`` and accepted if its shape is right;
    integer errors become float. Jacobians must be ndarrays, one per vertex position.
    """
    et = g.etype
    name = f"{et.__name__}.{method}"
    if not isinstance(out, Linearization):
        if not isinstance(out, tuple) or not 1 <= len(out) <= 4:
            raise GraphError(f"{name} returned a {type(out).__name__}, expected a "
                             f"Linearization ({where(g)})")
        out = Linearization(*out)  # a plain (error, jacobians[, ...]) tuple
    dim = et.dimension
    e = out.error
    if type(e) is not np.ndarray or e.dtype.kind != "f":
        try:
            e = np.asarray(e, dtype=float)
        except (TypeError, ValueError):
            e = np.zeros(0)  # reported below with the original's type
    if e.shape != (m, dim):
        got = (f"shape {out.error.shape}" if isinstance(out.error, np.ndarray)
               else f"a {type(out.error).__name__}")
        raise GraphError(f"{name} returned an error of {got}, expected ({m}, {dim}) "
                         f"({where(g)})")
    if e is not out.error:
        out = out._replace(error=e)
    if out.active is not None and np.shape(out.active) != (m,):
        raise GraphError(f"{name} returned an active mask of shape {np.shape(out.active)}, "
                         f"expected ({m},) ({where(g)})")
    if method == "linearize":
        J = out.jacobians
        vts = et.vertex_types
        if not isinstance(J, tuple | list) or len(J) != len(vts):
            got = (f"{len(J)} Jacobians" if isinstance(J, tuple | list)
                   else f"a {type(J).__name__}")
            raise GraphError(f"{name} returned {got}, expected a tuple of {len(vts)} (one "
                             f"per vertex position) ({where(g)})")
        rows = et.jacobian_rows()
        for i, (j, vt) in enumerate(zip(J, vts, strict=True)):
            if type(j) is not np.ndarray or j.shape != (m, rows, vt.dimension):
                got = (f"shape {j.shape}" if isinstance(j, np.ndarray)
                       else f"a {type(j).__name__}")
                raise GraphError(f"{name} returned a Jacobian of {got} for position {i} "
                                 f"({vt.__name__}), expected ({m}, {rows}, {vt.dimension}) "
                                 f"({where(g)})")
    return out


def reduced_error(g: EdgeGroup, out: Linearization) -> np.ndarray:
    """Check and return ``e_lin`` of a reduced linearisation."""
    r = g.etype.linearization_rows
    name = g.etype.__name__
    if out.reduced_error is None:
        raise GraphError(f"{name}: linearization_rows is set, so linearize must return a "
                         "Linearization with reduced_error (e_lin)")
    e_lin = out.reduced_error
    # The Jacobians' (m, r, d) shapes were checked with the rest of the output (_checked).
    if np.shape(e_lin) != (g.size, r):
        raise GraphError(f"{name}: a reduced linearisation needs e_lin ({g.size}, {r}), got "
                         f"shape {np.shape(e_lin)}")
    if not g.info_is_identity:
        raise GraphError(f"{name}: a reduced linearisation needs an identity information "
                         "matrix")
    if not np.isfinite(e_lin.sum()):
        raise FloatingPointError(f"{name}: non-finite reduced error at linearisation")
    return e_lin


def raise_non_finite_edge(g: EdgeGroup, e: np.ndarray, J: tuple[np.ndarray, ...]) -> None:
    """Raise naming the first edge of ``g`` with a non-finite error or Jacobian, if any."""
    ok = np.isfinite(e.reshape(len(e), -1)).all(axis=1)
    for j in J:
        ok &= np.isfinite(j.reshape(len(j), -1)).all(axis=1)
    if ok.all():
        return
    ids = g.vertex_ids[int(np.flatnonzero(~ok)[0])].tolist()
    raise FloatingPointError(
        f"{g.etype.__name__} on vertices {ids}: non-finite error or Jacobian at linearisation"
    )


def first_non_finite(groups: Iterable[EdgeGroup]) -> str:
    """The first edge whose error was not finite at the last evaluation, named (or a hint).

    Args:
        groups: The graph's edge groups.
    """
    for g in groups:
        bad = np.flatnonzero(~np.isfinite(g.last_chi2))
        if len(bad):
            return (f"{g.etype.__name__} on vertices {g.vertex_ids[int(bad[0])].tolist()} "
                    f"(and {len(bad) - 1} more edges of its type); check the estimates")
    return "check the estimates"
