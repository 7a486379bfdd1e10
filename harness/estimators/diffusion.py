"""The Gaussian kernel on free space: diffusion for time ``h^2 / 2`` on the masked grid.

On the plane the Gaussian kernel of standard deviation ``h`` is the heat kernel of unit
diffusivity at time ``t = h^2 / 2``; with reflecting walls, it is the heat kernel of the
Neumann problem, which the square's KDE writes with wall images
(:mod:`harness.estimators.kde`). On free space (:class:`harness.domains.base.FreeSpace`)
the same definition needs no images: the kernel is ``exp(t A)`` with ``A`` the
Fokker-Planck operator of unit diffusivity and no drift
(:class:`harness.fokker_planck.FokkerPlanck`, ``sigma = 1``, ``v = 0``), which has no flux
through closed faces. Mass diffuses only along paths in free space, so the kernel never
leaks through a wall, however thin, and every component keeps its mass.

Resolution. The control grid's cells are ``dx = 1/30`` on the paper's grid, close to the
bandwidth ``h = 0.04``; robots put on cell centres and the grid's heat kernel in place of
the Gaussian then err by about 10 % of a kernel peak. So the diffusion runs on a grid
``r`` times finer per axis (:func:`refine`: every control cell split into ``r x r``
subcells, free as their cell is, the faces between subcells of one free cell open and
those on the cell's sides open as the cell's face is), with ``r`` the least integer
with ``dx / r <= h / cells_per_bandwidth`` (:func:`refinement`; 3 at the paper's grid,
1 from ``n = 75`` on, default ``cells_per_bandwidth = 3``). Two errors, both
``O((s / h)^2)`` for the fine spacing ``s``, remain:

* binning: each robot splits its mass bilinearly over the four nearest subcell centres
  (:func:`bin_targets`; a face that is closed sends the share back, so no mass crosses
  a wall): at most ``(s^2 / 8) (|K_xx| + |K_yy|) <= (s / h)^2 / 4`` of a kernel peak;
* the grid's heat kernel: a Neumann cosine mode ``kappa`` is damped by ``exp(-t 4
  sin^2(kappa s / 2) / s^2)`` per axis instead of ``exp(-t kappa^2)``; the difference is
  ``4 e^-2 / 12 s^2 / t = 0.090 (s / h)^2`` of the mode's amplitude per axis to leading
  order in ``s^2 / t`` (at ``t kappa^2 = 2``; 2 % more at ``s = h / 3``), twice that in 2-D.

These are worst cases; on the open square at ``s = h / 3`` the KDE of 4000 uniform robots
is within 0.13 % (L2) of the Gaussian one with wall images, 2 % for the gradient (read by
a central difference over ``2 s``, error ``s^2 / 6 |p'''|``), and the error falls like
``s^2`` (tests/test_kde_free_space.py).

The exponential. ``A`` is symmetric (with no drift every open face has rate ``1 / dx^2``
both ways) and negative semi-definite with spectrum in ``[-Lambda, 0]``, ``Lambda = 2
max_i |A_ii|`` (Gershgorin). With ``X = I + (2 / Lambda) A`` (spectrum in ``[-1, 1]``)
and ``z = t Lambda / 2``,

    exp(t A) = sum_k c_k T_k(X),    c_0 = e^-z I_0(z),  c_k = 2 e^-z I_k(z),

the Chebyshev series of ``exp`` (``T_k`` Chebyshev polynomials, ``I_k`` modified Bessel
functions; :class:`HeatKernel`). It is truncated after ``K`` terms with ``sum_{k > K} c_k
<= tol`` (``tol = 1e-10``, far below the fine grid's ``O((s / h)^2)`` error) and the kept
coefficients divided by their sum, so that the constants (eigenvalue 0, ``T_k(1) = 1``)
are kept exactly: mass is conserved to round-off on every component and the 2-norm
error is at most ``2 tol``. ``K`` grows like ``sqrt(2 z log(1 / tol))``: 35 products with
``A`` at the paper's settings (``z = 25.9``; 40 at ``tol = 1e-13``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
from scipy.special import ive

from harness.compiled.binning import free_binning
from harness.compiled.diffusion import chebyshev_heat
from harness.domains.base import FreeSpace, components
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.velocity import VelocityField

CELLS_PER_BANDWIDTH = 3.0
"""Fine cells per bandwidth that :func:`refinement` asks for by default."""

HEAT_TOLERANCE = 1e-10
"""Tail of the Chebyshev coefficients :class:`HeatKernel` drops."""


def refinement(
    grid: Grid, bandwidth: float, cells_per_bandwidth: float = CELLS_PER_BANDWIDTH
) -> int:
    """The least ``r >= 1`` with ``max(dx, dy) / r <= h / cells_per_bandwidth``."""
    if not (np.isfinite(bandwidth) and bandwidth > 0):
        raise ValueError(f"bandwidth must be > 0, got {bandwidth}")
    if not (np.isfinite(cells_per_bandwidth) and cells_per_bandwidth > 0):
        raise ValueError(f"cells_per_bandwidth must be > 0, got {cells_per_bandwidth}")
    cell = max(grid.dx, grid.dy)
    return max(1, math.ceil(cell * cells_per_bandwidth / bandwidth - 1e-9))


def refine(free: FreeSpace, r: int) -> FreeSpace:
    """``free`` on the grid ``r`` times finer per axis: a subcell is free when its cell
    is, faces inside a free cell are open, faces on a cell's sides are open when that
    face is; components recomputed, the raster kept. ``refine(free, 1)`` is ``free``.
    """
    if r == 1:
        return free
    g = free.grid
    fine = Grid(g.nx * r, g.ny * r, g.x0, g.x1, g.y0, g.y1)
    cells = np.kron(free.cells, np.ones((r, r), dtype=bool))
    # x faces: fine column boundary j | j + 1; on a cell side when (j + 1) % r == 0
    cols = np.arange(fine.nx - 1)
    side = (cols + 1) % r == 0
    coarse_col = (cols + 1) // r - 1  # the coarse face on that side
    rows = np.arange(fine.ny) // r
    face_x = np.where(
        side[None, :],
        free.face_x[rows[:, None], np.clip(coarse_col, 0, g.nx - 2)[None, :]],
        free.cells[rows[:, None], (cols // r)[None, :]],
    )
    lines = np.arange(fine.ny - 1)
    side_y = (lines + 1) % r == 0
    coarse_line = (lines + 1) // r - 1
    columns = np.arange(fine.nx) // r
    face_y = np.where(
        side_y[:, None],
        free.face_y[np.clip(coarse_line, 0, g.ny - 2)[:, None], columns[None, :]],
        free.cells[(lines // r)[:, None], columns[None, :]],
    )
    labels = components(cells, face_x, face_y)
    return FreeSpace(fine, cells, face_x, face_y, labels, free.raster)


def gradient_matrix(free: FreeSpace) -> sp.csr_matrix:
    """Sparse ``(2M, M)`` matrix of :meth:`harness.domains.base.FreeSpace.gradient`
    (central differences, the cell itself behind a closed face, rows of blocked cells 0).
    """
    g = free.grid
    idx = np.arange(g.size).reshape(g.shape)
    cells = free.cells
    east, west, north, south = idx.copy(), idx.copy(), idx.copy(), idx.copy()
    east[:, :-1] = np.where(free.face_x, idx[:, 1:], idx[:, :-1])
    west[:, 1:] = np.where(free.face_x, idx[:, :-1], idx[:, 1:])
    north[:-1, :] = np.where(free.face_y, idx[1:, :], idx[:-1, :])
    south[1:, :] = np.where(free.face_y, idx[:-1, :], idx[1:, :])
    rows = idx[cells]
    m = g.size
    data_x = np.full(rows.size, 0.5 / g.dx)
    data_y = np.full(rows.size, 0.5 / g.dy)
    r = np.concatenate([rows, rows, m + rows, m + rows])
    c = np.concatenate([east[cells], west[cells], north[cells], south[cells]])
    v = np.concatenate([data_x, -data_x, data_y, -data_y])
    out = sp.csr_matrix((v, (r, c)), shape=(2 * m, m))
    out.sum_duplicates()
    out.eliminate_zeros()
    return out


@dataclass
class HeatKernel:
    """``f -> exp(t A) f`` for the drift-free Fokker-Planck operator of unit diffusivity on
    free space (Chebyshev series, see the module docstring).

    Args:
        free: Free space (its grid is the one ``f`` lives on).
        time: ``t >= 0`` (length^2: the diffusivity is 1).
        tol: Coefficient tail dropped (the 2-norm error is at most twice it).
    """

    free: FreeSpace
    time: float
    tol: float = HEAT_TOLERANCE
    matrix: sp.csr_matrix = field(init=False, repr=False)
    stencil: np.ndarray | None = field(init=False, repr=False)
    coefficients: np.ndarray = field(init=False, repr=False)
    scale: float = field(init=False)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.time) and self.time >= 0):
            raise ValueError(f"time must be >= 0, got {self.time}")
        grid = self.free.grid
        a = FokkerPlanck(grid, 1.0, free=self.free).matrix(VelocityField.zeros(grid))
        a = sp.csr_matrix((a.data.copy(), a.indices.copy(), a.indptr.copy()), shape=a.shape)
        a.eliminate_zeros()  # the closed faces' zero entries
        self.matrix = a
        self.stencil = None
        if grid.nx >= 2:
            # the weights (1 / dx^2, 1 / dy^2 and their sums on the diagonal) are most
            # often exact in float32: then half the bytes per term and the same bits
            wide = five_point_stencil(a, grid.nx)
            narrow = wide.astype(np.float32)
            self.stencil = narrow if np.array_equal(narrow, wide) else wide
        spread = 2.0 * float(np.max(-a.diagonal(), initial=0.0))  # Lambda
        self.scale = 2.0 / spread if spread > 0 else 0.0
        z = 0.5 * self.time * spread
        self.coefficients = chebyshev_exp(z, self.tol)

    @property
    def terms(self) -> int:
        """Products with ``A`` per application."""
        return int(self.coefficients.size - 1)

    def __call__(self, f: np.ndarray) -> np.ndarray:
        """``exp(t A) f`` for ``f`` of shape ``(M,)`` or ``(M, c)``: the compiled
        recurrence (:func:`harness.compiled.diffusion.chebyshev_heat`) on each column,
        equal to :meth:`reference` to round-off (the reference itself on a grid of one
        cell per row).
        """
        f = np.asarray(f, dtype=float)
        nx, s, c = self.free.grid.nx, self.scale, self.coefficients
        if self.stencil is None:  # one cell per row: no five-point layout
            return self.reference(f)
        if f.ndim == 1:
            return chebyshev_heat(np.ascontiguousarray(f), self.stencil, nx, s, c)
        columns = [chebyshev_heat(np.ascontiguousarray(col), self.stencil, nx, s, c) for col in f.T]
        return np.stack(columns, axis=1) if columns else np.empty_like(f)

    def reference(self, f: np.ndarray) -> np.ndarray:
        """The plain statement of :meth:`__call__`: the recurrence with sparse products."""
        f = np.asarray(f, dtype=float)
        c = self.coefficients
        out = c[0] * f
        if c.size == 1:
            return out
        a, s = self.matrix, self.scale
        prev = f
        cur = f + s * (a @ f)  # T_1(X) f
        out += c[1] * cur
        for k in range(2, c.size):
            nxt = 2.0 * (cur + s * (a @ cur)) - prev
            out += c[k] * nxt
            prev, cur = cur, nxt
        return out


def five_point_stencil(a: sp.csr_matrix, nx: int) -> np.ndarray:
    """``(5, M)`` the rows of a five-point operator ``a`` on a grid of ``nx`` cells per
    row: the weights of cells ``i - nx``, ``i - 1``, ``i``, ``i + 1``, ``i + nx`` (the CSR
    column order), 0 where ``a`` has no entry.

    Raises:
        ValueError: ``a`` has an entry off those five diagonals, or ``nx < 2`` (the
            offsets ``-1`` and ``-nx`` would coincide).
    """
    if nx < 2:
        raise ValueError(f"five-point stencil needs nx >= 2, got {nx}")
    coo = a.tocoo()
    offset = coo.col.astype(np.int64) - coo.row.astype(np.int64)
    slot = np.full(offset.shape, -1)
    for k, off in enumerate((-nx, -1, 0, 1, nx)):
        slot[offset == off] = k
    if (slot < 0).any():
        raise ValueError("operator has entries off the five-point stencil")
    out = np.zeros((5, a.shape[0]))
    np.add.at(out, (slot, coo.row), coo.data)
    return out


def chebyshev_exp(z: float, tol: float = HEAT_TOLERANCE) -> np.ndarray:
    """Coefficients ``c_0 .. c_K`` of ``exp(z (x - 1)) = sum_k c_k T_k(x)`` on ``[-1, 1]``,
    ``c_0 = e^-z I_0(z)``, ``c_k = 2 e^-z I_k(z)``, truncated where the dropped tail is at
    most ``tol`` and divided by their sum (so the series is exactly 1 at ``x = 1``).
    """
    if z == 0.0:
        return np.ones(1)
    top = int(z + 40.0 * math.sqrt(z) + 60.0)
    k = np.arange(top + 1)
    c = ive(k, z) * np.where(k == 0, 1.0, 2.0)
    tail = np.cumsum(c[::-1])[::-1]  # tail[k] = sum_{j >= k} c_j
    keep = int(np.argmax(tail <= tol)) if (tail <= tol).any() else top + 1
    kept = c[: max(keep, 1)]
    return kept / kept.sum()


class FreeKernel:
    """The Gaussian kernel of bandwidth ``h`` on free space, as the KDE of robot positions
    (:meth:`kde`) and as the operator on densities given by cell values (:meth:`smooth`):
    both bin onto the fine grid (:func:`refine`), diffuse for ``h^2 / 2``
    (:class:`HeatKernel`) and read the value and the gradient at the control cells'
    centres. :meth:`smooth` bins the density's expected share, so that for robots drawn
    from a density constant on each cell ``E[kde] = smooth(p)`` exactly.

    Args:
        free: Free space on the control grid.
        bandwidth: ``h > 0`` (length).
        refine_by: Subcells per cell side; :func:`refinement` of ``cells_per_bandwidth``
            when None.
        cells_per_bandwidth: Fine cells per bandwidth asked of :func:`refinement`.
    """

    def __init__(
        self,
        free: FreeSpace,
        bandwidth: float,
        refine_by: int | None = None,
        cells_per_bandwidth: float = CELLS_PER_BANDWIDTH,
    ) -> None:
        grid = free.grid
        r = refinement(grid, bandwidth, cells_per_bandwidth) if refine_by is None else refine_by
        if int(r) != r or r < 1:
            raise ValueError(f"refine_by must be an integer >= 1, got {refine_by}")
        self.free, self.bandwidth, self.r = free, float(bandwidth), int(r)
        self.fine = refine(free, self.r)
        self.heat = HeatKernel(self.fine, 0.5 * self.bandwidth**2)
        self.targets = bin_targets(self.fine)
        self.home = home_cells(self.fine)
        self.read, self.read_gradient = readout(free, self.fine, self.r)
        self._read_both = sp.vstack([self.read, self.read_gradient]).tocsr()  # one product
        fg = self.fine.grid
        self._bounds = (fg.x0, fg.x1, fg.y0, fg.y1)
        # spread's whole linear map from control cells to fine bins: each free cell's
        # value on its r x r subcells, then their expected binning
        expected = expected_binning(self.targets, self.fine.cells)
        self._spread = (expected @ spread_matrix(free, self.fine, self.r)).tocsr()

    def kde(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(p, grad p)`` on the control grid from robot positions ``(2, N)``."""
        fg = self.fine.grid
        w = free_binning(
            np.ascontiguousarray(positions, dtype=float), *self._bounds, fg.nx, fg.ny,
            self.targets, self.home,
        )  # fmt: skip
        return self.density(w.ravel() / fg.cell_area)

    def smooth(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(K_h p, grad K_h p)`` for cell values ``p`` ``(ny, nx)`` on the control grid
        (1 / length^2; blocked cells ignored): ``p`` spread evenly over each cell's
        subcells, binned by its expected share, diffused and read out.
        """
        return self.density(self.spread(p))

    def spread(self, p: np.ndarray) -> np.ndarray:
        """The expected binned density ``(M_fine,)`` (1 / length^2) of robots drawn from
        the density ``p`` ``(ny, nx)`` taken constant on each control cell (blocked cells
        ignored): each cell's value on its ``r x r`` subcells (:func:`spread_matrix`),
        binned by the expected shares (:func:`expected_binning`), as one sparse product.
        """
        return np.asarray(self._spread @ np.asarray(p, dtype=float).ravel())

    def density(self, fine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The diffused fine field ``fine`` ``(M_fine,)`` read at the control centres."""
        g = self.free.grid
        u = self.heat(fine)
        np.maximum(u, 0.0, out=u)  # round-off of the series below 0
        both = self._read_both @ u
        return both[: g.size].reshape(g.shape), both[g.size :].reshape(2, *g.shape)


def spread_matrix(free: FreeSpace, fine: FreeSpace, r: int) -> sp.csr_matrix:
    """``(M_fine, M)`` sparse: a field given by control-cell values as the fine field
    equal to its cell's value on each of the cell's ``r x r`` subcells; the columns of
    blocked cells are 0 (their values are ignored).
    """
    g, fg = free.grid, fine.grid
    fj, fi = np.divmod(np.arange(fg.size), fg.nx)
    coarse = (fj // r) * g.nx + fi // r
    on = free.cells.ravel()[coarse]
    rows = np.flatnonzero(on)
    return sp.csr_matrix((np.ones(rows.size), (rows, coarse[rows])), shape=(fg.size, g.size))


def bin_targets(free: FreeSpace) -> np.ndarray:
    """``(M, 4, 4)`` int: for each cell and quadrant ``q = 2 (y >= centre) + (x >=
    centre)`` of a robot in it, the cells receiving its four bilinear shares (own, the
    x neighbour, the y neighbour, the diagonal one). A share whose cell lies behind a
    closed face (or the wall) stays on the side it can reach: the x or y neighbour when
    its face is open, else the own cell; the diagonal cell receives its share when one of
    the two paths to it (x then y, y then x) is open.
    """
    g = free.grid
    ny, nx = g.shape
    jj, ii = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    own = jj * nx + ii
    fx = np.zeros((ny, nx + 1), dtype=bool)
    fx[:, 1:-1] = free.face_x  # fx[j, i] open face between (j, i - 1) and (j, i)
    fy = np.zeros((ny + 1, nx), dtype=bool)
    fy[1:-1, :] = free.face_y

    def open_x(j: np.ndarray, i: np.ndarray, sx: int) -> np.ndarray:
        jc, ic = np.clip(j, 0, ny - 1), np.clip(i, 0, nx - 1)
        return np.where((j >= 0) & (j < ny), fx[jc, ic + (sx > 0)], False)

    def open_y(j: np.ndarray, i: np.ndarray, sy: int) -> np.ndarray:
        jc, ic = np.clip(j, 0, ny - 1), np.clip(i, 0, nx - 1)
        return np.where((i >= 0) & (i < nx), fy[jc + (sy > 0), ic], False)

    out = np.empty((ny, nx, 4, 4), dtype=np.int64)
    for q in range(4):
        sx, sy = (1 if q & 1 else -1), (1 if q & 2 else -1)
        ox, oy = open_x(jj, ii, sx), open_y(jj, ii, sy)
        xn = np.where(ox, own + sx, own)
        yn = np.where(oy, own + sy * nx, own)
        route = (ox & open_y(jj, ii + sx, sy)) | (oy & open_x(jj + sy, ii, sx))
        diag = np.where(route, own + sy * nx + sx, np.where(ox, xn, yn))
        out[:, :, q, 0], out[:, :, q, 1], out[:, :, q, 2], out[:, :, q, 3] = own, xn, yn, diag
    return out.reshape(g.size, 4, 4)


def home_cells(free: FreeSpace) -> np.ndarray:
    """``(M,)`` int: each cell itself when free, else the nearest free cell (centre
    distance): where a robot found in a blocked cell is counted.
    """
    g = free.grid
    _, (iy, ix) = ndi.distance_transform_edt(
        ~free.cells, sampling=(g.dy, g.dx), return_indices=True
    )
    return np.ascontiguousarray((iy * g.nx + ix).ravel(), dtype=np.int64)


def bilinear_shares(
    free: FreeSpace, targets: np.ndarray, home: np.ndarray, positions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's four bilinear shares on free space: ``(cells, shares)``, both
    ``(N, 4)``, the cells :func:`bin_targets` gives for the robot's quadrant of its cell
    (:func:`home_cells`, four times, for a robot in a blocked cell) and the shares
    ``(1 - fx)(1 - fy), fx (1 - fy), (1 - fx) fy, fx fy`` (``fx, fy`` its offsets from
    the cell's centre, in cells, at most 1/2), summing to 1. The numpy statement of the
    split :func:`harness.compiled.binning.free_binning` makes; the free-space KDE's
    reference, the kernel laws' interpolation and the decentralised robots' kernels use it.
    """
    g = free.grid
    tx = (positions[0] - g.x0) / g.dx
    ty = (positions[1] - g.y0) / g.dy
    ix = np.clip(np.floor(tx).astype(np.int64), 0, g.nx - 1)
    iy = np.clip(np.floor(ty).astype(np.int64), 0, g.ny - 1)
    ux, uy = tx - ix - 0.5, ty - iy - 0.5
    fx, fy = np.minimum(np.abs(ux), 0.5), np.minimum(np.abs(uy), 0.5)
    cell = iy * g.nx + ix
    q = 2 * (uy >= 0) + (ux >= 0)
    t = targets[cell, q]
    shares = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    blocked = ~free.cells.ravel()[cell]
    t[blocked] = home[cell[blocked]][:, None]
    return t, shares


def bin_reference(
    free: FreeSpace, targets: np.ndarray, home: np.ndarray, positions: np.ndarray
) -> np.ndarray:
    """Numpy statement of :func:`harness.compiled.binning.free_binning`: the bilinear
    shares of each robot (1 / N) on the cells :func:`bin_targets` gives, the whole 1 / N
    on :func:`home_cells` for a robot in a blocked cell; ``(ny, nx)``, summing to 1.
    """
    g = free.grid
    t, shares = bilinear_shares(free, targets, home, positions)
    w = np.bincount(t.ravel(), shares.ravel(), g.size)
    return (w / positions.shape[1]).reshape(g.shape)


def expected_binning(targets: np.ndarray, cells: np.ndarray) -> sp.csr_matrix:
    """``(M, M)`` sparse ``B``: the expected bin weights of a robot placed uniformly in
    each free cell (column), by the shares of :func:`bin_targets`. In a quadrant the
    offsets ``fx, fy`` are uniform on ``[0, 1/2]``, so the shares' means are ``9 / 16, 3 /
    16, 3 / 16, 1 / 16``, each quadrant with probability 1/4. Columns of blocked cells
    are 0; the others sum to 1.
    """
    m = targets.shape[0]
    free = np.flatnonzero(cells.ravel())
    share = np.array([9.0, 3.0, 3.0, 1.0]) / 64.0
    rows = targets[free].reshape(free.size, 16)
    cols = np.repeat(free, 16)
    data = np.tile(np.tile(share, 4), free.size)
    out = sp.csr_matrix((data, (rows.ravel(), cols)), shape=(m, m))
    out.sum_duplicates()
    return out


def readout(free: FreeSpace, fine: FreeSpace, r: int) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse ``(M, M_fine)`` value and ``(2M, M_fine)`` gradient read at the control
    cells' centres from a fine field: for odd ``r`` the centre subcell and the central
    difference across its neighbours (inside the cell), for even ``r`` the mean of the
    four subcells around the centre and their differences; for ``r = 1`` the field itself
    and :func:`gradient_matrix`. Rows of blocked cells are 0.
    """
    g, fg = free.grid, fine.grid
    if r == 1:
        mask = sp.diags(free.cells.ravel().astype(float))
        return sp.csr_matrix(mask), gradient_matrix(free)
    jj, ii = np.nonzero(free.cells)
    rows = jj * g.nx + ii
    m, mf = g.size, fg.size

    def at(dy: int, dx: int, base: int) -> np.ndarray:
        return (r * jj + base + dy) * fg.nx + (r * ii + base + dx)

    if r % 2:
        c = r // 2
        value = sp.csr_matrix((np.ones(rows.size), (rows, at(0, 0, c))), shape=(m, mf))
        e, w, n, s = at(0, 1, c), at(0, -1, c), at(1, 0, c), at(-1, 0, c)
        hx, hy = 0.5 / fg.dx, 0.5 / fg.dy
        gr = np.concatenate([rows, rows, m + rows, m + rows])
        gc = np.concatenate([e, w, n, s])
        gv = np.concatenate([np.full(rows.size, hx), np.full(rows.size, -hx),
                             np.full(rows.size, hy), np.full(rows.size, -hy)])  # fmt: skip
    else:
        b = r // 2 - 1  # subcells b and b + 1 straddle the centre
        quad = [at(0, 0, b), at(0, 1, b), at(1, 0, b), at(1, 1, b)]  # (y, x) = 00, 01, 10, 11
        value = sp.csr_matrix(
            (np.full(4 * rows.size, 0.25), (np.tile(rows, 4), np.concatenate(quad))),
            shape=(m, mf),
        )
        hx, hy = 0.5 / fg.dx, 0.5 / fg.dy
        sign_x = [-hx, hx, -hx, hx]
        sign_y = [-hy, -hy, hy, hy]
        gr = np.concatenate([np.tile(rows, 4), np.tile(m + rows, 4)])
        gc = np.concatenate(quad + quad)
        gv = np.concatenate([np.full(rows.size, v) for v in sign_x + sign_y])
    grad = sp.csr_matrix((gv, (gr, gc)), shape=(2 * m, mf))
    grad.sum_duplicates()
    return value, grad
