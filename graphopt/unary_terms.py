"""The normal equations' terms of a group of unary edges on one free vertex, in few numpy calls.

A motion-only BA's group — every edge on the one pose, a diagonal information per edge, one
robust kernel or none — is evaluated 17 times in ORB-SLAM's 100-match ``PoseOptimization``.
What the general weighting (:meth:`~graphopt.linearizer.Linearizer._sq`, ``_robustify``,
``_record``, :func:`~graphopt.row_weights.weighted_rows` and
:class:`~graphopt.linear.single_block.SingleBlockAssembler`) decides per call from the group's
kernels, levels and information — which kernel, which edges are active, how many — is decided
here once per :attr:`~graphopt.edge_group.EdgeGroup.activity_version` (:func:`weighing`);
a call is then the arithmetic alone (:func:`unary_terms`): the same numbers as the general
path, up to the order of two products (``e·(Ω·ρ')`` for ``(Ω·e)·ρ'``). :func:`compiled_group`
and :func:`compiled_terms` take the same numbers from a type's compiled loop
(:mod:`graphopt.compiled`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from graphopt.compiled import CompiledUnary, kernel_code
from graphopt.robust_kernel import RobustKernel
from graphopt.row_weights import row_dots
from graphopt.storage import EdgeGroup


class Weighing(NamedTuple):
    """How a group's edges are weighed at one activity version.

    Attributes:
        version: The group's :attr:`~graphopt.edge_group.EdgeGroup.activity_version`.
        active: ``(m,)`` the active edges, ``None`` when all are.
        count: How many are active.
        kernel: The one kernel of every edge, ``None`` for none.
        info: ``Ω``'s diagonal, ``(rows,)`` or ``(m, rows)``; ``None`` for the identity.
        active_info: ``(m, rows)`` ``info`` zeroed at the inactive edges (``None`` when all
            are active, ``info`` is ``None`` or it was not asked for): the weights' factor, one
            product fewer a call.
    """

    version: tuple[int, int]
    active: np.ndarray | None
    count: int
    kernel: RobustKernel | None
    info: np.ndarray | None
    active_info: np.ndarray | None = None


def weighing(g: EdgeGroup, active_info: bool = True) -> Weighing | None:
    """The group's :class:`Weighing`, or ``None`` where :func:`unary_terms` does not apply
    (a full information matrix, or edges with different kernels).

    Args:
        g: A finalised group.
        active_info: Also :attr:`Weighing.active_info` (what :func:`unary_terms` reads; a
            compiled loop does not).
    """
    if g.info_is_identity:
        info = None
    elif g.info_diagonal is not None:
        info = g.info_diagonal
    else:
        return None
    kernel = g.sole_kernel
    if kernel is None and g.kernels:
        return None  # different kernels, or some edges without one
    act = g.active_edges
    count = g.size if act is None else int(np.count_nonzero(act))
    both = None if act is None or info is None or not active_info else info * act[:, None]
    return Weighing(g.activity_version, act, count, kernel, info, both)


def unary_terms(wg: Weighing, e: np.ndarray, J: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray | None,
                           np.ndarray | None]:
    """``e'Ωe`` per edge (every edge's, and 0 where inactive), its sum, the robust sum and,
    with ``J``, the terms ``Hᵀ = (Jᵀρ'ΩJ)ᵀ`` ``(d, d)`` and ``Jᵀρ'Ωe`` ``(d,)`` of the group.

    An inactive edge weighs zero instead of having its rows zeroed (the same numbers for
    finite rows; a non-finite one reaches ``H``, where the caller finds it).

    Args:
        wg: The group's weighing at the current activity version.
        e: ``(m, rows)`` errors.
        J: ``(m, rows, d)`` Jacobians on the free vertex, or ``None`` for none.
    """
    info = wg.info
    oe = e if info is None else e * info
    s = every = row_dots(e, oe)
    act = wg.active
    if act is not None:  # an inactive edge's non-finite error must not reach the sums
        s = np.where(act, s, 0.0)
    kernel = wg.kernel
    chi = float(s.sum())
    w: np.ndarray | None = None
    if kernel is None:
        rchi = chi
    elif J is None:
        rchi = float(kernel.cost(s).sum())
    else:
        rho, w = kernel.cost_and_clipped_weight(s)
        rchi = float(rho.sum())
    if J is None:
        return every, s, chi, rchi, None, None
    both = wg.active_info
    if both is not None:  # Ω·act·ρ' as (Ω·act)·ρ': the same products, act being 0 or 1
        wd = both if w is None else both * w[:, None]
    else:
        if act is not None:
            w = act if w is None else w * act
        if w is None:
            wd = info
        else:
            wd = w[:, None] if info is None else info * w[:, None]
    d = J.shape[-1]
    J2 = J.reshape(-1, d)
    if wd is None:
        return every, s, chi, rchi, J2.T @ J2, e.reshape(-1) @ J2
    return (every, s, chi, rchi, (J * wd[..., None]).reshape(-1, d).T @ J2,
            (e * wd).reshape(-1) @ J2)


class CompiledGroup(NamedTuple):
    """A group's :class:`~graphopt.compiled.CompiledUnary` with its weighing's inputs.

    Attributes:
        unary: The type's loop.
        info: ``(m|1, rows)`` the information's diagonal (one row: shared; ones: identity).
        active: ``(m,)`` the active edges, ``(0,)`` when all are.
        code: The kernel's code (:func:`~graphopt.compiled.kernel_code`).
        delta: Its width.
        count: How many edges are active.
    """

    unary: CompiledUnary
    info: np.ndarray
    active: np.ndarray
    code: int
    delta: float
    count: int


def compiled_group(unary: CompiledUnary | None, wg: Weighing | None) -> CompiledGroup | None:
    """The group's compiled evaluation at this weighing, or ``None`` where the loop does not
    apply (no loop, no fused weighing, a kernel it has no code for).

    Args:
        unary: The type's loop, or ``None``.
        wg: The group's weighing, or ``None``.
    """
    kc = None if unary is None or wg is None else kernel_code(wg.kernel)
    if kc is None:
        return None
    assert unary is not None and wg is not None
    info = (np.ones((1, unary.rows)) if wg.info is None
            else np.ascontiguousarray(wg.info.reshape(-1, unary.rows), dtype=float))
    active = (np.zeros(0, dtype=bool) if wg.active is None
              else np.ascontiguousarray(wg.active, dtype=bool))
    return CompiledGroup(unary, info, active, *kc, wg.count)


def compiled_terms(cg: CompiledGroup, x: np.ndarray, lin: bool
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                              float, float]:
    """:func:`unary_terms`' numbers and the errors from the compiled loop:
    ``(e, every, s, H, b, chi2, robust chi2)`` (``H`` and ``b`` zero unless ``lin``).

    Args:
        cg: The group's compiled evaluation.
        x: The free vertex's estimate.
        lin: Also ``H`` and ``b``.
    """
    u = cg.unary
    return u.fn(x, *u.args, cg.info, cg.active, cg.code, cg.delta, lin)
