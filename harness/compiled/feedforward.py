"""Compiled inversion of the Scharfetter-Gummel face flux, face by face: the velocity
whose flux of ``(p_L, p_R)`` is a given flux (:func:`harness.targets.feedforward.sg_velocity`
holds the equation and the iteration; :func:`harness.targets.feedforward.sg_velocity_reference`
is the numpy statement that tests compare against).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _bernoulli(z: float) -> tuple[float, float]:  # pragma: no cover - compiled
    """``B(z) = z / (e^z - 1)`` and ``B'(z)`` (series for ``|z| < 1e-3``)."""
    if abs(z) < 1e-3:
        return 1 - z / 2 + z * z / 12 - z**4 / 720, -0.5 + z / 6 - z**3 / 180
    b = z / math.expm1(z)
    return b, b / z + b / math.expm1(-z)


@numba.njit(cache=True, nogil=True)
def sg_velocity_faces(
    flux: np.ndarray,
    p_left: np.ndarray,
    p_right: np.ndarray,
    sigma: float,
    h: np.ndarray,
    max_iter: int,
) -> tuple[np.ndarray, bool]:  # pragma: no cover - compiled
    """The face velocities ``u`` with ``(sigma / h) [(B(z) + z) p_L - B(z) p_R] = flux``,
    ``z = u h / sigma`` (``sigma > 0``), each face by Newton's iteration kept inside the
    bracket ``z_0 + y / max(p), z_0 + y / min(p)`` (bisection when a step leaves it),
    one more step after a step below ``1e-12 (1 + |z|)``; and whether every face
    converged within ``max_iter`` steps.
    """
    out = np.empty_like(flux)
    ok = True
    for i in range(flux.size):
        pl, pr = p_left[i], p_right[i]
        y = flux[i] * h[i] / sigma
        z0 = math.log(pr / pl)
        lo_p, hi_p = min(pl, pr), max(pl, pr)
        if y >= 0:
            lo, hi = z0 + y / hi_p, z0 + y / lo_p
        else:
            lo, hi = z0 + y / lo_p, z0 + y / hi_p
        z = z0 + 2 * y / (pl + pr)
        converged = False
        done = False
        for _ in range(max_iter):
            b, slope = _bernoulli(z)
            g = (b + z) * pl - b * pr - y
            if g == 0:
                done = True
                break
            if g < 0:
                lo = z
            else:
                hi = z
            new = z - g / ((1 + slope) * pl - slope * pr)
            if new < lo or new > hi:
                new = 0.5 * (lo + hi)
            small = abs(new - z) <= 1e-12 * (1 + abs(z))
            z = new
            if converged:
                done = True
                break
            converged = small
        ok = ok and done
        out[i] = z * sigma / h[i]
    return out, ok
