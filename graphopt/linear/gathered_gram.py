"""``GatheredGram``: sums of block products ``AᵀB`` per output by batched BLAS calls over
gathered blocks (see the class), planned first — sizes for a cost model — and built once
chosen."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["GatheredGram"]


#: What :meth:`GatheredGram.build` makes.
_BUILT = frozenset({"ia", "ib", "pads", "chunks", "_bufa", "_bufb"})


class GatheredGram:
    """``out[j] = Σ_{q: piece[q]=j} A[a_idx[q]]ᵀ · B[b_idx[q]]`` by batched BLAS products.

    For sums with many terms per output (the pairs of U blocks that share V blocks, in a
    Schur complement with few U blocks; a camera's ``JᵀJ`` over its observations), a product per
    output beats a sparse contraction: the ``(r, d)`` blocks of an output's terms are gathered,
    whole rows at a time, into two contiguous ``(n·r, d)`` matrices and multiplied by BLAS
    (about 0.14 ns per multiply-add against SciPy's sparse loop's 0.4). Outputs with similar
    term counts share one ``np.matmul`` call: each is padded to the largest count of its chunk
    with zero blocks, and a chunk gathers at most ``max_blocks`` blocks a side, so that it stays
    in cache. Outputs with more terms than that are split into pieces (the caller sums the
    pieces of a target). Where every term of a chunk has ``a == b`` and ``B`` is ``A``, one
    gather serves both sides. Everything but the numbers is fixed here.

    Args:
        target: ``(q,)`` target of every term.
        a_idx: ``(q,)`` left block of every term.
        b_idx: ``(q,)`` right block of every term.
        n_targets: Number of targets.
        r: Rows of a block.
        d: Columns of a block.
        max_blocks: Most blocks a chunk gathers per side.
        ratio: Largest ratio of term counts padded to one size.

    Attributes:
        targets: ``(n_out,)`` target of every output (a target's pieces are separate outputs).
        n_out: Number of outputs.
        padded: Blocks multiplied, padding included.
        gathered: Blocks gathered when ``B`` is ``A``, padding included.
        n_chunks: Number of ``np.matmul`` calls.
    """

    def __init__(
        self,
        target: np.ndarray,
        a_idx: np.ndarray,
        b_idx: np.ndarray,
        n_targets: int,
        r: int,
        d: int,
        max_blocks: int = 1024,
        ratio: float = 1.1,
    ) -> None:
        self.r, self.d = r, d
        if n_targets == 1 and 0 < len(target) <= max_blocks:
            self._one_output(np.asarray(a_idx), np.asarray(b_idx), r, d)
            return
        target = np.asarray(target, dtype=np.int64)
        order = np.argsort(target, kind="stable")
        target = target[order]
        a_idx = np.asarray(a_idx, dtype=np.int64)[order]
        b_idx = np.asarray(b_idx, dtype=np.int64)[order]
        cnt = np.bincount(target, minlength=n_targets)
        start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        rank = np.arange(len(target)) - start[target]
        # Pieces of at most max_blocks terms; a piece is one output.
        n_pieces = -(-cnt // max_blocks)
        first = np.concatenate([[0], np.cumsum(n_pieces)[:-1]])
        piece = first[target] + rank // max_blocks
        pos = rank % max_blocks  # place of a term within its piece
        n_out = int(n_pieces.sum())
        piece_target = np.repeat(np.arange(n_targets), n_pieces)
        pcnt = np.bincount(piece, minlength=n_out)
        same = np.bincount(piece, weights=a_idx != b_idx, minlength=n_out) == 0
        # Chunks: pieces of one kind (a == b or not) and one count level, padded to the
        # level's largest count.
        level = np.floor(np.log(np.maximum(pcnt, 1)) / np.log(ratio) + 1e-9).astype(np.int64)
        porder = np.lexsort((pcnt, level, ~same))
        key = (~same[porder]).astype(np.int64) * (int(level.max(initial=0)) + 1) + level[porder]
        bounds = np.flatnonzero(np.diff(key)) + 1
        slot = np.empty(n_out, dtype=np.int64)  # first padded slot of every output
        p0 = 0
        spans = []
        for b0, b1 in zip(np.r_[0, bounds].tolist(), np.r_[bounds, n_out].tolist(), strict=True):
            m = int(pcnt[porder[b1 - 1]])
            per = max(1, max_blocks // m)
            for o0 in range(b0, b1, per):
                n = min(per, b1 - o0)
                slot[o0:o0 + n] = p0 + m * np.arange(n)
                spans.append((p0, n, m, o0, bool(same[porder[o0]])))
                p0 += n * m
        self.padded = p0
        self.gathered = sum(n * m * (1 if sm else 2) for _, n, m, _, sm in spans)
        self.targets = piece_target[porder]
        self.n_out = n_out
        self.n_chunks = len(spans)
        # What build() needs: a cost model reads the sizes above and may choose another
        # product (a local BA's camera blocks: 0.2 of its 5 ms set-up for a Gram not taken).
        self._plan = (a_idx, b_idx, piece, pos, porder, slot, spans, len(target))

    def __getattr__(self, name: str) -> Any:
        """``ia``, ``ib``, ``pads``, ``chunks`` of a Gram not built yet: built on first read."""
        if name in _BUILT and self.__dict__.get("_plan") is not None:
            self.build()
            return getattr(self, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def build(self) -> None:
        """The gather indices, padding and buffers of the planned chunks (once; a chosen
        Gram is built at set-up, not at its first call)."""
        if self._plan is None:
            return
        a_idx, b_idx, piece, pos, porder, slot, spans, q = self._plan
        self._plan = None
        p0, n_out, r, d = self.padded, self.n_out, self.r, self.d
        out_of = np.empty(n_out, dtype=np.int64)
        out_of[porder] = np.arange(n_out)  # output row of every piece
        dest = slot[out_of[piece]] + pos
        # Padding slots gather block 0, then are zeroed; int32 where it fits (np.take widens a
        # chunk's indices, at most max_blocks, on the fly): 8 bytes per term fewer.
        idx_t = np.int32 if max(q, int(a_idx.max(initial=0)),
                                int(b_idx.max(initial=0))) < 2**31 else np.intp
        self.ia = np.zeros(p0, dtype=idx_t)
        self.ib = np.zeros(p0, dtype=idx_t)
        self.ia[dest], self.ib[dest] = a_idx, b_idx
        filled = np.zeros(p0, dtype=bool)
        filled[dest] = True
        pads, q0 = [], 0
        # Chunks as (first slot, outputs, padded count, first output, same, pad range).
        self.chunks: list[tuple[int, int, int, int, bool, int, int]] = []
        for c0, n, m, o0, sm in spans:  # padding slots of every chunk, relative to its start
            pad = np.flatnonzero(~filled[c0:c0 + n * m])
            pads.append(pad)
            self.chunks.append((c0, n, m, o0, sm, q0, q0 + len(pad)))
            q0 += len(pad)
        self.pads = np.concatenate(pads) if pads else np.zeros(0, dtype=np.intp)
        largest = max((n * m for _, n, m, _, _, _, _ in self.chunks), default=0)
        self._bufa = np.zeros(largest * r * d)
        self._bufb = np.zeros(largest * r * d)

    def _one_output(self, a_idx: np.ndarray, b_idx: np.ndarray, r: int, d: int) -> None:
        """The general plan of one output of at most ``max_blocks`` terms (a pose's block) in
        O(1) numpy calls: one chunk, one piece, no padding, the terms in their order.

        Args:
            a_idx: ``(q,)`` left blocks.
            b_idx: ``(q,)`` right blocks.
            r: Rows of a block.
            d: Columns of a block.
        """
        q = len(a_idx)
        same = bool(np.array_equal(a_idx, b_idx))
        idx_t = np.int32 if max(q, int(a_idx.max()), int(b_idx.max())) < 2**31 else np.intp
        self.ia = a_idx.astype(idx_t)
        self.ib = b_idx.astype(idx_t)
        self.chunks = [(0, 1, q, 0, same, 0, 0)]
        self.n_chunks = 1
        self._plan = None  # (built)
        self.pads = np.zeros(0, dtype=np.intp)
        self.padded = q
        self.gathered = q * (1 if same else 2)
        self.targets = np.zeros(1, dtype=np.int64)
        self.n_out = 1
        self._bufa = np.zeros(q * r * d)
        self._bufb = np.zeros(q * r * d)

    def __call__(self, A: np.ndarray, out: np.ndarray, B: np.ndarray | None = None) -> None:
        """Write every output into ``out``.

        Args:
            A: ``(nA, r·d)`` left blocks as rows (C-contiguous).
            out: ``(n_out, d, d)`` output (overwritten).
            B: ``(nB, r·d)`` right blocks as rows; ``None``: the same as ``A``.
        """
        if self._plan is not None:
            self.build()
        r, d = self.r, self.d
        w = r * d
        for p0, n, m, o0, same, q0, q1 in self.chunks:
            a = self._bufa[:n * m * w].reshape(n * m, w)
            np.take(A, self.ia[p0:p0 + n * m], axis=0, out=a, mode="clip")  # clip: unbuffered
            if q1 > q0:
                a[self.pads[q0:q1]] = 0.0
            b = a
            if not same or B is not None:
                b = self._bufb[:n * m * w].reshape(n * m, w)
                np.take(A if B is None else B, self.ib[p0:p0 + n * m], axis=0, out=b,
                        mode="clip")
            np.matmul(a.reshape(n, m * r, d).transpose(0, 2, 1), b.reshape(n, m * r, d),
                      out=out[o0:o0 + n])
