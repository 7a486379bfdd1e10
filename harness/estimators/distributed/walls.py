"""Radio links and walls: the communication graph on a domain with obstacles.

By default radio passes through obstacles (``estimator.through_walls: true``): the
graph is the one of the robots' positions alone
(:func:`harness.estimators.distributed.graph.communication_graph`), as on the square. With
``through_walls: false`` a link needs a line of sight: robots ``i`` and ``j`` stay
neighbours only when the segment ``X_i X_j`` crosses no blocked square of the robots' map
of obstacles (:attr:`harness.domains.base.FreeSpace.raster`, ``r x r`` squares of side
``L / r`` over the grid's square, 1 blocked, row along y), decided exactly on that map by
walking the squares the segment crosses (Amanatides and Woo, "A fast voxel traversal
algorithm for ray tracing", Eurographics 1987). A segment through a corner shared by two
squares visits one of them (the one along x first); each pair is walked once, from the
robot of the lower index, so the graph stays symmetric.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from harness.domains.base import FreeSpace
from harness.estimators.distributed.graph import canonical_csr


@numba.njit(cache=True, nogil=True)
def _clear(ax, ay, bx, by, raster, side):  # pragma: no cover - compiled
    """Whether the segment from ``(ax, ay)`` to ``(bx, by)`` (coordinates from the
    map's corner) crosses no blocked square of ``raster`` (squares of side ``side``).
    """
    r = raster.shape[0]
    cx = min(max(int(np.floor(ax / side)), 0), r - 1)
    cy = min(max(int(np.floor(ay / side)), 0), r - 1)
    ex = min(max(int(np.floor(bx / side)), 0), r - 1)
    ey = min(max(int(np.floor(by / side)), 0), r - 1)
    if raster[cy, cx] != 0:
        return False
    dx, dy = bx - ax, by - ay
    step_x = 1 if dx > 0 else -1
    step_y = 1 if dy > 0 else -1
    inf = np.inf
    t_x = ((cx + (step_x > 0)) * side - ax) / dx if dx != 0.0 else inf
    t_y = ((cy + (step_y > 0)) * side - ay) / dy if dy != 0.0 else inf
    d_x = side / abs(dx) if dx != 0.0 else inf
    d_y = side / abs(dy) if dy != 0.0 else inf
    for _ in range(4 * r + 4):
        if cx == ex and cy == ey:
            return True
        if t_x <= t_y:
            cx += step_x
            t_x += d_x
        else:
            cy += step_y
            t_y += d_y
        if cx < 0 or cy < 0 or cx >= r or cy >= r:
            return True  # left the map: the end square is beyond it (clipped)
        if raster[cy, cx] != 0:
            return False
    return True


@numba.njit(cache=True, parallel=True, nogil=True)
def _visible(indptr, indices, px, py, raster, side):  # pragma: no cover - compiled
    """``keep[k]`` for every entry ``k`` of a symmetric CSR pattern: whether its pair has a
    line of sight (computed for ``i < j``; ``j > i`` entries copied from their mirror).
    """
    n = indptr.size - 1
    keep = np.zeros(indices.size, dtype=np.bool_)
    for i in numba.prange(n):
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if i < j:
                keep[k] = _clear(px[i], py[i], px[j], py[j], raster, side)
    for i in range(n):  # mirror: entry (j, i) from (i, j), rows sorted
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if j < i:
                lo, hi = indptr[j], indptr[j + 1]
                while lo < hi:  # binary search of i in row j
                    mid = (lo + hi) // 2
                    if indices[mid] < i:
                        lo = mid + 1
                    else:
                        hi = mid
                keep[k] = keep[lo]
    return keep


def line_of_sight(adj: sp.csr_matrix, positions: np.ndarray, free: FreeSpace) -> sp.csr_matrix:
    """The links of ``adj`` (symmetric 0/1 CSR, sorted rows) whose segment crosses no
    blocked square of ``free``'s raster (module docstring); same format.
    """
    g = free.grid
    raster = np.ascontiguousarray(free.raster, dtype=np.uint8)
    side = (g.x1 - g.x0) / raster.shape[0]
    pts = np.asarray(positions, dtype=float)
    px = np.ascontiguousarray(pts[0] - g.x0)
    py = np.ascontiguousarray(pts[1] - g.y0)
    keep = _visible(adj.indptr, adj.indices, px, py, raster, side)
    n = adj.shape[0]
    rows = np.repeat(np.arange(n), np.diff(adj.indptr))
    indptr = np.zeros(n + 1, dtype=np.int64)
    indptr[1:] = np.cumsum(np.bincount(rows[keep], minlength=n))
    indices = adj.indices[keep]
    return canonical_csr(indptr, indices, np.ones(indices.size), n)
