"""Compiled Chebyshev series of the heat kernel on free space
(:class:`harness.estimators.diffusion.HeatKernel`): ``exp(t A) f`` with ``A`` the
drift-free operator, a five-point stencil whose closed faces have weight 0.

:meth:`harness.estimators.diffusion.HeatKernel.reference` is the sparse statement that
tests compare against: the same recurrence with ``scipy.sparse`` products. The loop
adds each row's five products in the column order of the CSR matrix (south, west, the
cell, east, north), as ``csr_matvec`` does, and a closed face's zero weight adds an
exact zero, so the two agree to round-off (bit for bit where neither contracts a
product and a sum into one rounding).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def chebyshev_heat(
    f: np.ndarray,
    stencil: np.ndarray,
    nx: int,
    scale: float,
    coefficients: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled; compared with the reference in tests
    """``sum_k c_k T_k(I + scale A) f`` by the three-term recurrence.

    Args:
        f: ``(M,)`` values on the grid's cells (row-major, ``nx`` per row).
        stencil: ``(5, M)`` the rows of ``A``: weights of the cell ``i - nx``, ``i - 1``,
            ``i``, ``i + 1``, ``i + nx`` (0 where the face is closed or absent); float64,
            or float32 when that holds the weights exactly (each product is then the
            same double-precision product, from half the bytes).
        nx: Cells per row.
        scale: ``2 / Lambda``.
        coefficients: ``c_0 .. c_K``.

    Returns:
        ``(M,)`` the series applied to ``f``.
    """
    m = f.size
    out = np.empty(m)
    c0 = coefficients[0]
    for i in range(m):
        out[i] = c0 * f[i]
    terms = coefficients.size
    if terms == 1:
        return out
    # padded buffers: the value of cell i sits at i + nx; the pads stay 0. Three of
    # them in turn, so that no loop writes the array it reads (which would keep the
    # compiler from its vector loop)
    size = m + 2 * nx
    prev = np.zeros(size)
    cur = np.zeros(size)
    nxt = np.zeros(size)
    for i in range(m):
        prev[nx + i] = f[i]
    s_, w_, d_, e_, n_ = stencil[0], stencil[1], stencil[2], stencil[3], stencil[4]
    # T_1 f = f + scale A f
    _advance(prev, prev, cur, out, s_, w_, d_, e_, n_, nx, m, scale, coefficients[1], False)
    for k in range(2, terms):
        # T_k f = 2 (T_{k-1} f + scale A T_{k-1} f) - T_{k-2} f
        _advance(cur, prev, nxt, out, s_, w_, d_, e_, n_, nx, m, scale, coefficients[k], True)
        prev, cur, nxt = cur, nxt, prev
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _advance(
    src: np.ndarray,
    back: np.ndarray,
    dst: np.ndarray,
    out: np.ndarray,
    s_: np.ndarray,
    w_: np.ndarray,
    d_: np.ndarray,
    e_: np.ndarray,
    n_: np.ndarray,
    nx: int,
    m: int,
    scale: float,
    ck: float,
    second: bool,
) -> None:  # pragma: no cover - compiled
    """One term: ``dst = 2 (src + scale A src) - back`` (``second``) or ``src + scale A
    src`` (the first), ``out += ck dst``; on the padded buffers (cell i at i + nx).
    """
    south = src[0:m]
    west = src[nx - 1 : nx - 1 + m]
    centre = src[nx : nx + m]
    east = src[nx + 1 : nx + 1 + m]
    north = src[2 * nx : 2 * nx + m]
    old = back[nx : nx + m]
    new = dst[nx : nx + m]
    for i in range(m):
        a = s_[i] * south[i]
        a += w_[i] * west[i]
        a += d_[i] * centre[i]
        a += e_[i] * east[i]
        a += n_[i] * north[i]
        v = centre[i] + scale * a
        if second:
            v = 2.0 * v - old[i]
        new[i] = v
        out[i] += ck * v
