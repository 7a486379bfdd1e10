"""Kernel laws of the robots' positions: the MMD flow and Stein variational gradient
descent (config group ``control``: ``control=mmd``, ``control=svgd``).

Both laws turn the robots' positions (no density estimate) into a velocity field on the
grid, which the robots follow by bilinear interpolation of its cell centres. Both have a
mean-field form, the same law with the swarm's empirical measure replaced by a density
(:attr:`harness.records.ControlInput.density`), which the mean-field plant and the agents
plant's ``N -> infinity`` limit use. Neither puts a density in a denominator.

Kernels. Both laws use the normalised Gaussian of length ``l`` with wall images, one per
wall and the corner images (the product of the 1-D sums), per axis

    k_N(u, x) = g(x - u) + g(x - (2 lo - u)) + g(x - (2 hi - u))     (even images: Neumann)
    k_D(u, x) = g(x - u) - g(x - (2 lo - u)) - g(x - (2 hi - u))     (odd images: Dirichlet)

with ``g(z) = exp(-z^2 / 2 l^2) / (sqrt(2 pi) l)`` (:func:`image_kernel`). ``k_N`` is the
KDE's mirrored kernel (:func:`harness.kde.kernel_1d`): its derivative in ``x`` vanishes
at the walls. ``k_D`` vanishes for ``u`` or ``x`` on a wall. Both are symmetric and, with
all their images, the heat kernels of the interval at time ``l^2 / 2`` with Neumann and
Dirichlet conditions, so positive semi-definite (each cosine, resp. sine, mode is
multiplied by ``exp(-kappa^2 l^2 / 2) > 0``). The images left out lie at least a domain
side ``L`` away: ``exp(-(L / l)^2 / 2)`` of a peak, 1.5e-8 at the largest allowed ``l = L
/ 6`` (:data:`LENGTH_PER_SIDE`), 5e-61 at the default ``l = 0.06``.

Sums. Everything is separable per axis: a sum over sources on a tensor grid with weights
``W``, evaluated at the points of a tensor grid, is ``G_y^T W G_x`` with 1-D kernel
matrices. With robots the sources are the fine binning nodes of the KDE of bandwidth
``l`` (spacing about ``l / (1.2 bin_factor)``, :func:`harness.kde.binning_nodes`) and the
weights the robots' linear binning (:func:`harness.compiled.binning.linear_binning`, as in
:meth:`harness.kde.KDE.binned`), so a call costs ``O(N)`` for the binning plus ``O(B^2
n)`` for the sums: 0.1 to 0.2 ms at ``N = 1024`` and 0.7 to 0.9 ms at ``N = 65536``
(30 x 30 grid, ``l = 0.06``, one BLAS thread; the binning is the KDE's compiled
parallel one), against 0.04 to 0.05 ms for the mean-field form. From the robots'
weights ``w`` the laws subtract ``W*_n = int hat_n p_*``, the weights' expectation for
robots drawn from ``p_*`` (``hat_n`` the bilinear hat of node ``n``), computed once by the
midpoint rule of the target's continuous density on :data:`TARGET_REFINEMENT` sub-cells
per node interval, where the hats are linear (:func:`_fine_target`,
:func:`_expected_weights`; 1.6e-4 relative against a finer rule): the binning's own bias
(the KDE's, ``O((s / l)^2)`` for node spacing ``s``) then cancels at ``p = p_*``. Without
robots the sources are the cell centres (or faces) and the weights the cell masses ``p
dx dy``. The plain sums over robots (``O(N)`` per point, ``O(N^2)`` at the robots) are
:func:`mmd_feedback_reference` and :func:`svgd_feedback_reference`, written with the
images in 2-D and kept as the references.

Noise compensation. The robots' noise adds ``sigma Laplacian p`` to the mean field. Both
laws add the open-loop drift ``sigma grad log p_*`` (:class:`harness.control.LangevinControl`),
on the faces as :func:`harness.control.paper_law` does, which makes ``p_*`` the exact
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
from typing import ClassVar

import numpy as np
import scipy.linalg as sla
from scipy.interpolate import RectBivariateSpline
from threadpoolctl import threadpool_limits

from harness.compiled.binning import linear_binning
from harness.components import Control, flag, integer, number, require, speed_cap
from harness.control import paper_law
from harness.densities import Target
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.kde import binning_nodes
from harness.records import Command, ControlInput, Estimate
from harness.velocity import VelocityField, centres_to_face_x, centres_to_face_y

__all__ = [
    "MMDControl",
    "SVGDControl",
    "image_kernel",
    "mmd_feedback_reference",
    "slowest_rate",
    "svgd_feedback_reference",
]

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
        :func:`harness.kde.kernel_1d`'s ``(G, dG)`` (without its cut-off of far images).
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


def _check_length(grid: Grid, length: float) -> float:
    side = min(grid.x1 - grid.x0, grid.y1 - grid.y0)
    value = number("length", length, 0.0, strict=True)
    require(
        value <= side / LENGTH_PER_SIDE,
        "length",
        length,
        f"a number in (0, {side / LENGTH_PER_SIDE:g}] (the domain side over {LENGTH_PER_SIDE:g})",
    )
    return value


class _Nodes:
    """The fine binning nodes of kernel length ``l`` on a grid (those of
    :class:`harness.kde.KDE` of bandwidth ``l``) and the robots' linear binning on them.
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
is put on for the robot form (:func:`_fine_target`)."""


def _fine_target(target: Target, nodes: _Nodes) -> tuple[Grid, np.ndarray]:
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


def _expected_weights(fine: Grid, values: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """``W*_n = int hat_n p_*``, the expectation of the robots' binned weights for robots
    drawn from the density ``values`` on ``fine`` (:func:`_fine_target`): the midpoint
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


def _field(feedback: np.ndarray, drift: VelocityField) -> VelocityField:
    """Feedback centres averaged onto the faces, plus the drift's own centres and faces."""
    return VelocityField(
        feedback + drift.centres,
        centres_to_face_x(feedback[0]) + drift.face_x,
        centres_to_face_y(feedback[1]) + drift.face_y,
    )


def _drift(target: Target, sigma: float, on: bool) -> VelocityField:
    """``sigma grad log p_*`` as :func:`harness.control.paper_law` puts it on the grid
    (centres and face differences of ``log p_*``), or zero.
    """
    zero = np.zeros(target.grid.shape)
    return paper_law(zero, np.zeros((2, *zero.shape)), target, 0.0, sigma if on else 0.0)


def _density(inp: ControlInput, grid: Grid) -> np.ndarray:
    if inp.density is None:
        raise ValueError("a kernel law needs the robots' positions or, without robots, a density")
    p = np.asarray(inp.density, dtype=float)
    if p.shape != grid.shape:
        raise ValueError(f"density of shape {p.shape} does not fit the grid {grid.shape}")
    return p


class MMDControl:
    """Gradient flow of the maximum mean discrepancy (``control=mmd``).

    Law (Arbel, Korba, Salim, Gretton, "Maximum mean discrepancy gradient flow",
    NeurIPS 2019, arXiv 1906.04370: the particles descend the witness function of the
    MMD between their empirical measure ``mu_N`` and the target), with the robots'
    noise compensated:

        v(x) = -beta grad [(k_l * mu_N)(x) - (k_l * p_*)(x)] + sigma grad log p_*(x),

    ``k_l`` the normalised Gaussian of length ``l`` with even wall images (``k_N`` per
    axis, the KDE's mirrored kernel; module docstring). ``k_l * mu_N = (1/N) sum_j
    k_l(x, X_j)`` is the KDE of the positions with bandwidth ``l`` and ``k_l * p_*`` its
    expectation; ``beta`` in length^4 / s (the paper's step size times its kernel's
    normalisation), so that ``beta grad(k * p)`` is a velocity. Defaults ``beta =
    0.0048``, ``l = 0.06`` (``conf/control/mmd.yaml``; the module docstring says how they
    were chosen).

    Inputs: the robots' positions ``(2, N)`` as observed, or without robots the density
    ``p`` that stands for them (then ``k_l * p``, the noise-free KDE of the cell masses,
    :class:`harness.smoothing.Smoother`'s kernel-matrix form); the target ``p_*``. No
    density estimate, and no density in a denominator.

    Grid. The feedback is evaluated at the cell centres by binned sums (module
    docstring), ``-beta grad sum_n (w_n - W*_n) k_l(u_n, .)``: ``w`` the robots' linear
    binning on the nodes (so the first term is the gradient of
    :meth:`harness.kde.KDE.binned` of bandwidth ``l``, to round-off) and ``W*`` its
    expectation for robots drawn from ``p_*`` (the module docstring). Subtracting the
    binned target rather than ``k_l * p_*`` itself cancels the binning's bias at ``p =
    p_*``: the expected feedback there is 1.5e-4 of the largest feedback at the paper's
    start instead of 4.9e-3 (``l = 0.06``, 30 x 30 grid; ``tests/test_kernel_laws.py``
    bounds it). On the faces the
    feedback is the mean of the centres; the compensation sits on the faces as in
    :func:`harness.control.paper_law`. In the mean-field form both terms are quadratures
    of cell values at the centres (:class:`harness.smoothing.Smoother`'s kernel-matrix
    form), so the feedback vanishes to round-off at ``p = p_*`` and ``p_*`` is the exact
    discrete steady state of the Fokker-Planck step.

    Robots interpolate the centre values bilinearly. Against the exact per-robot sum
    (:func:`mmd_feedback_reference`, ``O(N^2)``) the interpolated feedback errs by ``dx^2
    / 8`` times its second derivatives at the kernel's scale, plus the binning: by
    ``tests/test_kernel_laws.py`` (rms over the robots, relative to the exact feedback's
    rms; ``l = 0.06``, 30 x 30 grid, 400 to 1024 robots) 4 to 5 % with the swarm at the
    paper's start and 7 to 9 % with the swarm drawn from ``p_*``, where the feedback is
    the swarm's fluctuation alone; 14 % and 5 % there for ``l = 0.04`` and ``0.08``. At
    the centres the binned sums err by 0.5 to 1 % (rms) against the plain sums. Within
    half a cell of a wall the robots take the nearest centre's value, whose normal
    component is not zero (the exact one is, at the wall); the reflection keeps them
    inside.

    Fixed point with noise (derived). With the mean field ``d_t p = -div(p v) + sigma
    Laplacian p`` and the compensation,

        d_t p = div( p grad[ beta k_l * (p - p_*) + sigma log(p / p_*) ] ),

    the Wasserstein gradient flow of ``F(p) = beta / 2 ||p - p_*||_k^2 + sigma KL(p ||
    p_*)`` (``||f||_k^2 = <f, k_l * f>``): ``dF/dt = -int p |grad(beta k_l * (p - p_*) +
    sigma log(p / p_*))|^2 <= 0``, with zero normal flux at the walls (``k_l``'s normal
    derivative vanishes there, and so does the total flux). At a steady state ``beta k_l
    * (p - p_*) + sigma log(p / p_*) = c`` on the domain; multiplying by ``p - p_*`` and
    integrating gives ``beta ||p - p_*||_k^2 + sigma int (p - p_*) log(p / p_*) = 0``,
    two non-negative terms (``k_l`` is positive definite on the Neumann modes), so ``p =
    p_*``: for ``sigma > 0``, ``p_*`` is the only steady state. Without the compensation
    the steady state solves ``beta k_l * (p - p_*) + sigma log p = c``, biased towards
    uniform by about ``sigma / beta`` times ``k_l^{-1}`` of ``log p``.

    Stability (known). For ``sigma = 0`` the MMD flow converges to the global minimum
    only under conditions (Arbel et al.: a bound on a negative Sobolev distance along
    the flow); it can stall at particle configurations where the witness gradient
    vanishes on the particles, and MMD is not displacement convex. The paper regularises
    it by noise injection (evaluating the gradient at noisy positions), with a
    convergence result under a condition on the noise level; here the robots' own noise
    plus the
    compensation make the mean field the gradient flow of ``F`` with the entropy term,
    whose only steady state is ``p_*`` (above): ``F`` is a Lyapunov function (no rate is
    claimed beyond the linearisation). Linearised about ``p_*``, a perturbation ``phi``
    obeys ``d_t phi = div(p_* grad(beta k_l * phi + sigma phi / p_*))``: on the uniform
    target a cosine mode of wavenumber ``kappa`` decays at ``kappa^2 (beta exp(-kappa^2
    l^2 / 2) + sigma)``, the paper's law's ``kappa^2 (alpha + sigma)`` smoothed by the
    kernel.

    Args:
        target: The target on the grid (run-time argument).
        beta: Gain ``>= 0`` (length^4 / s).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s), for the compensation.
        length: Kernel length ``l`` (length), in ``(0, L / 6]``.
        bin_factor: Binning nodes per grid cell and axis (capped by the kernel,
            :func:`harness.kde.binning_nodes`), ``>= 1``.
        noise_compensation: Add ``sigma grad log p_*``.
        v_max: Speed cap (length / s), or None.

    Attributes:
        nodes: The binning nodes (those of :class:`harness.kde.KDE` of bandwidth ``l``).
        target_weights: ``W*``, the robots' expected binned weights at ``p_*``.
        drift: The compensation ``sigma grad log p_*`` as a field (zero without it).
        resolution: ``l``, the smallest scale the feedback resolves (the sampled-data
            step bound is taken at it, :func:`harness.checks.check_built`).
    """

    gives_field: ClassVar[bool] = True
    # precomputed from the static target: refused with target=moving (harness.build)
    follows_moving_target: ClassVar[bool] = False
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = False

    uses = "positions, target smoothed by the kernel"
    divides_by_density = False

    def __init__(
        self,
        target: Target,
        beta: float,
        sigma: float,
        length: float,
        bin_factor: int = 4,
        noise_compensation: bool = True,
        v_max: float | None = None,
    ) -> None:
        self.target = target
        g = target.grid
        self.beta = number("beta", beta, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self.length = _check_length(g, length)
        self.resolution = self.length  # the smallest scale the law's feedback resolves
        self.noise_compensation = flag("noise_compensation", noise_compensation)
        self.v_max = speed_cap(v_max)
        self.nodes = _Nodes(g, self.length, integer("bin_factor", bin_factor, 1))
        self.drift = _drift(target, self.sigma, self.noise_compensation)
        n = self.nodes
        self._from_nodes = self._kernels(n.x, n.y, g.x, g.y)
        self._from_cells = self._kernels(g.x, g.y, g.x, g.y)
        # k_l * p_* as the binned KDE of robots drawn from p_* gives it in expectation,
        # and for the mean-field form the quadrature of p_*'s cell values
        self.target_weights = _expected_weights(*_fine_target(target, n), n)
        self._target_cells = self._sums(target.p * g.cell_area, self._from_cells)

    def _kernels(
        self, sx: np.ndarray, sy: np.ndarray, px: np.ndarray, py: np.ndarray
    ) -> tuple[np.ndarray, ...]:
        """``(k_N, d k_N / dx)`` per axis from sources ``(sx, sy)`` to points ``(px, py)``."""
        g, ell = self.target.grid, self.length
        kx, _, dkx = image_kernel(sx, px, ell, g.x0, g.x1, +1)
        ky, _, dky = image_kernel(sy, py, ell, g.y0, g.y1, +1)
        return kx, dkx, ky, dky

    @staticmethod
    def _sums(w: np.ndarray, kernels: tuple[np.ndarray, ...]) -> np.ndarray:
        """``grad (k_l * w)`` at the points, ``(2, ny_p, nx_p)``, for source weights ``w``."""
        kx, dkx, ky, dky = kernels
        wkx = w @ kx
        return np.stack([ky.T @ (w @ dkx), dky.T @ wkx])

    def feedback(self, inp: ControlInput) -> np.ndarray:
        """The feedback ``-beta grad(k_l * (mu_N - p_*))`` at the cell centres, ``(2,
        ny, nx)`` (length / s): of the positions, or without them of the density.
        """
        if inp.positions is not None:
            return self.binned(self.nodes.weights(inp.positions))
        p = _density(inp, self.target.grid)
        grad = self._sums(p * self.target.grid.cell_area, self._from_cells)
        return -self.beta * (grad - self._target_cells)

    def binned(self, weights: np.ndarray) -> np.ndarray:
        """The feedback at the cell centres, ``(2, ny, nx)`` (length / s), of robots whose
        linear binning on the nodes (:attr:`nodes`) is ``weights`` ``(By + 1, Bx + 1)``
        (sum 1): ``-beta grad sum_n (w_n - W*_n) k_l(u_n, .)``.
        """
        return -self.beta * self._sums(weights - self.target_weights, self._from_nodes)

    def feedback_at(
        self,
        xs: np.ndarray,
        ys: np.ndarray,
        positions: np.ndarray | None = None,
        density: np.ndarray | None = None,
    ) -> np.ndarray:
        """The feedback at the points of the tensor grid ``xs`` x ``ys`` (inside the
        domain, walls included), ``(2, len(ys), len(xs))`` (length / s): the same sums
        as :meth:`feedback` with the kernels evaluated at these points.
        """
        g = self.target.grid
        xs, ys = np.atleast_1d(xs), np.atleast_1d(ys)
        if positions is not None:
            n = self.nodes
            w = n.weights(positions) - self.target_weights
            return -self.beta * self._sums(w, self._kernels(n.x, n.y, xs, ys))
        if density is None:
            raise ValueError("give positions or a density")
        kernels = self._kernels(g.x, g.y, xs, ys)
        grad = self._sums(np.asarray(density) * g.cell_area, kernels)
        return -self.beta * (grad - self._sums(self.target.p * g.cell_area, kernels))

    def __call__(self, inp: ControlInput) -> Command:
        """The field: the feedback at the centres (faces: their means) plus the drift."""
        return Command(_field(self.feedback(inp), self.drift)).capped(self.v_max)

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``beta max(p0)``: linearised about ``p0``, the feedback's flux is ``beta p0
        grad(k_l * phi)``, a diffusion of local diffusivity ``beta p0`` smoothed by
        ``k_l`` (the step bound takes that smoothing at the law's ``resolution``).
        """
        return self.beta * float(np.max(p0))


class SVGDControl:
    """Stein variational gradient descent as a swarm law (``control=svgd``).

    Law (Liu, Wang, "Stein variational gradient descent", NeurIPS 2016, arXiv
    1608.04471, with the diagonal matrix-valued kernel of Wang, Tang, Bajaj, Liu, "Stein
    variational gradient descent with matrix-valued kernels", NeurIPS 2019, arXiv
    1910.12794, chosen for the walls), component ``a`` of the velocity at ``x``:

        v_a(x) = (eps / N) sum_j [ k_a(X_j, x) d_a log p_*(X_j) + d/dX_{j,a} k_a(X_j, x) ]
                 + sigma d_a log p_*(x),

    with ``K = diag(k_x, k_y)``, ``k_x(u, x) = k_D(u_1, x_1) k_N(u_2, x_2)`` (odd images
    across the x-walls, even across the y-walls) and ``k_y`` the reverse (module
    docstring); ``eps`` in length^4 / s with these normalised kernels (Liu and Wang's
    unnormalised RBF ``exp(-|x - u|^2 / 2 l^2)`` has the step ``eps / (2 pi l^2)``, in
    length^2 / s). Defaults ``eps = 0.0064``, ``l = 0.06`` (``conf/control/svgd.yaml``; the
    module docstring says how they were chosen).

    Walls (derived). On a bounded domain Stein's identity has a boundary term: ``int
    [k_a(y, x) d_a log p_*(y) + d_{y_a} k_a(y, x)] p_*(y) dy = oint k_a(y, x) p_*(y)
    n_a(y) dS``, which the plain Gaussian leaves, so plain SVGD's fixed point is not
    ``p_*``. ``k_a(y, x) = 0`` for ``y`` on an a-wall (odd images), and ``n_a = 0`` on the
    other walls, so the boundary term vanishes and the mean field is

        v_a(x) = eps int k_a(y, x) p(y) d_a log(p_* / p)(y) dy
               = -eps int k_a(y, x) p_*(y) d_a (p / p_*)(y) dy,

    zero at ``p = p_*``; ``k_a(y, x) = 0`` for ``x`` on an a-wall too, so the normal
    velocity vanishes at the walls.

    Inputs: the robots' positions ``(2, N)`` as observed, or without robots the density
    ``p`` that stands for them; the target's score ``grad log p_*``. No density estimate,
    and no density in a denominator.

    Grid. With robots, binned sums at the cell centres (module docstring), ``eps sum_n
    (w_n - W*_n) [k_a(u_n, .) s_a(u_n) + d_{u_a} k_a(u_n, .)]``: ``w`` the robots' linear
    binning on the nodes, ``W*`` its expectation for robots drawn from ``p_*`` (module
    docstring) and ``s`` the score at the nodes, the derivative of the cubic spline of
    ``log p_*`` on the fine grid (:meth:`score`; 2e-6 of its rms from the closed form
    for the default target). The ``W*`` term is zero in the continuum (Stein's identity
    with these kernels, below) and cancels the binning's bias at ``p = p_*``: the
    expected velocity there is 1.2e-4 of the largest at the paper's start instead of
    4.1e-3 (``l = 0.06``, 30 x 30 grid; ``tests/test_kernel_laws.py`` bounds it); it also
    makes the fixed point the
    binned ``p_*`` whatever the score's error. Against the plain sum over the robots
    (:func:`svgd_feedback_reference`) the binned centres err by 0.5 to 1 % (rms); the
    robots, which interpolate the centres bilinearly, by 4 to 5 % (rms over the robots,
    relative to the exact velocity's rms) with the swarm at the paper's start and 5 to 7
    % with the swarm drawn from ``p_*`` (400 to 1024 robots; the same interpolation error
    as :class:`MMDControl`, which says more). The mean-field form is the second line of
    the mean field above on the grid: on each interior face ``-p*_f (r_R - r_L) / h``
    with ``r = p / p_*`` and ``p*_f`` the logarithmic mean of its two cells (so that
    ``p*_f (log p*_R - log p*_L) = p*_R - p*_L``, a discrete Stein identity), summed with
    ``k_a`` from the faces to the centres: linear in ``p``, zero to round-off at ``p =
    p_*``. Face values: the mean of the centres; the compensation on the faces as in
    :func:`harness.control.paper_law`, so that ``p_*`` is the exact discrete steady state.

    Fixed point with noise (derived). The mean field is ``d_t p = -div(p v) + sigma
    Laplacian p`` with zero normal flux. Without compensation the flux at ``p = p_*`` is
    ``-sigma grad p_* != 0``: ``p_*`` is not a steady state; the steady state solves
    ``p v_svgd = sigma grad p``, in the local limit (``l -> 0``: ``v_svgd = eps p grad
    log(p_* / p)``) ``grad log p = eps p / (eps p + sigma) grad log p_*``, flatter than
    ``p_*`` where ``eps p`` is not large against ``sigma``. With the compensation
    (chosen), write ``u = grad log(p_* / p)``; the total flux ``p v - sigma grad p`` is
    ``p (v_svgd + sigma u)`` and

        d/dt KL(p || p_*) = -eps sum_a <p u_a, k_a (p u_a)> - sigma int p |u|^2 <= 0,

    so KL decreases and is stationary only at ``u = 0``, ``p = p_*`` (for ``sigma > 0``,
    or ``eps > 0`` and ``k_a`` strictly positive definite): ``p_*`` is the only steady
    state. The noise with its compensation is the Wasserstein gradient flow of the same
    KL, added to SVGD's.

    Stability (known). SVGD's mean field is the gradient flow of ``KL(p || p_*)`` in the
    Stein geometry (Liu, "Stein variational gradient descent as gradient flow", NeurIPS
    2017, arXiv 1704.07520). KL decreases by the squared kernel Stein discrepancy, which
    does not bound KL in general; exponential rates follow from a Stein log-Sobolev
    inequality (Duncan, Nuesken, Szpruch, arXiv 1912.00894), proved for kernels whose
    Fourier transform decays quadratically (Carrillo, Skrzeczkowski, Warnett, arXiv
    2412.10295), not the Gaussian's. The compensated noise adds ``sigma int p |u|^2``,
    the relative Fisher information, so KL decays at least at the rate of Langevin
    dynamics (``p_*`` bounded above and below on the square satisfies a log-Sobolev
    inequality) however small SVGD's part: slow at the default ``sigma`` (about 1 /
    (sigma lambda) = 2100 s). Linearised about ``p_*`` a perturbation obeys ``d_t phi =
    div(eps p_* k_a [p_* d_a (phi / p_*)] + sigma p_* grad(phi / p_*))``: the feedback is
    weighted by ``p_*^2`` where the paper's law has ``alpha p_*``, so it is weak on the
    target's floor.

    Args:
        target: The target on the grid (run-time argument).
        eps: Step ``>= 0`` (length^4 / s).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s), for the compensation.
        length: Kernel length ``l`` (length), in ``(0, L / 6]``.
        bin_factor: Binning nodes per grid cell and axis (capped by the kernel), ``>= 1``.
        noise_compensation: Add ``sigma grad log p_*``.
        v_max: Speed cap (length / s), or None.

    Attributes:
        nodes, target_weights, drift, resolution: As :class:`MMDControl`'s.
        log_target: The cubic spline of ``log p_*`` whose derivative is :meth:`score`.
    """

    gives_field: ClassVar[bool] = True
    # precomputed from the static target: refused with target=moving (harness.build)
    follows_moving_target: ClassVar[bool] = False
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = False

    uses = "positions, target score"
    divides_by_density = False

    def __init__(
        self,
        target: Target,
        eps: float,
        sigma: float,
        length: float,
        bin_factor: int = 4,
        noise_compensation: bool = True,
        v_max: float | None = None,
    ) -> None:
        self.target = target
        g = target.grid
        self.eps = number("eps", eps, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self.length = _check_length(g, length)
        self.resolution = self.length
        self.noise_compensation = flag("noise_compensation", noise_compensation)
        self.v_max = speed_cap(v_max)
        self.nodes = n = _Nodes(g, self.length, integer("bin_factor", bin_factor, 1))
        self.drift = _drift(target, self.sigma, self.noise_compensation)
        fine, values = _fine_target(target, n)
        self.target_weights = _expected_weights(fine, values, n)
        self.log_target = RectBivariateSpline(
            fine.y, fine.x, np.log(values), bbox=[g.y0, g.y1, g.x0, g.x1], kx=3, ky=3
        )
        ny, nx = np.meshgrid(n.y, n.x, indexing="ij")
        self._node_score = self.score(np.stack([nx.ravel(), ny.ravel()])).reshape(2, *nx.shape)
        self._from_nodes = self._robot_kernels(g.x, g.y)
        self._from_faces = self._face_kernels(g.x, g.y)
        # the face values p*_f of the discrete Stein identity: logarithmic means
        self._face_x = _log_mean(target.p[:, :-1], target.p[:, 1:])
        self._face_y = _log_mean(target.p[:-1, :], target.p[1:, :])

    def score(self, points: np.ndarray) -> np.ndarray:
        """The score ``grad log p_*`` the robot form uses, at points ``(2, P)``: the
        derivative of the cubic spline of ``log p_*`` (1 / length), ``(2, P)``.
        """
        x, y = points
        s = self.log_target
        return np.stack([s.ev(y, x, dy=1), s.ev(y, x, dx=1)])

    def _robot_kernels(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, ...]:
        """From the nodes to the points ``(px, py)``: ``k_D`` with its source derivative
        and ``k_N``, per axis.
        """
        g, n, ell = self.target.grid, self.nodes, self.length
        dx_, ddx, _ = image_kernel(n.x, px, ell, g.x0, g.x1, -1)
        nx_, _, _ = image_kernel(n.x, px, ell, g.x0, g.x1, +1)
        dy_, ddy, _ = image_kernel(n.y, py, ell, g.y0, g.y1, -1)
        ny_, _, _ = image_kernel(n.y, py, ell, g.y0, g.y1, +1)
        return dx_, ddx, nx_, dy_, ddy, ny_

    def _face_kernels(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, ...]:
        """From the interior faces (``k_D`` along the face normal) and the centres
        (``k_N`` along the face) to the points ``(px, py)``.
        """
        g, ell = self.target.grid, self.length
        fx = g.x0 + g.dx * np.arange(1, g.nx)
        fy = g.y0 + g.dy * np.arange(1, g.ny)
        dx_, _, _ = image_kernel(fx, px, ell, g.x0, g.x1, -1)
        nx_, _, _ = image_kernel(g.x, px, ell, g.x0, g.x1, +1)
        dy_, _, _ = image_kernel(fy, py, ell, g.y0, g.y1, -1)
        ny_, _, _ = image_kernel(g.y, py, ell, g.y0, g.y1, +1)
        return dx_, nx_, dy_, ny_

    def _robot_sums(self, w: np.ndarray, kernels: tuple[np.ndarray, ...]) -> np.ndarray:
        """``eps sum_n w_n [k_a(u_n, .) s_a(u_n) + d_{u_a} k_a(u_n, .)]`` at the points."""
        kdx, dkdx, knx, kdy, dkdy, kny = kernels
        sx, sy = self._node_score
        vx = kny.T @ ((w * sx) @ kdx + w @ dkdx)
        vy = (kdy.T @ (w * sy) + dkdy.T @ w) @ knx
        return self.eps * np.stack([vx, vy])

    def _stein_sums(self, p: np.ndarray, kernels: tuple[np.ndarray, ...]) -> np.ndarray:
        """``-eps sum_f k_a(f, .) p*_f (r_R - r_L) / h dx dy`` over the interior faces."""
        g = self.target.grid
        kdx, knx, kdy, kny = kernels
        r = np.asarray(p, dtype=float) / self.target.p
        jx = -self._face_x * np.diff(r, axis=1) / g.dx  # (ny, nx - 1)
        jy = -self._face_y * np.diff(r, axis=0) / g.dy  # (ny - 1, nx)
        scale = self.eps * g.cell_area
        return scale * np.stack([kny.T @ jx @ kdx, kdy.T @ jy @ knx])

    def feedback(self, inp: ControlInput) -> np.ndarray:
        """The SVGD velocity at the cell centres, ``(2, ny, nx)`` (length / s): of the
        positions (binned), or without them the mean-field form of the density.
        """
        if inp.positions is not None:
            return self.binned(self.nodes.weights(inp.positions))
        return self._stein_sums(_density(inp, self.target.grid), self._from_faces)

    def binned(self, weights: np.ndarray) -> np.ndarray:
        """The SVGD velocity at the cell centres, ``(2, ny, nx)`` (length / s), of robots
        whose linear binning on the nodes (:attr:`nodes`) is ``weights`` ``(By + 1, Bx +
        1)`` (sum 1): ``eps sum_n (w_n - W*_n) [k_a(u_n, .) s_a(u_n) + d_{u_a} k_a(u_n, .)]``.
        """
        return self._robot_sums(weights - self.target_weights, self._from_nodes)

    def feedback_at(
        self,
        xs: np.ndarray,
        ys: np.ndarray,
        positions: np.ndarray | None = None,
        density: np.ndarray | None = None,
    ) -> np.ndarray:
        """The SVGD velocity at the points of the tensor grid ``xs`` x ``ys`` (inside the
        domain, walls included), ``(2, len(ys), len(xs))``: the sums of :meth:`feedback`
        with the kernels evaluated at these points.
        """
        xs, ys = np.atleast_1d(xs), np.atleast_1d(ys)
        if positions is not None:
            w = self.nodes.weights(positions) - self.target_weights
            return self._robot_sums(w, self._robot_kernels(xs, ys))
        if density is None:
            raise ValueError("give positions or a density")
        return self._stein_sums(density, self._face_kernels(xs, ys))

    def __call__(self, inp: ControlInput) -> Command:
        """The field: the SVGD velocity at the centres (faces: their means) plus the drift."""
        return Command(_field(self.feedback(inp), self.drift)).capped(self.v_max)

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``eps max(p0)``: linearised about ``p0`` the flux ``p v`` is ``-eps p0 k_a *
        [d_a phi - phi d_a log p_*]``, a diffusion of local diffusivity ``eps p0``
        smoothed by ``k_a`` (conservative for the step bound, as for
        :meth:`MMDControl.feedback_diffusivity`).
        """
        return self.eps * float(np.max(p0))


def _log_mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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


def _blocks(points: np.ndarray, sources: int) -> list[slice]:
    """Slices of the points such that each block pairs at most ``_CHUNK`` of them with
    the sources.
    """
    step = max(1, _CHUNK // max(sources, 1))
    return [slice(i, i + step) for i in range(0, points.shape[1], step)]


def _images(
    u: np.ndarray, lo: float, hi: float, parity: int
) -> list[tuple[float, float, np.ndarray]]:
    """The source coordinate and its two wall images: ``(sign, d image / d u, image)``."""
    return [(1.0, 1.0, u), (float(parity), -1.0, 2 * lo - u), (float(parity), -1.0, 2 * hi - u)]


def mmd_feedback_reference(
    points: np.ndarray,
    positions: np.ndarray,
    target_points: np.ndarray,
    target_masses: np.ndarray,
    grid: Grid,
    beta: float,
    length: float,
) -> np.ndarray:
    """The MMD feedback ``-beta grad_x [(1/N) sum_j k(x, X_j) - sum_c m_c k(x, y_c)]`` at
    ``points`` ``(2, P)``, by plain sums over the robots ``(2, N)`` and the target's
    quadrature points ``y_c`` ``(2, C)`` with masses ``m_c``, with the 2-D Gaussian and its
    eight even wall images written out (``O(P (N + C))``); returns ``(2, P)``.
    """
    norm = 1.0 / (2.0 * np.pi * length**2)

    def grad(sources: np.ndarray, weights: np.ndarray) -> np.ndarray:
        out = np.zeros((2, points.shape[1]))
        for block in _blocks(points, sources.shape[1]):
            px, py = points[0, block, None], points[1, block, None]
            for sx, _, ix in _images(sources[0], grid.x0, grid.x1, 1):
                for sy, _, iy in _images(sources[1], grid.y0, grid.y1, 1):
                    zx, zy = px - ix, py - iy
                    k = sx * sy * norm * np.exp(-(zx**2 + zy**2) / (2 * length**2))
                    out[0, block] += (-zx / length**2 * k) @ weights
                    out[1, block] += (-zy / length**2 * k) @ weights
        return out

    n = positions.shape[1]
    return -beta * (grad(positions, np.full(n, 1.0 / n)) - grad(target_points, target_masses))


def svgd_feedback_reference(
    points: np.ndarray,
    sources: np.ndarray,
    weights: np.ndarray,
    score: np.ndarray,
    grid: Grid,
    eps: float,
    length: float,
) -> np.ndarray:
    """The SVGD velocity ``eps sum_j w_j [k_a(u_j, x) s_a(u_j) + d_{u_j,a} k_a(u_j, x)]``
    at ``points`` ``(2, P)`` by the plain sum over the sources ``u`` ``(2, S)`` with weights
    ``w`` (``1 / N`` for robots) and scores ``s`` ``(2, S)``: ``k_x`` with odd images across
    the x-walls and even ones across the y-walls, ``k_y`` the reverse, written out in 2-D
    (``O(P S)``; ``O(N^2)`` at the robots); returns ``(2, P)``.
    """
    norm = 1.0 / (2.0 * np.pi * length**2)
    out = np.zeros((2, points.shape[1]))
    for block in _blocks(points, sources.shape[1]):
        px, py = points[0, block, None], points[1, block, None]
        for a, (parity_x, parity_y) in ((0, (-1, 1)), (1, (1, -1))):
            for sx, jx, ix in _images(sources[0], grid.x0, grid.x1, parity_x):
                for sy, jy, iy in _images(sources[1], grid.y0, grid.y1, parity_y):
                    zx, zy = px - ix, py - iy
                    k = sx * sy * norm * np.exp(-(zx**2 + zy**2) / (2 * length**2))
                    # d/du_a k(x - u') = (x - u')_a / l^2 k (d u'_a / d u_a), u' the image
                    z, chain = (zx, jx) if a == 0 else (zy, jy)
                    out[a, block] += (k * score[a] + chain * z / length**2 * k) @ weights
    return eps * out


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
