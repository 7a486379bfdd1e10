"""Kernel density estimate of the swarm and its gradient on the grid.

For robot positions ``X_1..X_N`` and the Gaussian kernel of bandwidth ``h``
(``K_h(z) = exp(-|z|^2 / 2h^2) / (2 pi h^2)``, separable into two 1-D kernels
``g_h``), the paper's measurement is

    p_KDE(x)      = (1/N) sum_k K_h(x - X_k)
    grad p_KDE(x) = (1/N) sum_k grad K_h(x - X_k)      (analytic kernel derivative)

evaluated at the cell centres. With ``mirror=True`` each robot also contributes
its images across the walls (``2 x0 - X`` and ``2 x1 - X`` per axis, and the
corner images), the reflection KDE: it integrates to 1 over the domain up to
tails of ``exp(-(L/h)^2 / 2)``, so no mass is lost near the walls, and its normal
derivative vanishes at the walls like that of a reflected diffusion.

Two evaluation paths give the same estimator:

* ``exact``: ``p = Gy Gx^T / N`` with the ``n x N`` matrices of 1-D kernel
  values ``Gx[i, k] = g_h(x_i - X_k)`` (plus images); cost ``O(N n)`` kernel
  evaluations and ``O(N n^2)`` flops.
* ``binned``: linear binning of the robots onto the nodes of a grid ``factor``
  times finer (weights summing to 1 per robot), then the exact kernel sum over
  the ``(B + 1)^2`` nodes (``B = factor n``); cost ``O(N + n B^2)``. The binning
  error is ``O((s / h)^2)`` for node spacing ``s``: relative ``~1e-3`` for the
  paper's settings. The binning grid need not follow the evaluation grid, only the
  kernel: on grids finer than ``h / KERNEL_CELLS`` per cell the spacing stays at
  ``h / (KERNEL_CELLS factor)`` (:func:`binning_nodes`), the paper's accuracy, so the
  cost does not grow like ``n^3`` (at ``n = 256``, ``h = 0.04``: 120 nodes per
  axis instead of 1024).

``method="auto"`` uses ``exact`` up to ``exact_max_robots`` robots.

On free space (``free`` given, a domain with obstacles) the kernel is the heat kernel of
the masked domain at time ``h^2 / 2`` instead of the Gaussian with wall images: the
robots are binned on a finer grid's free cells and diffused with no flux through closed
faces (:class:`harness.estimators.diffusion.FreeKernel`, whose docstring gives its
errors); ``method`` and ``bin_factor`` do not apply there. With ``free`` None every path
is the square's.

Measurement noise (notes section 3). For independent samples of ``p`` the KDE
fluctuates with variance ``Var[p_KDE] ~ k p`` and ``Var[d_i p_KDE] ~ k_g p``,

    k   = int K^2       / (N h^2) = 1 / (4 pi N h^2)     (1 / length^2)
    k_g = int (d_i K)^2 / (N h^4) = 1 / (8 pi N h^4)     (1 / length^4)

(see :func:`noise_constants`); the variance of the gradient is proportional to
``p``, not to ``grad p``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from harness.compiled.binning import linear_binning
from harness.domains.base import FreeSpace
from harness.estimators.diffusion import FreeKernel
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.records import Estimate, StepInput

_SQRT_2PI = np.sqrt(2.0 * np.pi)


def noise_constants(n_robots: int, bandwidth: float) -> tuple[float, float]:
    """KDE noise constants ``(k, k_g)`` for the Gaussian kernel in 2-D.

    ``Var[p_KDE(x)] ~ k p(x)`` and ``Var[d_x p_KDE(x)] = Var[d_y p_KDE(x)] ~ k_g p(x)``
    with ``k = 1 / (4 pi N h^2)`` and ``k_g = 1 / (8 pi N h^4)``. For ``N = 1024``,
    ``h = 0.04``: ``k ~ 0.049`` (1 / length^2) and ``k_g ~ 15.2`` (1 / length^4).
    """
    if n_robots < 1 or not bandwidth > 0:
        raise ValueError(f"need N >= 1 and h > 0, got N={n_robots}, h={bandwidth}")
    k = 1.0 / (4.0 * np.pi * n_robots * bandwidth**2)
    k_g = 1.0 / (8.0 * np.pi * n_robots * bandwidth**4)
    return k, k_g


IMAGE_CUTOFF = 9.0
"""Images of robots farther than this many bandwidths from a wall contribute less
than ``exp(-81/2) ~ 3e-18`` of a kernel peak and are skipped."""


def _gauss_inplace(e: np.ndarray) -> np.ndarray:
    """``e <- exp(-e^2 / 2)`` in place, the exponent clipped at -200 (``e^-200 ~
    1e-87``): exponentials that underflow take a slow path in libm.
    """
    np.square(e, out=e)
    e *= -0.5
    np.maximum(e, -200.0, out=e)
    return np.exp(e, out=e)


def kernel_1d(
    points: np.ndarray,
    centres: np.ndarray,
    h: float,
    lo: float,
    hi: float,
    mirror: bool,
    out: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """1-D kernel matrix ``G[k, i] = g_h(c_i - X_k)`` and ``dG[k, i] = d/dc_i`` of it.

    ``g_h(z) = exp(-z^2 / 2h^2) / (sqrt(2 pi) h)`` and ``d/dc g_h(c - X) = -(c - X) /
    h^2 g_h(c - X)``. With ``mirror`` the images ``2 lo - X`` and ``2 hi - X`` of
    the robots within ``IMAGE_CUTOFF h`` of a wall are added. Rows are robots, so
    adding images to a subset of robots touches whole rows. ``out`` is an optional
    pair of ``(N, n)`` buffers reused between calls.
    """
    inv_h = 1.0 / h
    norm = 1.0 / (_SQRT_2PI * h)
    shape = (points.size, centres.size)
    g, dg = out if out is not None else (np.empty(shape), np.empty(shape))
    # z = (c - X) / h, then g = norm exp(-z^2/2) and dg = -(norm / h) z exp(-z^2/2).
    np.subtract(centres[None, :] * inv_h, points[:, None] * inv_h, out=dg)
    np.copyto(g, dg)
    _gauss_inplace(g)
    dg *= g
    if mirror:
        for wall in (lo, hi):
            near = np.flatnonzero(np.abs(points - wall) < IMAGE_CUTOFF * h)
            if near.size:
                zi = np.subtract.outer((2.0 * wall - points[near]) * -inv_h, -centres * inv_h)
                gi = _gauss_inplace(zi.copy())
                g[near] += gi
                dg[near] += zi * gi
    g *= norm
    dg *= -norm * inv_h
    return g, dg


_kernel_1d = kernel_1d  # the former private name (kept for older callers)


KERNEL_CELLS = 1.2
"""Binning base cells per bandwidth: the binning spacing is at least
``h / (KERNEL_CELLS bin_factor)`` (:func:`binning_nodes`); 1.2 is the paper's 30 x 30
grid at ``h = 0.04``, whose binning accuracy is kept on finer grids."""


def binning_nodes(n: int, length: float, bandwidth: float, factor: int) -> int:
    """Binning intervals along one axis: ``factor n``, but at most ``ceil(factor
    KERNEL_CELLS length / h)`` (no finer than the kernel needs). The relative binning
    error ``(s / h)^2 / 8`` of spacing ``s`` is then at most ``1 / (8 (KERNEL_CELLS
    factor)^2)`` = 5.4e-3 of a kernel peak for ``factor = 4``, on every grid.
    """
    by_kernel = math.ceil(factor * KERNEL_CELLS * length / bandwidth - 1e-9)
    return max(1, min(factor * n, by_kernel))


@dataclass
class KDE:
    """Gaussian KDE of robot positions on a grid, with its analytic gradient.

    Args:
        grid: The grid whose cell centres the estimate is evaluated at.
        bandwidth: Kernel standard deviation ``h > 0`` (length).
        mirror: Add wall images (reflection KDE) so no mass is lost at the walls.
        method: ``exact``, ``binned`` or ``auto``.
        bin_factor: Refinement of the binning grid relative to ``grid`` (capped by the
            kernel, :func:`binning_nodes`).
        exact_max_robots: ``auto`` uses ``exact`` up to this many robots.
        free: Free space of a domain with obstacles: the kernel is then diffusion on it
            (:class:`~harness.estimators.diffusion.FreeKernel`, always reflecting:
            ``mirror`` must be True); None for the square.
    """

    METHODS = ("auto", "exact", "binned")

    grid: Grid
    bandwidth: float
    mirror: bool = True
    method: str = "auto"
    bin_factor: int = 4
    exact_max_robots: int = 512
    free: FreeSpace | None = None
    bins: tuple[int, int] = field(init=False)
    _node_kernels: tuple[np.ndarray, ...] = field(init=False, repr=False)
    _work: dict[int, tuple[np.ndarray, ...]] = field(init=False, repr=False, default_factory=dict)
    _paths: dict[str, Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]] = field(
        init=False, repr=False
    )

    def __post_init__(self) -> None:
        if not (np.isfinite(self.bandwidth) and self.bandwidth > 0):
            raise ValueError(f"kde bandwidth must be > 0, got {self.bandwidth}")
        if self.method not in self.METHODS:
            raise ValueError(f"kde method must be exact, binned or auto, got {self.method!r}")
        if self.bin_factor < 1:
            raise ValueError(f"kde bin_factor must be >= 1, got {self.bin_factor}")
        g = self.grid
        h, f = self.bandwidth, self.bin_factor
        self.bins = (binning_nodes(g.nx, g.x1 - g.x0, h, f), binning_nodes(g.ny, g.y1 - g.y0, h, f))
        self._nodes_x = np.linspace(g.x0, g.x1, self.bins[0] + 1)
        self._nodes_y = np.linspace(g.y0, g.y1, self.bins[1] + 1)
        kx, dkx = kernel_1d(self._nodes_x, g.x, self.bandwidth, g.x0, g.x1, self.mirror)
        ky, dky = kernel_1d(self._nodes_y, g.y, self.bandwidth, g.y0, g.y1, self.mirror)
        self._node_kernels = (kx, dkx, ky, dky)
        self._paths = {name: getattr(self, name) for name in self.METHODS}
        self.diffusion: FreeKernel | None = None
        if self.free is not None:
            if self.free.grid != g:
                raise ValueError("kde free space resolved on another grid")
            if not self.mirror:
                raise ValueError("kde mirror must be True on free space (its walls reflect)")
            self.diffusion = FreeKernel(self.free, self.bandwidth)

    def __call__(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Estimate ``(p_KDE, grad p_KDE)`` from positions of shape ``(2, N)``.

        Returns:
            ``p`` of shape ``(ny, nx)`` (1 / length^2) and ``grad p`` of shape
            ``(2, ny, nx)`` (1 / length^3).
        """
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2 or positions.shape[0] != 2 or positions.shape[1] < 1:
            raise ValueError(f"positions must have shape (2, N) with N >= 1, got {positions.shape}")
        if self.diffusion is not None:
            return self.diffusion.kde(positions)
        return self._paths[self.method](positions)

    def auto(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`exact` up to ``exact_max_robots`` robots, :meth:`binned` above."""
        if positions.shape[1] <= self.exact_max_robots:
            return self.exact(positions)
        return self.binned(positions)

    def exact(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Direct separable kernel sum over all robots."""
        g = self.grid
        n = positions.shape[1]
        if n not in self._work:
            # Buffers reused from call to call: fresh arrays of this size come from
            # mmap and cost page faults that dominate small-N timings.
            self._work = {n: tuple(np.empty((n, m)) for m in (g.nx, g.nx, g.ny, g.ny))}
        bx, bdx, by, bdy = self._work[n]
        kx, dkx = kernel_1d(positions[0], g.x, self.bandwidth, g.x0, g.x1, self.mirror, (bx, bdx))
        ky, dky = kernel_1d(positions[1], g.y, self.bandwidth, g.y0, g.y1, self.mirror, (by, bdy))
        # p[j, i] = (1/N) sum_k Gy[k, j] Gx[k, i]; the gradient uses dGx or dGy.
        p = ky.T @ kx
        gx = ky.T @ dkx
        gy = dky.T @ kx
        p /= n
        gx /= n
        gy /= n
        return p, np.stack([gx, gy])

    def bin_weights(self, positions: np.ndarray) -> np.ndarray:
        """Linear-binning weights on the fine nodes, shape ``(By + 1, Bx + 1)``,
        summing to 1 (each robot splits its 1/N over the 4 surrounding nodes).
        """
        g = self.grid
        bx, by = self.bins
        tx = (positions[0] - g.x0) * (bx / (g.x1 - g.x0))
        ty = (positions[1] - g.y0) * (by / (g.y1 - g.y0))
        ix = np.clip(tx.astype(np.intp), 0, bx - 1)
        iy = np.clip(ty.astype(np.intp), 0, by - 1)
        fx = tx - ix
        fy = ty - iy
        base = iy * (bx + 1) + ix
        size = (bx + 1) * (by + 1)
        w00 = (1 - fx) * (1 - fy)
        w10 = fx * (1 - fy)
        w01 = (1 - fx) * fy
        w11 = fx * fy
        weights = (
            np.bincount(base, w00, size)
            + np.bincount(base + 1, w10, size)
            + np.bincount(base + bx + 1, w01, size)
            + np.bincount(base + bx + 2, w11, size)
        )
        return weights.reshape(by + 1, bx + 1) / positions.shape[1]

    def binned(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear binning on the fine nodes (compiled; :meth:`bin_weights` is the
        numpy reference), then the exact kernel sum over the nodes.
        """
        g = self.grid
        w = linear_binning(
            np.ascontiguousarray(positions, dtype=float),
            g.x0,
            g.x1,
            g.y0,
            g.y1,
            *self.bins,
        )
        kx, dkx, ky, dky = self._node_kernels
        wkx = w @ kx
        p = ky.T @ wkx
        gx = ky.T @ (w @ dkx)
        gy = dky.T @ wkx
        return p, np.stack([gx, gy])


class KDEEstimator:
    """``p_hat = p_KDE``, ``q_hat = grad p_KDE``: no filter (``estimator=kde``). On free
    space the plant's KDE is the diffusion one (:class:`KDE` with ``free``).
    """

    uses_kde = True
    free_space = True

    def __init__(self, grid: Grid, model: FokkerPlanck) -> None:
        self.grid = grid

    def resolution(self, measured: float | None) -> float | None:
        """The measurement's own resolution (length)."""
        return measured

    def initialize(self, inp: StepInput) -> Estimate:
        """The raw KDE."""
        assert inp.p_kde is not None and inp.grad_kde is not None
        return Estimate(inp.p_kde, inp.grad_kde)

    step = initialize
