"""What the kernel laws of the robots' positions share: the MMD flow
(:mod:`harness.control.mmd`, ``control=mmd``) and Stein variational gradient descent
(:mod:`harness.control.svgd`, ``control=svgd``).

Both laws turn the robots' positions (no density estimate) into a velocity field on the
grid, which the robots follow by bilinear interpolation of its cell centres. Both have a
mean-field form, the same law with the swarm's empirical measure replaced by a density
(:attr:`harness.records.ControlInput.density`), which the mean-field plant and the agents
plant's ``N -> infinity`` limit use. Neither puts a density in a denominator.

Free space. On a domain with obstacles the kernel is the heat kernel of free space
instead of the images, and each robot gets its own velocity
(:mod:`harness.control.free_kernels`); the kernels and sums below are the square's.

Kernels. Both laws use the normalised Gaussian of length ``l`` with wall images, one per
wall and the corner images (the product of the 1-D sums), per axis

    k_N(u, x) = g(x - u) + g(x - (2 lo - u)) + g(x - (2 hi - u))     (even images: Neumann)
    k_D(u, x) = g(x - u) - g(x - (2 lo - u)) - g(x - (2 hi - u))     (odd images: Dirichlet)

with ``g(z) = exp(-z^2 / 2 l^2) / (sqrt(2 pi) l)`` (:func:`image_kernel`). ``k_N`` is the
KDE's mirrored kernel (:func:`harness.estimators.kde.kernel_1d`): its derivative in ``x`` vanishes
at the walls. ``k_D`` vanishes for ``u`` or ``x`` on a wall. Both are symmetric and, with
all their images, the heat kernels of the interval at time ``l^2 / 2`` with Neumann and
Dirichlet conditions, so positive semi-definite (each cosine, resp. sine, mode is
multiplied by ``exp(-kappa^2 l^2 / 2) > 0``). The images left out lie at least a domain
side ``L`` away: ``exp(-(L / l)^2 / 2)`` of a peak, 1.5e-8 at the largest allowed ``l = L
/ 6`` (:data:`LENGTH_PER_SIDE`), 5e-61 at the default ``l = 0.06``.

Sums. Everything is separable per axis: a sum over sources on a tensor grid with weights
``W``, evaluated at the points of a tensor grid, is ``G_y^T W G_x`` with 1-D kernel
matrices. With robots the sources are the fine binning nodes of the KDE of bandwidth
``l`` (spacing about ``l / (1.2 bin_factor)``, :func:`harness.estimators.kde.binning_nodes`) and the
weights the robots' linear binning (:func:`harness.compiled.binning.linear_binning`, as in
:meth:`harness.estimators.kde.KDE.binned`), so a call costs ``O(N)`` for the binning plus ``O(B^2
n)`` for the sums: 0.1 to 0.2 ms at ``N = 1024`` and 0.7 to 0.9 ms at ``N = 65536``
(30 x 30 grid, ``l = 0.06``, one BLAS thread; the binning is the KDE's compiled
parallel one), against 0.04 to 0.05 ms for the mean-field form. From the robots'
weights ``w`` the laws subtract ``W*_n = int hat_n p_*``, the weights' expectation for
robots drawn from ``p_*`` (``hat_n`` the bilinear hat of node ``n``), computed once by the
midpoint rule of the target's continuous density on :data:`TARGET_REFINEMENT` sub-cells
per node interval, where the hats are linear (:func:`fine_target`,
:func:`expected_weights`; 1.6e-4 relative against a finer rule): the binning's own bias
(the KDE's, ``O((s / l)^2)`` for node spacing ``s``) then cancels at ``p = p_*``. Without
robots the sources are the cell centres (or faces) and the weights the cell masses ``p
dx dy``. The plain sums over robots (``O(N)`` per point, ``O(N^2)`` at the robots) are
:func:`harness.control.mmd.mmd_feedback_reference` and
:func:`harness.control.svgd.svgd_feedback_reference`, written with the
images in 2-D and kept as the references.

Noise compensation. The robots' noise adds ``sigma Laplacian p`` to the mean field. Both
laws add the open-loop drift ``sigma grad log p_*`` (:class:`harness.control.heat.LangevinControl`),
on the faces as :func:`harness.control.paper.paper_law` does, which makes ``p_*`` the exact
discrete steady state of the Fokker-Planck step where the feedback vanishes; each law's
docstring derives its fixed point with and without it.

Defaults. Gains: matched to the paper's law at its default gain (``alpha = 0.003``),
whose mean-field loop linearised about the default target decays at 1 / 33.9 s on its
slowest mode (30 x 30 grid, ``sigma = 5e-5``; the Poincare estimate ``1 / ((alpha + sigma)
lambda)`` gives 34.5 s): :func:`slowest_rate` computes that rate for each law, and a
secant search on the gain gave ``beta = 0.00479`` and ``eps = 0.00636`` at ``l = 0.06``
(rounded to 0.0048 and 0.0064; ``tests/test_kernel_laws.py`` checks the match to 1 %).
Kernel length ``l = 0.06`` (1.8 cells of the paper's grid, 1.5 KDE bandwidths): the
robots' interpolation of the grid field errs (rms, swarm drawn from ``p_*``) by 14, 8
and 5 % at ``l = 0.04``, 0.06 and 0.08, while a longer kernel weakens SVGD's slowest
mode (rate at ``eps = 0.003``: 0.019, 0.015, 0.011 / s) and both laws' fine modes
(``exp(-kappa^2 l^2 / 2)``).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla
from scipy.interpolate import RectBivariateSpline
from threadpoolctl import threadpool_limits

from harness.compiled.binning import linear_binning
from harness.control.paper import paper_law
from harness.estimators.kde import binning_nodes
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import number, require
from harness.protocols import Control, MemoryEstimate, default_memory
from harness.records import ControlInput, Estimate
from harness.targets.densities import Target
from harness.velocity import VelocityField, centres_to_face_x, centres_to_face_y

_SQRT_2PI = math.sqrt(2.0 * math.pi)


LENGTH_PER_SIDE = 6.0
"""The kernel length ``l`` is at most the domain's shorter side over this: the images
left out (at least a domain side away) then weigh at most ``exp(-18)`` = 1.5e-8 of a
peak."""


def image_kernel(
    sources: np.ndarray, points: np.ndarray, length: float, lo: float, hi: float, parity: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D Gaussian kernel with one wall image per wall, and its two derivatives.

    ``G[k, i] = g(x_i - u_k) + parity (g(x_i - (2 lo - u_k)) + g(x_i - (2 hi - u_k)))``
    for sources ``u`` and points ``x`` in ``[lo, hi]``, ``g`` the normalised Gaussian of
    standard deviation ``length`` (1 / length); ``parity`` +1 gives the Neumann (mirror)
    kernel ``k_N``, -1 the Dirichlet kernel ``k_D``, 0 the plain Gaussian.

    Returns:
        ``(G, dG/du, dG/dx)``, each of shape ``(sources, points)``; the derivatives in 1 /
        length^2. With ``parity = +1``, ``G`` and ``dG/dx`` are
        :func:`harness.estimators.kde.kernel_1d`'s ``(G, dG)`` (without its cut-off of far images).
    """
    u = np.asarray(sources, dtype=float)[:, None]
    x = np.asarray(points, dtype=float)[None, :]
    inv = 1.0 / length
    norm = 1.0 / (_SQRT_2PI * length)

    def term(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = (x - image) * inv
        return norm * np.exp(np.maximum(-0.5 * z * z, -300.0)), z

    g0, z0 = term(u)
    g, d_point = g0.copy(), -z0 * g0 * inv
    d_source = -d_point  # d/du g(x - u) = -d/dx g(x - u)
    if parity:
        for wall in (lo, hi):
            gi, zi = term(2.0 * wall - u)
            g += parity * gi
            # d/dx and d/du of g(x - 2 wall + u) are both -z / l g
            d_point += parity * (-zi * gi * inv)
            d_source += parity * (-zi * gi * inv)
    return g, d_source, d_point


MIN_LENGTH_CELLS = 0.1
"""The kernel length ``l`` is at least this fraction of a cell, as ``kde.bandwidth`` must
be: the laws evaluate their kernels at the cell centres and at binning nodes no closer
than a cell over ``bin_factor``, so a narrower kernel falls between them (its sums there
are no longer its integrals), and its factors ``1 / l`` and ``1 / l^2`` overflow for a
tiny ``l`` (``1e-300``)."""


def check_length(grid: Grid, length: float) -> float:
    """The kernel length ``l`` (length), refused unless :data:`MIN_LENGTH_CELLS` times the
    cell size ``<= l <=`` the domain side over :data:`LENGTH_PER_SIDE`
    (:class:`~harness.parameters.ParameterError` naming ``length``).
    """
    side = min(grid.x1 - grid.x0, grid.y1 - grid.y0)
    value = number("length", length, 0.0, strict=True)
    require(
        value <= side / LENGTH_PER_SIDE,
        "length",
        length,
        f"a number in (0, {side / LENGTH_PER_SIDE:g}] (the domain side over {LENGTH_PER_SIDE:g})",
    )
    cell = max(grid.dx, grid.dy)
    require(
        value >= MIN_LENGTH_CELLS * cell,
        "length",
        length,
        f"at least {MIN_LENGTH_CELLS:g} x the cell size {cell:.3g} = "
        f"{MIN_LENGTH_CELLS * cell:.3g} (a narrower kernel falls between cell centres)",
    )
    return value


FINE_CELL_BYTES = 64
"""Bytes per cell of the target's fine grid (:func:`fine_target`, :data:`TARGET_REFINEMENT`
cells per binning interval and axis) that a kernel law holds at its peak while it is
built: eight float64 arrays of that grid (measured with ``tracemalloc``: 49 bytes a cell
for ``svgd``, whose spline of ``log p_*`` adds its coefficients, 40 for ``mmd``)."""


NODE_BYTES = 96
"""Bytes per binning node (``(Bx + 1) (By + 1)``) and per node-to-point kernel entry:
twelve float64 arrays (the weights, the scores at the nodes and their meshgrids; the
six 1-D kernels of :meth:`Nodes` to the cell centres and their temporaries)."""


def kernel_memory(grid: Grid, length: object, bin_factor: object) -> MemoryEstimate:
    """What a kernel law of ``length`` and ``bin_factor`` allocates, before it is built:
    the grid arrays (:func:`~harness.protocols.default_memory`), the target on the fine grid
    of :data:`TARGET_REFINEMENT` sub-cells per binning interval (:data:`FINE_CELL_BYTES`
    a cell, most of it for a large ``bin_factor``) and the nodes with their kernels
    (:data:`NODE_BYTES`); named by ``bin_factor``. Parameters the law would refuse give
    the grid arrays only (the law refuses them when it is built).
    """
    base = default_memory(grid).nbytes
    ok = (
        isinstance(length, (int, float))
        and not isinstance(length, bool)
        and math.isfinite(length)
        and length > 0
        and isinstance(bin_factor, int)
        and not isinstance(bin_factor, bool)
        and bin_factor >= 1
    )
    if not ok:
        return MemoryEstimate(base, "")
    assert isinstance(length, (int, float)) and isinstance(bin_factor, int)
    bx = binning_nodes(grid.nx, grid.x1 - grid.x0, float(length), bin_factor)
    by = binning_nodes(grid.ny, grid.y1 - grid.y0, float(length), bin_factor)
    fine = TARGET_REFINEMENT**2 * bx * by * FINE_CELL_BYTES
    nodes = ((bx + 1) * (by + 1) + (bx + 1) * grid.nx + (by + 1) * grid.ny) * NODE_BYTES
    return MemoryEstimate(base + fine + nodes, "bin_factor")


class Nodes:
    """The fine binning nodes of kernel length ``l`` on a grid (those of
    :class:`harness.estimators.kde.KDE` of bandwidth ``l``) and the robots' linear binning on them.
    """

    def __init__(self, grid: Grid, length: float, bin_factor: int) -> None:
        self.grid = grid
        self.bins = (
            binning_nodes(grid.nx, grid.x1 - grid.x0, length, bin_factor),
            binning_nodes(grid.ny, grid.y1 - grid.y0, length, bin_factor),
        )
        self.x = np.linspace(grid.x0, grid.x1, self.bins[0] + 1)
        self.y = np.linspace(grid.y0, grid.y1, self.bins[1] + 1)

    def weights(self, positions: np.ndarray) -> np.ndarray:
        """Linear-binning weights ``(By + 1, Bx + 1)`` of the positions ``(2, N)``, each
        robot adding ``1 / N`` (compiled, the KDE's own binning).
        """
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2 or positions.shape[0] != 2 or positions.shape[1] < 1:
            raise ValueError(f"positions must have shape (2, N) with N >= 1, got {positions.shape}")
        g = self.grid
        return linear_binning(np.ascontiguousarray(positions), g.x0, g.x1, g.y0, g.y1, *self.bins)


TARGET_REFINEMENT = 4
"""Sub-cells per binning interval and axis of the grid the target's continuous density
is put on for the robot form (:func:`fine_target`)."""


def fine_target(target: Target, nodes: Nodes) -> tuple[Grid, np.ndarray]:
    """The target's continuous density on the grid of :data:`TARGET_REFINEMENT` cells
    per binning interval (the nodes lie on its cell edges), normalised on it: the
    density's own cell values, or without a density (or where it is not positive there)
    the exponential of the cubic spline of ``log p_*``'s cell values.
    """
    g, r = target.grid, TARGET_REFINEMENT
    fine = Grid(nodes.bins[0] * r, nodes.bins[1] * r, g.x0, g.x1, g.y0, g.y1)
    values = None
    if target.density is not None:
        values = np.asarray(target.density.on_grid(fine), dtype=float)
    if values is None or not (np.isfinite(values).all() and values.min() > 0):
        spline = RectBivariateSpline(g.y, g.x, target.log_p, bbox=[g.y0, g.y1, g.x0, g.x1])
        values = np.exp(spline(fine.y, fine.x))
    return fine, values / fine.integrate(values)


def expected_weights(fine: Grid, values: np.ndarray, nodes: Nodes) -> np.ndarray:
    """``W*_n = int hat_n p_*``, the expectation of the robots' binned weights for robots
    drawn from the density ``values`` on ``fine`` (:func:`fine_target`): the midpoint
    rule on ``fine``, whose cells lie between nodes, where the hat functions are linear
    (error ``O((s / r)^2)`` relative, smooth: no kink of a hat inside a cell).
    """
    bx, by = nodes.bins
    rx, ry = fine.nx // bx, fine.ny // by
    fx = (np.arange(rx) + 0.5) / rx  # offsets of the sub-cell centres in an interval
    fy = (np.arange(ry) + 0.5) / ry
    masses = values * fine.cell_area
    m = masses.reshape(by, ry, bx, rx)
    out = np.zeros((by + 1, bx + 1))
    # each sub-cell splits its mass bilinearly over its interval's four nodes
    for wy, sy in ((1.0 - fy, 0), (fy, 1)):
        for wx, sx in ((1.0 - fx, 0), (fx, 1)):
            out[sy : sy + by, sx : sx + bx] += np.einsum("jbic,b,c->ji", m, wy, wx)
    return out


def kernel_field(feedback: np.ndarray, drift: VelocityField) -> VelocityField:
    """Feedback centres averaged onto the faces, plus the drift's own centres and faces."""
    return VelocityField(
        feedback + drift.centres,
        centres_to_face_x(feedback[0]) + drift.face_x,
        centres_to_face_y(feedback[1]) + drift.face_y,
    )


def noise_drift(target: Target, sigma: float, on: bool) -> VelocityField:
    """``sigma grad log p_*`` as :func:`harness.control.paper.paper_law` puts it on the grid
    (centres and face differences of ``log p_*``), or zero.
    """
    zero = np.zeros(target.grid.shape)
    return paper_law(zero, np.zeros((2, *zero.shape)), target, 0.0, sigma if on else 0.0)


def input_density(inp: ControlInput, grid: Grid) -> np.ndarray:
    """The density that stands for the robots in a law's input without robots
    (:attr:`harness.records.ControlInput.density`), checked to lie on ``grid``.
    """
    if inp.density is None:
        raise ValueError("a kernel law needs the robots' positions or, without robots, a density")
    p = np.asarray(inp.density, dtype=float)
    if p.shape != grid.shape:
        raise ValueError(f"density of shape {p.shape} does not fit the grid {grid.shape}")
    return p


def log_mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The logarithmic mean ``(a - b) / (log a - log b)`` (``a`` where ``a = b``), for
    positive ``a``, ``b``.
    """
    la, lb = np.log(a), np.log(b)
    d = la - lb
    close = np.abs(d) < 1e-6
    safe = np.where(close, 1.0, d)
    # series about a = b: m = b (1 + d / 2 + d^2 / 6 + ...) with d = log(a / b)
    return np.where(close, b * (1.0 + d / 2.0 + d * d / 6.0), (a - b) / safe)


_CHUNK = 1 << 20
"""Point-source pairs per block of the plain sums (8 MB per array)."""


def point_blocks(points: np.ndarray, sources: int) -> list[slice]:
    """Slices of the points such that each block pairs at most ``_CHUNK`` of them with
    the sources.
    """
    step = max(1, _CHUNK // max(sources, 1))
    return [slice(i, i + step) for i in range(0, points.shape[1], step)]


def wall_images(
    u: np.ndarray, lo: float, hi: float, parity: int
) -> list[tuple[float, float, np.ndarray]]:
    """The source coordinate and its two wall images: ``(sign, d image / d u, image)``."""
    return [(1.0, 1.0, u), (float(parity), -1.0, 2 * lo - u), (float(parity), -1.0, 2 * hi - u)]


def slowest_rate(
    control: Control,
    target: Target,
    sigma: float,
    step: float = 1e-6,
) -> float:
    """The slowest decay rate (1 / s) of the mean-field loop linearised about ``p_*``.

    The loop is ``dp/dt = A(v(p)) p`` with ``A`` the Fokker-Planck operator of noise
    ``sigma`` (:class:`harness.fokker_planck.FokkerPlanck`) and ``v(p)`` the law's field
    of the density ``p`` (its mean-field form; for a law of estimates, fed the exact
    estimates ``p`` and the grid gradient of ``p``). Its Jacobian at ``p_*`` is taken by
    central differences of relative size ``step`` (dense: grids up to about 40 x 40); the
    rate is the smallest real part of ``-lambda`` over the eigenvalues other than the
    mass mode's zero.
    """
    grid = target.grid
    model = FokkerPlanck(grid, sigma)

    def rhs(p: np.ndarray) -> np.ndarray:
        est = Estimate(p, grid.gradient(p))
        field = control(ControlInput(0.0, est, density=p)).field
        assert field is not None, "a law with a mean-field form gives a field"
        return model.rate(p, field).ravel()

    m = grid.size
    jac = np.empty((m, m))
    p0 = target.p
    h = step * float(np.max(p0))
    for k in range(m):
        e = np.zeros(m)
        e[k] = h
        jac[:, k] = (rhs(p0 + e.reshape(grid.shape)) - rhs(p0 - e.reshape(grid.shape))) / (2 * h)
    with threadpool_limits(limits=1):  # a threaded dense eigensolver crawls on a shared host
        rates = np.sort(-sla.eigvals(jac).real)
    return float(rates[1])
