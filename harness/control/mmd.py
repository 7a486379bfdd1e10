"""``control=mmd``: the MMD flow of the robots' positions toward ``p_*``
(:class:`MMDControl`, with its derivation and source), on the kernel sums of
:mod:`harness.control.kernels`; :func:`mmd_feedback_reference` is the plain sum over
robots.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from harness.control.free_kernels import FreeKernelSums, free_command
from harness.control.kernels import (
    Nodes,
    check_length,
    expected_weights,
    fine_target,
    image_kernel,
    input_density,
    kernel_field,
    kernel_memory,
    noise_drift,
    point_blocks,
    wall_images,
)
from harness.grid import Grid
from harness.parameters import flag, integer, number, speed_cap
from harness.protocols import MemoryEstimate
from harness.records import Command, ControlInput
from harness.targets.densities import Target


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
    :class:`harness.estimators.smoothing.Smoother`'s kernel-matrix form); the target ``p_*``. No
    density estimate, and no density in a denominator.

    Grid. The feedback is evaluated at the cell centres by binned sums (module
    docstring), ``-beta grad sum_n (w_n - W*_n) k_l(u_n, .)``: ``w`` the robots' linear
    binning on the nodes (so the first term is the gradient of
    :meth:`harness.estimators.kde.KDE.binned` of bandwidth ``l``, to round-off) and ``W*`` its
    expectation for robots drawn from ``p_*`` (the module docstring). Subtracting the
    binned target rather than ``k_l * p_*`` itself cancels the binning's bias at ``p =
    p_*``: the expected feedback there is 1.5e-4 of the largest feedback at the paper's
    start instead of 4.9e-3 (``l = 0.06``, 30 x 30 grid; ``tests/test_kernel_laws.py``
    bounds it). On the faces the
    feedback is the mean of the centres; the compensation sits on the faces as in
    :func:`harness.control.paper.paper_law`. In the mean-field form both terms are quadratures
    of cell values at the centres (:class:`harness.estimators.smoothing.Smoother`'s kernel-matrix
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

    Free space (``target.free``, a domain with obstacles). The same law with ``k_l``
    the heat kernel of free space at time ``l^2 / 2``
    (:mod:`harness.control.free_kernels`):

        v(x) = -beta grad [(k_l * mu_N)(x) - (k_l * p_*)(x)] + sigma grad log p_*(x),

    ``k_l = exp(t A)`` with ``A`` the Laplacian of free space with no flux through
    closed faces: the Gaussian of length ``l`` away from obstacles, decaying with the
    distance along free space across a wall (below 1e-10 of the plane's Gaussian
    straight across the rooms' wall, 0 between components). The robots' binned
    density on the kernel's fine cells minus ``p_*``'s expected binned density is
    diffused once per step; the feedback is its gradient read at the centres (the
    field) and interpolated at each robot on free space (the robots' own velocities),
    whose components toward an obstacle are removed. The derivation of the fixed
    point above holds with this kernel (symmetric, positive definite, zero normal
    derivative at closed faces): the mean field is the Wasserstein gradient flow of
    ``F`` on free space, and at a steady state ``beta k_l * (p - p_*) + sigma log(p /
    p_*) = c_i`` on each component ``i``. Neither the kernel nor the noise crosses a
    wall, so each component keeps its mass; the builder refuses a target with mass
    where no robot starts, and on a connected domain ``p = p_*`` is the only steady
    state. The mean-field feedback vanishes exactly at ``p = p_*``. The robots'
    rule at obstacles acts only within a fine cell (or a raster square) of them; its
    effect on the swarm's fixed point is measured in docs/domains.md.

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
            :func:`harness.estimators.kde.binning_nodes`), ``>= 1``.
        noise_compensation: Add ``sigma grad log p_*``.
        v_max: Speed cap (length / s), or None.

    Attributes:
        nodes: The binning nodes (those of :class:`harness.estimators.kde.KDE` of bandwidth ``l``).
        target_weights: ``W*``, the robots' expected binned weights at ``p_*``.
        drift: The compensation ``sigma grad log p_*`` as a field (zero without it).
        resolution: ``l``, the smallest scale the feedback resolves (the sampled-data
            step bound is taken at it, :func:`harness.runs.checks.check_built`).
    """

    gives_field: ClassVar[bool] = True
    # precomputed from the static target: refused with target=moving (harness.runs.build)
    follows_moving_target: ClassVar[bool] = False
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = False

    uses = "positions, target smoothed by the kernel"
    divides_by_density = False
    free_space = True  # heat kernel of free space (tests/test_kernel_laws_free_space.py)

    @classmethod
    def memory_estimate(
        cls, grid: Grid, length: object = None, bin_factor: object = 4, **params: object
    ) -> MemoryEstimate:
        """What the law allocates (:func:`~harness.control.kernels.kernel_memory`), named by
        ``bin_factor``.
        """
        return kernel_memory(grid, length, bin_factor)

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
        self.length = check_length(g, length)
        self.resolution = self.length  # the smallest scale the law's feedback resolves
        self.noise_compensation = flag("noise_compensation", noise_compensation)
        self.v_max = speed_cap(v_max)
        self.nodes = Nodes(g, self.length, integer("bin_factor", bin_factor, 1))
        self.drift = noise_drift(target, self.sigma, self.noise_compensation)
        self.sums = None if target.free is None else FreeKernelSums(target, self.length)
        if self.sums is not None:
            return
        n = self.nodes
        self._from_nodes = self._kernels(n.x, n.y, g.x, g.y)
        self._from_cells = self._kernels(g.x, g.y, g.x, g.y)
        # k_l * p_* as the binned KDE of robots drawn from p_* gives it in expectation,
        # and for the mean-field form the quadrature of p_*'s cell values
        self.target_weights = expected_weights(*fine_target(target, n), n)
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
        if self.sums is not None:
            return self._free_feedback(inp)[0]
        if inp.positions is not None:
            return self.binned(self.nodes.weights(inp.positions))
        p = input_density(inp, self.target.grid)
        grad = self._sums(p * self.target.grid.cell_area, self._from_cells)
        return -self.beta * (grad - self._target_cells)

    def _free_feedback(self, inp: ControlInput) -> tuple[np.ndarray, np.ndarray | None]:
        """On free space: the feedback ``-beta grad k_l * (mu_N - p_*)`` at the cell
        centres ``(2, ny, nx)`` and, with robots, at the robots ``(2, N)`` (without the
        drift), ``k_l`` the heat kernel of free space (:mod:`harness.control.free_kernels`).
        """
        s = self.sums
        assert s is not None
        positions = inp.positions
        if positions is not None:
            q = s.binned(positions)
        else:
            q = s.spread(input_density(inp, self.target.grid))
        u = s.heat(q - s.target_fine)
        centres = -self.beta * s.gradient_at_centres(u)
        if positions is None:
            return centres, None
        return centres, -self.beta * s.at_robots(s.fine_gradient(u), positions)

    def binned(self, weights: np.ndarray) -> np.ndarray:
        """The feedback at the cell centres, ``(2, ny, nx)`` (length / s), of robots whose
        linear binning on the nodes (:attr:`nodes`) is ``weights`` ``(By + 1, Bx + 1)``
        (sum 1): ``-beta grad sum_n (w_n - W*_n) k_l(u_n, .)``. On the square only.
        """
        if self.sums is not None:
            raise ValueError("binned evaluates the square's kernel sums (no obstacles)")
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
        if self.sums is not None:
            raise ValueError("feedback_at evaluates the square's kernel sums (no obstacles)")
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
        """The field: the feedback at the centres (faces: their means) plus the drift.
        On free space the field carries no flux through closed faces, and with robots
        each robot gets its own velocity (:meth:`FreeKernelSums.no_push
        <harness.control.free_kernels.FreeKernelSums.no_push>`).
        """
        if self.sums is None:
            return Command(kernel_field(self.feedback(inp), self.drift)).capped(self.v_max)
        return free_command(self.sums, self._free_feedback(inp), self.drift, inp).capped(self.v_max)

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``beta max(p0)``: linearised about ``p0``, the feedback's flux is ``beta p0
        grad(k_l * phi)``, a diffusion of local diffusivity ``beta p0`` smoothed by
        ``k_l`` (the step bound takes that smoothing at the law's ``resolution``).
        """
        return self.beta * float(np.max(p0))


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
        for block in point_blocks(points, sources.shape[1]):
            px, py = points[0, block, None], points[1, block, None]
            for sx, _, ix in wall_images(sources[0], grid.x0, grid.x1, 1):
                for sy, _, iy in wall_images(sources[1], grid.y0, grid.y1, 1):
                    zx, zy = px - ix, py - iy
                    k = sx * sy * norm * np.exp(-(zx**2 + zy**2) / (2 * length**2))
                    out[0, block] += (-zx / length**2 * k) @ weights
                    out[1, block] += (-zy / length**2 * k) @ weights
        return out

    n = positions.shape[1]
    return -beta * (grad(positions, np.full(n, 1.0 / n)) - grad(target_points, target_masses))
