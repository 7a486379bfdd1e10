"""``control=svgd``: Stein variational gradient descent of the robots' positions toward
``p_*`` (:class:`SVGDControl`, with its derivation and source), on the kernel sums of
:mod:`harness.control.kernels`; :func:`svgd_feedback_reference` is the plain sum over
robots.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from scipy.interpolate import RectBivariateSpline

from harness.control.free_kernels import FreeKernelSums, free_command, stein_faces, stein_flux
from harness.control.kernels import (
    Nodes,
    check_length,
    expected_weights,
    fine_target,
    image_kernel,
    input_density,
    kernel_field,
    kernel_memory,
    log_mean,
    noise_drift,
    point_blocks,
    wall_images,
)
from harness.grid import Grid
from harness.parameters import flag, integer, number, speed_cap
from harness.protocols import MemoryEstimate
from harness.records import Command, ControlInput
from harness.targets.densities import Target


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
    :func:`harness.control.paper.paper_law`, so that ``p_*`` is the exact discrete steady state.

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

    Free space (``target.free``, a domain with obstacles). The law in its integrated
    form (the second line of the mean field above) with one scalar kernel for both
    components, ``k_l`` the heat kernel of free space at time ``l^2 / 2``
    (:mod:`harness.control.free_kernels`):

        v(x) = -eps int k_l(y, x) p_*(y) grad (p / p_*)(y) dy + sigma grad log p_*(x).

    On the square the matrix-valued kernel removes Stein's boundary term from the
    particle form; on free space the integrated form has none to remove. The robots
    enter by their binned density ``p`` on the kernel's fine cells: ``r = p / p_*``
    is differenced on the open faces (``p*_f`` the logarithmic mean, a closed face
    carries 0), each cell takes the mean of its two faces per axis, and the result is
    diffused once per step. By summation by parts this is the particle form ``(eps /
    N) sum_j [k(X_j, x) grad log p_*(X_j) + grad_{X_j} k(X_j, x)]`` with the
    derivative a difference on the fine cells and ``k p_*`` taken as 0 behind closed
    faces. The field is read at the centres; each robot's velocity is interpolated on
    free space, its components toward an obstacle removed. Fixed point: with ``u =
    grad log(p / p_*)`` the feedback is ``-eps k_l * (p u)``; the flux ``p v`` is 0
    through closed faces, so ``d/dt KL(p || p_*) = -eps sum_a <p u_a, k_l (p u_a)> -
    sigma int p |u|^2 <= 0`` (``k_l`` positive definite), stationary only at ``u = 0``:
    ``p`` proportional to ``p_*`` on each component, each component keeping its mass
    (neither the kernel nor the noise crosses a wall; the builder refuses a target
    with mass where no robot starts). The mean-field feedback vanishes exactly at
    ``p = p_*`` (``r = 1``). The robots' rule at obstacles acts only within a fine cell
    (or a raster square) of them; its effect is measured in docs/domains.md.

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
    # precomputed from the static target: refused with target=moving (harness.runs.build)
    follows_moving_target: ClassVar[bool] = False
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = False

    uses = "positions, target score"
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
        self.length = check_length(g, length)
        self.resolution = self.length
        self.noise_compensation = flag("noise_compensation", noise_compensation)
        self.v_max = speed_cap(v_max)
        self.nodes = n = Nodes(g, self.length, integer("bin_factor", bin_factor, 1))
        self.drift = noise_drift(target, self.sigma, self.noise_compensation)
        self.sums = None if target.free is None else FreeKernelSums(target, self.length)
        if self.sums is not None:
            self._fine_faces = stein_faces(self.sums)
            return
        fine, values = fine_target(target, n)
        self.target_weights = expected_weights(fine, values, n)
        self.log_target = RectBivariateSpline(
            fine.y, fine.x, np.log(values), bbox=[g.y0, g.y1, g.x0, g.x1], kx=3, ky=3
        )
        ny, nx = np.meshgrid(n.y, n.x, indexing="ij")
        self._node_score = self.score(np.stack([nx.ravel(), ny.ravel()])).reshape(2, *nx.shape)
        self._from_nodes = self._robot_kernels(g.x, g.y)
        self._from_faces = self._face_kernels(g.x, g.y)
        # the face values p*_f of the discrete Stein identity: logarithmic means
        self._face_x = log_mean(target.p[:, :-1], target.p[:, 1:])
        self._face_y = log_mean(target.p[:-1, :], target.p[1:, :])

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
        if self.sums is not None:
            return self._free_feedback(inp)[0]
        if inp.positions is not None:
            return self.binned(self.nodes.weights(inp.positions))
        return self._stein_sums(input_density(inp, self.target.grid), self._from_faces)

    def _free_feedback(self, inp: ControlInput) -> tuple[np.ndarray, np.ndarray | None]:
        """On free space: the SVGD velocity ``-eps k_l * [p_* grad(p / p_*)]`` at the
        cell centres ``(2, ny, nx)`` and, with robots, at the robots ``(2, N)`` (without
        the drift), ``k_l`` the heat kernel of free space and ``p`` the robots' binned
        density or the input density spread on the fine cells
        (:mod:`harness.control.free_kernels`; :func:`stein_flux`).
        """
        s = self.sums
        assert s is not None
        positions = inp.positions
        if positions is not None:
            q = s.binned(positions)
        else:
            q = s.spread(input_density(inp, self.target.grid))
        u = s.heat(stein_flux(s, self._fine_faces, q))
        centres = self.eps * s.values_at_centres(u)
        if positions is None:
            return centres, None
        return centres, self.eps * s.at_robots(u.T, positions)

    def binned(self, weights: np.ndarray) -> np.ndarray:
        """The SVGD velocity at the cell centres, ``(2, ny, nx)`` (length / s), of robots
        whose linear binning on the nodes (:attr:`nodes`) is ``weights`` ``(By + 1, Bx +
        1)`` (sum 1): ``eps sum_n (w_n - W*_n) [k_a(u_n, .) s_a(u_n) + d_{u_a} k_a(u_n, .)]``.
        On the square only.
        """
        if self.sums is not None:
            raise ValueError("binned evaluates the square's kernel sums (no obstacles)")
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
        if self.sums is not None:
            raise ValueError("feedback_at evaluates the square's kernel sums (no obstacles)")
        xs, ys = np.atleast_1d(xs), np.atleast_1d(ys)
        if positions is not None:
            w = self.nodes.weights(positions) - self.target_weights
            return self._robot_sums(w, self._robot_kernels(xs, ys))
        if density is None:
            raise ValueError("give positions or a density")
        return self._stein_sums(density, self._face_kernels(xs, ys))

    def __call__(self, inp: ControlInput) -> Command:
        """The field: the SVGD velocity at the centres (faces: their means) plus the drift.
        On free space the field carries no flux through closed faces, and with robots
        each robot gets its own velocity (:meth:`FreeKernelSums.no_push
        <harness.control.free_kernels.FreeKernelSums.no_push>`).
        """
        if self.sums is None:
            return Command(kernel_field(self.feedback(inp), self.drift)).capped(self.v_max)
        return free_command(self.sums, self._free_feedback(inp), self.drift, inp).capped(self.v_max)

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``eps max(p0)``: linearised about ``p0`` the flux ``p v`` is ``-eps p0 k_a *
        [d_a phi - phi d_a log p_*]``, a diffusion of local diffusivity ``eps p0``
        smoothed by ``k_a`` (conservative for the step bound, as for
        :meth:`MMDControl.feedback_diffusivity`).
        """
        return self.eps * float(np.max(p0))


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
    for block in point_blocks(points, sources.shape[1]):
        px, py = points[0, block, None], points[1, block, None]
        for a, (parity_x, parity_y) in ((0, (-1, 1)), (1, (1, -1))):
            for sx, jx, ix in wall_images(sources[0], grid.x0, grid.x1, parity_x):
                for sy, jy, iy in wall_images(sources[1], grid.y0, grid.y1, parity_y):
                    zx, zy = px - ix, py - iy
                    k = sx * sy * norm * np.exp(-(zx**2 + zy**2) / (2 * length**2))
                    # d/du_a k(x - u') = (x - u')_a / l^2 k (d u'_a / d u_a), u' the image
                    z, chain = (zx, jx) if a == 0 else (zy, jy)
                    out[a, block] += (k * score[a] + chain * z / length**2 * k) @ weights
    return eps * out
