"""Compiled (numba) inner loops for the per-robot work, O(N) in one pass.

Each function here has a plain-numpy reference elsewhere that defines what it
computes (``harness.agents.interpolate``/``reflect`` and
``harness.kde.KDE.bin_weights``); tests check that both agree. Compiled on first
use and cached on disk next to this file.
"""

from __future__ import annotations

import math
import os
import types
from collections.abc import Callable
from typing import Any

# Idle OpenMP workers sleep instead of spinning (unless the user chose otherwise):
# on a machine shared with other jobs (sweeps run one job per core) spinning
# workers steal the cores the next parallel region waits for, and a kernel of
# a few ms took hundreds. Read when numba first starts its OpenMP layer.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numba
import numpy as np


def _build(fn: Callable[..., Any], parallel: bool) -> Any:
    """``numba.njit(cache=True, nogil=True, parallel=parallel)`` of a copy of ``fn``
    named ``<fn>_parallel`` or ``<fn>_serial``.

    Why a copy: numba's on-disk cache names an entry by the function's qualified name
    and first line and keys it by signature and bytecode, not by the compile flags, so
    the serial and the parallel build of one function shared one entry, and whichever
    was compiled first was loaded by both (measured: the cached "parallel" assembly ran
    at the serial speed). The copies have their own names, so their own entries.
    """
    suffix = "_parallel" if parallel else "_serial"
    copy = types.FunctionType(
        fn.__code__, fn.__globals__, fn.__name__ + suffix, fn.__defaults__, fn.__closure__
    )
    copy.__qualname__ = fn.__qualname__ + suffix
    copy.__doc__, copy.__module__ = fn.__doc__, fn.__module__
    return numba.njit(cache=True, nogil=True, parallel=parallel)(copy)


def _euler_maruyama_step(
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
    scale: float = 1.0,
) -> None:
    """In place: ``pos += interp(vc, pos) dt + scale noise``, then reflect at the walls.

    ``pos`` is ``(2, N)``, ``vc`` the cell-centre velocity ``(2, ny, nx)`` and
    ``noise`` the standard (``scale = 1``: already scaled) Gaussian increments
    ``(2, N)``. Robots are independent and run in parallel (``prange``); each robot's
    arithmetic is the same whatever the thread count, so the result is too.
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    for k in numba.prange(n):
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
        px = px + vx * dt + noise[0, k] * scale
        py = py + vy * dt + noise[1, k] * scale
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


PARALLEL_MIN_ROBOTS = 1 << 15
"""Fewer robots run the serial build of the same loop: a parallel region costs more
than it saves on small swarms, and much more when the cores are oversubscribed."""

_em_serial = _build(_euler_maruyama_step, parallel=False)
_em_parallel = _build(_euler_maruyama_step, parallel=True)


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
    scale: float = 1.0,
) -> None:
    """Compiled Euler-Maruyama step (see :func:`_euler_maruyama_step`), parallel from
    ``PARALLEL_MIN_ROBOTS`` robots on; the serial and parallel builds run the same
    per-robot arithmetic, so they give the same bits.
    """
    kernel = _em_parallel if pos.shape[1] >= PARALLEL_MIN_ROBOTS else _em_serial
    kernel(pos, vc, noise, dt, x0, x1, y0, y1, nx, ny, scale)


@numba.njit(cache=True, nogil=True)
def _bin_range(
    pos: np.ndarray,
    start: int,
    stop: int,
    out: np.ndarray,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    bx: int,
    by: int,
    inv_n: float,
) -> None:
    """Add robots ``start .. stop - 1`` to ``out`` in order (see :func:`linear_binning`)."""
    sx = bx / (x1 - x0)
    sy = by / (y1 - y0)
    for k in range(start, stop):
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


BIN_CHUNK_MIN = 1 << 15
"""Fewest robots per binning chunk; chunks hold at least four times as many robots
as there are nodes, so clearing a chunk's private grid costs less than filling it."""

BIN_BATCH = 8
"""Chunks binned at once (private grids alive at once), a constant so that the
summation order never depends on the thread count."""


def bin_chunk_size(n_robots: int, nodes: int) -> int:
    """Robots per chunk of :func:`linear_binning`: a function of ``N`` and the node
    count only (never of the thread count).
    """
    return max(BIN_CHUNK_MIN, 4 * nodes)


@numba.njit(cache=True, nogil=True, parallel=True)
def linear_binning_chunked(
    pos: np.ndarray, x0: float, x1: float, y0: float, y1: float, bx: int, by: int, chunk: int
) -> np.ndarray:
    """Linear-binning weights on the ``(by + 1, bx + 1)`` nodes, each robot adding
    ``1/N`` split bilinearly over its four surrounding nodes.

    Robots are cut into consecutive chunks of ``chunk``; each chunk is summed in
    robot order into a private grid (chunks of a batch of ``BIN_BATCH`` in
    parallel), and the chunk grids are added to the result in chunk order. The
    float sums are therefore fixed by ``N`` and ``chunk`` alone, not by the number
    of threads; with one chunk (``N <= chunk``) the result is the plain serial sum.
    """
    n = pos.shape[1]
    inv_n = 1.0 / n
    out = np.zeros((by + 1, bx + 1))
    n_chunks = (n + chunk - 1) // chunk
    if n_chunks <= 1:
        _bin_range(pos, 0, n, out, x0, x1, y0, y1, bx, by, inv_n)
        return out
    work = np.empty((min(BIN_BATCH, n_chunks), by + 1, bx + 1))
    for first in range(0, n_chunks, BIN_BATCH):
        count = min(BIN_BATCH, n_chunks - first)
        for c in numba.prange(count):
            work[c, :, :] = 0.0
            start = (first + c) * chunk
            _bin_range(pos, start, min(start + chunk, n), work[c], x0, x1, y0, y1, bx, by, inv_n)
        for c in range(count):
            out += work[c]
    return out


def linear_binning(
    pos: np.ndarray, x0: float, x1: float, y0: float, y1: float, bx: int, by: int
) -> np.ndarray:
    """Linear-binning weights (compiled, parallel over fixed chunks); the numpy
    reference is :meth:`harness.kde.KDE.bin_weights`.
    """
    n = pos.shape[1]
    chunk = bin_chunk_size(n, (bx + 1) * (by + 1))
    if n <= chunk:  # one chunk: the serial loop, no parallel region
        out = np.zeros((by + 1, bx + 1))
        _bin_range(pos, 0, n, out, x0, x1, y0, y1, bx, by, 1.0 / n)
        return out
    return linear_binning_chunked(pos, x0, x1, y0, y1, bx, by, chunk)


@numba.njit(cache=True, nogil=True, inline="always")
def _face_rate_pair(u: float, sigma: float, h: float) -> tuple[float, float]:  # pragma: no cover
    """``(a_L / h, a_R / h)`` of one face, the statement of
    :func:`harness.fokker_planck.face_coefficients` operation for operation (so the same
    bits): ``Pe = u h / sigma``, ``a_R = (sigma / h) (1 - Pe / 2)`` for ``|Pe| < 1e-6``
    and ``u / expm1(Pe)`` otherwise, ``a_L = a_R + u``; upwind for ``sigma = 0``.
    """
    if sigma == 0.0:
        return max(u, 0.0) / h, max(-u, 0.0) / h
    scale = sigma / h
    pe = u / scale
    a_r = scale * (1.0 - 0.5 * pe) if abs(pe) < 1e-6 else u / math.expm1(pe)
    return (a_r + u) / h, a_r / h


def _assemble_operator(
    face_x: np.ndarray,
    face_y: np.ndarray,
    sigma: float,
    dx: float,
    dy: float,
    indptr: np.ndarray,
) -> np.ndarray:
    """CSR data of ``A(v)``, the finite-volume operator of eq. ``FP equation``
    (:meth:`harness.fokker_planck.FokkerPlanck.matrix`), straight from the face
    velocities: the face rates (one parallel pass over the faces), then the rows (one
    parallel pass over the cells).

    Row ``i`` (cell ``(row, col)``) holds, in column order, ``i - n_x``, ``i - 1``,
    ``i``, ``i + 1``, ``i + n_x`` where they exist: the inflow rates ``a_L`` of the faces
    below and to the left, ``a_R`` of the faces to the right and above, and on the
    diagonal the outflows ``0 - a_L(east) - a_L(north) - a_R(west) - a_R(south) + 0``,
    added in that order, which is the order in which ``np.bincount`` adds them in
    :meth:`~harness.fokker_planck.FokkerPlanck.matrix_reference` (x faces before y
    faces, the ``-a_L`` block before the ``-a_R`` block): the same bits.
    """
    ny, nx = face_x.shape[0], face_y.shape[1]
    xl = np.empty((ny, nx - 1))
    xr = np.empty((ny, nx - 1))
    yl = np.empty((ny - 1, nx))
    yr = np.empty((ny - 1, nx))
    for row in numba.prange(ny):
        for col in range(nx - 1):
            xl[row, col], xr[row, col] = _face_rate_pair(face_x[row, col], sigma, dx)
        if row < ny - 1:
            for col in range(nx):
                yl[row, col], yr[row, col] = _face_rate_pair(face_y[row, col], sigma, dy)
    out = np.empty(indptr[-1])
    for row in numba.prange(ny):
        for col in range(nx):
            jj = indptr[row * nx + col]
            if row > 0:  # the face below: this cell is its R side
                out[jj] = 0.0 + yl[row - 1, col]
                jj += 1
            if col > 0:  # the face to the left
                out[jj] = 0.0 + xl[row, col - 1]
                jj += 1
            centre = 0.0
            if col < nx - 1:  # the face to the right: this cell is its L side
                centre += -xl[row, col]
            if row < ny - 1:  # the face above
                centre += -yl[row, col]
            if col > 0:
                centre += -xr[row, col - 1]
            if row > 0:
                centre += -yr[row - 1, col]
            out[jj] = centre + 0.0
            jj += 1
            if col < nx - 1:
                out[jj] = 0.0 + xr[row, col]
                jj += 1
            if row < ny - 1:
                out[jj] = 0.0 + yr[row, col]
    return out


_assemble_serial = _build(_assemble_operator, parallel=False)
_assemble_parallel = _build(_assemble_operator, parallel=True)


def assemble_operator(
    face_x: np.ndarray,
    face_y: np.ndarray,
    sigma: float,
    dx: float,
    dy: float,
    indptr: np.ndarray,
) -> np.ndarray:
    """Compiled :func:`_assemble_operator`, parallel from ``PARALLEL_MIN_CELLS`` cells on
    (each row is written by one thread; both builds give the same bits).
    """
    kernel = _assemble_parallel if indptr.size - 1 >= PARALLEL_MIN_CELLS else _assemble_serial
    return kernel(
        np.ascontiguousarray(face_x, dtype=float), np.ascontiguousarray(face_y, dtype=float),
        float(sigma), float(dx), float(dy), indptr,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def paper_velocity(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    f_p: np.ndarray,
    f_grad: np.ndarray,
    t_p: np.ndarray,
    t_grad: np.ndarray,
    t_log_p: np.ndarray,
    alpha: float,
    sigma: float,
    dx: float,
    dy: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Centre and face values of the paper's law (eq. ``modified density feedback law
    using estimates``; :func:`harness.control.paper_law` holds the equation and its
    discretisation, :func:`harness.control.paper_law_reference` the numpy statement) in
    one pass,
    each value by the reference's operations in the reference's order (the same bits):

        feedback = (-alpha) (f_p q_hat - p_hat f_grad) / (f_p f_p),
        centres  = feedback + (sigma t_grad) / t_p,
        face_x   = 0.5 (feedback_x[:, 1:] + feedback_x[:, :-1])
                   + (sigma (log p_*[:, 1:] - log p_*[:, :-1])) / dx,   likewise face_y,

    ``f_*`` the feedback target's cell values and gradient, ``t_*`` the target's.
    """
    ny, nx = p_hat.shape
    neg = -alpha
    feedback = np.empty((2, ny, nx))
    centres = np.empty((2, ny, nx))
    for c in range(2):
        for j in range(ny):
            for i in range(nx):
                fp = f_p[j, i]
                fb = neg * (fp * q_hat[c, j, i] - p_hat[j, i] * f_grad[c, j, i]) / (fp * fp)
                feedback[c, j, i] = fb
                centres[c, j, i] = fb + sigma * t_grad[c, j, i] / t_p[j, i]
    face_x = np.empty((ny, nx - 1))
    for j in range(ny):
        for i in range(nx - 1):
            mean = 0.5 * (feedback[0, j, i + 1] + feedback[0, j, i])
            face_x[j, i] = mean + sigma * (t_log_p[j, i + 1] - t_log_p[j, i]) / dx
    face_y = np.empty((ny - 1, nx))
    for j in range(ny - 1):
        for i in range(nx):
            mean = 0.5 * (feedback[1, j + 1, i] + feedback[1, j, i])
            face_y[j, i] = mean + sigma * (t_log_p[j + 1, i] - t_log_p[j, i]) / dy
    return centres, face_x, face_y


ROW_BLOCK = 512
"""Rows per block of :func:`jacobi_series`: partial sums per block, added in block
order, so the residual norm does not depend on the thread count."""


def _jacobi_series(
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
    (A - diag A)``: ``r_{-1} = rhs``, ``delta_k = D^{-1} r_{k-1}``, ``r_k = N delta_k``,
    ``x_K = sum_{k <= K} delta_k``; the residual of ``x_K`` is exactly ``r_K``.
    Stops at the first ``K`` with ``||r_K||_1 <= tol ||rhs||_1`` or after ``max_iter``
    terms and returns ``(x_K + r_K, K + 1, ||r_K||_1 / ||rhs||_1)``. One parallel
    pass over blocks of rows per term; every sum has a fixed order (rows in CSR
    order, blocks in index order), so the result does not depend on the number of
    threads.
    """
    m = rhs.size
    diag = np.empty(m)
    for i in numba.prange(m):
        a_ii = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            if indices[jj] == i:
                a_ii += data[jj]
        diag[i] = 1.0 - dt * a_ii
    # off-diagonal entries of N D^{-1}, zero on the diagonal
    nd = np.empty(data.size)
    for i in numba.prange(m):
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            nd[jj] = 0.0 if j == i else dt * data[jj] / diag[j]
    norm_b = 0.0
    for i in range(m):
        norm_b += abs(rhs[i])
    x = np.zeros(m)
    if norm_b == 0.0:
        return x, 0, 0.0
    r_old = rhs.copy()
    r_new = np.empty(m)
    n_blocks = (m + ROW_BLOCK - 1) // ROW_BLOCK
    partial = np.empty(n_blocks)
    terms = 0
    res = np.inf
    while terms < max_iter:
        terms += 1
        for b in numba.prange(n_blocks):
            acc = 0.0
            for i in range(b * ROW_BLOCK, min((b + 1) * ROW_BLOCK, m)):
                x[i] += r_old[i] / diag[i]
                s = 0.0
                for jj in range(indptr[i], indptr[i + 1]):
                    s += nd[jj] * r_old[indices[jj]]
                r_new[i] = s
                acc += abs(s)
            partial[b] = acc
        res = 0.0
        for b in range(n_blocks):
            res += partial[b]
        res /= norm_b
        r_old, r_new = r_new, r_old
        if res <= tol:
            break
    for i in numba.prange(m):
        x[i] += r_old[i]
    return x, terms, res


@numba.njit(cache=True, nogil=True, inline="always")
def _stencil_sum(rhs, w, x, i, k, row, col, nx, ny):  # pragma: no cover - compiled
    """``rhs_i + sum_j N_ij x_j`` for cell ``i`` (``row``, ``col``) and column ``k`` of
    :func:`_red_black`; out-of-grid neighbours have weight 0, so cell ``i`` is read.
    """
    iw = i - 1 if col > 0 else i
    ie = i + 1 if col < nx - 1 else i
    is_ = i - nx if row > 0 else i
    in_ = i + nx if row < ny - 1 else i
    return (
        rhs[i, k] + w[i, 0] * x[iw, k] + w[i, 1] * x[ie, k]
        + w[i, 2] * x[is_, k] + w[i, 3] * x[in_, k]
    )  # fmt: skip


def _red_black(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    rhs: np.ndarray,
    nx: int,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, int, float]:
    """Solve ``(I - dt A) X = RHS`` for the ``c`` columns of ``rhs`` ``(M, c)`` by
    red-black Gauss-Seidel sweeps from ``X = 0``, then add the last residual (see
    :func:`harness.fokker_planck.red_black_solve`).

    ``A`` is a 5-point operator on a grid of ``nx`` columns (row ``k`` is cell ``(k //
    nx, k % nx)``; red cells have even ``row + col``), given by its CSR arrays, ``D =
    diag(I - dt A)`` and ``N = dt (A - diag A)``. A first pass turns the CSR rows into
    the stencil (``D`` and the four neighbour weights of ``N``, zero across walls), so a
    sweep reads fixed offsets. A sweep updates the red cells from the black ones, ``x_i
    <- (rhs_i + sum_j N_ij x_j) / D_i``, then the black cells from the new red ones.
    After a sweep the residual ``r = rhs - (D - N) x`` is zero on black cells; on red
    cells it is ``s_i - D_i x_i`` with ``s_i`` the sum the next red update computes
    anyway, so each sweep is one pass over the stencil. Sweeps stop at the first ``K``
    at which every column has ``||r||_1 <= tol ||rhs||_1`` (columns are swept together,
    sharing the stencil's reads); the red cells' new values are taken back (``x_i =
    (s_i - r_i) / D_i``, to round-off) and ``(X_K + R, K, max_c ||r_c||_1 /
    ||rhs_c||_1)`` is returned; after ``max_iter`` sweeps (at least one) the iterate
    ``X_K`` itself with its largest relative residual. An operator that is not 5-point
    on rows of ``nx`` cells (a coupling other than the four grid neighbours, or ``nx``
    not dividing the size) returns ``(0, -1, inf)``: the colouring would be wrong.
    Each phase is one parallel pass over the grid's rows (a cell's neighbours have the
    other colour, so the cells of one colour are independent), and every sum has a
    fixed order, so the result does not depend on the number of threads.
    """
    m, c = rhs.shape
    ny = m // nx
    diag = np.empty(m)
    w = np.zeros((m, 4))  # weights of the neighbours at -1, +1, -nx, +nx
    foreign = np.zeros(ny, dtype=np.int64)  # couplings that are not grid neighbours
    for row in numba.prange(ny):
        for col in range(nx):
            i = row * nx + col
            a_ii = 0.0
            for jj in range(indptr[i], indptr[i + 1]):
                step = indices[jj] - i
                if step == 0:
                    a_ii += data[jj]
                elif step == -1 and col > 0:
                    w[i, 0] += dt * data[jj]
                elif step == 1 and col < nx - 1:
                    w[i, 1] += dt * data[jj]
                elif step == -nx:
                    w[i, 2] += dt * data[jj]
                elif step == nx:
                    w[i, 3] += dt * data[jj]
                elif data[jj] != 0.0:
                    foreign[row] += 1
            diag[i] = 1.0 - dt * a_ii
    x = np.zeros((m, c))
    r = np.zeros((m, c))
    if ny * nx != m or foreign.sum() > 0:
        return x, -1, np.inf  # not a 5-point operator on rows of nx cells
    norm_b = np.zeros(c)
    for i in range(m):
        for k in range(c):
            norm_b[k] += abs(rhs[i, k])
    for k in range(c):
        if norm_b[k] == 0.0:
            norm_b[k] = 1.0  # a zero column stays zero, with zero residual
    partial = np.empty((ny, c))
    sweeps = 0
    res = np.inf
    while True:
        # red cells: the residual of the current iterate, then the update
        for row in numba.prange(ny):
            for k in range(c):  # a column at a time: the row's stencil stays in cache
                acc = 0.0
                for col in range(row % 2, nx, 2):
                    i = row * nx + col
                    s = _stencil_sum(rhs, w, x, i, k, row, col, nx, ny)
                    res_i = s - diag[i] * x[i, k]
                    r[i, k] = res_i
                    acc += abs(res_i)
                    x[i, k] = s / diag[i]
                partial[row, k] = acc
        if sweeps > 0:  # before the first sweep the black cells' residual is rhs
            res = 0.0
            for k in range(c):
                col_res = 0.0
                for row in range(ny):
                    col_res += partial[row, k]
                res = max(res, col_res / norm_b[k])
            if res <= tol or sweeps >= max(max_iter, 1):
                break
        # black cells from the new red ones
        for row in numba.prange(ny):
            for k in range(c):
                for col in range((row + 1) % 2, nx, 2):
                    i = row * nx + col
                    s = _stencil_sum(rhs, w, x, i, k, row, col, nx, ny)
                    x[i, k] = s / diag[i]
        sweeps += 1
    # back to the last full sweep on red cells, plus the residual when converged (the
    # returned norm is then that of the corrected vector's residual before correction)
    add = 1.0 if res <= tol else 0.0
    for row in numba.prange(ny):
        for col in range(row % 2, nx, 2):
            i = row * nx + col
            for k in range(c):
                x[i, k] = (x[i, k] - r[i, k] / diag[i]) + add * r[i, k]
    return x, sweeps, res


_red_black_serial = _build(_red_black, parallel=False)
_red_black_parallel = _build(_red_black, parallel=True)


def red_black(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    rhs: np.ndarray,
    nx: int,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, int, float]:
    """Compiled red-black Gauss-Seidel (see :func:`_red_black`) for ``rhs`` of shape
    ``(M,)`` or ``(M, c)`` (the result has the same shape), parallel from
    ``PARALLEL_MIN_CELLS`` values on; both builds give the same bits.
    """
    columns = rhs.reshape(rhs.shape[0], -1)
    kernel = _red_black_parallel if rhs.size >= PARALLEL_MIN_CELLS else _red_black_serial
    x, sweeps, res = kernel(indptr, indices, data, dt, columns, nx, tol, max_iter)
    return x.reshape(rhs.shape), sweeps, res


PARALLEL_MIN_CELLS = 1 << 16
"""Fewer cells (values, for several columns) run the serial build of the Jacobi series,
the red-black sweeps and the assembly of ``A(v)`` (a parallel region costs more than it
saves on small grids, and much more on a busy machine)."""

_jacobi_serial = _build(_jacobi_series, parallel=False)
_jacobi_parallel = _build(_jacobi_series, parallel=True)


def jacobi_series(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    rhs: np.ndarray,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, int, float]:
    """Compiled Jacobi-split series (see :func:`_jacobi_series`), parallel from
    ``PARALLEL_MIN_CELLS`` cells on; both builds give the same bits.
    """
    kernel = _jacobi_parallel if rhs.size >= PARALLEL_MIN_CELLS else _jacobi_serial
    return kernel(indptr, indices, data, dt, rhs, tol, max_iter)


def _band_gram(
    ex: np.ndarray,
    ey: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    wx: np.ndarray,
    wy: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The Gram matrix of :class:`harness.filters.local.BandPoisson`, its upper
    triangle ``out[i, j]``, ``j >= i`` (the strict lower triangle is not written), one
    row of pairs per (parallel) iteration, reading the extended transforms ``ex``,
    ``ey`` (``2 n_y x 2 n_x``) at the sum and difference frequencies:

        out[i, j] = wx_i wx_j (E_x(db, da) + E_x(sb, da) - E_x(db, sa) - E_x(sb, sa))
                  + wy_i wy_j (E_y(db, da) - E_y(sb, da) + E_y(db, sa) - E_y(sb, sa)),

    ``da = |a_i - a_j|``, ``sa = a_i + a_j`` (likewise ``b``). Each entry is computed
    on its own, so the result does not depend on the thread count. The numpy statement
    is :meth:`~harness.filters.local.BandPoisson.gram_reference`.
    """
    k = a.size
    for i in numba.prange(k):
        ai, bi, wxi, wyi = a[i], b[i], wx[i], wy[i]
        for j in range(i, k):
            da = abs(ai - a[j])
            sa = ai + a[j]
            db = abs(bi - b[j])
            sb = bi + b[j]
            gx = ex[db, da] + ex[sb, da] - ex[db, sa] - ex[sb, sa]
            gy = ey[db, da] - ey[sb, da] + ey[db, sa] - ey[sb, sa]
            out[i, j] = wxi * wx[j] * gx + wyi * wy[j] * gy


band_gram = _build(_band_gram, parallel=True)
band_gram_serial = _build(_band_gram, parallel=False)


@numba.njit(cache=True, nogil=True)
def squared_transition(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, dt: float, d: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """``(F1 o F1) d`` for ``F1 = I + dt A`` (CSR arrays of ``A`` without duplicate
    entries) and the columns of ``d`` ``(M, c)``: row ``i`` is ``sum_j (F1_ij)^2 d_j``,
    with ``F1_ii = 1 + dt a_ii`` and ``F1_ij = dt a_ij`` off the diagonal, in one pass
    over the matrix (a row without a stored diagonal keeps ``d_i``). The numpy statement
    is :func:`harness.filters.local.squared_transition_reference`.
    """
    m, c = d.shape
    out = d.copy()  # the identity's part; a stored diagonal adds (1 + f)^2 - 1
    for i in range(m):
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            f = dt * data[jj]
            f2 = f * f + (2.0 * f if j == i else 0.0)
            for k in range(c):
                out[i, k] += f2 * d[j, k]
    return out


@numba.njit(cache=True, nogil=True)
def weighted_laplacian(
    x: np.ndarray, cx: np.ndarray, cy: np.ndarray, dx: float, dy: float, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """In place ``out = G^T diag(c) G x = G_x^T (c_x o G_x x) + G_y^T (c_y o G_y x)`` on
    ``(ny, nx)`` fields, ``G`` the grid gradient (central differences, reflecting ghost
    cells: :meth:`harness.grid.Grid.gradient`, at least two cells per side), ``c = (c_x,
    c_y)`` the weights on the gradient grid. Matrix-free; the sparse product
    ``G.T @ diag(c) @ G`` is the reference.
    """
    ny, nx = x.shape
    out[:, :] = 0.0
    hx = 0.5 / dx
    hy = 0.5 / dy
    for j in range(ny):
        for i in range(nx):
            lo = max(i - 1, 0)
            hi = min(i + 1, nx - 1)
            # the derivative at (j, i) reads x[lo] and x[hi]; G_x^T scatters it back
            w = cx[j, i] * (hx * (x[j, hi] - x[j, lo]))
            out[j, hi] += hx * w
            out[j, lo] -= hx * w
    for j in range(ny):
        lo = max(j - 1, 0)
        hi = min(j + 1, ny - 1)
        for i in range(nx):
            w = cy[j, i] * (hy * (x[hi, i] - x[lo, i]))
            out[hi, i] += hy * w
            out[lo, i] -= hy * w


@numba.njit(cache=True, nogil=True)
def pinned_band_operator(
    cx: np.ndarray, cy: np.ndarray, dx: float, dy: float, position: np.ndarray, width: int
) -> np.ndarray:  # pragma: no cover - compiled
    """``G^T diag(c) G`` (:func:`weighted_laplacian`) in LAPACK's lower band storage,
    ``ab[r - q, q] = A[r, q]`` for ``r >= q`` (``(width + 1, M)``), with the cells
    renumbered by ``position`` and cell 0 (at position 0) pinned: its row and column
    replaced by the unit vector. The input of ``scipy.linalg.cholesky_banded(ab,
    lower=True)``; the sparse product ``G.T @ diag(c) @ G`` is the reference.

    Each gradient cell's derivative ``h (x_hi - x_lo)`` (``h = 1 / (2 dx)``) adds
    ``c h^2`` to the diagonal entries of ``lo`` and ``hi`` and ``-c h^2`` to their
    coupling.
    """
    ny, nx = cx.shape
    m = nx * ny
    ab = np.zeros((width + 1, m))
    for axis in range(2):
        c = cx if axis == 0 else cy
        h = 0.5 / dx if axis == 0 else 0.5 / dy
        h2 = h * h
        for j in range(ny):
            for i in range(nx):
                if axis == 0:
                    lo = j * nx + max(i - 1, 0)
                    hi = j * nx + min(i + 1, nx - 1)
                else:
                    lo = max(j - 1, 0) * nx + i
                    hi = min(j + 1, ny - 1) * nx + i
                w = c[j, i] * h2
                a = position[lo]
                b = position[hi]
                if abs(a - b) > width:
                    raise ValueError("pinned_band_operator: a coupling lies outside the band")
                ab[0, a] += w
                ab[0, b] += w
                ab[abs(a - b), min(a, b)] -= w
    for k in range(width + 1):  # pin cell 0: its column (its row holds only the diagonal)
        ab[k, 0] = 0.0
    ab[0, 0] = 1.0
    return ab


@numba.njit(cache=True, nogil=True)
def band_rows(factor: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The rows of a banded Cholesky factor ``L`` stored by columns (``factor[j, k] =
    L[j + k, j]``, ``(M, w + 1)``), each row's band left of the diagonal reversed into
    place: ``rows[j, t] = L[j, j - w + t]`` for ``t < w`` (zero where ``j - w + t <
    0``), so that the back substitution reads a contiguous row per column of ``L^T``.
    """
    m, width = factor.shape
    w = width - 1
    rows = np.zeros((m, w))
    for j in range(m):
        for k in range(1, min(width, m - j)):
            rows[j + k, w - k] = factor[j, k]
    return rows


@numba.njit(cache=True, nogil=True)
def band_cholesky_solve(factor: np.ndarray, b: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``x`` with ``L L^T x = b`` for a banded Cholesky factor ``L`` stored by columns,
    ``factor[j, k] = L[j + k, j]`` (``(M, w + 1)``, ``w`` the bandwidth): LAPACK's lower
    band storage (``scipy.linalg.cholesky_banded(..., lower=True)``) transposed, so that
    each column of ``L`` is contiguous. ``2 M w`` multiply-adds;
    ``scipy.linalg.cho_solve_banded`` is the reference. The iteration that applies one
    factor many times keeps :func:`band_rows` and the diagonal's reciprocals
    (:func:`_band_cholesky_inplace`).
    """
    y = b.copy()
    _band_cholesky_inplace(factor, band_rows(factor), 1.0 / factor[:, 0], y)
    return y


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _band_cholesky_inplace(
    factor: np.ndarray, rows: np.ndarray, inv_diag: np.ndarray, y: np.ndarray
) -> None:  # pragma: no cover - compiled
    """:func:`band_cholesky_solve` overwriting its right-hand side ``y`` with ``x``.

    Both substitutions run by columns (``L y = b`` along the columns of ``L``, ``L^T x
    = y`` along the columns of ``L^T``, i.e. :func:`band_rows`): each step scales one
    entry by its diagonal's reciprocal ``inv_diag`` and subtracts a contiguous segment,
    a loop without a reduction that compiles to vector instructions (measured at
    ``M = 900``, ``w = 60``: 12 and 18 us against 25 and 22 us for the column and dot
    forms with divisions; the whole preconditioner 23 against 53 us).
    """
    m, width = factor.shape
    w = width - 1
    for j in range(m):  # L y = b
        yj = y[j] * inv_diag[j]
        y[j] = yj
        top = min(width, m - j)
        col = factor[j, 1:top]
        seg = y[j + 1 : j + top]
        for k in range(top - 1):
            seg[k] -= col[k] * yj
    for j in range(m - 1, -1, -1):  # L^T x = y
        xj = y[j] * inv_diag[j]
        y[j] = xj
        lo = max(w - j, 0)
        row = rows[j, lo:w]
        seg = y[j - w + lo : j]
        for t in range(w - lo):
            seg[t] -= row[t] * xj


@numba.njit(cache=True, nogil=True, inline="always")
def _dot(u: np.ndarray, w: np.ndarray) -> float:  # pragma: no cover - compiled
    """``u . w`` summed in index order (no BLAS: the same bits on every machine)."""
    s = 0.0
    for i in range(u.size):
        s += u[i] * w[i]
    return s


@numba.njit(cache=True, nogil=True)
def _pinned_band_preconditioner(
    r: np.ndarray,
    factor: np.ndarray,
    rows: np.ndarray,
    inv_diag: np.ndarray,
    order: np.ndarray,
    out: np.ndarray,
    zp: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out = z - mean(z)``, ``z`` the solve of the pinned operator (cell 0 fixed) by
    its banded factor (with its :func:`band_rows` and diagonal reciprocals), cells in
    ``order`` (``order[0] = 0``); ``zp`` is work space.
    """
    m = r.size
    for i in range(m):
        zp[i] = r[order[i]]
    zp[0] = 0.0
    _band_cholesky_inplace(factor, rows, inv_diag, zp)
    mean = 0.0
    for i in range(m):
        mean += zp[i]
    mean /= m
    for i in range(m):
        out[order[i]] = zp[i] - mean


@numba.njit(cache=True, nogil=True)
def _off_constants_norm(r: np.ndarray) -> float:  # pragma: no cover - compiled
    """``||r - mean(r)||``."""
    mean = 0.0
    for i in range(r.size):
        mean += r[i]
    mean /= r.size
    s = 0.0
    for i in range(r.size):
        s += (r[i] - mean) ** 2
    return np.sqrt(s)


@numba.njit(cache=True, nogil=True)
def weighted_poisson_pcg(
    cx: np.ndarray,
    cy: np.ndarray,
    b: np.ndarray,
    dx: float,
    dy: float,
    factor: np.ndarray,
    rows: np.ndarray,
    inv_diag: np.ndarray,
    order: np.ndarray,
    tol: float,
    maxiter: int,
) -> tuple[np.ndarray, int, bool]:  # pragma: no cover - compiled
    """Preconditioned conjugate gradients for ``G^T diag(c) G x = b`` on ``(ny, nx)``
    fields (:func:`weighted_laplacian`) from ``x = 0``, preconditioned by the banded
    Cholesky factor of the pinned operator of an earlier ``c``, with its
    :func:`band_rows` and diagonal reciprocals (:func:`_pinned_band_preconditioner`);
    returns ``(x, iterations, converged)``.

    The iteration of :func:`harness.filters.local._pcg` (the reference, with a sparse
    LU), statement for statement: converged when ``||r|| <= tol ||b||``, or, when the
    iteration stops on ``r^T z <= 0`` or ``d^T A d <= 0``, when the residual off the
    constants is that small (the constants' part of ``b`` cannot be reduced).
    """
    ny, nx = b.shape
    m = b.size
    x = np.zeros((ny, nx))
    r = b.copy()
    z = np.empty((ny, nx))
    ad = np.empty((ny, nx))
    rf, zf, xf, adf = r.ravel(), z.ravel(), x.ravel(), ad.ravel()
    work = np.empty(m)
    b_norm = np.sqrt(_dot(b.ravel(), b.ravel()))
    if b_norm == 0.0:
        return x, 0, True
    _pinned_band_preconditioner(rf, factor, rows, inv_diag, order, zf, work)
    d = z.copy()
    df = d.ravel()
    rz = _dot(rf, zf)
    for it in range(1, maxiter + 1):
        weighted_laplacian(d, cx, cy, dx, dy, ad)
        curvature = _dot(df, adf)
        if rz <= 0.0 or curvature <= 0.0:
            return x, it - 1, _off_constants_norm(rf) <= tol * b_norm
        step = rz / curvature
        for i in range(m):
            xf[i] += step * df[i]
            rf[i] -= step * adf[i]
        if np.sqrt(_dot(rf, rf)) <= tol * b_norm:
            return x, it, True
        _pinned_band_preconditioner(rf, factor, rows, inv_diag, order, zf, work)
        rz_new = _dot(rf, zf)
        beta = rz_new / rz
        for i in range(m):
            df[i] = zf[i] + beta * df[i]
        rz = rz_new
    return x, maxiter, _off_constants_norm(rf) <= tol * b_norm


@numba.njit(cache=True, nogil=True)
def neumann_series(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    rhs: np.ndarray,
    terms: int,
) -> np.ndarray:  # pragma: no cover - compiled
    """``sum_{k <= terms} (dt A)^k rhs`` for the CSR arrays of ``A`` and the columns of
    ``rhs`` ``(M, c)``: the truncated series of
    :func:`harness.fokker_planck.implicit_solve`, each product summed over a row's
    stored entries in order from zero, as ``scipy.sparse``'s product does (the same
    bits as the numpy statement there).
    """
    m, c = rhs.shape
    total = rhs.copy()
    term = rhs.copy()
    nxt = np.empty((m, c))
    for _ in range(terms):
        for i in range(m):
            for k in range(c):
                nxt[i, k] = 0.0
            for jj in range(indptr[i], indptr[i + 1]):
                f = data[jj] * dt
                j = indices[jj]
                for k in range(c):
                    nxt[i, k] += f * term[j, k]
        for i in range(m):
            for k in range(c):
                term[i, k] = nxt[i, k]
                total[i, k] += nxt[i, k]
    return total


@numba.njit(cache=True, nogil=True)
def density_summary(
    before: np.ndarray, after: np.ndarray
) -> tuple[bool, float, float, float, float]:  # pragma: no cover - compiled
    """``(all of after finite, sum before, sum after, min after, max |before|)`` in one
    pass over two flat arrays: what :func:`harness.fokker_planck.check_density` checks.
    """
    finite = True
    s0 = 0.0
    s1 = 0.0
    low = np.inf
    top = 0.0
    for i in range(after.size):
        a = after[i]
        finite &= np.isfinite(a)
        s1 += a
        low = min(low, a)
    for i in range(before.size):
        s0 += before[i]
        top = max(top, abs(before[i]))
    return finite, s0, s1, low, top


def _band_transition_variance(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    d: np.ndarray,
    sq: np.ndarray,
    rho: np.ndarray,
    nx: int,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Rows of :func:`band_transition_variance` into ``out`` (``d``, ``sq = sqrt(d)``
    and ``rho`` padded with a zero row / column ``M`` that absent neighbours index).
    """
    m = out.shape[0]
    c = out.shape[1]
    one_rho = rho.shape[0] == 1
    bad = 0
    for i in numba.prange(m):
        fc = 1.0
        fw = 0.0
        fe = 0.0
        fs = 0.0
        fn = 0.0
        w = m
        e = m
        so = m
        no = m
        x = i % nx
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            f = dt * data[jj]
            if j == i:
                fc += f
            elif j == i - 1 and x > 0:
                fw, w = f, j
            elif j == i + 1 and x < nx - 1:
                fe, e = f, j
            elif j == i - nx:
                fs, so = f, j
            elif j == i + nx:
                fn, no = f, j
            else:
                bad += 1
        for k in range(c):
            kr = 0 if one_rho else k
            sc, sw, se, ss, sn = sq[i, k], sq[w, k], sq[e, k], sq[so, k], sq[no, k]
            acc = fc * fc * d[i, k] + fw * fw * d[w, k] + fe * fe * d[e, k]
            acc += fs * fs * d[so, k] + fn * fn * d[no, k]
            pairs = fc * fw * sc * sw * rho[kr, 0, w] + fc * fe * sc * se * rho[kr, 0, i]
            pairs += fc * fs * sc * ss * rho[kr, 1, so] + fc * fn * sc * sn * rho[kr, 1, i]
            pairs += fw * fe * sw * se * rho[kr, 2, w] + fs * fn * ss * sn * rho[kr, 3, so]
            # west (y, x-1) and south (y-1, x) to north (y+1, x) and east (y, x+1): (1, 1)
            pairs += fw * fn * sw * sn * rho[kr, 4, w] + fs * fe * ss * se * rho[kr, 4, so]
            # south to west and east to north: (1, -1)
            pairs += fs * fw * ss * sw * rho[kr, 5, so] + fe * fn * se * sn * rho[kr, 5, e]
            out[i, k] = max(acc + 2.0 * pairs, 0.0)  # a quadratic form: >= 0 but round-off
    if bad:
        raise ValueError("band_transition_variance needs a 5-point operator")


_btv_serial = _build(_band_transition_variance, parallel=False)
_btv_parallel = _build(_band_transition_variance, parallel=True)


def band_transition_variance(
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    dt: float,
    d: np.ndarray,
    rho: np.ndarray,
    nx: int,
) -> np.ndarray:
    """``diag(F1 S R S F1^T)`` for each column of ``d`` ``(M, c)``: ``F1 = I + dt A``
    (CSR arrays of a 5-point ``A`` on a grid of ``nx`` columns, without duplicates),
    ``S = diag(sqrt(d))`` and ``R`` the correlations of column ``k`` (``rho[k]``, or
    ``rho[0]`` for every column when ``rho`` has one; ``(c, 6, M)``, or ``(c, 6, M +
    1)`` with a zero column ``M``, the layout the kernel reads), so that row ``i`` is

        sum_j F1_ij^2 d_j + 2 sum_{j < l} F1_ij F1_il sqrt(d_j d_l) R_jl

    over the row's five entries (centre, west, east, south, north): five squares and
    ten pairs, whose correlations ``rho[k, o, j]`` are those of cell ``j`` with ``j +
    BAND_OFFSETS[o]`` (:data:`harness.filters.common.BAND_OFFSETS`: (0, 1), (1, 0),
    (0, 2), (2, 0), (1, 1), (1, -1) as ``(dy, dx)``), read at the pair's lower cell.
    Compiled, rows in parallel from ``PARALLEL_MIN_CELLS`` cells on (each row's
    arithmetic is the same either way); with ``rho = 0`` it is
    :func:`squared_transition`; :func:`harness.filters.local.transition_variance_reference`
    is the dense statement.

    Raises:
        ValueError: ``A`` couples cells that are not grid neighbours.
    """
    m, c = d.shape
    if rho.ndim != 3 or rho.shape[0] not in (1, c) or rho.shape[1] != 6:
        raise ValueError(f"rho must have shape (1 or {c}, 6, M or M + 1), got {rho.shape}")
    if rho.shape[2] not in (m, m + 1) or nx < 2 or m % nx:
        raise ValueError(f"rho, nx = {nx} and {m} cells do not fit one grid")
    dp = np.zeros((m + 1, c))
    dp[:m] = d
    sq = np.sqrt(dp)
    if rho.shape[2] == m + 1:  # already padded (BandLimit.correlations)
        rp = rho
    else:
        rp = np.zeros((rho.shape[0], rho.shape[1], m + 1))
        rp[:, :, :m] = rho
    out = np.empty((m, c))
    kernel = _btv_parallel if m >= PARALLEL_MIN_CELLS else _btv_serial
    kernel(indptr, indices, data, float(dt), dp, sq, rp, int(nx), out)
    return out
