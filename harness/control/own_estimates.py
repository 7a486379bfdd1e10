"""A field law evaluated by each robot on its own estimate, at its own position.

When the robots estimate the density on their own (each robot ``i`` holds ``p_hat_i``
and ``q_hat_i``, :class:`harness.records.RobotEstimates`), robot ``i`` moves by the
law's value from its own estimates: the law's cell-centre values at the four cells
around ``X_i`` from ``(p_hat_i, q_hat_i)`` there, interpolated bilinearly as
:func:`harness.velocity.interpolate` interpolates a broadcast field (nearest values beyond
the outer centres). With every robot holding the same estimate this is exactly what a
robot does with the broadcast field. A field law that has cell values
(:meth:`harness.control.field.FieldLaw.at_cells`) gets this for free.

A robot without a gradient estimate of its own takes the central differences of its own
``p_hat_i`` at the four cells (:func:`grid_gradient`, the ghost cells reflected about the
walls as in :meth:`harness.grid.Grid.gradient`): of order 2,

    (G f)_i = (f_{i+1} - f_{i-1}) / (2 dx),

or of order 4,

    (G_4 f)_i = (8 (f_{i+1} - f_{i-1}) - (f_{i+2} - f_{i-2})) / (12 dx),

along each axis. A Neumann cosine mode of wavenumber ``kappa`` is even about both walls,
so the reflection is exact for it and each operator multiplies its derivative by a
factor: ``sin(kappa dx) / (kappa dx)`` for ``G``, ``(8 sin(kappa dx) - sin(2 kappa dx))
/ (6 kappa dx)`` for ``G_4`` (errors ``(kappa dx)^2 / 6`` and ``(kappa dx)^4 / 30`` for
small ``kappa dx``). At the paper's kernel scale (``kappa = 1 / h``, ``h / dx = 1.2``)
the factors are 0.89 and 0.985; at ``kappa = 2 / h``, 0.60 and 0.82.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from harness.grid import ORDERS, Grid, grid_gradient
from harness.velocity import VelocityField


class CellLaw(Protocol):
    """A control law's cell-centre values at given cells (``FieldLaw.at_cells``)."""

    def __call__(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(vx, vy)`` (length / s) at flat ``cells`` from the estimates there."""
        ...


def _reflect(k: np.ndarray, n: int) -> np.ndarray:
    """Cell indices ``k`` (at most ``n`` cells beyond a wall) reflected into ``[0, n)``:
    the ghost cell ``-1 - k`` is cell ``k``, the ghost cell ``n + k`` is cell ``n - 1 - k``.
    """
    return np.where(k < 0, -1 - k, np.where(k >= n, 2 * n - 1 - k, k))


def own_velocities(
    grid: Grid,
    law: CellLaw,
    p_hat: np.ndarray,
    positions: np.ndarray,
    q_hat: np.ndarray | None = None,
    order: int = 2,
) -> np.ndarray:
    """Each robot's velocity from its own estimates at its own position, ``(2, N)``
    (length / time).

    Robot ``i`` evaluates the law's cell-centre values (``law``, a field law's
    ``at_cells``; for the paper's law eq. ``modified density feedback law using
    estimates``,

        v_i = -alpha (p_* q_hat_i - p_hat_i grad p_*) / p_*^2 + sigma grad p_* / p_*)

    at the four cell centres around ``X_i`` from ``(p_hat_i, q_hat_i)`` there, and
    interpolates bilinearly (module docstring).

    Args:
        grid: The grid.
        law: ``(p, qx, qy, cells) -> (vx, vy)`` at flat cell indices.
        p_hat: Robots' density estimates ``(N, M)`` (1 / length^2).
        positions: ``(2, N)`` (length).
        q_hat: Gradient estimates ``(N, 2M)`` (1 / length^3); None for the central
            differences of ``p_hat_i`` (evaluated only at the four cells).
        order: Their order with ``q_hat`` None, one of :data:`ORDERS`: 2 (``G
            p_hat_i``) or 4 (``G_4 p_hat_i``).

    Raises:
        ValueError: ``order`` is not one of :data:`ORDERS`.
    """
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    g = grid
    n = positions.shape[1]
    u = np.clip((positions[0] - g.x0) / g.dx - 0.5, 0.0, g.nx - 1)
    w = np.clip((positions[1] - g.y0) / g.dy - 0.5, 0.0, g.ny - 1)
    i0 = np.minimum(u.astype(np.intp), g.nx - 2)
    j0 = np.minimum(w.astype(np.intp), g.ny - 2)
    fx, fy = u - i0, w - j0
    ci = np.stack([i0, i0 + 1, i0, i0 + 1], axis=1)  # (N, 4): corners 00, 10, 01, 11
    cj = np.stack([j0, j0, j0 + 1, j0 + 1], axis=1)
    cells = cj * g.nx + ci
    rows = np.arange(n)[:, None]
    p = p_hat[rows, cells]
    if q_hat is None:

        def step(d: int) -> tuple[np.ndarray, np.ndarray]:
            """``f_{i+d} - f_{i-d}`` along x and along y, ghost cells reflected."""
            ip, im = _reflect(ci + d, g.nx), _reflect(ci - d, g.nx)
            jp, jm = _reflect(cj + d, g.ny), _reflect(cj - d, g.ny)
            return (
                p_hat[rows, cj * g.nx + ip] - p_hat[rows, cj * g.nx + im],
                p_hat[rows, jp * g.nx + ci] - p_hat[rows, jm * g.nx + ci],
            )

        dx1, dy1 = step(1)
        if order == 2:  # G (harness.grid.Grid.gradient)
            qx, qy = dx1 / (2 * g.dx), dy1 / (2 * g.dy)
        else:  # G_4
            dx2, dy2 = step(2)
            qx, qy = (8 * dx1 - dx2) / (12 * g.dx), (8 * dy1 - dy2) / (12 * g.dy)
    else:
        qx = q_hat[rows, cells]
        qy = q_hat[rows, g.size + cells]
    vx, vy = law(p, qx, qy, cells)
    out = np.empty((2, n))
    for c, v in enumerate((vx, vy)):
        out[c] = (v[:, 0] + fx * (v[:, 1] - v[:, 0])) * (1 - fy) + (
            v[:, 2] + fx * (v[:, 3] - v[:, 2])
        ) * fy
    return out


def own_velocities_reference(
    grid: Grid,
    field_law: Callable[[np.ndarray, np.ndarray], VelocityField],
    p_hat: np.ndarray,
    positions: np.ndarray,
    q_hat: np.ndarray | None = None,
    order: int = 2,
) -> np.ndarray:
    """Plain statement of :func:`own_velocities`: per robot the full field of
    ``field_law`` (``(p_hat, q_hat) -> VelocityField``, with ``q_hat`` the
    :func:`grid_gradient` of order ``order`` when None) and
    :func:`harness.velocity.interpolate` at ``X_i``.
    """
    from harness.velocity import interpolate

    out = np.empty((2, positions.shape[1]))
    for i in range(positions.shape[1]):
        p = p_hat[i].reshape(grid.shape)
        q = grid_gradient(grid, p, order) if q_hat is None else q_hat[i].reshape(2, *grid.shape)
        v = field_law(p, q)
        out[:, i] = interpolate(grid, v.centres, positions[:, i : i + 1])[:, 0]
    return out
