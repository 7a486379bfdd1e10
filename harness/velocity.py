"""Velocity fields on the grid: cell-centre values and face-normal values.

The control laws produce a velocity field ``v(x, t)``. Two views of it are used:

* ``centres``, shape ``(2, ny, nx)``: ``v`` at the cell centres. The robots
  interpolate it bilinearly and the logs record it.
* ``face_x``, shape ``(ny, nx - 1)``, and ``face_y``, shape ``(ny - 1, nx)``: the
  normal component on the interior faces (``face_x[j, i]`` sits between cells
  ``(j, i)`` and ``(j, i + 1)``). The finite-volume Fokker-Planck operator moves
  mass with these. Wall faces carry no flux (reflecting walls) and are not stored.

By default the face values are averages of the two neighbouring centres; a
control law may instead evaluate a term directly on the faces (the paper's law
does so for its drift ``sigma grad p_* / p_*``, which is what makes ``p_*`` an
exact discrete steady state). Velocities are in length per time unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.grid import Grid


@dataclass(frozen=True)
class VelocityField:
    """A velocity field on a :class:`~harness.grid.Grid` (length / time)."""

    centres: np.ndarray
    face_x: np.ndarray
    face_y: np.ndarray

    def __post_init__(self) -> None:
        _, ny, nx = self.centres.shape
        if self.centres.shape[0] != 2:
            raise ValueError(f"centres must have shape (2, ny, nx), got {self.centres.shape}")
        if self.face_x.shape != (ny, nx - 1) or self.face_y.shape != (ny - 1, nx):
            raise ValueError(
                f"face arrays {self.face_x.shape}, {self.face_y.shape} do not match "
                f"centres {self.centres.shape}"
            )

    @classmethod
    def from_centres(cls, centres: np.ndarray) -> VelocityField:
        """Face values as the mean of the two neighbouring cell centres."""
        centres = np.asarray(centres, dtype=float)
        return cls(centres, centres_to_face_x(centres[0]), centres_to_face_y(centres[1]))

    @classmethod
    def zeros(cls, grid: Grid) -> VelocityField:
        """The zero field."""
        return cls.from_centres(np.zeros((2, *grid.shape)))

    def capped(self, v_max: float) -> VelocityField:
        """Speeds at most ``v_max`` (length / time): centre vectors scaled by ``min(1,
        v_max / |v|)``, face-normal values clipped to ``[-v_max, v_max]``.
        """
        return VelocityField(
            cap_vectors(self.centres, v_max),
            np.clip(self.face_x, -v_max, v_max),
            np.clip(self.face_y, -v_max, v_max),
        )

    @classmethod
    def from_robots(
        cls, grid: Grid, positions: np.ndarray, velocities: np.ndarray
    ) -> VelocityField:
        """The swarm's mean velocity per cell: the field a law that moves each robot
        itself gives the density's transport.

        In cell ``c`` with robots ``i in c``: ``v_c = sum_{i in c} v_i / #c`` (zero in an
        empty cell), so ``p_hist v_c`` is the swarm's own flux per cell, with
        ``p_hist = #c / (N |c|)`` its histogram; the faces are the means of the
        neighbouring centres (:meth:`from_centres`).

        Args:
            grid: The grid.
            positions: ``(2, N)`` (length), inside the domain.
            velocities: ``(2, N)`` (length / time).
        """
        col = np.clip(((positions[0] - grid.x0) / grid.dx).astype(np.intp), 0, grid.nx - 1)
        row = np.clip(((positions[1] - grid.y0) / grid.dy).astype(np.intp), 0, grid.ny - 1)
        cell = row * grid.nx + col
        count = np.bincount(cell, minlength=grid.size).astype(float)
        occupied = np.maximum(count, 1.0)
        centres = np.stack(
            [np.bincount(cell, velocities[c], grid.size) / occupied for c in range(2)]
        )
        return cls.from_centres(centres.reshape(2, *grid.shape))

    def is_finite(self) -> bool:
        """True when every stored value is finite."""
        return bool(
            np.isfinite(self.centres).all()
            and np.isfinite(self.face_x).all()
            and np.isfinite(self.face_y).all()
        )


def cap_vectors(v: np.ndarray, v_max: float) -> np.ndarray:
    """Vectors along axis 0 (``(2, ...)``, length / time) scaled by ``min(1, v_max /
    |v|)``: the same direction, speed at most ``v_max`` (a new array).
    """
    if not v_max >= 0:
        raise ValueError(f"v_max must be >= 0, got {v_max}")
    speed = np.sqrt(v[0] ** 2 + v[1] ** 2)
    scale = np.minimum(1.0, v_max / np.maximum(speed, 1e-300))
    return v * scale


def centres_to_face_x(f: np.ndarray) -> np.ndarray:
    """Average of a cell field onto the interior x-faces, ``(ny, nx - 1)``."""
    return 0.5 * (f[:, 1:] + f[:, :-1])


def centres_to_face_y(f: np.ndarray) -> np.ndarray:
    """Average of a cell field onto the interior y-faces, ``(ny - 1, nx)``."""
    return 0.5 * (f[1:, :] + f[:-1, :])


def interpolate(grid: Grid, centres: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a cell-centred vector field at positions.

    Args:
        grid: The grid.
        centres: Field of shape ``(c, ny, nx)``.
        positions: Points of shape ``(2, N)`` inside the domain.

    Returns:
        Values of shape ``(c, N)``. Beyond the outermost cell centres (within half
        a cell of a wall) the field is extended by its nearest centre values.
    """
    c = centres.shape[0]
    u = np.clip((positions[0] - grid.x0) / grid.dx - 0.5, 0.0, grid.nx - 1)
    w = np.clip((positions[1] - grid.y0) / grid.dy - 0.5, 0.0, grid.ny - 1)
    i0 = np.minimum(u.astype(np.intp), grid.nx - 2)
    j0 = np.minimum(w.astype(np.intp), grid.ny - 2)
    fx = u - i0
    fy = w - j0
    base = j0 * grid.nx + i0
    flat = centres.reshape(c, -1)
    v00 = flat[:, base]
    v10 = flat[:, base + 1]
    v01 = flat[:, base + grid.nx]
    v11 = flat[:, base + grid.nx + 1]
    return (v00 + fx * (v10 - v00)) * (1 - fy) + (v01 + fx * (v11 - v01)) * fy
