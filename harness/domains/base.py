"""Free space, resolved on the control grid and on the robots' raster.

A domain ``Omega_free = [0, L]^2 minus the obstacles`` is given by one function,
:meth:`Domain.blocked` (is a point inside an obstacle?), on the grid's rectangle. From
it, for a grid of ``nx x ny`` cells of side ``dx, dy``:

* **Cells** (:meth:`Domain.free_cells`): a cell is free when its centre is free and at
  least half of its ``s x s`` sample points (``s = SAMPLES``, at the centres of an ``s
  x s`` split of the cell) are: a cell is free space, or not, as a whole.
* **Faces** (:meth:`Domain.open_faces`): the face between two cells is open (mass and
  probability flow through it) when both cells are free and every sample point on the
  segment joining their centres (``s + 1`` points, the centres included) and on the
  face itself (``s`` points, at the centres of an ``s``-split of it: a corner touching
  an obstacle does not close it) is free. A wall thinner than a cell but thicker than
  ``h / s`` closes the faces it crosses, so no flux leaks through it.
* **Components** (:func:`components`): the connected components of the graph
  of free cells joined through open faces (``scipy.sparse.csgraph``).
* **Raster** (:meth:`Domain.raster`): whether each of ``r x r`` squares of side ``L /
  r`` (``r = resolution``) has its centre blocked, the map the robots' compiled
  kernels look up at every move (:mod:`harness.plants.obstacles`).

What this costs: ``s^2`` calls of :meth:`Domain.blocked` per cell (about ``2 s``
more per face) once when the run is built, and ``r^2`` for the raster: at the
defaults ``s = 8`` and ``r = 1024`` about ``1.1`` million points, vectorised.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from harness.grid import Grid
from harness.parameters import ParameterError, integer, require

SAMPLES = 8
"""Sample points per cell side for :meth:`Domain.free_cells` and :meth:`Domain.open_faces`."""


@dataclass(frozen=True)
class FreeSpace:
    """Free space on a grid: what the operators, the estimators and the metrics read.

    Attributes:
        grid: The grid.
        cells: ``(ny, nx)`` booleans, True for a free cell.
        face_x: ``(ny, nx - 1)`` booleans, True for an open face between cells
            ``(j, i)`` and ``(j, i + 1)``.
        face_y: ``(ny - 1, nx)`` booleans, True for an open face between cells
            ``(j, i)`` and ``(j + 1, i)``.
        labels: ``(ny, nx)`` integers, the component of each free cell (0, 1, ...;
            -1 for a blocked cell), components numbered by their first cell in C order.
        raster: ``(r, r)`` uint8, the robots' map of obstacles (:meth:`Domain.raster`:
            1 blocked, row along y) on the grid's square.
    """

    grid: Grid
    cells: np.ndarray
    face_x: np.ndarray
    face_y: np.ndarray
    labels: np.ndarray
    raster: np.ndarray

    @property
    def n_components(self) -> int:
        """How many connected components free space has on the grid."""
        return int(self.labels.max()) + 1 if (self.labels >= 0).any() else 0

    @property
    def everywhere(self) -> bool:
        """Whether every cell is free and every face open (the plain rectangle)."""
        return bool(self.cells.all() and self.face_x.all() and self.face_y.all())

    @property
    def free_area(self) -> float:
        """Area of the free cells (length^2)."""
        return float(self.cells.sum()) * self.grid.cell_area

    def gradient(self, f: np.ndarray) -> np.ndarray:
        """Cell-centred gradient ``(2, ny, nx)`` of a scalar field on free space: central
        differences ``(f_E - f_W) / (2 dx)`` where a neighbour behind a closed face (an
        obstacle's, or the rectangle's wall) is the cell itself, the reflecting ghost
        cell of :meth:`harness.grid.Grid.gradient` (which this equals on the plain
        rectangle); 0 on blocked cells.
        """
        g = self.grid
        east, west, north, south = self.neighbours(np.asarray(f, dtype=float))
        out = np.stack([(east - west) / (2 * g.dx), (north - south) / (2 * g.dy)])
        return np.where(self.cells, out, 0.0)

    def neighbours(self, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(east, west, north, south)``, each ``(ny, nx)``: the value of ``f`` ``(ny,
        nx)`` at each cell's neighbour across that face, the cell's own where the face is
        closed or is the rectangle's wall (the reflecting ghost cell). Given the cells'
        flat indices, the indices of those neighbours.
        """
        east, west, north, south = f.copy(), f.copy(), f.copy(), f.copy()
        east[:, :-1] = np.where(self.face_x, f[:, 1:], f[:, :-1])
        west[:, 1:] = np.where(self.face_x, f[:, :-1], f[:, 1:])
        north[:-1, :] = np.where(self.face_y, f[1:, :], f[:-1, :])
        south[1:, :] = np.where(self.face_y, f[:-1, :], f[1:, :])
        return east, west, north, south

    def restrict(self, p: np.ndarray) -> np.ndarray:
        """``p`` set to 0 on blocked cells and scaled to integrate to 1 over the free ones.

        Raises:
            ValueError: when ``p`` has no mass on free cells.
        """
        q = np.where(self.cells, p, 0.0)
        mass = self.grid.integrate(q)
        if not mass > 0:
            raise ValueError("no mass on free space")
        return q / mass


MAX_RESOLUTION = 4096
"""Most squares per side of the robots' map (its ``r^2`` bytes and the plants' clearance
map of ``4 r^2`` bytes: 80 MiB at the most)."""

RASTER_POINTS = 1 << 20
"""Points tested at a time while the robots' map is drawn (bounds its temporaries)."""


class Domain(ABC):
    """Free space: the grid's rectangle less the obstacles :meth:`blocked` reports.

    Args:
        resolution: Squares per side of the robots' raster (:meth:`raster`, ``>= 16``).
    """

    name = "domain"

    def __init__(self, resolution: int = 1024) -> None:
        self.resolution = integer("resolution", resolution, 16)
        require(
            self.resolution <= MAX_RESOLUTION,
            "resolution",
            resolution,
            f"an integer from 16 to {MAX_RESOLUTION} (squares per side of the robots' map)",
        )

    @abstractmethod
    def blocked(self, x: np.ndarray, y: np.ndarray, length: float) -> np.ndarray:
        """Whether each point ``(x, y)`` (length) lies in an obstacle of the domain on
        ``[0, length]^2``; same shape as ``x``.
        """

    @property
    def trivial(self) -> bool:
        """Whether the domain has no obstacle (the plain rectangle)."""
        return False

    # --- the grid ---------------------------------------------------------------
    def free_cells(self, grid: Grid, samples: int = SAMPLES) -> np.ndarray:
        """``(ny, nx)`` booleans: the centre free and at least half of the cell's
        ``samples^2`` points free.
        """
        if self.trivial:
            return np.ones(grid.shape, dtype=bool)
        offsets = (np.arange(samples) + 0.5) / samples - 0.5  # in cells, about the centre
        sx = grid.x[None, :, None, None] + offsets[None, None, None, :] * grid.dx
        sy = grid.y[:, None, None, None] + offsets[None, None, :, None] * grid.dy
        sx, sy = np.broadcast_arrays(sx, sy)  # (ny, nx, s, s)
        side = _side(grid)
        hit = self.blocked(sx, sy, side)
        cx, cy = grid.mesh
        centre = self.blocked(cx, cy, side)
        return (hit.mean(axis=(2, 3)) <= 0.5) & ~centre

    def open_faces(self, grid: Grid, cells: np.ndarray | None = None,
                   samples: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Open faces ``(face_x, face_y)``: both cells free, and the segment between
        their centres and the face itself free at ``samples + 1`` points each.
        """
        cells = self.free_cells(grid, samples) if cells is None else cells
        face_x = cells[:, :-1] & cells[:, 1:]
        face_y = cells[:-1, :] & cells[1:, :]
        if self.trivial:
            return face_x, face_y
        t = np.linspace(0.0, 1.0, samples + 1)
        mid = (np.arange(samples) + 0.5) / samples
        side = _side(grid)
        # x faces: centres (x_i, y_j) -> (x_{i+1}, y_j); the face x = x_i + dx/2, y in cell j
        xc = grid.x[:-1, None] + t[None, :] * grid.dx  # (nx - 1, s + 1)
        across = self._any_blocked(xc[None], grid.y[:, None, None], side)
        yf = grid.y[:, None] + (mid[None, :] - 0.5) * grid.dy  # (ny, s)
        xf = (grid.x[:-1] + 0.5 * grid.dx)[None, :, None]
        along = self._any_blocked(xf, yf[:, None, :], side)
        face_x &= ~(across | along)
        # y faces: centres (x_i, y_j) -> (x_i, y_{j+1}); the face y = y_j + dy/2, x in cell i
        yc = grid.y[:-1, None] + t[None, :] * grid.dy  # (ny - 1, s + 1)
        across = self._any_blocked(grid.x[None, :, None], yc[:, None, :], side)
        xf2 = grid.x[:, None] + (mid[None, :] - 0.5) * grid.dx  # (nx, s)
        yf2 = (grid.y[:-1] + 0.5 * grid.dy)[:, None, None]
        along = self._any_blocked(xf2[None], yf2, side)
        face_y &= ~(across | along)
        return face_x, face_y

    def _any_blocked(self, x: np.ndarray, y: np.ndarray, side: float) -> np.ndarray:
        """Whether any point along the last axis of ``x, y`` (broadcast) is blocked."""
        bx, by = np.broadcast_arrays(x, y)
        return np.asarray(np.asarray(self.blocked(bx, by, side)).any(axis=-1), dtype=bool)

    def resolve(self, grid: Grid) -> FreeSpace:
        """Free cells, open faces and components on ``grid`` (:class:`FreeSpace`).

        Raises:
            ParameterError: when no cell of the grid is free.
        """
        cells = self.free_cells(grid)
        if not cells.any():
            raise ParameterError(
                "domain", self.name, "a domain with free space (its obstacles cover every cell)"
            )
        face_x, face_y = self.open_faces(grid, cells)
        labels = components(cells, face_x, face_y)
        raster = self.raster(_side(grid))
        for array in (cells, face_x, face_y, labels, raster):
            array.flags.writeable = False
        return FreeSpace(grid, cells, face_x, face_y, labels, raster)

    # --- the robots ---------------------------------------------------------------
    def raster(self, length: float) -> np.ndarray:
        """``(r, r)`` uint8, 1 where the centre of square ``(row, col)`` (side ``length /
        r``; row along y) is blocked: the robots' map of obstacles.
        """
        r = self.resolution
        centres = (np.arange(r) + 0.5) * (length / r)
        out = np.zeros((r, r), dtype=np.uint8)
        if self.trivial:
            return out
        rows = max(1, RASTER_POINTS // r)  # a block of rows at a time: bounded temporaries
        for start in range(0, r, rows):
            x, y = np.meshgrid(centres, centres[start : start + rows], indexing="xy")
            out[start : start + rows] = self.blocked(x, y, length)
        return out


def components(cells: np.ndarray, face_x: np.ndarray, face_y: np.ndarray) -> np.ndarray:
    """Component labels of the free cells joined through open faces (-1 on blocked
    cells), numbered in the order of each component's first cell (C order).
    """
    ny, nx = cells.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    rows = np.concatenate([idx[:, :-1][face_x], idx[:-1, :][face_y]])
    cols = np.concatenate([idx[:, 1:][face_x], idx[1:, :][face_y]])
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(ny * nx, ny * nx))
    _, raw = connected_components(graph, directed=False)
    labels = np.full(ny * nx, -1)
    free = cells.ravel()
    order: dict[int, int] = {}
    for cell in np.flatnonzero(free):
        labels[cell] = order.setdefault(int(raw[cell]), len(order))
    return labels.reshape(ny, nx)


def _side(grid: Grid) -> float:
    """The side of the grid's square (domains are defined on ``[0, L]^2``)."""
    return grid.x1 - grid.x0
