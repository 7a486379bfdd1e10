"""Compiled (numba) inner loops for the per-robot work, O(N) in one pass.

Each function here has a plain-numpy reference elsewhere that defines what it
computes (``harness.agents.interpolate``/``reflect`` and
``harness.kde.KDE.bin_weights``); tests check that both agree. Compiled on first
use and cached on disk next to this file.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=False, nogil=True)
def euler_maruyama_step(
    pos: np.ndarray,
    vc: np.ndarray,
    noise: np.ndarray,
    dt: float,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    nx: int,
    ny: int,
) -> None:
    """In place: ``pos += interp(vc, pos) dt + noise``, then reflect at the walls.

    ``pos`` is ``(2, N)``, ``vc`` the cell-centre velocity ``(2, ny, nx)`` and
    ``noise`` the already scaled Brownian increments ``(2, N)``.
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    for k in range(n):
        px = pos[0, k]
        py = pos[1, k]
        u = min(max((px - x0) / dx - 0.5, 0.0), nx - 1.0)
        w = min(max((py - y0) / dy - 0.5, 0.0), ny - 1.0)
        i0 = min(int(u), nx - 2)
        j0 = min(int(w), ny - 2)
        fx = u - i0
        fy = w - j0
        a = vc[0, j0, i0] + fx * (vc[0, j0, i0 + 1] - vc[0, j0, i0])
        b = vc[0, j0 + 1, i0] + fx * (vc[0, j0 + 1, i0 + 1] - vc[0, j0 + 1, i0])
        vx = a * (1.0 - fy) + b * fy
        a = vc[1, j0, i0] + fx * (vc[1, j0, i0 + 1] - vc[1, j0, i0])
        b = vc[1, j0 + 1, i0] + fx * (vc[1, j0 + 1, i0 + 1] - vc[1, j0 + 1, i0])
        vy = a * (1.0 - fy) + b * fy
        px = px + vx * dt + noise[0, k]
        py = py + vy * dt + noise[1, k]
        if px < x0:
            px = 2.0 * x0 - px
        if px > x1:
            px = 2.0 * x1 - px
        if py < y0:
            py = 2.0 * y0 - py
        if py > y1:
            py = 2.0 * y1 - py
        pos[0, k] = min(max(px, x0), x1)
        pos[1, k] = min(max(py, y0), y1)


@numba.njit(cache=True, nogil=True)
def linear_binning(
    pos: np.ndarray, x0: float, x1: float, y0: float, y1: float, bx: int, by: int
) -> np.ndarray:
    """Linear-binning weights on the ``(by + 1, bx + 1)`` nodes, each robot adding
    ``1/N`` split bilinearly over its four surrounding nodes.
    """
    out = np.zeros((by + 1, bx + 1))
    n = pos.shape[1]
    sx = bx / (x1 - x0)
    sy = by / (y1 - y0)
    inv_n = 1.0 / n
    for k in range(n):
        tx = (pos[0, k] - x0) * sx
        ty = (pos[1, k] - y0) * sy
        ix = min(max(int(tx), 0), bx - 1)
        iy = min(max(int(ty), 0), by - 1)
        fx = tx - ix
        fy = ty - iy
        out[iy, ix] += (1.0 - fx) * (1.0 - fy) * inv_n
        out[iy, ix + 1] += fx * (1.0 - fy) * inv_n
        out[iy + 1, ix] += (1.0 - fx) * fy * inv_n
        out[iy + 1, ix + 1] += fx * fy * inv_n
    return out


@numba.njit(cache=True, nogil=True)
def assemble_faces(
    a_l: np.ndarray, a_r: np.ndarray, slot: np.ndarray, diag_slot: np.ndarray, nnz: int
) -> np.ndarray:
    """CSR data of the finite-volume operator from its face rates (1 / time).

    Face ``f`` between cells ``L`` and ``R`` adds ``-a_l`` to ``(L, L)``, ``a_r`` to
    ``(L, R)``, ``a_l`` to ``(R, L)`` and ``-a_r`` to ``(R, R)``; ``slot`` holds the
    CSR positions of those four entries for every face (four blocks of ``F``), and
    ``diag_slot`` those of the diagonal. The additions run in the order of
    ``np.bincount`` over the concatenation ``[-a_l, a_r, a_l, -a_r, 0]`` (the
    reference in :meth:`harness.fokker_planck.FokkerPlanck.matrix_reference`), so the
    result is the same bit for bit.
    """
    out = np.zeros(nnz)
    nf = a_l.size
    for f in range(nf):
        out[slot[f]] += -a_l[f]
    for f in range(nf):
        out[slot[nf + f]] += a_r[f]
    for f in range(nf):
        out[slot[2 * nf + f]] += a_l[f]
    for f in range(nf):
        out[slot[3 * nf + f]] += -a_r[f]
    for c in range(diag_slot.size):
        out[diag_slot[c]] += 0.0
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def jacobi_series(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    rhs: np.ndarray,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, int, float]:
    """Solve ``(I - dt A) x = rhs`` by the Jacobi-split Neumann series, then add the
    last residual (see :func:`harness.fokker_planck.jacobi_solve` for the maths).

    ``A`` is given by its CSR arrays. With ``D = diag(1 - dt a_ii)`` and ``N = dt
    (A - diag A)``: ``delta_0 = D^{-1} rhs``, ``r_k = N delta_k``, ``delta_{k+1} = D^{-1}
    r_k``, ``x_K = sum_{k <= K} delta_k``; the residual of ``x_K`` is exactly ``r_K``.
    Stops at the first ``K`` with ``||r_K||_1 <= tol ||rhs||_1`` or after ``max_iter``
    terms and returns ``(x_K + r_K, K + 1, ||r_K||_1 / ||rhs||_1)``. Rows run in
    parallel; every sum has a fixed order, so the result does not depend on the
    number of threads.
    """
    m = rhs.size
    diag = np.empty(m)
    for i in numba.prange(m):
        a_ii = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            if indices[jj] == i:
                a_ii += data[jj]
        diag[i] = 1.0 - dt * a_ii
    norm_b = 0.0
    for i in range(m):
        norm_b += abs(rhs[i])
    x = np.zeros(m)
    r = np.zeros(m)
    delta = np.empty(m)
    for i in numba.prange(m):
        delta[i] = rhs[i] / diag[i]
    if norm_b == 0.0:
        return x, 0, 0.0
    terms = 0
    res = np.inf
    while terms < max_iter:
        terms += 1
        for i in numba.prange(m):
            x[i] += delta[i]
            s = 0.0
            for jj in range(indptr[i], indptr[i + 1]):
                j = indices[jj]
                if j != i:
                    s += data[jj] * delta[j]
            r[i] = dt * s
        res = 0.0
        for i in range(m):
            res += abs(r[i])
        res /= norm_b
        if res <= tol:
            break
        for i in numba.prange(m):
            delta[i] = r[i] / diag[i]
    for i in numba.prange(m):
        x[i] += r[i]
    return x, terms, res
