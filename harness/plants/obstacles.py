"""The robots' map of obstacles on a domain with obstacles: where robots may be, how they
start there, and how a move made outside the compiled steps keeps to it.

The map is free space's raster (:attr:`harness.domains.base.FreeSpace.raster`, ``r x
r`` squares of side ``L / r``, 1 blocked) with, per square, its clearance: 0 on a
blocked square, else the chessboard distance in squares to the nearest blocked one (at
most 255). The compiled steps read the clearances: a robot whose move spans fewer
squares than its square's clearance cannot meet an obstacle and costs one look-up; the
others walk their move square by square and reflect at the first obstacle face they
cross, or stay where they were (:mod:`harness.compiled.obstacles`).

On the plain square there is no map (:meth:`RobotMap.of` gives None) and the compiled
steps get :data:`NO_MAP`, which they never read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_cdt

from harness.compiled.agents import avoid_moves
from harness.domains.base import FreeSpace
from harness.grid import Grid
from harness.targets.densities import Density

NO_MAP = np.zeros((1, 1), dtype=np.uint8)
"""The clearances the compiled steps get on the plain square (never read there)."""

MAX_DRAWS = 1 << 22
"""Draws of the initial density without one in free space after which
:meth:`RobotMap.sample` gives up."""


def clearance(raster: np.ndarray) -> np.ndarray:
    """``(r, r)`` uint8: 0 on a blocked square of ``raster`` (1 blocked), else the
    chessboard distance (squares) to the nearest blocked square, at most 255.
    """
    blocked = np.asarray(raster) != 0
    if not blocked.any():
        return np.full(blocked.shape, 255, dtype=np.uint8)
    distance = distance_transform_cdt(~blocked, metric="chessboard")
    return np.ascontiguousarray(np.minimum(distance, 255).astype(np.uint8))


@dataclass(frozen=True)
class RobotMap:
    """The robots' map of obstacles on ``grid``'s rectangle (module docstring).

    Attributes:
        grid: The grid (its rectangle is the map's).
        raster: ``(r, r)`` uint8, 1 on a blocked square (row along y).
        clear: ``(r, r)`` uint8 clearances (:func:`clearance`).
    """

    grid: Grid
    raster: np.ndarray
    clear: np.ndarray

    @classmethod
    def of(cls, free: FreeSpace | None) -> RobotMap | None:
        """The map of ``free``'s raster; None on the plain square (``free`` None)."""
        if free is None:
            return None
        raster = np.ascontiguousarray(free.raster, dtype=np.uint8)
        return cls(free.grid, raster, clearance(raster))

    @property
    def resolution(self) -> int:
        """Squares per side ``r``."""
        return int(self.raster.shape[0])

    def squares(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(row, col)`` of the squares holding the points ``(x, y)`` (the compiled
        look-up's arithmetic, :func:`harness.compiled.obstacles.square_of`).
        """
        g, r = self.grid, self.resolution
        sx, sy = (g.x1 - g.x0) / r, (g.y1 - g.y0) / r
        col = np.clip(np.floor((np.asarray(x) - g.x0) / sx), 0, r - 1).astype(np.intp)
        row = np.clip(np.floor((np.asarray(y) - g.y0) / sy), 0, r - 1).astype(np.intp)
        return row, col

    def blocked(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether each point ``(x, y)`` lies in a blocked square of the map."""
        row, col = self.squares(x, y)
        return np.asarray(self.raster[row, col] != 0)

    def sample(self, density: Density, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` positions ``(2, n)`` drawn from ``density`` restricted to the map's free
        squares, by rejection: draw ``n``, keep those in free squares, draw again for
        the rest (sized by the acceptance so far). The first draw is the plain square's.

        Raises:
            ValueError: when ``MAX_DRAWS`` draws gave none in free space.
        """
        kept: list[np.ndarray] = []
        got = drawn = 0
        want = n
        while got < n:
            points = density.sample(want, self.grid, rng)
            inside = points[:, ~self.blocked(points[0], points[1])]
            kept.append(inside[:, : n - got])
            got += kept[-1].shape[1]
            drawn += want
            if got == 0 and drawn >= MAX_DRAWS:
                raise ValueError(
                    f"the initial density put none of {drawn} draws in free space "
                    "(the robots' map of obstacles): it has no mass there"
                )
            rate = got / drawn
            need = n - got
            want = int(min(np.ceil(1.2 * need / rate) + 16 if rate > 0 else 8 * drawn, MAX_DRAWS))
        return np.ascontiguousarray(np.hstack(kept))

    def avoid(self, old: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """In place: each robot's move from ``old`` to ``positions`` (``(2, N)``, inside
        the rectangle) by the obstacle rule (:func:`harness.compiled.obstacles.avoid`).
        """
        g = self.grid
        avoid_moves(old, positions, self.clear, g.x0, g.x1, g.y0, g.y1)
        return positions
