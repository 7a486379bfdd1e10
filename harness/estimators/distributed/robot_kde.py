"""Each robot's own KDE kernel on the grid.

The swarm's KDE is a mean over robots,

    p_KDE(x) = (1/N) sum_i phi_i(x),        phi_i(x) = K_h(x - X_i)  (with wall images),

so robot ``i`` knows its own term ``phi_i`` from its position alone; consensus
(:mod:`harness.estimators.distributed.consensus`) tracks the mean. ``K_h`` is the Gaussian of
:mod:`harness.estimators.kde` with its wall images; ``phi_i`` is separable, ``outer(ky[i],
kx[i])``, and is kept as its 1-D factors (:func:`kernel_factors`).
"""

from __future__ import annotations

import numba
import numpy as np

from harness.estimators.kde import IMAGE_CUTOFF
from harness.grid import Grid


@numba.njit(cache=True, nogil=True)
def _gauss_run(s, c0, dx, n, h, g, dg):  # pragma: no cover - compiled
    """``g[k] += exp(-(c_k - s)^2 / 2h^2)`` and ``dg[k] += (c_k - s) exp(...)`` on the
    uniform centres ``c_k = c0 + k dx``: one exponential at the centre nearest ``s``,
    then products outwards, ``E_{k+1} = E_k rho_k``, ``rho_{k+1} = rho_k a`` with
    ``rho = exp(-(c_k - s) dx / h^2 - dx^2 / 2h^2)`` and ``a = exp(-dx^2 / h^2)`` (each
    factor is at most 1 going away from the peak; stops below 1e-300).
    """
    inv_h2 = 1.0 / (h * h)
    a = np.exp(-dx * dx * inv_h2)
    half = 0.5 * dx * dx * inv_h2
    k0 = min(max(int(np.floor((s - c0) / dx + 0.5)), 0), n - 1)
    u = c0 + k0 * dx - s
    peak = np.exp(-0.5 * u * u * inv_h2)
    g[k0] += peak
    dg[k0] += u * peak
    for direction in (1, -1):
        e = peak
        rho = np.exp(-direction * u * dx * inv_h2 - half)
        k = k0 + direction
        while 0 <= k < n:
            e *= rho
            if e < 1e-300:
                break
            g[k] += e
            dg[k] += (c0 + k * dx - s) * e
            rho *= a
            k += direction


@numba.njit(cache=True, parallel=True, nogil=True)
def _kernel_factors_1d(points, c0, dx, n, h, lo, hi, cutoff):  # pragma: no cover
    """Rows ``g_h(c_k - X_i)`` and ``d/dc_k`` of them with the wall images (as
    :func:`harness.estimators.kde.kernel_1d`: images of the robots within ``cutoff h`` of a
    wall), by :func:`_gauss_run`.
    """
    m = points.size
    g = np.zeros((m, n))
    dg = np.zeros((m, n))
    norm = 1.0 / (np.sqrt(2.0 * np.pi) * h)
    for i in numba.prange(m):
        x = points[i]
        _gauss_run(x, c0, dx, n, h, g[i], dg[i])
        for wall in (lo, hi):
            if abs(x - wall) < cutoff * h:
                _gauss_run(2.0 * wall - x, c0, dx, n, h, g[i], dg[i])
        for k in range(n):
            g[i, k] *= norm
            dg[i, k] *= -norm / (h * h)
    return g, dg


def kernel_factors(
    grid: Grid, positions: np.ndarray, bandwidth: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """1-D kernel factors per robot, ``(kx, dkx, ky, dky)`` of shapes ``(N, nx)``,
    ``(N, nx)``, ``(N, ny)``, ``(N, ny)``, with the wall images of :mod:`harness.estimators.kde`.

    Robot ``i``'s kernel on the grid is ``phi_i = outer(ky[i], kx[i])`` (1 / length^2),
    its gradient ``(outer(ky[i], dkx[i]), outer(dky[i], kx[i]))`` (1 / length^3); their
    means over robots are :meth:`harness.estimators.kde.KDE.exact`. Compiled with two exponentials
    per robot, axis and image (:func:`_gauss_run`); :func:`harness.estimators.kde.kernel_1d` is the
    reference (tests compare).
    """
    g = grid
    pts = np.asarray(positions, dtype=float)
    out = []
    for p, n, d, c, lo, hi in ((pts[0], g.nx, g.dx, g.x, g.x0, g.x1),
                               (pts[1], g.ny, g.dy, g.y, g.y0, g.y1)):  # fmt: skip
        out.append(
            _kernel_factors_1d(
                np.ascontiguousarray(p), float(c[0]), d, n, bandwidth, lo, hi, IMAGE_CUTOFF
            )
        )
    (kx, dkx), (ky, dky) = out
    return kx, dkx, ky, dky


def robot_kernels(
    grid: Grid, positions: np.ndarray, bandwidth: float, gradient: bool = False
) -> np.ndarray:
    """The robots' own kernels ``phi_i = K_h(x - X_i)`` on the grid, shape ``(N, M)``
    (1 / length^2), or with ``gradient`` ``(N, 3M)``: ``[phi_i, d_x phi_i, d_y phi_i]``.
    """
    kx, dkx, ky, dky = kernel_factors(grid, positions, bandwidth)
    n = kx.shape[0]
    phi = (ky[:, :, None] * kx[:, None, :]).reshape(n, -1)
    if not gradient:
        return phi
    gx = (ky[:, :, None] * dkx[:, None, :]).reshape(n, -1)
    gy = (dky[:, :, None] * kx[:, None, :]).reshape(n, -1)
    return np.concatenate([phi, gx, gy], axis=1)
