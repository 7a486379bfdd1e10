"""``domain=rooms``: two rooms side by side, joined by one door in the wall between them."""

from __future__ import annotations

import numpy as np

from harness.domains.base import Domain, FreeSpace
from harness.grid import Grid
from harness.parameters import number, require


class Rooms(Domain):
    """The square split by a vertical wall with one door.

    The wall fills ``|x - wall| <= thickness / 2`` (as fractions of the side ``L``) for
    every height except the door, ``door_low < y / L < door_high``.

    Args:
        wall: The wall's centre line, a fraction of the side in ``(0, 1)``.
        thickness: The wall's thickness, a fraction of the side ``> 0``.
        door: ``[low, high]``, the door's extent along y as fractions of the side,
            ``0 <= low < high <= 1``.
        resolution: Squares per side of the robots' raster.
    """

    name = "rooms"

    def __init__(
        self,
        wall: float = 0.5,
        thickness: float = 0.06,
        door: tuple[float, float] = (0.42, 0.58),
        resolution: int = 1024,
    ) -> None:
        super().__init__(resolution)
        self.wall = number("wall", wall, 0.0, strict=True)
        require(self.wall < 1.0, "wall", wall, "a fraction of the side in (0, 1)")
        self.thickness = number("thickness", thickness, 0.0, strict=True)
        half = self.thickness / 2
        require(
            self.wall - half > 0 and self.wall + half < 1,
            "thickness",
            thickness,
            f"a wall inside the square: wall +- thickness / 2 within (0, 1) (wall={self.wall})",
        )
        pair = list(door) if door is not None and not isinstance(door, str) else []
        require(len(pair) == 2, "door", door, "[low, high], fractions of the side")
        low, high = number("door", pair[0]), number("door", pair[1])
        require(0 <= low < high <= 1, "door", door, "[low, high] with 0 <= low < high <= 1")
        self.door = (low, high)

    def resolve(self, grid: Grid) -> FreeSpace:
        """Free space on ``grid`` (:meth:`Domain.resolve`), once the door is known to be
        at least one cell of the grid wide (a narrower one would be shut or open
        depending on where the cells fall).

        Raises:
            ParameterError: naming ``door`` when it is narrower than a cell.
        """
        low, high = self.door
        cell = grid.dy / (grid.y1 - grid.y0)
        require(
            high - low >= cell,
            "door",
            list(self.door),
            f"a door at least one cell of the grid wide ({cell:.4g} of the side)",
        )
        return super().resolve(grid)

    def blocked(self, x: np.ndarray, y: np.ndarray, length: float) -> np.ndarray:
        """In the wall and not in the door."""
        u, v = np.asarray(x) / length, np.asarray(y) / length
        in_wall = np.abs(u - self.wall) <= self.thickness / 2
        in_door = (v > self.door[0]) & (v < self.door[1])
        return in_wall & ~in_door
