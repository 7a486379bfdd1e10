"""Theory quantities computed on the grid: the weighted Poincare constant and the
Lyapunov function of the paper's stability proofs.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.grid import Grid


def lyapunov(grid: Grid, p: np.ndarray, p_star: np.ndarray) -> float:
    """``V = 1/2 int (p - p_*)^2 / p_*`` (the Lyapunov function in the proofs of the
    paper's Theorems ``thm:exponential stability`` and ``thm:ISS``; units 1 / length^2).
    """
    return 0.5 * grid.integrate((p - p_star) ** 2 / p_star)


def weighted_laplacian(grid: Grid, weight: np.ndarray) -> sp.csr_matrix:
    """Finite-volume matrix of ``-div(w grad f)`` with zero-flux walls; the face
    weight is the arithmetic mean of the two cells. Symmetric positive
    semi-definite (after scaling by the cell area), constants in its kernel.
    """
    idx = np.arange(grid.size).reshape(grid.shape)
    rows, cols, vals = [], [], []
    for left, right, wl, wr, h in (
        (idx[:, :-1], idx[:, 1:], weight[:, :-1], weight[:, 1:], grid.dx),
        (idx[:-1, :], idx[1:, :], weight[:-1, :], weight[1:, :], grid.dy),
    ):
        c = (0.5 * (wl + wr) / h**2).ravel()
        a, b = left.ravel(), right.ravel()
        rows += [a, b, a, b]
        cols += [a, b, b, a]
        vals += [c, c, -c, -c]
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(grid.size, grid.size),
    )


def poincare_constant(grid: Grid, p_star: np.ndarray) -> float:
    """The ``p_*``-weighted Poincare constant ``lambda`` on the grid.

    The smallest non-zero eigenvalue of ``-div(p_* grad f) = lambda p_* f`` with
    zero-flux walls (the constant of eq. ``poincare inequality`` with ``g = p_*``,
    in its sharp form). Near ``p_*`` the closed loop with exact estimates,
    ``d_t p = div((alpha p + sigma p_*) grad(p / p_*))``, linearises to
    ``p_* d_t f = (alpha + sigma) div(p_* grad f)`` for ``f = (p - p_*) / p_*``, so
    ``||p - p_*||`` decays at the rate ``(alpha + sigma) lambda``. For uniform
    ``p_*`` on the unit square ``lambda = pi^2``. Units 1 / length^2.
    """
    k = weighted_laplacian(grid, p_star).tocsc()
    m = sp.diags(p_star.ravel()).tocsc()
    # shift-invert about a small negative value finds the eigenvalues nearest 0; a fixed
    # start vector (ARPACK's default is random) makes the value the same in every run
    v0 = np.linspace(1.0, 2.0, k.shape[0])
    vals = spla.eigsh(k, k=2, M=m, sigma=-1e-3, which="LM", return_eigenvectors=False, v0=v0)
    vals = np.sort(vals)
    return float(vals[1])
