"""Sparse Cholesky with CHOLMOD (scikit-sparse): symbolic analysis once, numeric refactorisation
every iteration."""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError
from graphopt.linear.indexing import concat_ranges
from graphopt.solvers.base import LinearSolver
from graphopt.solvers.rank import checked_solve, shift_diagonal

try:  # scikit-sparse is optional: it needs SuiteSparse headers to build.
    from sksparse.cholmod import CholmodNotPositiveDefiniteError
    from sksparse.cholmod import analyze as _cholmod_analyze

    CHOLMOD_AVAILABLE = True
    CHOLMOD_IMPORT_ERROR = ""
except ImportError as _exc:  # pragma: no cover - depends on the machine
    CHOLMOD_AVAILABLE = False
    CHOLMOD_IMPORT_ERROR = str(_exc)


def cholmod_blas() -> str:
    """The BLAS that CHOLMOD runs on, as the file the process mapped for it (Linux), e.g.
    ``".../openblas-pthread/libblas.so.3"`` or Debian's reference ``".../blas/libblas.so.3"``;
    ``""`` when CHOLMOD is not loaded or the process's maps cannot be read.

    Supernodal factorisations spend their time in BLAS: on the reference BLAS they are several
    times slower (``scripts/bootstrap.sh`` installs OpenBLAS as the system BLAS).
    """
    if not CHOLMOD_AVAILABLE:
        return ""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "libblas" in line or "openblas" in line}
    except OSError:
        return ""
    return os.path.realpath(sorted(paths)[0]) if paths else ""


class LinearSolverCholmod(LinearSolver):
    """Supernodal/simplicial Cholesky from SuiteSparse with a fill-reducing ordering.

    ``mode="auto"`` is CHOLMOD's choice (supernodal when its flop count per entry of ``L`` is
    at least 40) except for systems whose diagonal blocks have at most 3 unknowns (2-D poses and
    points), which get the simplicial factorisation: their supernodes are small and the BLAS
    calls on them cost more than they save. Measured on the 29,997-unknown system of the
    10,000-pose graph ``w10000`` (one thread, OpenBLAS, AMD ordering): simplicial 47 ms per
    factorisation and solve, supernodal 71 ms; on the 3-D sphere (13,194 unknowns, 6x6 blocks)
    supernodal 131 ms, simplicial 319 ms.

    Every factorisation is held to the rank rule of :mod:`graphopt.solvers.rank` through the
    factor's diagonal (``Factor.D()`` reads it in place, ``L_kk²`` of a supernodal ``LLᵀ``, ``D``
    of a simplicial ``LDLᵀ``, without converting the factor): CHOLMOD itself rejects only a
    non-positive pivot of an ``LLᵀ`` factor, and only an exactly zero one of the simplicial
    ``LDLᵀ``, which otherwise factorises indefinite and singular matrices alike. On w10000
    (29,997 unknowns; factorisation 43 ms simplicial, 54 ms supernodal) reading and screening
    the pivots takes 0.14 ms and 0.8 ms; the probe of a system with a pivot below the screen
    (w10000's smallest ratio is about 1e-7) adds 0.8 ms (a second right-hand-side column).

    ``ordering="auto"`` is CHOLMOD's default (AMD, METIS where AMD fills badly) for systems
    whose blocks have at most 3 unknowns and NESDIS (CHOLMOD's nested dissection) for the
    others — applied to the graph of the blocks when the optimizer asks :meth:`block_order`
    before it builds the pattern (which is then factorised in the order given), else to the
    scalar unknowns. Measured, one thread, factorisation and solve: the sphere's supernodal factor
    (13,194 unknowns, 6x6 blocks) 81–83 ms with NESDIS or METIS against 99 ms with AMD (fill
    2.09M against 2.56M entries; NESDIS's analysis 24 ms against 9, once); w10000's simplicial
    factor 46 ms with CHOLMOD's default against 87 ms with NESDIS (fill 1.23M against 1.26M);
    a BAL street scene's reduced camera system (300 cameras, 9x9 blocks, 2,700 unknowns)
    39 ms with NESDIS against 74 ms with AMD (fill 0.77M against 0.89M).
    ``"best"`` (CHOLMOD tries AMD, METIS and NESDIS and keeps the least fill) matched these
    choices at 4–10 times their analysis time.

    Args:
        mode: ``"auto"``, ``"simplicial"`` or ``"supernodal"``.
        ordering: ``"auto"`` (above), or CHOLMOD's ordering method: ``"default"``, ``"amd"``,
            ``"colamd"``, ``"metis"``, ``"nesdis"``, ``"natural"`` or ``"best"``.
    """

    name = "cholmod"

    def __init__(self, mode: str = "auto", ordering: str = "auto") -> None:
        if not CHOLMOD_AVAILABLE:
            raise ImportError(f"CHOLMOD (scikit-sparse) is not available: {CHOLMOD_IMPORT_ERROR}")
        if mode not in ("auto", "simplicial", "supernodal"):
            raise ValueError(f"unknown CHOLMOD mode {mode!r}; choose auto, simplicial or "
                             "supernodal")
        self.mode, self.ordering = mode, ordering
        self._factor = None
        self._blocks_ordered = False

    def block_order(self, keys: np.ndarray, block_sizes: np.ndarray) -> np.ndarray | None:
        """For ``ordering="auto"``: the ordering of the class docstring applied to the graph of
        the blocks (AMD for blocks of at most 3 unknowns, NESDIS for larger ones); ``analyze``
        then keeps the order it is given.

        Measured, one thread (the fill and flops equal those of the scalar orderings): on
        w10000 (10,000 3x3 blocks) the simplicial factorisation of the matrix so ordered takes
        41–42 ms against 46–47 ms in CHOLMOD's own order of the scalar unknowns: a block's
        unknowns stay together in memory, and CHOLMOD's numeric factorisation no longer
        permutes what it reads; the sphere's set-up (2,200 6x6 blocks) takes 42 ms against
        50–60, NESDIS working on a graph a sixth the size.

        Args:
            keys: Sorted unique block keys ``col · n_blocks + row``, both triangles.
            block_sizes: Size of every block.
        """
        self._blocks_ordered = False
        if self.ordering != "auto" or not len(block_sizes):
            return None
        nb = len(block_sizes)
        rows, cols = keys % nb, keys // nb
        low = rows >= cols
        b = sp.csc_matrix((np.ones(int(low.sum())), (rows[low], cols[low])), shape=(nb, nb))
        method = "default" if int(np.max(block_sizes)) <= 3 else "nesdis"
        order = _cholmod_analyze(b, mode="simplicial", ordering_method=method).P()
        self._blocks_ordered = True
        return np.asarray(order, dtype=np.int64)

    def analyze(self, pattern: sp.csc_matrix, block_sizes: np.ndarray) -> None:
        """Symbolic analysis (ordering, elimination tree) of the pattern.

        Args:
            pattern: Full symmetric CSC pattern.
            block_sizes: Diagonal block sizes.
        """
        super().analyze(pattern, block_sizes)
        # CHOLMOD reads one triangle of a symmetric matrix (sksparse passes the lower one), and
        # its numeric factorisation first permutes and transposes what it is given: handing it
        # the lower triangle alone halves that copy (w10000: 42.6 ms against 46.3 a
        # factorisation, the gather of the triangle included).
        if self._diag_pos is not None and pattern.has_sorted_indices:
            # A column's lower part runs from its diagonal entry to its end: no pass over
            # every entry (w10000: 3 ms against 14).
            lens = pattern.indptr[1:] - self._diag_pos
            self._lower = concat_ranges(self._diag_pos, lens)
            indptr = np.concatenate([[0], np.cumsum(lens)])
        else:
            cols = np.repeat(np.arange(pattern.shape[0]), np.diff(pattern.indptr))
            lower = pattern.indices >= cols
            self._lower = np.flatnonzero(lower)
            indptr = np.concatenate([[0], np.cumsum(np.bincount(cols[lower],
                                                                minlength=pattern.shape[1]))])
        self._nnz = pattern.nnz
        # One matrix object whose values are overwritten for every factorisation: SciPy's
        # constructor checks cost 0.15 ms a call, a tenth of a small graph's iteration.
        self._lower_csc = sp.csc_matrix(
            (np.zeros(len(self._lower)), pattern.indices[self._lower],
             indptr.astype(pattern.indptr.dtype)), shape=pattern.shape)
        self._lower_csc.has_sorted_indices = True
        # Analyse with a structurally full matrix (ones) so the symbolic factor covers all
        # entries of the pattern whatever the values become.
        probe = self._lower_csc
        probe.data.fill(1.0)
        small_blocks = bool(len(block_sizes)) and int(np.max(block_sizes)) <= 3
        mode = "simplicial" if self.mode == "auto" and small_blocks else self.mode
        ordering = self.ordering
        if ordering == "auto":  # the pattern comes in the block order asked for, if it was
            ordering = ("natural" if self._blocks_ordered
                        else "default" if small_blocks else "nesdis")
        self._blocks_ordered = False  # a next pattern is ordered only if asked again
        self._factor = _cholmod_analyze(probe, mode=mode, ordering_method=ordering)
        self._order = self._factor.P()  # the unknown eliminated at each step

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side.
        """
        assert self._factor is not None
        f = self._factor
        stopped_at = None
        try:
            f.cholesky_inplace(self._lower_matrix(data))
        except CholmodNotPositiveDefiniteError as exc:
            stopped_at = int(exc.column)  # L->minor: the step with the non-positive pivot
        pivots = f.D()  # read in place: L_kk² of a supernodal LLᵀ, D of a simplicial LDLᵀ
        x = checked_solve(self.name, pivots[:stopped_at], data[self.diag_pos], f, rhs,
                          lambda s: self._shifted_is_definite(data, s),
                          unknowns=self._order, stopped_at=stopped_at)
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("CHOLMOD produced non-finite values")
        return x

    def _lower_matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """The lower triangle of the matrix with ``data`` in the analysed (full) pattern (the
        same object every call: CHOLMOD copies what it reads)."""
        if len(data) != self._nnz:
            raise ValueError(f"cholmod: {len(data)} values for a pattern of {self._nnz}")
        # The positions come from the pattern, so they are in range: "wrap" skips the buffered
        # bounds check of the default mode and halves the gather (w10000: 0.5 ms against 1.0).
        np.take(data, self._lower, out=self._lower_csc.data, mode="wrap")
        return self._lower_csc

    def _shifted_is_definite(self, data: np.ndarray, scale: np.ndarray) -> bool:
        """Whether ``A + τ·S`` factorises with positive, finite pivots (the factor is left in
        place: the next solve refactorises)."""
        assert self._factor is not None
        try:
            self._factor.cholesky_inplace(
                self._lower_matrix(shift_diagonal(data, self.diag_pos, scale)))
        except CholmodNotPositiveDefiniteError:
            return False
        d = self._factor.D()
        return bool(np.all(np.isfinite(d)) and np.all(d > 0))
