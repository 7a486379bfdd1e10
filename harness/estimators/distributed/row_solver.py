"""``(I - dt A)^{-1}`` applied to every robot's row by one sparse LU.

The per-robot filters' implicit predict falls back on it when the Jacobi sweeps or the
Neumann series would take too many terms (:mod:`harness.estimators.distributed.filters`). One
factorisation serves every robot; the triangular solves are compiled and run over
blocks of robots at once.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@numba.njit(cache=True, parallel=True, nogil=True)
def _lu_solve_columns(lp, li, lx, up, ui, ux, perm_r, perm_c, b, chunks):  # pragma: no cover
    """``x = A^{-1} b`` column by column for ``b`` ``(M, K)`` (columns are robots), from
    SuperLU's factors ``Pr A Pc = L U`` (CSC; ``L`` unit lower): ``c[perm_r] = b``,
    ``c <- L^{-1} c``, ``c <- U^{-1} c``, ``x = c[perm_c]``. Column chunks run in parallel;
    each column's arithmetic is fixed, so the result does not depend on the threads.
    """
    m, k = b.shape
    out = np.empty_like(b)
    step = (k + chunks - 1) // chunks
    for ch in numba.prange(chunks):
        lo = ch * step
        hi = min(k, lo + step)
        if lo >= hi:
            continue
        c = np.empty((m, hi - lo))
        for i in range(m):
            c[perm_r[i], :] = b[i, lo:hi]
        for j in range(m):
            for q in range(lp[j], lp[j + 1]):
                r = li[q]
                if r > j:
                    c[r, :] -= lx[q] * c[j, :]
        for j in range(m - 1, -1, -1):
            diag = 0.0
            for q in range(up[j], up[j + 1]):
                if ui[q] == j:
                    diag = ux[q]
            c[j, :] /= diag
            for q in range(up[j], up[j + 1]):
                r = ui[q]
                if r < j:
                    c[r, :] -= ux[q] * c[j, :]
        for i in range(m):
            out[i, lo:hi] = c[perm_c[i], :]
    return out


class RowSolver:
    """``A^{-1}`` applied to every row of an ``(N, M)`` array: one sparse LU (SuperLU,
    COLAMD), triangular solves compiled and vectorised over robots
    (:func:`_lu_solve_columns`); ``splu(A).solve`` is the reference (tests compare).
    """

    def __init__(self, a: sp.spmatrix, chunks: int | None = None, width: int = 16) -> None:
        lu = spla.splu(sp.csc_matrix(a))
        lo, up = lu.L.tocsc(), lu.U.tocsc()
        lo.sort_indices()
        up.sort_indices()
        self._args = (
            lo.indptr, lo.indices, lo.data, up.indptr, up.indices, up.data,
            lu.perm_r.astype(np.intp), lu.perm_c.astype(np.intp),
        )  # fmt: skip
        self.chunks, self.width = chunks, width

    def solve_rows(self, x: np.ndarray) -> np.ndarray:
        """``A^{-1} x_i`` for every row ``x_i``, shape ``(N, M)``; in ``chunks`` blocks
        of rows, by default blocks of ``width`` rows (a block's work array stays in
        cache).
        """
        b = np.ascontiguousarray(x.T)
        chunks = self.chunks or max(1, -(-b.shape[1] // self.width))
        return np.ascontiguousarray(_lu_solve_columns(*self._args, b, chunks).T)
