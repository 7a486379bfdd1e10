"""The KDE's kernel applied to a density given on the grid: the noise-free KDE.

For ``N`` robots drawn independently from ``p`` the KDE of :mod:`harness.kde` has
expectation ``(K_h * p)(c) = int p(x) K(c, x) dx``, with ``K`` the Gaussian kernel of
bandwidth ``h`` and its wall images. For ``p`` given by cell values, the integral is
taken with the cell centres as nodes,

    (K_h * p)(c_i) = sum_j p_j K(c_i, x_j) dx dy,

which for a Gaussian of bandwidth ``h`` sampled at spacing ``dx`` is exact up to
aliasing of relative size ``exp(-2 pi^2 h^2 / dx^2)`` (1e-12 for the paper's
``h = 0.04``, ``dx = 1/30``). Separable per axis: ``K_h * p = G_y^T p G_x dx dy``
with the 1-D kernel matrices ``G[j, i] = k(c_i, x_j)`` of :func:`harness.kde.kernel_1d`;
the gradient takes the derivative matrices in place of ``G`` on its own axis.

With wall images, each Neumann cosine mode ``cos(k_x x) cos(k_y y)`` is an
eigenfunction: ``K_h * cos = exp(-|k|^2 h^2 / 2) cos`` (the images make the
convolution act on the even periodic extension). :func:`transfer` gives that factor,
which the sampled-data step bound uses (:func:`harness.control.sampled_data_dt_bound`).
"""

from __future__ import annotations

import numpy as np

from harness.densities import Target
from harness.grid import Grid
from harness.kde import kernel_1d


class Smoother:
    """``p -> (K_h * p, grad (K_h * p))`` on a grid.

    Args:
        grid: The grid.
        bandwidth: Kernel standard deviation ``h > 0`` (length).
        mirror: Wall images, as in the KDE.
    """

    def __init__(self, grid: Grid, bandwidth: float, mirror: bool = True) -> None:
        self.grid, self.bandwidth = grid, bandwidth
        self.gx, self.dgx = kernel_1d(grid.x, grid.x, bandwidth, grid.x0, grid.x1, mirror)
        self.gy, self.dgy = kernel_1d(grid.y, grid.y, bandwidth, grid.y0, grid.y1, mirror)

    def __call__(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``K_h * p`` ``(ny, nx)`` (1 / length^2) and its gradient ``(2, ny, nx)``
        (1 / length^3) for cell values ``p`` (1 / length^2).
        """
        a = self.grid.cell_area
        rows = self.gy.T @ p  # smoothed along y: (ny, nx)
        smooth = rows @ self.gx * a
        grad_x = rows @ self.dgx * a
        grad_y = (self.dgy.T @ p) @ self.gx * a
        return smooth, np.stack([grad_x, grad_y])


def transfer(k: np.ndarray, bandwidth: float | None) -> np.ndarray:
    """Factor ``exp(-k^2 h^2 / 2)`` by which the mirrored Gaussian kernel multiplies
    a cosine mode of wavenumber ``k`` (1 / length); 1 when ``bandwidth`` is None.
    """
    k = np.asarray(k, dtype=float)
    if bandwidth is None:
        return np.ones_like(k)
    return np.exp(-0.5 * (k * bandwidth) ** 2)


def smoothed_target(target: Target, bandwidth: float, mirror: bool = True) -> Target:
    """The target as the KDE sees it, ``p~_* = K_h * p_*``, with its grid gradient.

    Exact (:func:`harness.swarm_metrics.smoothed_density`) when the target's continuous
    density has a closed form; otherwise the noise-free KDE of its cell values
    (:class:`Smoother`). ``p~_* >= min p_*`` (the mirrored kernel has unit mass on the
    domain), so it is a valid target for the laws.
    """
    from harness.swarm_metrics import smoothed_density

    values = None
    if target.density is not None:
        try:
            values = smoothed_density(target.density, target.grid, bandwidth, mirror)
        except TypeError:  # no closed form for this density
            values = None
    if values is None:
        values = Smoother(target.grid, bandwidth, mirror)(target.p)[0]
    return Target.from_values(target.grid, values)
