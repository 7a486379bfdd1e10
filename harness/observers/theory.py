"""Theory quantities computed on the grid: the weighted Poincare constant and the
Lyapunov function of the paper's stability proofs.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.domains.base import FreeSpace
from harness.grid import Grid


def lyapunov(grid: Grid, p: np.ndarray, p_star: np.ndarray, free: FreeSpace | None = None) -> float:
    """``V = 1/2 int (p - p_*)^2 / p_*`` (the Lyapunov function in the proofs of the
    paper's Theorems ``thm:exponential stability`` and ``thm:ISS``; units 1 / length^2),
    over free space on a domain with obstacles (``free``: the free cells, where
    ``p_* > 0``; ``p_*`` is 0 on the blocked ones).
    """
    if free is None:
        return 0.5 * grid.integrate((p - p_star) ** 2 / p_star)
    cells = free.cells
    ratio = np.zeros(grid.shape)
    ratio[cells] = (p[cells] - p_star[cells]) ** 2 / p_star[cells]
    return 0.5 * grid.integrate(ratio)


def weighted_laplacian(
    grid: Grid, weight: np.ndarray, free: FreeSpace | None = None
) -> sp.csr_matrix:
    """Finite-volume matrix of ``-div(w grad f)`` with zero-flux walls; the face
    weight is the arithmetic mean of the two cells. Symmetric positive
    semi-definite (after scaling by the cell area), constants in its kernel. With
    ``free``, only its open faces carry flux (a closed face is a wall), so the
    constants of each connected component are in its kernel.
    """
    idx = np.arange(grid.size).reshape(grid.shape)
    rows, cols, vals = [], [], []
    ones = (np.ones((grid.ny, grid.nx - 1), bool), np.ones((grid.ny - 1, grid.nx), bool))
    open_x, open_y = ones if free is None else (free.face_x, free.face_y)
    for left, right, wl, wr, h, face in (
        (idx[:, :-1], idx[:, 1:], weight[:, :-1], weight[:, 1:], grid.dx, open_x),
        (idx[:-1, :], idx[1:, :], weight[:-1, :], weight[1:, :], grid.dy, open_y),
    ):
        c = (0.5 * (wl + wr) / h**2)[face]
        a, b = left[face], right[face]
        rows += [a, b, a, b]
        cols += [a, b, b, a]
        vals += [c, c, -c, -c]
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(grid.size, grid.size),
    )


def poincare_constant(grid: Grid, p_star: np.ndarray, free: FreeSpace | None = None) -> float:
    """The ``p_*``-weighted Poincare constant ``lambda`` on the grid.

    The smallest non-zero eigenvalue of ``-div(p_* grad f) = lambda p_* f`` with
    zero-flux walls (the constant of eq. ``poincare inequality`` with ``g = p_*``,
    in its sharp form). Near ``p_*`` the closed loop with exact estimates,
    ``d_t p = div((alpha p + sigma p_*) grad(p / p_*))``, linearises to
    ``p_* d_t f = (alpha + sigma) div(p_* grad f)`` for ``f = (p - p_*) / p_*``, so
    ``||p - p_*||`` decays at the rate ``(alpha + sigma) lambda``. For uniform
    ``p_*`` on the unit square ``lambda = pi^2``. Units 1 / length^2.

    On a domain with obstacles (``free``) the problem lives on the free cells with
    flux through open faces only. With ``C`` connected components the eigenvalue 0 has
    multiplicity ``C`` (a constant on each component: mass cannot move between them),
    and ``lambda`` is the next one, the slowest rate within the components, which is
    the loop's rate once each component holds its target mass (the build refuses a
    target with mass where no robot can go).
    """
    if free is None:
        k = weighted_laplacian(grid, p_star).tocsc()
        m = sp.diags(p_star.ravel()).tocsc()
        zeros = 1
    else:
        keep = np.flatnonzero(free.cells.ravel())
        k = weighted_laplacian(grid, p_star, free).tocsr()[keep][:, keep].tocsc()
        m = sp.diags(p_star.ravel()[keep]).tocsc()
        zeros = free.n_components
    # shift-invert about a small negative value finds the eigenvalues nearest 0; a fixed
    # start vector (ARPACK's default is random) makes the value the same in every run
    v0 = np.linspace(1.0, 2.0, k.shape[0])
    vals = spla.eigsh(
        k, k=zeros + 1, M=m, sigma=-1e-3, which="LM", return_eigenvectors=False, v0=v0
    )
    vals = np.sort(vals)
    return float(vals[zeros])
