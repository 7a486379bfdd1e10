"""The KDE's kernel applied to a density given on the grid: the noise-free KDE.

For ``N`` robots drawn independently from ``p`` the KDE of :mod:`harness.kde` has
expectation ``(K_h * p)(c) = int p(x) K(c, x) dx``, with ``K`` the Gaussian kernel of
bandwidth ``h`` and its wall images. For ``p`` given by cell values, the integral is
taken with the cell centres as nodes,

    (K_h * p)(c_i) = sum_j p_j K(c_i, x_j) dx dy,

which for a Gaussian of bandwidth ``h`` sampled at spacing ``dx`` is exact up to
aliasing: the cosine mode of wavenumber ``kappa`` picks up its alias about the sampling
wavenumber with the factor ``exp(-(2 pi / dx - kappa)^2 h^2 / 2)``, ``exp(-2 pi^2 h^2 /
dx^2)`` = 5e-13 for the constant mode on the paper's grid (``h = 0.04``, ``dx = 1/30``)
but up to ``exp(-pi^2 h^2 / (2 dx^2))`` = 8e-4 next to the Nyquist mode, which the
kernel itself damps to 1e-3 (a test measures it; :class:`Smoother` explains why its
transform form is used only where that factor is below round-off). Separable per
axis: ``K_h * p = G_y^T p G_x dx dy`` with the 1-D kernel matrices ``G[j, i] = k(c_i,
x_j)`` of :func:`harness.kde.kernel_1d`; the gradient takes the derivative matrices in
place of ``G`` on its own axis.

With wall images, each Neumann cosine mode ``cos(k_x x) cos(k_y y)`` is an
eigenfunction: ``K_h * cos = exp(-|k|^2 h^2 / 2) cos`` (the images make the
convolution act on the even periodic extension). :func:`transfer` gives that factor,
which the sampled-data step bound uses (:func:`harness.control.sampled_data_dt_bound`).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from harness.densities import Target
from harness.grid import Grid
from harness.kde import kernel_1d

ALIAS_TOLERANCE = 1e-13
"""Largest aliasing factor ``exp(-pi^2 (h / dx)^2 / 2)`` at which :class:`Smoother`
uses the cosine transforms instead of the kernel matrices."""

TRANSFORM_MIN_SIDE = 129
"""Fewest cells per side on which :class:`Smoother` uses the cosine transforms: on
smaller grids the matrix products are faster (measured at n = 64 and 128)."""


class Smoother:
    """``p -> (K_h * p, grad (K_h * p))`` on a grid.

    Two forms of the same operator. The kernel matrices (module docstring) treat ``p``
    as point masses at the cell centres; with wall images the cosine mode ``a`` then
    comes out multiplied by ``exp(-(kappa_a h)^2 / 2)`` plus its alias about the
    sampling wavenumber, ``exp(-(2 pi / dx - kappa_a)^2 h^2 / 2)`` (Poisson summation),
    largest at the grid's Nyquist mode, where it is ``exp(-pi^2 (h / dx)^2 / 2)``. The
    transform form multiplies the Neumann cosine coefficients by :func:`transfer` and
    differentiates the cosine series exactly (sine coefficients ``-kappa_a c_a``). The
    two agree to that factor where it is below ``ALIAS_TOLERANCE`` on both axes (``h /
    dx > 2.46``, grids finer than about 62 cells per side at ``h = 0.04``). The
    transforms cost ``O(M log M)`` against the matrices' ``O(M^1.5)``, but with their
    constants the matrices are faster up to n = 128 (0.2 against 0.5 ms at n = 64, 0.9
    to 1.7 against 1.2 to 2.0 ms at 128) and slower at 256 (7.6 to 8.9 against 4.4 to
    7.3 ms; one core, ranges over runs on a host whose speed drifts). The transforms
    also hold every wall image where the matrices hold the first one per wall; the next
    ones lie a domain length ``L`` away, so the two agree when ``exp(-(L / h)^2 / 2)`` is
    negligible too (``L / h > 7.7``; 25 at the paper's ``h``). So the transforms are used
    where both factors are below ``ALIAS_TOLERANCE``, the kernel has its wall images and
    the grid has at least ``TRANSFORM_MIN_SIDE`` cells per side; elsewhere the matrices, whose
    aliasing on coarse grids is what the KDE's own quadrature has.

    Args:
        grid: The grid.
        bandwidth: Kernel standard deviation ``h > 0`` (length).
        mirror: Wall images, as in the KDE.
    """

    def __init__(self, grid: Grid, bandwidth: float, mirror: bool = True) -> None:
        self.grid, self.bandwidth = grid, bandwidth
        self.gx, self.dgx = kernel_1d(grid.x, grid.x, bandwidth, grid.x0, grid.x1, mirror)
        self.gy, self.dgy = kernel_1d(grid.y, grid.y, bandwidth, grid.y0, grid.y1, mirror)
        alias = np.exp(-0.5 * (np.pi * bandwidth / max(grid.dx, grid.dy)) ** 2)
        # the transforms hold every wall image, the matrices the first one per wall (the
        # next are a domain length away): equal where exp(-(L / h)^2 / 2) is negligible
        span = min(grid.x1 - grid.x0, grid.y1 - grid.y0)
        images = np.exp(-0.5 * (span / bandwidth) ** 2)
        self.spectral = bool(
            mirror
            and max(alias, images) <= ALIAS_TOLERANCE
            and min(grid.nx, grid.ny) >= TRANSFORM_MIN_SIDE
        )
        kx = np.pi * np.arange(grid.nx) / (grid.x1 - grid.x0)
        ky = np.pi * np.arange(grid.ny) / (grid.y1 - grid.y0)
        self._transfer = transfer(ky, bandwidth)[:, None] * transfer(kx, bandwidth)[None, :]
        # the derivative of mode a is -kappa_a times sine mode a - 1 (orthonormal DST-II
        # index a - 1 for a = 1 .. n - 1; index n - 1 is the mode a = n, absent)
        self._kx, self._ky = kx, ky

    def __call__(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``K_h * p`` ``(ny, nx)`` (1 / length^2) and its gradient ``(2, ny, nx)``
        (1 / length^3) for cell values ``p`` (1 / length^2).
        """
        if self.spectral:
            return self.transformed(p)
        return self.matrices(p)

    def transformed(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The transform form (see the class docstring)."""
        coef = sfft.dctn(p, type=2, norm="ortho") * self._transfer
        along_y = sfft.idct(coef, type=2, norm="ortho", axis=0)  # x still in modes
        smooth = sfft.idct(along_y, type=2, norm="ortho", axis=1)
        grad_x = sfft.idst(_derivative(along_y, self._kx, axis=1), type=2, norm="ortho", axis=1)
        along_x = sfft.idct(coef, type=2, norm="ortho", axis=1)  # y still in modes
        grad_y = sfft.idst(_derivative(along_x, self._ky, axis=0), type=2, norm="ortho", axis=0)
        return smooth, np.stack([grad_x, grad_y])

    def matrices(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The kernel-matrix form (see the module docstring)."""
        a = self.grid.cell_area
        rows = self.gy.T @ p  # smoothed along y: (ny, nx)
        smooth = rows @ self.gx * a
        grad_x = rows @ self.dgx * a
        grad_y = (self.dgy.T @ p) @ self.gx * a
        return smooth, np.stack([grad_x, grad_y])


def _derivative(coef: np.ndarray, k: np.ndarray, axis: int) -> np.ndarray:
    """Orthonormal DST-II coefficients of the derivative along ``axis`` (0 or 1) of the
    cosine series with orthonormal DCT-II coefficients ``coef`` ``(n_y, n_x)``: ``d/dx
    phi_a = -k_a psi_{a-1}`` for ``a >= 1`` (both ``sqrt(2 / n)`` normalised), nothing at
    index ``n - 1``.
    """
    out = np.zeros(coef.shape)  # C order whatever the input's (the transforms' speed)
    if axis == 0:
        np.multiply(coef[1:, :], -k[1:, None], out=out[:-1, :])
    else:
        np.multiply(coef[:, 1:], -k[None, 1:], out=out[:, :-1])
    return out


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

    From the target's continuous density by :func:`harness.swarm_metrics.smoothed_density`
    (exact for a density with a closed form, else the noise-free KDE of its cell values);
    for a target given by cell values only, the noise-free KDE of those
    (:class:`Smoother`). ``p~_* >= min p_*`` (the mirrored kernel has unit mass on the
    domain), so it is a valid target for the laws.
    """
    from harness.swarm_metrics import smoothed_density

    if target.density is None:
        values = Smoother(target.grid, bandwidth, mirror)(target.p)[0]
    else:
        values = smoothed_density(target.density, target.grid, bandwidth, mirror)
    return Target.from_values(target.grid, values)
