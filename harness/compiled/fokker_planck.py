"""Compiled loops of the Fokker-Planck step (:mod:`harness.fokker_planck`): the
assembly of ``A(v)`` of eq. ``FP equation`` from the face velocities, the implicit
solvers of ``(I - dt A) x = rhs`` (the Jacobi-split series, red-black Gauss-Seidel on
several columns at once, the truncated Neumann series) and the density checks of a
step. Each has a numpy or sparse-LU statement in :mod:`harness.fokker_planck` that
tests compare against; the parallel ones give the same bits as their serial builds,
whatever the thread count.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from harness.compiled import PARALLEL_MIN_CELLS, SerialParallel


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
    open_x: np.ndarray,
    open_y: np.ndarray,
    sigma: float,
    dx: float,
    dy: float,
    indptr: np.ndarray,
) -> np.ndarray:
    """CSR data of ``A(v)``, the finite-volume operator of eq. ``FP equation``
    (:meth:`harness.fokker_planck.FokkerPlanck.matrix`), straight from the face
    velocities: the face rates (one parallel pass over the faces), then the rows (one
    parallel pass over the cells). A closed face (``open_x`` or ``open_y`` False: an
    obstacle's, :class:`harness.domains.base.FreeSpace`) has both rates 0, whatever its
    velocity (which need not be finite there).

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
            if open_x[row, col]:
                xl[row, col], xr[row, col] = _face_rate_pair(face_x[row, col], sigma, dx)
            else:
                xl[row, col], xr[row, col] = 0.0, 0.0
        if row < ny - 1:
            for col in range(nx):
                if open_y[row, col]:
                    yl[row, col], yr[row, col] = _face_rate_pair(face_y[row, col], sigma, dy)
                else:
                    yl[row, col], yr[row, col] = 0.0, 0.0
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


assemble_operator = SerialParallel(
    _assemble_operator, "indptr", lambda indptr: indptr.size - 1, PARALLEL_MIN_CELLS
)
"""Compiled :func:`_assemble_operator` (contiguous float arrays and float scalars),
parallel from ``PARALLEL_MIN_CELLS`` cells on (each row is written by one thread; both
builds give the same bits)."""


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


jacobi_series = SerialParallel(_jacobi_series, "rhs", lambda rhs: rhs.size, PARALLEL_MIN_CELLS)
"""Compiled Jacobi-split series (see :func:`_jacobi_series`), parallel from
``PARALLEL_MIN_CELLS`` cells on; both builds give the same bits."""


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


red_black = SerialParallel(_red_black, "rhs", lambda rhs: rhs.size, PARALLEL_MIN_CELLS)
"""Compiled red-black Gauss-Seidel (see :func:`_red_black`) for ``rhs`` of shape ``(M,
c)``, parallel from ``PARALLEL_MIN_CELLS`` values on; both builds give the same bits."""


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
