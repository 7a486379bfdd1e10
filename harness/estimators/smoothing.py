"""The KDE's kernel applied to a density given on the grid: the noise-free KDE.

For ``N`` robots drawn independently from ``p`` the KDE of :mod:`harness.estimators.kde` has
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
x_j)`` of :func:`harness.estimators.kde.kernel_1d`; the gradient takes the derivative matrices in
place of ``G`` on its own axis.

With wall images, each Neumann cosine mode ``cos(k_x x) cos(k_y y)`` is an
eigenfunction: ``K_h * cos = exp(-|k|^2 h^2 / 2) cos`` (the images make the
convolution act on the even periodic extension). :func:`transfer` gives that factor,
which the sampled-data step bound uses (:func:`harness.control.field.sampled_data_dt_bound`).

``K_h * p`` and the cell masses. :func:`smoothed_density` and :func:`cell_masses` ask
the density: one with closed forms gives them itself (the optional methods ``smoothed``
and ``cell_masses`` of :class:`~harness.targets.densities.Density`; the densities of
:mod:`harness.targets.densities` have them, exact to round-off); for any other density they
fall back to approximations from its cell values, :func:`smoothed_density_cells` (the
noise-free KDE of the cell values, :class:`Smoother`) and
:func:`cell_masses_midpoint` (cell value times cell area).
:func:`smoothed_density_quadrature` is the plain reference: composite Gauss-Legendre
quadrature of ``p(x) K(c, x)`` with the KDE's own kernel function, for any density
given as a function ``p(x, y)``; it agrees with the closed forms to ~1e-12.

``estimator=smoothed`` (:class:`SmoothedEstimator`) is the noise-free KDE of the plant's
mean-field density as the estimate.

On free space (``free`` given) ``K_h`` is the KDE's own kernel there, diffusion for time
``h^2 / 2`` with no flux through closed faces (:class:`harness.estimators.diffusion.FreeKernel`):
:class:`Smoother` and :func:`smoothed_target` apply the very operator whose expectation
the free-space KDE of robots drawn from ``p`` (constant on each cell) has, ``E[KDE] = K_h
p``. Its bias against ``p`` itself is that of the Neumann heat semigroup: ``O(h^2)``
inside (``(h^2 / 2) Laplacian p``), ``O(h)`` within about ``h`` of a wall or an obstacle
where ``p``'s normal derivative does not vanish (the kernel reflects there), so ``O(h^{3/2})``
in L2; it vanishes as ``h -> 0``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.fft as sfft

from harness.domains.base import FreeSpace
from harness.estimators.diffusion import FreeKernel
from harness.estimators.kde import kernel_1d
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import ParameterError, flag, number
from harness.records import Estimate, StepInput
from harness.targets.densities import Density, ExactCellMasses, ExactSmoothing, Target

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
        free: Free space of a domain with obstacles: ``K_h`` is then the diffusion
            kernel of :class:`~harness.estimators.diffusion.FreeKernel` (``mirror`` must
            be True); None for the square.
    """

    def __init__(
        self, grid: Grid, bandwidth: float, mirror: bool = True, free: FreeSpace | None = None
    ) -> None:
        self.grid, self.bandwidth = grid, bandwidth
        self.diffusion: FreeKernel | None = None
        if free is not None:
            if free.grid != grid:
                raise ValueError("smoother free space resolved on another grid")
            if not mirror:
                raise ValueError("smoother mirror must be True on free space (its walls reflect)")
            self.diffusion = FreeKernel(free, bandwidth)
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
        if self.diffusion is not None:
            return self.diffusion.smooth(p)
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

    From the target's continuous density by :func:`harness.estimators.smoothing.smoothed_density`
    (exact for a density with a closed form, else the noise-free KDE of its cell values);
    for a target given by cell values only, the noise-free KDE of those
    (:class:`Smoother`). ``p~_* >= min p_*`` (the mirrored kernel has unit mass on the
    domain), so it is a valid target for the laws. On free space (``target.free``) the
    diffusion kernel of the free-space KDE applied to the target's cell values,
    restricted to free space.
    """
    if target.free is not None:
        values = Smoother(target.grid, bandwidth, mirror, target.free)(target.p)[0]
        return Target.from_values(target.grid, values, target.free)
    if target.density is None:
        values = Smoother(target.grid, bandwidth, mirror)(target.p)[0]
    else:
        values = smoothed_density(target.density, target.grid, bandwidth, mirror)
    return Target.from_values(target.grid, values)


def smoothed_density(
    density: Density, grid: Grid, bandwidth: float, mirror: bool = True
) -> np.ndarray:
    """``K_h * p`` at the cell centres: the density's own ``smoothed`` (exact) when it
    has one (:class:`~harness.targets.densities.ExactSmoothing`), else
    :func:`smoothed_density_cells` (approximate).

    Args:
        density: The continuous density the robots are sampled from, restricted to the
            grid's domain.
        grid: The grid (cell centres, domain and walls).
        bandwidth: Kernel standard deviation ``h > 0`` (length), as in the KDE.
        mirror: Wall images, as the KDE's ``mirror``.

    Returns:
        Shape ``(ny, nx)``, 1 / length^2. Its grid integral is 1 up to the midpoint
        rule's error.
    """
    if not bandwidth > 0:
        raise ValueError(f"bandwidth must be > 0, got {bandwidth}")
    if isinstance(density, ExactSmoothing):
        return density.smoothed(grid, bandwidth, mirror)
    return smoothed_density_cells(density, grid, bandwidth, mirror)


def smoothed_density_cells(
    density: Density, grid: Grid, bandwidth: float, mirror: bool = True
) -> np.ndarray:
    """``K_h * p`` approximated from the density's cell values (``on_grid``): the
    noise-free KDE of the cell values (:class:`harness.estimators.smoothing.Smoother`), with the
    cell centres as quadrature nodes. The approximate path of
    :func:`smoothed_density`, for a density without a closed form: its error is the
    midpoint rule's on cells of the grid (``O(dx^2)`` for a smooth density, larger where
    ``p`` jumps inside a cell; 9e-4 relative for the default target on the paper's
    grid), against round-off for the closed forms. It is also the slower path on fine
    grids (the kernel matrices of the grid): 0.19 s against 3 ms for the default
    target's closed form on 128 x 128 cells (1.4 and 2.3 ms on 30 x 30).
    """
    return Smoother(grid, bandwidth, mirror)(density.on_grid(grid))[0]


def smoothed_density_quadrature(
    density_fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
    grid: Grid,
    bandwidth: float,
    mirror: bool = True,
    panel: float | None = None,
    order: int = 12,
) -> np.ndarray:
    """Reference ``K_h * p`` by composite Gauss-Legendre quadrature with the KDE's kernel.

    ``(K_h * p)(c) = sum_a sum_b W_a W_b p(x_a, y_b) k_x(c_x, x_a) k_y(c_y, y_b)``
    over tensor Gauss-Legendre nodes (``order`` per panel, panels of width at most
    ``panel``, default ``h / 2``), where ``k`` is :func:`harness.estimators.kde.kernel_1d`, the very
    function the KDE evaluates (its 9 h image cutoff included). For a density that is
    smooth on the domain the error is far below 1e-10.

    Args:
        density_fn: ``p(x, y)`` on the domain (1 / length^2), vectorised.
        grid, bandwidth, mirror: As :func:`smoothed_density`.
        panel: Largest panel width (length).
        order: Gauss-Legendre points per panel.

    Returns:
        Shape ``(ny, nx)``, 1 / length^2.
    """
    panel = bandwidth / 2 if panel is None else panel
    t, w = np.polynomial.legendre.leggauss(order)

    def nodes(lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
        m = max(1, int(np.ceil((hi - lo) / panel)))
        edges = np.linspace(lo, hi, m + 1)
        half = 0.5 * np.diff(edges)[:, None]
        mid = 0.5 * (edges[:-1] + edges[1:])[:, None]
        return (mid + half * t).ravel(), (half * w).ravel()

    xq, wx = nodes(grid.x0, grid.x1)
    yq, wy = nodes(grid.y0, grid.y1)
    kx, _ = kernel_1d(xq, grid.x, bandwidth, grid.x0, grid.x1, mirror)
    ky, _ = kernel_1d(yq, grid.y, bandwidth, grid.y0, grid.y1, mirror)
    xx, yy = np.meshgrid(xq, yq, indexing="xy")
    vals = density_fn(xx, yy) * np.outer(wy, wx)
    return ky.T @ vals @ kx


def cell_masses(density: Density, grid: Grid) -> np.ndarray:
    """The mass ``int_cell p`` of every cell, shape ``(ny, nx)`` (dimensionless, sum 1):
    the density's own ``cell_masses`` (exact) when it has one
    (:class:`~harness.targets.densities.ExactCellMasses`), else :func:`cell_masses_midpoint`
    (approximate).
    """
    if isinstance(density, ExactCellMasses):
        return density.cell_masses(grid)
    return cell_masses_midpoint(density, grid)


def cell_masses_midpoint(density: Density, grid: Grid) -> np.ndarray:
    """Cell masses approximated as cell value times cell area (``on_grid``, normalised
    on the grid, so they sum to 1): the approximate path of :func:`cell_masses`, for a
    density without a closed form; the midpoint rule's error per cell.
    """
    return density.on_grid(grid) * grid.cell_area


class SmoothedEstimator:
    """``p_hat = K_h * p``, ``q_hat = grad(K_h * p)``: the noise-free KDE of the plant's
    mean-field density ``p`` (``estimator=smoothed``), what the KDE of infinitely many
    robots distributed as ``p`` would measure (:class:`harness.estimators.smoothing.Smoother`).
    On the mean-field plant it is the ``N -> infinity`` limit of the agent loop with the
    raw KDE.

    Args:
        grid, model: Run-time arguments.
        bandwidth: Kernel standard deviation ``h > 0`` (length).
        mirror: Wall images.
    """

    uses_kde = False

    free_space = True

    def __init__(
        self, grid: Grid, model: FokkerPlanck, bandwidth: float, mirror: bool = True
    ) -> None:
        self.bandwidth = number("bandwidth", bandwidth, 0.0, strict=True)
        mirror = flag("mirror", mirror)
        if model.free is not None and not mirror:
            raise ParameterError("mirror", mirror, "true on a domain with obstacles")
        self.smoother = Smoother(grid, self.bandwidth, mirror, model.free)

    def resolution(self, measured: float | None) -> float | None:
        """The kernel's bandwidth ``h`` (length)."""
        return self.bandwidth

    def initialize(self, inp: StepInput) -> Estimate:
        """The smoothed mean-field density and its gradient."""
        return Estimate(*self.smoother(inp.p_true))

    step = initialize
