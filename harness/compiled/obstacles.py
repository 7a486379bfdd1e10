"""Compiled obstacle rule of the robots' moves on a domain with obstacles, on the robots'
map (:class:`harness.plants.obstacles.RobotMap`).

The map is the ``(r, r)`` raster of :meth:`harness.domains.base.Domain.raster`: square
``(row, col)`` covers ``[x0 + col s_x, x0 + (col + 1) s_x) x [y0 + row s_y, y0 + (row + 1)
s_y)`` (``s = L / r``). It is handed to the kernels as its *clearance* ``c``: 0 on a blocked
square, else the chessboard distance (in squares, at most 255) to the nearest blocked one.

The rule (:func:`avoid`), for a robot moving from a free point ``A`` to ``B`` (``B``
already reflected at the rectangle's walls):

1. When ``B``'s square is fewer squares from ``A``'s (chessboard) than ``A``'s clearance,
   every square the segment ``AB`` meets is free: ``B`` is kept. One look-up; the usual case.
2. Otherwise the segment is walked square by square (Amanatides and Woo's traversal) to
   the first blocked square it enters. None: ``B`` is kept (if its own square is free).
3. The robot is reflected at the face of that square through which the segment entered
   it, as at a wall: the coordinate across the face is mirrored, ``x -> 2 x_f - x``
   (``y`` likewise for a horizontal face), the other kept.
4. The mirrored point ``B'`` is kept when it lies in the rectangle, its square is free and
   the segment from the crossing point to ``B'`` enters no blocked square; otherwise the
   robot stays at ``A`` (its move over the step is dropped).

Every point a robot is left at is in a free square (by the look-up itself), and no
straight part of its path crosses a blocked square, so a robot never enters an obstacle
of the map nor tunnels through one however long its step.

The rule runs inside the compiled steps (:mod:`harness.compiled.agents`,
:mod:`harness.compiled.robots`); their disk cache is keyed by this module's source too
(:func:`harness.compiled.stamp_by_package`).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def square_of(x: float, x0: float, side: float, r: int) -> int:
    """The index of the raster column (row) holding coordinate ``x``, within ``[0, r)``."""
    k = int(np.floor((x - x0) / side))
    return min(max(k, 0), r - 1)


@numba.njit(cache=True, nogil=True)
def first_blocked(
    ax: float,
    ay: float,
    col: int,
    row: int,
    bx: float,
    by: float,
    clear: np.ndarray,
    x0: float,
    y0: float,
    sx: float,
    sy: float,
) -> tuple[float, int, int, int]:
    """The first blocked square the segment from ``A = (ax, ay)`` (in square ``(row,
    col)``, not itself tested) to ``B`` enters: ``(t, axis, col, row)`` with ``A + t (B -
    A)`` the entry point and ``axis`` 0 when it is entered through a vertical face
    (crossing x), 1 through a horizontal one; ``axis = -1`` when there is none.
    """
    r = clear.shape[0]
    dx = bx - ax
    dy = by - ay
    inf = np.inf
    if dx > 0.0:
        step_c = 1
        t_x = (x0 + (col + 1) * sx - ax) / dx
        d_x = sx / dx
    elif dx < 0.0:
        step_c = -1
        t_x = (x0 + col * sx - ax) / dx
        d_x = -sx / dx
    else:
        step_c = 0
        t_x = inf
        d_x = inf
    if dy > 0.0:
        step_r = 1
        t_y = (y0 + (row + 1) * sy - ay) / dy
        d_y = sy / dy
    elif dy < 0.0:
        step_r = -1
        t_y = (y0 + row * sy - ay) / dy
        d_y = -sy / dy
    else:
        step_r = 0
        t_y = inf
        d_y = inf
    while True:
        if t_x <= t_y:
            if not t_x <= 1.0:
                break
            col += step_c
            t = t_x
            t_x += d_x
            axis = 0
        else:
            if not t_y <= 1.0:
                break
            row += step_r
            t = t_y
            t_y += d_y
            axis = 1
        if col < 0 or col >= r or row < 0 or row >= r:
            break
        if clear[row, col] == 0:
            return t, axis, col, row
    return 1.0, -1, col, row


@numba.njit(cache=True, nogil=True)
def avoid(
    ax: float,
    ay: float,
    bx: float,
    by: float,
    clear: np.ndarray,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
) -> tuple[float, float]:
    """Where a robot moving from the free point ``A`` to ``B`` (inside the rectangle
    ``[x0, x1] x [y0, y1]``) ends on the map of clearances ``clear`` (module docstring):
    ``B``, its mirror image at the first obstacle face the move crosses, or ``A``.
    """
    r = clear.shape[0]
    sx = (x1 - x0) / r
    sy = (y1 - y0) / r
    c0 = square_of(ax, x0, sx, r)
    r0 = square_of(ay, y0, sy, r)
    c1 = square_of(bx, x0, sx, r)
    r1 = square_of(by, y0, sy, r)
    if max(abs(c1 - c0), abs(r1 - r0)) < clear[r0, c0]:
        return bx, by
    t, axis, cb, rb = first_blocked(ax, ay, c0, r0, bx, by, clear, x0, y0, sx, sy)
    if axis < 0:
        if clear[r1, c1] > 0:
            return bx, by
        return ax, ay
    if axis == 0:
        # entered through a vertical face: mirror x at it
        if bx > ax:
            face = x0 + cb * sx
            sc = cb - 1
        else:
            face = x0 + (cb + 1) * sx
            sc = cb + 1
        qx = 2.0 * face - bx
        qy = by
        hx = face
        hy = ay + t * (by - ay)
        sr = rb
    else:
        if by > ay:
            face = y0 + rb * sy
            sr = rb - 1
        else:
            face = y0 + (rb + 1) * sy
            sr = rb + 1
        qx = bx
        qy = 2.0 * face - by
        hx = ax + t * (bx - ax)
        hy = face
        sc = cb
    if not (x0 <= qx <= x1 and y0 <= qy <= y1):
        return ax, ay
    _, again, _, _ = first_blocked(hx, hy, sc, sr, qx, qy, clear, x0, y0, sx, sy)
    if again >= 0 or clear[square_of(qy, y0, sy, r), square_of(qx, x0, sx, r)] == 0:
        return ax, ay
    return qx, qy
