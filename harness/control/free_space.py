"""What the laws that move robots to points (:mod:`harness.control.guidance`,
:mod:`harness.control.assignment`) need of free space
(:class:`harness.domains.base.FreeSpace`): the robots' map of obstacles looked up at
points and along segments, the free cell each robot counts in, and points drawn in the
free part of a cell.

A free cell may be partly blocked, and a blocked cell partly free (a cell is free or
not as a whole, :mod:`harness.domains.base`): a robot may stand in the free part of a
blocked cell. Such a robot counts in the nearest free cell (by the distance between
cell centres, :func:`nearest_free_cells`), so every robot has a free cell to move from.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

from harness.domains.base import FreeSpace
from harness.grid import Grid

TRIES = 32
"""Uniform draws in a cell before :func:`points_in_free_cells` takes its centre."""


def blocked(free: FreeSpace, points: np.ndarray) -> np.ndarray:
    """Whether each point ``(2, ...)`` (length) lies in a blocked square of the robots'
    raster (``free.raster``: square ``(row, col)`` covers ``[col s, (col + 1) s) x [row
    s, (row + 1) s)``, ``s = L / r``, measured from the grid's lower-left corner).
    """
    g = free.grid
    r = free.raster.shape[0]
    col = np.clip(((points[0] - g.x0) * (r / (g.x1 - g.x0))).astype(np.intp), 0, r - 1)
    row = np.clip(((points[1] - g.y0) * (r / (g.y1 - g.y0))).astype(np.intp), 0, r - 1)
    return free.raster[row, col].astype(bool)


def segments_blocked(free: FreeSpace, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Whether the straight segment from each ``start`` to ``end`` (both ``(2, n)``)
    meets a blocked square of the raster, sampled at steps of a quarter of a raster
    square (a blocked square the segment crosses by less than that may be missed).
    """
    g = free.grid
    side = (g.x1 - g.x0) / free.raster.shape[0]
    length = np.sqrt(((end - start) ** 2).sum(axis=0))
    count = int(np.ceil(float(length.max(initial=0.0)) / (side / 4))) + 1
    out = np.zeros(start.shape[1], dtype=bool)
    for t in np.linspace(0.0, 1.0, count + 1):
        out |= blocked(free, start + t * (end - start))
    return out


def nearest_free_cells(free: FreeSpace) -> np.ndarray:
    """``(M,)`` flat index of the nearest free cell of every cell (itself when free;
    the nearest by the distance between cell centres in cells, ties by
    :func:`scipy.ndimage.distance_transform_edt`).
    """
    _, (row, col) = distance_transform_edt(~free.cells, return_indices=True)
    return (row * free.grid.nx + col).ravel()


def centres(grid: Grid, cells: np.ndarray) -> np.ndarray:
    """The centres ``(2, n)`` (length) of flat cells ``cells``."""
    row, col = np.divmod(np.asarray(cells, dtype=np.intp), grid.nx)
    return np.stack([grid.x[col], grid.y[row]])


def points_in_free_cells(
    free: FreeSpace, cells: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """One point ``(2, n)`` in the free part of each of the flat free cells ``cells``:
    uniform in the cell given the raster's free squares and a straight way from the
    cell's centre (a point's segment from the centre meets no blocked square), by up
    to :data:`TRIES` rounds of uniform draws (``(2, n)`` from ``rng`` each round, for
    the points still wanting); the cell's centre (free, :mod:`harness.domains.base`)
    for a point still wanting after them.
    """
    g = free.grid
    cells = np.asarray(cells, dtype=np.intp)
    row, col = np.divmod(cells, g.nx)
    out = centres(g, cells)
    wanting = np.ones(cells.size, dtype=bool)
    for _ in range(TRIES):
        if not wanting.any():
            break
        idx = np.flatnonzero(wanting)
        u = rng.random((2, idx.size))
        p = np.stack([g.x0 + (col[idx] + u[0]) * g.dx, g.y0 + (row[idx] + u[1]) * g.dy])
        ok = ~blocked(free, p) & ~segments_blocked(free, out[:, idx], p)
        out[:, idx[ok]] = p[:, ok]
        wanting[idx[ok]] = False
    return out


def visible_free_cells(free: FreeSpace, positions: np.ndarray) -> np.ndarray:
    """The flat free cell each robot at ``positions`` ``(2, N)`` starts its way from:
    among its own cell and the 8 around it, the nearest free one (by the distance to
    its centre) whose centre it sees (the segment meets no blocked square of the
    raster, :func:`segments_blocked`); the nearest free cell
    (:func:`nearest_free_cells`) when it sees none.
    """
    g = free.grid
    own_row, own_col = np.divmod(_cell_of(g, positions), g.nx)
    best = nearest_free_cells(free)[own_row * g.nx + own_col]
    best_distance = np.full(positions.shape[1], np.inf)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            row, col = own_row + dr, own_col + dc
            inside = (row >= 0) & (row < g.ny) & (col >= 0) & (col < g.nx)
            cell = np.where(inside, row * g.nx + col, 0)
            ok = inside & free.cells.ravel()[cell]
            c = centres(g, cell)
            distance = np.sqrt(((c - positions) ** 2).sum(axis=0))
            ok &= distance < best_distance
            if ok.any():
                idx = np.flatnonzero(ok)
                seen = ~segments_blocked(free, positions[:, idx], c[:, idx])
                idx = idx[seen]
                best[idx], best_distance[idx] = cell[idx], distance[idx]
    return best


def _cell_of(grid: Grid, positions: np.ndarray) -> np.ndarray:
    """The flat cell of each position (:func:`harness.control.waypoints.cell_of`)."""
    col = np.clip(((positions[0] - grid.x0) / grid.dx).astype(np.intp), 0, grid.nx - 1)
    row = np.clip(((positions[1] - grid.y0) / grid.dy).astype(np.intp), 0, grid.ny - 1)
    return row * grid.nx + col
