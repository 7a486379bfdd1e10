"""Compiled steps of the robots that are not ideal integrators: unicycles
(:mod:`harness.plants.unicycles`) and double integrators (:mod:`harness.plants.double_integrators`),
and the bilinear interpolation of a held field at the robots. O(N), one pass each; the
numpy statements the tests compare against are
:func:`harness.plants.unicycles.unicycle_step_reference`,
:func:`harness.plants.double_integrators.double_integrator_step_reference` and
:func:`harness.velocity.interpolate`.

Robots are independent and run in parallel (``prange``) from
:data:`harness.compiled.agents.PARALLEL_MIN_ROBOTS` on; each robot's arithmetic is the
same whatever the thread count, so the results are too.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from harness.compiled import SerialParallel
from harness.compiled.agents import PARALLEL_MIN_ROBOTS
from harness.compiled.obstacles import avoid


def _interpolate_robots(
    pos: np.ndarray,
    vc: np.ndarray,
    out: np.ndarray,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    nx: int,
    ny: int,
) -> None:
    """``out[:, k]`` = the bilinear interpolant of the cell-centre velocity ``vc``
    ``(2, ny, nx)`` at ``pos[:, k]`` (``(2, N)``), extended by the nearest centre values
    beyond the outermost centres (as :func:`harness.velocity.interpolate`).
    """
    dx = (x1 - x0) / nx
    dy = (y1 - y0) / ny
    n = pos.shape[1]
    for k in numba.prange(n):
        u = min(max((pos[0, k] - x0) / dx - 0.5, 0.0), nx - 1.0)
        w = min(max((pos[1, k] - y0) / dy - 0.5, 0.0), ny - 1.0)
        i0 = min(int(u), nx - 2)
        j0 = min(int(w), ny - 2)
        fx = u - i0
        fy = w - j0
        for c in range(2):
            a = vc[c, j0, i0] + fx * (vc[c, j0, i0 + 1] - vc[c, j0, i0])
            b = vc[c, j0 + 1, i0] + fx * (vc[c, j0 + 1, i0 + 1] - vc[c, j0 + 1, i0])
            out[c, k] = a * (1.0 - fy) + b * fy


interpolate_robots = SerialParallel(
    _interpolate_robots, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS
)
"""Compiled :func:`_interpolate_robots`."""


def _unicycle_step(
    pos: np.ndarray,
    heading: np.ndarray,
    v: np.ndarray,
    noise: np.ndarray,
    v_max: np.ndarray,
    omega_max: np.ndarray,
    lookahead: np.ndarray,
    applied: np.ndarray,
    dt: float,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    scale: float,
    clear: np.ndarray,
    obstacles: bool,
) -> float:
    """In place, one hold of ``dt`` for every unicycle (the equations are in
    :mod:`harness.plants.unicycles`): the exact hold of the feedback-linearising law under the
    commanded velocity ``v[:, k]`` when it stays within the limits, else one arc of the
    clipped speeds; the scaled noise; the walls, and when ``obstacles`` the obstacles of
    the map of clearances ``clear`` (:func:`harness.compiled.obstacles.avoid`; not read
    otherwise), the heading kept as at the walls. ``heading`` holds the unit vectors
    ``e(theta)`` ``(2, N)``; ``applied[:, k]`` gets the displacement over ``dt``. The
    commanded velocity is ``v[:, k]``; a field's is interpolated first, in a pass of its
    own (:func:`_interpolate_robots`: measured at N = 1024 and 10^6, the two passes take
    about 0.8 times the time of interpolating inside this loop). Returns the sum over
    robots of ``|applied - commanded|``.

    The exact hold needs no angle: with ``tau = tan(psi / 2)``, ``tau_0 = (e_perp . v) /
    (|v| + e . v)``, ``tau_1 = tau_0 exp(-|v| dt / l)``, ``cos psi = (1 - tau^2) / (1 +
    tau^2)`` and ``sin psi = 2 tau / (1 + tau^2)``, and ``e(theta_1)`` is ``e(theta_0)``
    turned by ``psi_0 - psi_1``; only the arc at a limit takes angles.
    """
    n = pos.shape[1]
    inv_dt = 1.0 / dt
    total = 0.0
    for k in numba.prange(n):
        vx = v[0, k]
        vy = v[1, k]
        c = heading[0, k]
        s = heading[1, k]
        along = c * vx + s * vy
        across = c * vy - s * vx
        square = vx * vx + vy * vy
        speed = math.sqrt(square) if square < 1e300 else math.hypot(vx, vy)
        ell = lookahead[k]
        # cos and sin of psi_0 and psi_1 through tau = tan(psi / 2)
        if speed > 0.0:
            inv_speed = 1.0 / speed
            c0 = along * inv_speed
            s0 = across * inv_speed
        else:
            c0 = 1.0
            s0 = 0.0
        decay = math.exp(-speed * dt / ell)
        if c0 < 0.0 and s0 == 0.0:  # psi_0 = pi: the law's unstable rest, no turn
            c1 = -1.0
            s1 = 0.0
        elif decay == 0.0:  # aligned within the hold (tan(psi_0 / 2) may be inf)
            c1 = 1.0
            s1 = 0.0
        else:
            # tan(psi_0 / 2) by the form without cancellation on each side of pi / 2
            tau = s0 / (1.0 + c0) if c0 >= 0.0 else (1.0 - c0) / s0
            tau *= decay
            if abs(tau) <= 1.0:
                q = tau * tau
                r = 1.0 / (1.0 + q)
                c1 = (1.0 - q) * r
                s1 = 2.0 * tau * r
            else:
                w = 1.0 / tau
                q = w * w
                r = 1.0 / (q + 1.0)
                c1 = (q - 1.0) * r
                s1 = 2.0 * w * r
        top_cos = max(abs(c0), abs(c1))
        top_sin = 1.0 if c1 >= 0.0 >= c0 else max(abs(s0), abs(s1))
        # the turn psi_0 - psi_1 as a rotation
        rc = c0 * c1 + s0 * s1
        rs = s0 * c1 - c0 * s1
        if speed * top_cos <= v_max[k] and speed * top_sin <= omega_max[k] * ell:
            # within the limits: the exact hold, the point ahead moves by v dt
            nc = c * rc - s * rs
            ns = s * rc + c * rs
            ddx = vx * dt + ell * (c - nc)
            ddy = vy * dt + ell * (s - ns)
        else:
            # at a limit: one arc of the clipped (u, omega)
            omega = min(max(math.atan2(rs, rc) * inv_dt, -omega_max[k]), omega_max[k])
            u = min(max(along, -v_max[k]), v_max[k])
            half = 0.5 * omega * dt
            sinc = math.sin(half) / half if abs(half) > 1e-6 else 1.0 - half * half / 6.0
            hc = math.cos(half)
            hs = math.sin(half)
            ddx = u * dt * sinc * (c * hc - s * hs)
            ddy = u * dt * sinc * (s * hc + c * hs)
            tc = hc * hc - hs * hs
            ts = 2.0 * hs * hc
            nc = c * tc - s * ts
            ns = s * tc + c * ts
        # back onto the unit circle (one Newton step of 1 / sqrt: the rotation left it
        # within round-off)
        fix = 1.5 - 0.5 * (nc * nc + ns * ns)
        heading[0, k] = nc * fix
        heading[1, k] = ns * fix
        applied[0, k] = ddx * inv_dt
        applied[1, k] = ddy * inv_dt
        px = pos[0, k] + ddx + noise[0, k] * scale
        py = pos[1, k] + ddy + noise[1, k] * scale
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
        if obstacles:
            px, py = avoid(pos[0, k], pos[1, k], px, py, clear, x0, x1, y0, y1)
        pos[0, k] = px
        pos[1, k] = py
        ex = applied[0, k] - vx
        ey = applied[1, k] - vy
        total += math.sqrt(ex * ex + ey * ey)
    return total


unicycle_step = SerialParallel(_unicycle_step, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS)
"""Compiled :func:`_unicycle_step`."""


def _double_integrator_step(
    pos: np.ndarray,
    vel: np.ndarray,
    v: np.ndarray,
    noise: np.ndarray,
    a_max: np.ndarray,
    gain: np.ndarray,
    applied: np.ndarray,
    dt: float,
    x0: float,
    x1: float,
    y0: float,
    y1: float,
    scale: float,
    clear: np.ndarray,
    obstacles: bool,
) -> None:
    """In place, one hold of ``dt`` for every double integrator (the equations are in
    :mod:`harness.plants.double_integrators`): the exact solution of the saturated velocity
    loop, the scaled noise, the walls, and when ``obstacles`` the obstacles of the map of
    clearances ``clear`` (:func:`harness.compiled.obstacles.avoid`; not read otherwise),
    the velocity kept as at the walls; ``applied[:, k]`` gets the displacement over
    ``dt``.
    """
    n = pos.shape[1]
    for k in numba.prange(n):
        g = gain[k]
        a = a_max[k]
        wx = vel[0, k]
        wy = vel[1, k]
        ex = v[0, k] - wx
        ey = v[1, k] - wy
        gap = math.sqrt(ex * ex + ey * ey)
        dispx = 0.0
        dispy = 0.0
        rest = dt
        if g * gap > a:
            ts = (gap - a / g) / a  # time until the loop leaves the limit
            tau = min(ts, dt)
            ax = a * ex / gap
            ay = a * ey / gap
            dispx = wx * tau + 0.5 * ax * tau * tau
            dispy = wy * tau + 0.5 * ay * tau * tau
            wx = wx + ax * tau
            wy = wy + ay * tau
            rest = dt - tau
        if rest > 0.0:
            decay = math.exp(-g * rest)
            lag = -math.expm1(-g * rest) / g
            dispx += v[0, k] * rest + (wx - v[0, k]) * lag
            dispy += v[1, k] * rest + (wy - v[1, k]) * lag
            wx = v[0, k] + (wx - v[0, k]) * decay
            wy = v[1, k] + (wy - v[1, k]) * decay
        vel[0, k] = wx
        vel[1, k] = wy
        applied[0, k] = dispx / dt
        applied[1, k] = dispy / dt
        px = pos[0, k] + dispx + noise[0, k] * scale
        py = pos[1, k] + dispy + noise[1, k] * scale
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
        if obstacles:
            px, py = avoid(pos[0, k], pos[1, k], px, py, clear, x0, x1, y0, y1)
        pos[0, k] = px
        pos[1, k] = py


double_integrator_step = SerialParallel(
    _double_integrator_step, "pos", lambda pos: pos.shape[1], PARALLEL_MIN_ROBOTS
)
"""Compiled :func:`_double_integrator_step`."""
