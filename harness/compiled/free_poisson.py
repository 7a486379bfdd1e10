"""Compiled gradient update on free space
(:class:`harness.estimators.filters.free_poisson.FreePoisson`): the weighted Poisson operator
``G^T diag(c) G`` matrix-free with the free-space gradient (the cell itself behind a
closed face), its pinned band for a banded Cholesky factor, and the conjugate-gradient
iteration preconditioned by that factor.

Fields are whole grids, flattened; blocked cells carry 0 throughout (the gradient never
reads them, so the operator's rows and columns there are 0 and the pinned band holds
the unit vector). :meth:`~harness.estimators.filters.free_poisson.FreePoisson.solve_reference`
is the numpy statement that tests compare against: the same iteration on the free cells
with the sparse product and a sparse LU of the same pinned operator.
"""

from __future__ import annotations

import numba
import numpy as np

from harness.compiled.filters import _band_cholesky_inplace, _dot


@numba.njit(cache=True, nogil=True)
def free_weighted_laplacian(
    x: np.ndarray,
    c: np.ndarray,
    hx: float,
    hy: float,
    lo: np.ndarray,
    hi: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """In place ``out = G^T diag(c) G x`` for ``(M,)`` fields and ``(2M,)`` weights ``c``.

    Gradient cell ``k`` (``k < M`` along x, ``k >= M`` along y) is ``h (x[hi[k]] -
    x[lo[k]])`` with ``h = hx`` or ``hy`` (``1 / (2 dx)``): ``hi`` the neighbour across
    the open face, else the cell itself, likewise ``lo``; ``lo = hi`` for a cell with no
    open face on that axis, and for blocked cells, adds nothing.
    """
    m = x.size
    for i in range(m):
        out[i] = 0.0
    for k in range(2 * m):
        h = hx if k < m else hy
        a, b = lo[k], hi[k]
        if a == b:
            continue
        w = c[k] * (h * (x[b] - x[a]))
        out[b] += h * w
        out[a] -= h * w


@numba.njit(cache=True, nogil=True)
def free_pinned_band_operator(
    c: np.ndarray,
    hx: float,
    hy: float,
    lo: np.ndarray,
    hi: np.ndarray,
    position: np.ndarray,
    width: int,
    pinned: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """``G^T diag(c) G`` (:func:`free_weighted_laplacian`) in LAPACK's lower band storage,
    ``ab[r - q, q] = A[r, q]`` for ``r >= q`` (``(width + 1, M)``), cells renumbered by
    ``position``, the ``pinned`` cells' rows and columns replaced by the unit vector. The
    input of ``scipy.linalg.cholesky_banded(ab, lower=True)``.

    Raises:
        ValueError: a coupling lies outside the band.
    """
    m = position.size
    ab = np.zeros((width + 1, m))
    for k in range(2 * m):
        h = hx if k < m else hy
        if lo[k] == hi[k]:
            continue
        w = c[k] * h * h
        a = position[lo[k]]
        b = position[hi[k]]
        if abs(a - b) > width:
            raise ValueError("free_pinned_band_operator: a coupling lies outside the band")
        ab[0, a] += w
        ab[0, b] += w
        ab[abs(a - b), min(a, b)] -= w
    for i in range(m):
        if pinned[i]:
            p = position[i]
            for t in range(width + 1):  # its column
                ab[t, p] = 0.0
            for t in range(1, min(width, p) + 1):  # its row: A[p, p - t]
                ab[t, p - t] = 0.0
            ab[0, p] = 1.0
    return ab


@numba.njit(cache=True, nogil=True)
def _off_constants(
    r: np.ndarray, labels: np.ndarray, counts: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``out = r`` less its mean on every component (``labels`` ``-1``: blocked, 0)."""
    if counts.size == 1:  # one component: the same sums without the indexed store
        total = 0.0
        for i in range(r.size):
            if labels[i] >= 0:
                total += r[i]
        mean = total / counts[0]
        for i in range(r.size):
            out[i] = r[i] - mean if labels[i] >= 0 else 0.0
        return
    sums = np.zeros(counts.size)
    for i in range(r.size):
        if labels[i] >= 0:
            sums[labels[i]] += r[i]
    for i in range(r.size):
        lab = labels[i]
        out[i] = r[i] - sums[lab] / counts[lab] if lab >= 0 else 0.0


@numba.njit(cache=True, nogil=True)
def _precondition(
    r: np.ndarray,
    factor: np.ndarray,
    rows: np.ndarray,
    inv_diag: np.ndarray,
    order: np.ndarray,
    pinned: np.ndarray,
    labels: np.ndarray,
    counts: np.ndarray,
    work: np.ndarray,
    raw: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out`` = the pinned operator's solve of ``r`` (pinned entries of ``r`` set to 0;
    banded factor with its rows and diagonal reciprocals, cells in ``order``), less its
    mean on every component.
    """
    m = r.size
    for i in range(m):
        cell = order[i]
        work[i] = 0.0 if pinned[cell] else r[cell]
    _band_cholesky_inplace(factor, rows, inv_diag, work)
    for i in range(m):
        raw[order[i]] = work[i]
    _off_constants(raw, labels, counts, out)


@numba.njit(cache=True, nogil=True)
def free_poisson_pcg(
    c: np.ndarray,
    b: np.ndarray,
    hx: float,
    hy: float,
    lo: np.ndarray,
    hi: np.ndarray,
    factor: np.ndarray,
    rows: np.ndarray,
    inv_diag: np.ndarray,
    order: np.ndarray,
    pinned: np.ndarray,
    labels: np.ndarray,
    counts: np.ndarray,
    tol: float,
    maxiter: int,
) -> tuple[np.ndarray, int, bool]:  # pragma: no cover - compiled
    """Preconditioned conjugate gradients for ``G^T diag(c) G x = b`` from ``x = 0``
    (``b`` with zero mean on every component, 0 on blocked cells); returns ``(x,
    iterations, converged)``.

    The iteration of :meth:`harness.estimators.filters.free_poisson.FreePoisson._pcg`,
    statement for statement: converged when the residual off the components' constants
    is at most ``tol ||b||``; stops on ``r^T z <= 0`` or ``d^T A d <= 0``.
    """
    m = b.size
    x = np.zeros(m)
    r = b.copy()
    z = np.empty(m)
    ad = np.empty(m)
    off = np.empty(m)
    work = np.empty(m)
    raw = np.empty(m)
    b_norm = np.sqrt(_dot(b, b))
    if b_norm == 0.0:
        return x, 0, True
    _precondition(r, factor, rows, inv_diag, order, pinned, labels, counts, work, raw, z)
    d = z.copy()
    rz = _dot(r, z)
    for it in range(1, maxiter + 1):
        _off_constants(r, labels, counts, off)
        if np.sqrt(_dot(off, off)) <= tol * b_norm:
            return x, it - 1, True
        free_weighted_laplacian(d, c, hx, hy, lo, hi, ad)
        curvature = _dot(d, ad)
        if rz <= 0.0 or curvature <= 0.0:
            break
        step = rz / curvature
        for i in range(m):
            x[i] += step * d[i]
            r[i] -= step * ad[i]
        _precondition(r, factor, rows, inv_diag, order, pinned, labels, counts, work, raw, z)
        rz_new = _dot(r, z)
        beta = rz_new / rz
        for i in range(m):
            d[i] = z[i] + beta * d[i]
        rz = rz_new
    _off_constants(r, labels, counts, off)
    return x, maxiter, np.sqrt(_dot(off, off)) <= tol * b_norm
