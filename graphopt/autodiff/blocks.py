"""One block of edges through the tape (:func:`graphopt.autodiff.jacobians.autodiff_linearize`):
the error on jets, then the reverse pass; and a block's arrays as the inputs of a traced
program (:mod:`graphopt.autodiff.programs`)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

import graphopt.autodiff.programs as programs
import graphopt.autodiff.tape as tape
from graphopt.autodiff.jet import Jet
from graphopt.autodiff.reverse import backward
from graphopt.errors import GraphError

__all__ = ["Block", "first_blocks", "inputs_of", "split"]


def inputs_of(arrays: list[list[Any]], z: np.ndarray, rows: np.ndarray) -> list[Any]:
    """A block's arrays as a program's inputs (the absent ones and slices left out)."""
    return [a for arr in arrays for a in arr if isinstance(a, np.ndarray)] + [z, rows]


def split(arrays: list[list[Any]], inputs: list[Any]) -> list[list[Any]]:
    """:func:`inputs_of`' arrays (traced views of them) back in the positions' order."""
    it = iter(inputs)
    return [[next(it) if isinstance(a, np.ndarray) else a for a in arr] for arr in arrays]


class Block:
    """One block through the tape: the error on jets, then the reverse pass.

    Args:
        edge_type: The edge class.
        pos: The vertex positions.
        measurement: ``(m, …)`` all measurements.
        ctx: The caller's context.
        want: Derived values recomputed on jets.
        split: The group is evaluated in several blocks (a sub-context per block).
        dim: Error dimension.
        n: Total directions.
    """

    def __init__(self, edge_type: Any, pos: list[Any], measurement: np.ndarray,
                 ctx: Any, want: bool, split: bool, dim: int, n: int) -> None:
        self.edge_type, self.pos, self.measurement, self.ctx = edge_type, pos, measurement, ctx
        self.want, self.split, self.dim, self.n = want, split, dim, n

    def __call__(self, sl: slice, arrays: list[list[Any]], rows: np.ndarray | None,
                 z: np.ndarray | None = None) -> tuple[Any, Any, np.ndarray | None]:
        """``(error (a jet, or plain without derivatives), active or None, J (dim, n, mb) or
        None)`` of block ``sl`` from its arrays, ``rows`` the scratch for ``J``, ``z`` its
        measurements (traced: then the error's value is returned, not the jet)."""
        ctx = self.ctx
        blocks = [p.build(sl, a) for p, a in zip(self.pos, arrays, strict=True)]
        sub = ctx.subset(sl) if ctx is not None and self.split else ctx
        if sub is not None and (self.want or getattr(sub, "derived", None) is not None):
            derived = tuple(b[1] for b in blocks) if self.want else None
            if sub is ctx:  # (the caller's: not changed)
                sub = replace(sub, derived=derived)
            else:
                sub.derived = derived
        mb = sl.stop - sl.start
        traced = z is not None
        z = self.measurement[sl] if z is None else z
        with tape.recording():
            ev = self.edge_type.evaluate([b[0] for b in blocks], z, sub)
        eb, ab = (ev.error, ev.active) if hasattr(ev, "error") else (ev, None)
        # (a jet's own shape: np.shape would go through the array-function protocol)
        shape = eb.value.shape if type(eb) is Jet else np.shape(eb)
        if tuple(shape) != (mb, self.dim):
            raise GraphError(f"{self.edge_type.__name__}.error returned shape "
                             f"{tuple(shape)}, expected {(mb, self.dim)}")
        if type(eb) is not Jet:
            tape.clear()
            return eb, ab, None
        J = backward(eb, self.n, rows) if eb._tape is not None else None
        tape.clear()
        return (eb.value if traced else eb), ab, J


def first_blocks(plan: programs.Plan, run: Block, sl: slice, arrays: list[list[Any]],
                  inputs: list[Any], traced: slice | None) -> tuple[Any, slice | None]:
    """A block of a plan without a checked program: traced (``None`` if that failed: the
    caller uses the tape), or the tape's block and the program checked against it. Returns
    ``(the block's results, the block traced in this call)``."""
    if plan.program is None:
        out = plan.trace(inputs, lambda t: run(sl, split(arrays, t), t[-1], t[-2]))
        return out, (sl if out is not None else None)
    out = run(sl, arrays, inputs[-1])  # the tape's block, then the program's on a copy of
    if type(out[0]) is Jet and out[2] is not None:  # its inputs: the same, bit for bit?
        plan.check(inputs[:-1] + [np.empty(inputs[-1].size)], out[0].value, out[1], out[2])
    else:
        plan.dead = True
    return out, traced
