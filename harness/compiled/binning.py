"""Compiled linear binning of the robots onto the KDE's fine nodes
(:meth:`harness.estimators.kde.KDE.binned`);
:meth:`harness.estimators.kde.KDE.bin_weights` is the numpy statement that tests compare
against. O(N), parallel over fixed chunks of robots, with sums whose order does not
depend on the thread count.
"""

from __future__ import annotations

import numba
import numpy as np


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
    reference is :meth:`harness.estimators.kde.KDE.bin_weights`.
    """
    n = pos.shape[1]
    chunk = bin_chunk_size(n, (bx + 1) * (by + 1))
    if n <= chunk:  # one chunk: the serial loop, no parallel region
        out = np.zeros((by + 1, bx + 1))
        _bin_range(pos, 0, n, out, x0, x1, y0, y1, bx, by, 1.0 / n)
        return out
    return linear_binning_chunked(pos, x0, x1, y0, y1, bx, by, chunk)


@numba.njit(cache=True, nogil=True)
def free_binning(
    pos: np.ndarray,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    nx: int,
    ny: int,
    targets: np.ndarray,
    home: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled
    """Bilinear shares of each robot (``1/N``) on the cells of a grid of ``nx x ny``
    cells on ``[x0, x1] x [y0, y1]`` with free space: the four shares of a robot in cell
    ``c``, quadrant ``q``, go to ``targets[c, q]``
    (:func:`harness.estimators.diffusion.bin_targets`), the whole ``1/N`` to ``home[c]``
    when ``c`` is blocked (``home[c] != c``). Robots in order, serial;
    :func:`harness.estimators.diffusion.bin_reference` is the numpy statement. Returns
    ``(ny, nx)`` weights summing to 1.
    """
    n = pos.shape[1]
    inv_n = 1.0 / n
    out = np.zeros(ny * nx)
    sx = nx / (x1 - x0)
    sy = ny / (y1 - y0)
    for k in range(n):
        tx = (pos[0, k] - x0) * sx
        ty = (pos[1, k] - y0) * sy
        ix = min(max(int(np.floor(tx)), 0), nx - 1)
        iy = min(max(int(np.floor(ty)), 0), ny - 1)
        c = iy * nx + ix
        if home[c] != c:
            out[home[c]] += inv_n
            continue
        ux = tx - ix - 0.5
        uy = ty - iy - 0.5
        fx = min(abs(ux), 0.5)
        fy = min(abs(uy), 0.5)
        q = (2 if uy >= 0 else 0) + (1 if ux >= 0 else 0)
        out[targets[c, q, 0]] += (1.0 - fx) * (1.0 - fy) * inv_n
        out[targets[c, q, 1]] += fx * (1.0 - fy) * inv_n
        out[targets[c, q, 2]] += (1.0 - fx) * fy * inv_n
        out[targets[c, q, 3]] += fx * fy * inv_n
    return out.reshape(ny, nx)
