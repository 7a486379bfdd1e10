"""Immutable cell-centred grid on a rectangle.

Every field in the harness is a numpy array of shape ``(ny, nx)``: row ``j`` lies
at height ``y_j`` and column ``i`` at abscissa ``x_i`` (the layout of
``foxglove.Grid``: columns along x, rows along y from the origin). Vector fields
have shape ``(2, ny, nx)`` with component 0 along x and component 1 along y.
Flattened fields use C order, so cell ``(j, i)`` has index ``j * nx + i``.

Cell centres are ``x_i = x0 + (i + 1/2) dx`` and ``y_j = y0 + (j + 1/2) dy``. All
integrals are midpoint sums, ``int f = dx dy sum_ij f_ij``, and every norm the
harness reports is the discrete L2 norm ``||f|| = (int f^2)^(1/2)``, in the units
of ``f`` times length.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Grid:
    """Cell-centred ``nx`` x ``ny`` grid on ``[x0, x1] x [y0, y1]``.

    Args:
        nx: Number of cells along x (``>= 4``).
        ny: Number of cells along y (``>= 4``).
        x0, x1, y0, y1: Rectangle bounds, length units (the unit square by default).
    """

    nx: int
    ny: int
    x0: float = 0.0
    x1: float = 1.0
    y0: float = 0.0
    y1: float = 1.0

    def __post_init__(self) -> None:
        for name in ("nx", "ny"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 4:
                raise ValueError(f"Grid.{name} must be an integer >= 4, got {value!r}")
        for name in ("x0", "x1", "y0", "y1"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(
                value, (int, float, np.integer, np.floating)
            ):
                raise ValueError(f"Grid.{name} must be a number, got {value!r}")
            # the bounds reach compiled code, which is typed by its arguments: floats only
            object.__setattr__(self, name, float(value))
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise ValueError(
                f"Grid bounds must satisfy x1 > x0 and y1 > y0, got "
                f"[{self.x0}, {self.x1}] x [{self.y0}, {self.y1}]"
            )

    @classmethod
    def square(cls, n: int, length: float = 1.0) -> Grid:
        """The ``n`` x ``n`` grid on ``[0, length]^2``."""
        return cls(n, n, 0.0, length, 0.0, length)

    # --- geometry -----------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """Array shape of a scalar field, ``(ny, nx)``."""
        return (self.ny, self.nx)

    @property
    def size(self) -> int:
        """Number of cells ``M = nx * ny``."""
        return self.nx * self.ny

    @property
    def dx(self) -> float:
        """Cell width along x (length)."""
        return (self.x1 - self.x0) / self.nx

    @property
    def dy(self) -> float:
        """Cell height along y (length)."""
        return (self.y1 - self.y0) / self.ny

    @property
    def cell_area(self) -> float:
        """Cell area ``dx * dy`` (length^2)."""
        return self.dx * self.dy

    @property
    def area(self) -> float:
        """Area of the domain (length^2)."""
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    @cached_property
    def x(self) -> np.ndarray:
        """Cell-centre abscissae, shape ``(nx,)``."""
        return self.x0 + (np.arange(self.nx) + 0.5) * self.dx

    @cached_property
    def y(self) -> np.ndarray:
        """Cell-centre ordinates, shape ``(ny,)``."""
        return self.y0 + (np.arange(self.ny) + 0.5) * self.dy

    @cached_property
    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(X, Y)``, each of shape ``(ny, nx)``."""
        return np.meshgrid(self.x, self.y, indexing="xy")

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Boolean mask of points inside the closed rectangle."""
        return (x >= self.x0) & (x <= self.x1) & (y >= self.y0) & (y <= self.y1)

    # --- integrals and norms ------------------------------------------------------
    def integrate(self, f: np.ndarray) -> float:
        """Midpoint integral ``int f dx`` of a scalar field (or the sum over the
        components of a vector field).
        """
        return float(np.sum(f) * self.cell_area)

    def inner(self, f: np.ndarray, g: np.ndarray) -> float:
        """L2 inner product ``<f, g> = int f . g dx`` (vector fields: summed over
        components).
        """
        return float(np.vdot(f, g).real * self.cell_area)

    def l2(self, f: np.ndarray) -> float:
        """L2 norm ``||f|| = <f, f>^(1/2)``."""
        return float(np.sqrt(self.inner(f, f)))

    def normalise(self, f: np.ndarray) -> np.ndarray:
        """``f / int f``: a field scaled to unit mass."""
        mass = self.integrate(f)
        if not np.isfinite(mass) or mass <= 0:
            raise ValueError(f"cannot normalise a field of mass {mass}")
        return f / mass

    # --- discrete gradient --------------------------------------------------------
    def gradient(self, f: np.ndarray) -> np.ndarray:
        """Cell-centred gradient of a scalar field, shape ``(2, ny, nx)``.

        Central differences ``(f_{i+1} - f_{i-1}) / (2 dx)`` with reflecting ghost
        cells at the walls (``f_{-1} = f_0``, ``f_n = f_{n-1}``), the Neumann
        closure of the reflecting walls. It maps each Neumann cosine mode
        ``cos(a pi (x - x0) / L)`` exactly onto ``-sin(a pi dx / L) / dx sin(a pi (x -
        x0) / L)``, so the gradients of distinct modes stay orthogonal (DCT to DST)
        and the operator has no near-null modes besides the constants. Second order
        inside and for fields with zero normal derivative at the walls (cosine
        modes, the reflection KDE); at a wall cell of a field whose normal
        derivative does not vanish it returns about half that derivative. The same
        operator is :attr:`gradient_matrix`.
        """
        f = np.asarray(f, dtype=float)
        gx = np.empty_like(f)
        gy = np.empty_like(f)
        gx[:, 1:-1] = (f[:, 2:] - f[:, :-2]) / (2 * self.dx)
        gx[:, 0] = (f[:, 1] - f[:, 0]) / (2 * self.dx)
        gx[:, -1] = (f[:, -1] - f[:, -2]) / (2 * self.dx)
        gy[1:-1, :] = (f[2:, :] - f[:-2, :]) / (2 * self.dy)
        gy[0, :] = (f[1, :] - f[0, :]) / (2 * self.dy)
        gy[-1, :] = (f[-1, :] - f[-2, :]) / (2 * self.dy)
        return np.stack([gx, gy])

    @cached_property
    def gradient_matrix(self) -> sp.csr_matrix:
        """Sparse ``(2M, M)`` matrix ``G`` with ``G @ f.ravel() ==
        gradient(f).ravel()``.
        """
        dx_1d = gradient_1d(self.nx, self.dx)
        dy_1d = gradient_1d(self.ny, self.dy)
        gx = sp.kron(sp.identity(self.ny), dx_1d)
        gy = sp.kron(dy_1d, sp.identity(self.nx))
        return sp.vstack([gx, gy]).tocsr()


def gradient_1d(n: int, h: float) -> sp.csr_matrix:
    """1-D central-difference matrix with reflecting ghost cells at both ends."""
    d = sp.lil_matrix((n, n))
    for i in range(1, n - 1):
        d[i, i - 1] = -0.5 / h
        d[i, i + 1] = 0.5 / h
    d[0, 0], d[0, 1] = -0.5 / h, 0.5 / h
    d[n - 1, n - 2], d[n - 1, n - 1] = -0.5 / h, 0.5 / h
    return d.tocsr()


ORDERS = (2, 4)
"""The orders of the central differences :func:`grid_gradient` and
:func:`own_velocities` take."""


def grid_gradient(grid: Grid, f: np.ndarray, order: int = 2) -> np.ndarray:
    """``G f`` (order 2: :meth:`harness.grid.Grid.gradient`) or ``G_4 f`` (order 4) of a
    field ``(ny, nx)``, shape ``(2, ny, nx)`` (module docstring).

    Raises:
        ValueError: ``order`` is not one of :data:`ORDERS`.
    """
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    if order == 2:
        return grid.gradient(f)
    f = np.asarray(f, dtype=float)
    e = np.pad(f, 2, mode="symmetric")  # the ghost cells reflected about the walls
    gx = (8 * (e[2:-2, 3:-1] - e[2:-2, 1:-3]) - (e[2:-2, 4:] - e[2:-2, :-4])) / (12 * grid.dx)
    gy = (8 * (e[3:-1, 2:-2] - e[1:-3, 2:-2]) - (e[4:, 2:-2] - e[:-4, 2:-2])) / (12 * grid.dy)
    return np.stack([gx, gy])
