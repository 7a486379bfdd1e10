"""Compiled Euler-Maruyama step of the robots (eq. ``Langevin equation``), O(N) in one
pass; :meth:`harness.plants.agents.Swarm.step_reference` (with
:func:`harness.velocity.interpolate` and :func:`harness.plants.agents.reflect`) is the numpy
statement that tests compare against.
"""

from __future__ import annotations

import numba
import numpy as np

from harness.compiled import SerialParallel
from harness.compiled.obstacles import avoid

PARALLEL_MIN_ROBOTS = 1 << 15
"""Fewer robots run the serial build of the same loop: a parallel region costs more
than it saves on small swarms, and much more when the cores are oversubscribed."""


def _euler_maruyama_step(
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
    scale: float = 1.0,
) -> None:
    """In place: ``pos += interp(vc, pos) dt + scale noise``, then reflect at the walls.

    ``pos`` is ``(2, N)``, ``vc`` the cell-centre velocity ``(2, ny, nx)`` and
    ``noise`` the standard (``scale = 1``: already scaled) Gaussian increments
    ``(2, N)``. Robots are independent and run in parallel (``prange``); each robot's
    arithmetic is the same whatever the thread count, so the result is too.
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    for k in numba.prange(n):
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
        px = px + vx * dt + noise[0, k] * scale
        py = py + vy * dt + noise[1, k] * scale
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


euler_maruyama_step = SerialParallel(
    _euler_maruyama_step, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS
)
"""Compiled :func:`_euler_maruyama_step`, parallel from ``PARALLEL_MIN_ROBOTS`` robots on;
the serial and parallel builds run the same per-robot arithmetic, so they give the same
bits."""


def _euler_maruyama_step_free(
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
    scale: float,
    clear: np.ndarray,
) -> None:
    """:func:`_euler_maruyama_step` on a domain with obstacles: after the walls each
    move is reflected at the obstacles of the map of clearances ``clear`` (``(r, r)``
    uint8, :func:`harness.compiled.obstacles.avoid`). A function of its own, so that the
    plain rectangle's step keeps its code and its speed (measured: a flag in one loop
    made the step of 10^6 robots 25 to 50 % slower on the rectangle).
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    for k in numba.prange(n):
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
        px = px + vx * dt + noise[0, k] * scale
        py = py + vy * dt + noise[1, k] * scale
        if px < x0:
            px = 2.0 * x0 - px
        if px > x1:
            px = 2.0 * x1 - px
        if py < y0:
            py = 2.0 * y0 - py
        if py > y1:
            py = 2.0 * y1 - py
        px = min(max(px, x0), x1)
        py = min(max(py, y0), y1)
        px, py = avoid(pos[0, k], pos[1, k], px, py, clear, x0, x1, y0, y1)
        pos[0, k] = px
        pos[1, k] = py


euler_maruyama_step_free = SerialParallel(
    _euler_maruyama_step_free, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS
)
"""Compiled :func:`_euler_maruyama_step_free`."""


def _avoid_moves(
    old: np.ndarray,
    pos: np.ndarray,
    clear: np.ndarray,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
) -> None:
    """In place: each robot's move from ``old[:, k]`` to ``pos[:, k]`` (``(2, N)``, inside
    the rectangle) by the obstacle rule :func:`harness.compiled.obstacles.avoid` on the
    map of clearances ``clear``, for moves made outside the compiled steps (a law's own
    velocities per robot, the localisation error).
    """
    n = pos.shape[1]
    for k in numba.prange(n):
        bx, by = avoid(old[0, k], old[1, k], pos[0, k], pos[1, k], clear, x0, x1, y0, y1)
        pos[0, k] = bx
        pos[1, k] = by


avoid_moves = SerialParallel(_avoid_moves, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS)
"""Compiled :func:`_avoid_moves`."""


def _speed_sums(
    pos: np.ndarray,
    vc: np.ndarray,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    nx: int,
    ny: int,
) -> tuple[float, float, float]:
    """``(sum |v_k|^2, max |v_k|, sum |v_k|)`` over robots ``k`` of the bilinear
    interpolant of the cell-centre velocity ``vc`` ``(2, ny, nx)`` at ``pos`` ``(2, N)``
    (the interpolation of :func:`_euler_maruyama_step`; numpy statement:
    :func:`harness.observers.motion.speed_sums_reference`). Sums run in parallel, so their last
    bits depend on the thread count.
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    sq = 0.0
    peak = 0.0
    total = 0.0
    for k in numba.prange(n):
        u = min(max((pos[0, k] - x0) / dx - 0.5, 0.0), nx - 1.0)
        w = min(max((pos[1, k] - y0) / dy - 0.5, 0.0), ny - 1.0)
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
        s2 = vx * vx + vy * vy
        s = np.sqrt(s2)
        sq += s2
        total += s
        peak = max(peak, s)
    return sq, peak, total


speed_sums = SerialParallel(_speed_sums, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS)
"""Compiled :func:`_speed_sums`, parallel from ``PARALLEL_MIN_ROBOTS`` robots on."""
