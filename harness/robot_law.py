"""A field law evaluated by each robot on its own estimate, at its own position.

When the robots estimate the density on their own (each robot ``i`` holds ``p_hat_i``
and ``q_hat_i``, :class:`harness.records.RobotEstimates`), robot ``i`` moves by the
law's value from its own estimates: the law's cell-centre values at the four cells
around ``X_i`` from ``(p_hat_i, q_hat_i)`` there, interpolated bilinearly as
:func:`harness.agents.interpolate` interpolates a broadcast field (nearest values beyond
the outer centres). With every robot holding the same estimate this is exactly what a
robot does with the broadcast field. A field law that has cell values
(:meth:`harness.control.FieldLaw.at_cells`) gets this for free.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from harness.grid import Grid
from harness.velocity import VelocityField


class CellLaw(Protocol):
    """A control law's cell-centre values at given cells (``FieldLaw.at_cells``)."""

    def __call__(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(vx, vy)`` (length / s) at flat ``cells`` from the estimates there."""
        ...


def own_velocities(
    grid: Grid,
    law: CellLaw,
    p_hat: np.ndarray,
    positions: np.ndarray,
    q_hat: np.ndarray | None = None,
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
        q_hat: Gradient estimates ``(N, 2M)`` (1 / length^3); None for the grid
            gradient ``G p_hat_i`` (evaluated only at the four cells).
    """
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
        ip, im = np.minimum(ci + 1, g.nx - 1), np.maximum(ci - 1, 0)
        jp, jm = np.minimum(cj + 1, g.ny - 1), np.maximum(cj - 1, 0)
        # the grid gradient G (harness.grid.Grid.gradient), reflecting ghost cells
        qx = (p_hat[rows, cj * g.nx + ip] - p_hat[rows, cj * g.nx + im]) / (2 * g.dx)
        qy = (p_hat[rows, jp * g.nx + ci] - p_hat[rows, jm * g.nx + ci]) / (2 * g.dy)
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
) -> np.ndarray:
    """Plain statement of :func:`own_velocities`: per robot the full field of
    ``field_law`` (``(p_hat, q_hat) -> VelocityField``) and
    :func:`harness.agents.interpolate` at ``X_i``.
    """
    from harness.agents import interpolate

    out = np.empty((2, positions.shape[1]))
    for i in range(positions.shape[1]):
        p = p_hat[i].reshape(grid.shape)
        q = grid.gradient(p) if q_hat is None else q_hat[i].reshape(2, *grid.shape)
        v = field_law(p, q)
        out[:, i] = interpolate(grid, v.centres, positions[:, i : i + 1])[:, 0]
    return out
