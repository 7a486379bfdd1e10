"""Compiled (numba) inner loops for the per-robot work, O(N) in one pass.

Each function here has a plain-numpy reference elsewhere that defines what it
computes (``harness.agents.interpolate``/``reflect`` and
``harness.kde.KDE.bin_weights``); tests check that both agree. Compiled on first
use and cached on disk next to this file.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=False, nogil=True)
def euler_maruyama_step(
    pos: np.ndarray,
    vc: np.ndarray,
    noise: np.ndarray,
    dt: float,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    nx: int,
    ny: int,
) -> None:
    """In place: ``pos += interp(vc, pos) dt + noise``, then reflect at the walls.

    ``pos`` is ``(2, N)``, ``vc`` the cell-centre velocity ``(2, ny, nx)`` and
    ``noise`` the already scaled Brownian increments ``(2, N)``.
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    for k in range(n):
        px = pos[0, k]
        py = pos[1, k]
        u = min(max((px - x0) / dx - 0.5, 0.0), nx - 1.0)
        w = min(max((py - y0) / dy - 0.5, 0.0), ny - 1.0)
        i0 = min(int(u), nx - 2)
        j0 = min(int(w), ny - 2)
        fx = u - i0
        fy = w - j0
        a = vc[0, j0, i0] + fx * (vc[0, j0, i0 + 1] - vc[0, j0, i0])
        b = vc[0, j0 + 1, i0] + fx * (vc[0, j0 + 1, i0 + 1] - vc[0, j0 + 1, i0])
        vx = a * (1.0 - fy) + b * fy
        a = vc[1, j0, i0] + fx * (vc[1, j0, i0 + 1] - vc[1, j0, i0])
        b = vc[1, j0 + 1, i0] + fx * (vc[1, j0 + 1, i0 + 1] - vc[1, j0 + 1, i0])
        vy = a * (1.0 - fy) + b * fy
        px = px + vx * dt + noise[0, k]
        py = py + vy * dt + noise[1, k]
        if px < x0:
            px = 2.0 * x0 - px
        if px > x1:
            px = 2.0 * x1 - px
        if py < y0:
            py = 2.0 * y0 - py
        if py > y1:
            py = 2.0 * y1 - py
        pos[0, k] = min(max(px, x0), x1)
        pos[1, k] = min(max(py, y0), y1)


@numba.njit(cache=True, nogil=True)
def linear_binning(
    pos: np.ndarray, x0: float, x1: float, y0: float, y1: float, bx: int, by: int
) -> np.ndarray:
    """Linear-binning weights on the ``(by + 1, bx + 1)`` nodes, each robot adding
    ``1/N`` split bilinearly over its four surrounding nodes.
    """
    out = np.zeros((by + 1, bx + 1))
    n = pos.shape[1]
    sx = bx / (x1 - x0)
    sy = by / (y1 - y0)
    inv_n = 1.0 / n
    for k in range(n):
        tx = (pos[0, k] - x0) * sx
        ty = (pos[1, k] - y0) * sy
        ix = min(max(int(tx), 0), bx - 1)
        iy = min(max(int(ty), 0), by - 1)
        fx = tx - ix
        fy = ty - iy
        out[iy, ix] += (1.0 - fx) * (1.0 - fy) * inv_n
        out[iy, ix + 1] += fx * (1.0 - fy) * inv_n
        out[iy + 1, ix] += (1.0 - fx) * fy * inv_n
        out[iy + 1, ix + 1] += fx * fy * inv_n
    return out
