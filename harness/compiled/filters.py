"""Compiled loops of the fast density filters (:mod:`harness.estimators.filters.local`): the
variance prediction (``(F1 o F1) d``, and ``diag(F1 S R S F1^T)`` with the band's
correlations), the band Gram matrix of
:class:`~harness.estimators.filters.poisson.BandPoisson`, and the small grids' gradient
update (matrix-free ``G^T diag(c) G``, its pinned band assembled for the factor, banded
Cholesky solves by columns, the conjugate-gradient iteration). Each has a numpy, sparse or
LAPACK statement that tests compare against.
"""

from __future__ import annotations

import numba
import numpy as np

from harness.compiled import PARALLEL_MIN_CELLS, SerialParallel


def _band_gram(
    ex: np.ndarray,
    ey: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    wx: np.ndarray,
    wy: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The Gram matrix of :class:`harness.estimators.filters.poisson.BandPoisson`, its upper
    triangle ``out[i, j]``, ``j >= i`` (the strict lower triangle is not written), one
    row of pairs per (parallel) iteration, reading the extended transforms ``ex``,
    ``ey`` (``2 n_y x 2 n_x``) at the sum and difference frequencies:

        out[i, j] = wx_i wx_j (E_x(db, da) + E_x(sb, da) - E_x(db, sa) - E_x(sb, sa))
                  + wy_i wy_j (E_y(db, da) - E_y(sb, da) + E_y(db, sa) - E_y(sb, sa)),

    ``da = |a_i - a_j|``, ``sa = a_i + a_j`` (likewise ``b``). Each entry is computed
    on its own, so the result does not depend on the thread count. The numpy statement
    is :meth:`~harness.estimators.filters.poisson.BandPoisson.gram_reference`.
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


band_gram = SerialParallel(_band_gram)
"""Compiled :func:`_band_gram`, always the parallel build (``band_gram.serial`` is the
serial one)."""


@numba.njit(cache=True, nogil=True)
def squared_transition(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, dt: float, d: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """``(F1 o F1) d`` for ``F1 = I + dt A`` (CSR arrays of ``A`` without duplicate
    entries) and the columns of ``d`` ``(M, c)``: row ``i`` is ``sum_j (F1_ij)^2 d_j``,
    with ``F1_ii = 1 + dt a_ii`` and ``F1_ij = dt a_ij`` off the diagonal, in one pass
    over the matrix (a row without a stored diagonal keeps ``d_i``). The numpy statement
    is :func:`harness.estimators.filters.local.squared_transition_reference`.
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

    The iteration of :func:`harness.estimators.filters.poisson._pcg` (the reference, with a
    sparse LU), statement for statement: converged when ``||r|| <= tol ||b||``, or, when the
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


band_transition_variance_rows = SerialParallel(
    _band_transition_variance, "out", lambda out: out.shape[0], PARALLEL_MIN_CELLS
)
"""Compiled :func:`_band_transition_variance`, rows in parallel from ``PARALLEL_MIN_CELLS``
cells on."""


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
    1)`` with a zero column ``M``, the layout the compiled rows read), so that row ``i`` is

        sum_j F1_ij^2 d_j + 2 sum_{j < l} F1_ij F1_il sqrt(d_j d_l) R_jl

    over the row's five entries (centre, west, east, south, north): five squares and
    ten pairs, whose correlations ``rho[k, o, j]`` are those of cell ``j`` with ``j +
    BAND_OFFSETS[o]`` (:data:`harness.estimators.filters.common.BAND_OFFSETS`: (0, 1), (1, 0),
    (0, 2), (2, 0), (1, 1), (1, -1) as ``(dy, dx)``), read at the pair's lower cell.
    Compiled, rows in parallel from ``PARALLEL_MIN_CELLS`` cells on (each row's
    arithmetic is the same either way); with ``rho = 0`` it is
    :func:`squared_transition`;
    :func:`harness.estimators.filters.local.transition_variance_reference`
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
    band_transition_variance_rows(indptr, indices, data, float(dt), dp, sq, rp, int(nx), out)
    return out
