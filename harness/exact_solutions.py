"""Exact solutions and theory values used by the tests and benchmarks.

Each function states a fact that does not depend on the harness's numerics:
a continuum formula, or a closed-form property of the discrete scheme.
"""

from __future__ import annotations

import numpy as np

from harness.grid import Grid


def cosine_mode(grid: Grid, kx: int, ky: int) -> np.ndarray:
    """Neumann cosine mode ``cos(kx pi (x - x0)/Lx) cos(ky pi (y - y0)/Ly)`` at the
    cell centres. On a cell-centred grid it is an exact eigenvector of the
    finite-volume Laplacian with zero-flux walls.
    """
    lx, ly = grid.x1 - grid.x0, grid.y1 - grid.y0
    x, y = grid.mesh
    return np.cos(kx * np.pi * (x - grid.x0) / lx) * np.cos(ky * np.pi * (y - grid.y0) / ly)


def continuum_decay_rate(grid: Grid, kx: int, ky: int, sigma: float) -> float:
    """Decay rate ``sigma pi^2 (kx^2 / Lx^2 + ky^2 / Ly^2)`` (1 / time) of the cosine
    mode under ``d_t p = sigma Laplacian(p)`` with zero-flux walls.
    """
    lx, ly = grid.x1 - grid.x0, grid.y1 - grid.y0
    return sigma * np.pi**2 * (kx**2 / lx**2 + ky**2 / ly**2)


def discrete_decay_rate(grid: Grid, kx: int, ky: int, sigma: float) -> float:
    """Eigenvalue magnitude of the cosine mode for the 5-point finite-volume
    Laplacian: ``sigma (4/dx^2 sin^2(kx pi dx / 2Lx) + 4/dy^2 sin^2(ky pi dy / 2Ly))``.
    It equals the continuum rate up to ``O(dx^2)``.
    """
    lx, ly = grid.x1 - grid.x0, grid.y1 - grid.y0
    return sigma * (
        4 / grid.dx**2 * np.sin(kx * np.pi * grid.dx / (2 * lx)) ** 2
        + 4 / grid.dy**2 * np.sin(ky * np.pi * grid.dy / (2 * ly)) ** 2
    )


def histogram_noise(grid: Grid, p: np.ndarray, n_robots: int) -> tuple[float, float]:
    """Mean and standard deviation of ``||h - p_bar||^2`` for the histogram ``h`` of
    ``N`` independent samples of a density whose cell averages are ``p_bar``.

    With cell probabilities ``pi_j = a p_j`` (``a`` the cell area) the counts are
    multinomial, so ``E ||h - p_bar||^2 = sum_j a Var[h_j] = (1 - sum pi_j^2) /
    (N a)`` and, treating cells as independent with ``Var[(h_j - p_j)^2] ~ 2
    Var[h_j]^2``, the standard deviation is ``sqrt(2 sum_j pi_j^2) / (N a)``.
    """
    a = grid.cell_area
    pi = p * a
    mean = (1.0 - float(np.sum(pi**2))) / (n_robots * a)
    std = float(np.sqrt(2.0 * np.sum(pi**2))) / (n_robots * a)
    return mean, std
