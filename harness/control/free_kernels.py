"""The kernel laws (:mod:`harness.control.mmd`, :mod:`harness.control.svgd`) on free space.

On the square the laws' kernels are Gaussians of length ``l`` with wall images
(:mod:`harness.control.kernels`): the heat kernels of the rectangle, Neumann or
Dirichlet per axis, at time ``l^2 / 2``. A kernel centred on one side of an obstacle's
thin wall would reach robots on the other side and pull them through it. On free
space (:class:`harness.domains.base.FreeSpace`) the kernel is the heat kernel of free
space itself: ``k_l(x, y) = exp(t A)(x, y)``, ``t = l^2 / 2``, with ``A`` the
drift-free Fokker-Planck operator of unit diffusivity on free space (no flux through
closed faces; :class:`harness.estimators.diffusion.HeatKernel`). It is the Gaussian of
length ``l`` away from obstacles (the plane's heat kernel at ``t = l^2 / 2``); across a
wall it is the density of a random walk that has to go round it, so ``k_l(x, y)``
decays with the distance along free space, not the straight line, and it is zero
between components. It is symmetric (``A`` is symmetric with no drift), conserves mass
(each column sums to 1 over its component, to round-off) and is positive definite
(eigenvalues ``exp(t lambda) > 0``). Its normal derivative vanishes at closed faces
(Neumann).

Grid. Like the free-space KDE (:class:`harness.estimators.diffusion.FreeKernel`, whose
fine grid, binning and read-out this module uses), the kernel acts on a grid ``r``
times finer than the control grid (``r`` from :func:`harness.estimators.diffusion.refinement`
at ``h = l``: 2 at the defaults, fine cells of ``1 / 60``, ``l / s = 3.6``), its
errors ``O((s / l)^2)`` of a kernel peak (that module's docstring). The robots enter
by their bilinear binning on the fine cells (:func:`harness.compiled.binning.free_binning`:
no share crosses a closed face; a robot in the free part of a blocked cell counts in
the nearest free one); a density on the control cells by its expected binning
(:func:`harness.estimators.diffusion.expected_binning`), so that for robots drawn from
a density constant on each cell the expected binned density is that density's
(:meth:`FreeKernelSums.spread`): the laws' feedback then vanishes in expectation at
``p = p_*``. The field at the control centres is read from the fine grid
(:func:`harness.estimators.diffusion.readout`); the velocity of each robot is the
bilinear interpolant of the fine grid's values at its position over the four cells
its binning would feed (:meth:`FreeKernelSums.at_robots`: a cell behind a closed face
is replaced by one the robot reaches, so no value from the far side of a wall enters).

No push into obstacles (:meth:`FreeKernelSums.no_push`). A robot's velocity component
toward a closed face of its fine cell (an obstacle's face inside the rectangle) or
toward a blocked square of the robots' raster next to its own square is set to 0; the
field's centres on blocked cells and its closed faces are 0
(:func:`harness.control.field.no_flux_into_obstacles`). The rectangle's own walls are
left as on the square (the robots reflect there; the Neumann kernel's normal
derivative is 0 at them).

Cost: one application of ``exp(t A)`` per step (a Chebyshev series, about 60 products
with the sparse fine ``A`` at the defaults; two columns for SVGD), the robots' binning
and a gather: ``O(N + r^2 n^2 K)``.
"""

from __future__ import annotations

import numpy as np

from harness.compiled.binning import free_binning
from harness.control.field import no_flux_into_obstacles
from harness.control.kernels import kernel_field, log_mean
from harness.domains.base import FreeSpace
from harness.estimators.diffusion import (
    FreeKernel,
    bilinear_shares,
    bin_targets,
    home_cells,
)
from harness.records import Command, ControlInput
from harness.targets.densities import Target
from harness.velocity import VelocityField


def gather(
    free: FreeSpace,
    targets: np.ndarray,
    home: np.ndarray,
    values: np.ndarray,
    positions: np.ndarray,
) -> np.ndarray:
    """Bilinear interpolant on free space of cell values ``values`` ``(c, M)`` at
    ``positions`` ``(2, N)``: the transpose of
    :func:`harness.estimators.diffusion.bin_reference` (the same four cells and shares
    per robot, from :func:`~harness.estimators.diffusion.bin_targets` ``targets``; the
    home cell :func:`~harness.estimators.diffusion.home_cells` for a robot in a blocked
    cell). Away from obstacles and walls it is the plain bilinear interpolant
    of the cell centres; the shares of a robot sum to 1. Returns ``(c, N)``.
    """
    t, shares = bilinear_shares(free, targets, home, positions)
    return np.einsum("cnk,nk->cn", values[:, t], shares)


class FreeKernelSums:
    """The heat kernel of free space at time ``l^2 / 2`` and what the kernel laws do
    with it (module docstring): the robots' and a density's fine densities, the kernel,
    the read-outs at the control centres and at the robots, and the rule that removes
    the velocity into obstacles.

    Args:
        target: The target, on a domain with obstacles (``target.free`` not None).
        length: Kernel length ``l`` (length).

    Attributes:
        free: Free space on the control grid.
        kernel: The :class:`~harness.estimators.diffusion.FreeKernel` of bandwidth ``l``
            (fine free space ``kernel.fine``, ``kernel.heat`` = ``exp(t A)``).
        target_fine: ``p_*``'s expected binned density on the fine cells, ``(M_fine,)``.
    """

    def __init__(self, target: Target, length: float) -> None:
        free = target.free
        if free is None:
            raise ValueError("FreeKernelSums needs a target on a domain with obstacles")
        self.free = free
        self.kernel = k = FreeKernel(free, length)
        fine = k.fine
        self._coarse = (bin_targets(free), home_cells(free))
        self.target_fine = self.spread(target.p)
        # each fine cell's flat index where free, its home (nearest free) cell elsewhere
        fg = fine.grid
        self._fine_cell_of = k.home
        # closed interior faces of each fine cell: east, west, north, south
        east = np.zeros(fg.shape, dtype=bool)
        west = np.zeros(fg.shape, dtype=bool)
        north = np.zeros(fg.shape, dtype=bool)
        south = np.zeros(fg.shape, dtype=bool)
        east[:, :-1] = ~fine.face_x
        west[:, 1:] = ~fine.face_x
        north[:-1, :] = ~fine.face_y
        south[1:, :] = ~fine.face_y
        self._closed = np.stack([east.ravel(), west.ravel(), north.ravel(), south.ravel()])

    @property
    def fine(self) -> FreeSpace:
        """Free space on the fine grid."""
        return self.kernel.fine

    def spread(self, p: np.ndarray) -> np.ndarray:
        """The expected binned density ``(M_fine,)`` (1 / length^2) of robots drawn from
        the density ``p`` ``(ny, nx)`` taken constant on each control cell (blocked
        cells ignored).
        """
        return self.kernel.spread(p)

    def binned(self, positions: np.ndarray) -> np.ndarray:
        """The robots' binned density ``(M_fine,)`` (1 / length^2) on the fine cells
        (:func:`~harness.compiled.binning.free_binning`, each robot ``1 / N``).
        """
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2 or positions.shape[0] != 2 or positions.shape[1] < 1:
            raise ValueError(f"positions must have shape (2, N) with N >= 1, got {positions.shape}")
        fg = self.fine.grid
        k = self.kernel
        w = free_binning(
            np.ascontiguousarray(positions), fg.x0, fg.x1, fg.y0, fg.y1, fg.nx, fg.ny,
            k.targets, k.home,
        )  # fmt: skip
        return w.ravel() / fg.cell_area

    def heat(self, f: np.ndarray) -> np.ndarray:
        """``exp(t A) f`` on the fine grid, ``f`` of shape ``(M_fine,)`` or ``(M_fine, c)``."""
        return self.kernel.heat(f)

    def values_at_centres(self, u: np.ndarray) -> np.ndarray:
        """Fine values ``(M_fine, c)`` read at the control centres, ``(c, ny, nx)``
        (0 on blocked cells).
        """
        g = self.free.grid
        return np.asarray(self.kernel.read @ u).T.reshape(-1, *g.shape)

    def gradient_at_centres(self, u: np.ndarray) -> np.ndarray:
        """The gradient of the fine field ``u`` ``(M_fine,)`` at the control centres,
        ``(2, ny, nx)`` (0 on blocked cells).
        """
        g = self.free.grid
        return np.asarray(self.kernel.read_gradient @ u).reshape(2, *g.shape)

    def fine_gradient(self, u: np.ndarray) -> np.ndarray:
        """The gradient of the fine field ``u`` at the fine centres, ``(2, M_fine)``
        (:meth:`~harness.domains.base.FreeSpace.gradient`: the cell itself behind a
        closed face).
        """
        fine = self.fine
        return fine.gradient(u.reshape(fine.grid.shape)).reshape(2, -1)

    def at_robots(self, values: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Fine values ``(c, M_fine)`` at the robots, ``(c, N)`` (:func:`gather`)."""
        k = self.kernel
        return gather(self.fine, k.targets, k.home, values, positions)

    def centres_at_robots(self, centres: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """Control-centre values ``(c, ny, nx)`` at the robots, ``(c, N)`` (:func:`gather`
        on the control grid).
        """
        targets, home = self._coarse
        return gather(self.free, targets, home, centres.reshape(centres.shape[0], -1), positions)

    def no_push(self, v: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """The robots' velocities ``v`` ``(2, N)`` with each component toward an
        obstacle set to 0: toward a closed interior face of the robot's fine cell (its
        home cell when the cell is blocked) or toward a blocked square of the raster
        next to the robot's own square (a new array).
        """
        fg = self.fine.grid
        col = np.clip(((positions[0] - fg.x0) / fg.dx).astype(np.intp), 0, fg.nx - 1)
        row = np.clip(((positions[1] - fg.y0) / fg.dy).astype(np.intp), 0, fg.ny - 1)
        cell = self._fine_cell_of[row * fg.nx + col]
        east, west, north, south = self._closed[:, cell]
        raster = self.free.raster
        rr = raster.shape[0]
        side_x, side_y = (fg.x1 - fg.x0) / rr, (fg.y1 - fg.y0) / rr
        rc = np.clip(((positions[0] - fg.x0) / side_x).astype(np.intp), 0, rr - 1)
        rw = np.clip(((positions[1] - fg.y0) / side_y).astype(np.intp), 0, rr - 1)

        def at(dr: int, dc: int) -> np.ndarray:
            r2, c2 = rw + dr, rc + dc
            inside = (r2 >= 0) & (r2 < rr) & (c2 >= 0) & (c2 < rr)
            return inside & (raster[np.clip(r2, 0, rr - 1), np.clip(c2, 0, rr - 1)] > 0)

        east |= at(0, 1)
        west |= at(0, -1)
        north |= at(1, 0)
        south |= at(-1, 0)
        out = np.array(v, dtype=float)
        out[0] = np.where((east & (out[0] > 0)) | (west & (out[0] < 0)), 0.0, out[0])
        out[1] = np.where((north & (out[1] > 0)) | (south & (out[1] < 0)), 0.0, out[1])
        return out


def free_command(
    sums: FreeKernelSums,
    feedback: tuple[np.ndarray, np.ndarray | None],
    drift: VelocityField,
    inp: ControlInput,
) -> Command:
    """A kernel law's command on free space from its feedback at the centres and at the
    robots (None without robots): the field of the centres (faces: their means) plus
    the drift, with no flux through closed faces; each robot's velocity its feedback
    plus the drift's centres interpolated on free space (:meth:`FreeKernelSums.centres_at_robots`),
    without components into obstacles (:meth:`FreeKernelSums.no_push`).
    """
    centres, robots = feedback
    field = no_flux_into_obstacles(kernel_field(centres, drift), sums.free)
    if robots is None or inp.positions is None:
        return Command(field)
    positions = np.asarray(inp.positions, dtype=float)
    v = robots + sums.centres_at_robots(drift.centres, positions)
    return Command(field, sums.no_push(v, positions))


def stein_faces(sums: FreeKernelSums) -> tuple[np.ndarray, np.ndarray]:
    """``p*_f`` on the fine grid's x- and y-faces: the logarithmic mean of the two
    cells' :attr:`FreeKernelSums.target_fine` on open faces (so that ``p*_f (log p*_R -
    log p*_L) = p*_R - p*_L``, the discrete Stein identity of
    :class:`harness.control.svgd.SVGDControl`), 0 on closed faces and where ``p_*`` is 0.
    """
    fine = sums.fine
    q = sums.target_fine.reshape(fine.grid.shape)

    def face(a: np.ndarray, b: np.ndarray, open_: np.ndarray) -> np.ndarray:
        ok = open_ & (a > 0) & (b > 0)
        return np.where(ok, log_mean(np.where(ok, a, 1.0), np.where(ok, b, 1.0)), 0.0)

    return face(q[:, :-1], q[:, 1:], fine.face_x), face(q[:-1, :], q[1:, :], fine.face_y)


def stein_flux(
    sums: FreeKernelSums, faces: tuple[np.ndarray, np.ndarray], q: np.ndarray
) -> np.ndarray:
    """``-p_* grad(q / p_*)`` on the fine cells, ``(M_fine, 2)`` (x, y): on each open
    face ``-p*_f (r_R - r_L) / s`` with ``r = q / p_*`` (:func:`stein_faces`; 0 on
    closed faces), each cell the mean of its two faces along the axis (a closed face
    or the wall counting 0). ``q`` ``(M_fine,)`` is a density on the fine cells.
    """
    fg = sums.fine.grid
    qs = sums.target_fine
    positive = qs > 0
    r = np.where(positive, q / np.where(positive, qs, 1.0), 0.0).reshape(fg.shape)
    fx, fy = faces
    jx = -fx * np.diff(r, axis=1) / fg.dx
    jy = -fy * np.diff(r, axis=0) / fg.dy
    cx = np.zeros(fg.shape)
    cy = np.zeros(fg.shape)
    cx[:, 1:] += 0.5 * jx
    cx[:, :-1] += 0.5 * jx
    cy[1:, :] += 0.5 * jy
    cy[:-1, :] += 0.5 * jy
    return np.stack([cx.ravel(), cy.ravel()], axis=1)
