"""Compiled optimality check of an assignment's dual potentials (ot's large-N assignment,
:func:`harness.control.matching.large_assignment`), O(n^2) in one pass without temporaries;
:func:`harness.control.matching.violations_reference` is the numpy statement that tests compare
against.
"""

from __future__ import annotations

import numba
import numpy as np

from harness.compiled import SerialParallel

PARALLEL_MIN_ROBOTS = 2048
"""Fewer robots run the serial build (the check is then a few ms)."""


def _violations(
    x: np.ndarray,
    y: np.ndarray,
    u: np.ndarray,
    w: np.ndarray,
    tol: float,
    cols: np.ndarray,
    vals: np.ndarray,
) -> None:
    """In place: per robot ``i``, the points ``j`` of most negative reduced cost ``r_ij =
    |x_i - y_j|^2 - u_i - w_j < -tol``, at most ``k = cols.shape[1]`` of them, most
    negative first, into ``cols[i]`` (``-1`` where fewer) and ``vals[i]``.

    ``x`` ``(n, 2)`` robots, ``y`` ``(m, 2)`` points, ``u`` ``(n,)`` and ``w`` ``(m,)`` the
    dual potentials. Rows are independent and run in parallel (``prange``); each row
    scans the points in order and keeps its ``k`` smallest in a sorted buffer (ties kept
    in scan order), whatever the thread count.
    """
    n = x.shape[0]
    m = y.shape[0]
    k = cols.shape[1]
    for i in numba.prange(n):
        for s in range(k):
            cols[i, s] = -1
            vals[i, s] = 0.0
        found = 0
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        ui = u[i]
        for j in range(m):
            d0 = xi0 - y[j, 0]
            d1 = xi1 - y[j, 1]
            r = d0 * d0 + d1 * d1 - ui - w[j]
            if r >= -tol:
                continue
            if found == k and r >= vals[i, k - 1]:
                continue
            pos = found if found < k else k - 1
            while pos > 0 and vals[i, pos - 1] > r:
                vals[i, pos] = vals[i, pos - 1]
                cols[i, pos] = cols[i, pos - 1]
                pos -= 1
            vals[i, pos] = r
            cols[i, pos] = j
            if found < k:
                found += 1


violations = SerialParallel(_violations, "x", lambda x: x.shape[0], PARALLEL_MIN_ROBOTS)
"""Compiled :func:`_violations`, parallel from ``PARALLEL_MIN_ROBOTS`` robots on (the
same bits either way)."""
