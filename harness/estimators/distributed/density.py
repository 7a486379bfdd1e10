"""The per-robot density filter's step, compiled over robots.

Each robot runs the density filter of :mod:`harness.estimators.filters.local` on its tracked
observation ``y_i``: the exact state transition ``x^- = (I - dt A)^{-1} x``, variances
by ``d^- = (F1 o F1) d + q dt k`` (``F1 = I + dt A``), and the diagonal update with
``r = r_scale k max(y_i, r_floor)``; arrays are ``(N, M)``, one robot per row. ``A`` is a
5-point operator, applied as fixed-offset stencils on padded fields
(:func:`stencil_coefficients`); the implicit predict is solved by Jacobi sweeps with an
a posteriori stop at a remainder below ``1e-15 ||x||_1`` (:func:`jacobi_sweeps`: ratio
``q ~ rho / 2`` against the Neumann series' ``rho``), or by one sparse LU with
triangular solves over robots (:class:`~harness.estimators.distributed.row_solver.RowSolver`)
beyond :data:`ROBOT_MAX_SWEEPS` sweeps.

Why this is not :class:`harness.estimators.filters.local.LocalFilters` applied to many columns:
every robot's predict, variance prediction and update run in one compiled pass over its
own row (one robot per iteration, in parallel over robots), with its own a posteriori
number of sweeps. The centralised filter's predict (red-black sweeps over all columns
at once, :func:`harness.fokker_planck.implicit_solve`), its variance product
(:func:`harness.estimators.filters.local.squared_transition`, the diagonal of ``F1 o F1`` summed as
``(dt a_rr)^2 + 2 dt a_rr`` on top of the identity) and its update (``1 / (1/d^- +
1/r)``) are the same maths in other roundings, so calling them would change the robots'
bits; :func:`density_filter_reference` states the step with them (tests compare).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.row_solver import RowSolver
from harness.estimators.filters.common import MeasurementModel
from harness.estimators.filters.local import squared_transition
from harness.fokker_planck import implicit_solve, series_terms
from harness.grid import Grid

ROBOT_MAX_SWEEPS = 60
"""Above this many Jacobi sweeps the per-robot predict uses one sparse LU and
triangular solves vectorised over robots (a sweep costs about 1/80 of the LU path at
``n = 30``, measured with ``python -m benchmarks.distributed``)."""


@numba.njit(cache=True, nogil=True)
def _stencil_apply(coef, nx, src, out):  # pragma: no cover - compiled
    """``out = S src`` for the 5-point stencil ``S`` with rows ``coef = [centre, west,
    east, south, north]`` ``(5, M)``; ``src`` is the field padded with ``nx`` zeros on
    each side (``src[nx + r]`` is cell ``r``), so every neighbour is a fixed offset and
    the loop vectorises (the coefficients of missing neighbours are 0).
    """
    m = out.size
    c0, cw, ce, cs, cn = coef[0], coef[1], coef[2], coef[3], coef[4]
    # shifted views: non-negative loop indices, so no wrap-around test blocks SIMD
    sc, sw, se = src[nx : nx + m], src[nx - 1 : nx - 1 + m], src[nx + 1 : nx + 1 + m]
    ss, sn = src[:m], src[2 * nx : 2 * nx + m]
    for r in range(m):
        out[r] = c0[r] * sc[r] + cw[r] * sw[r] + ce[r] * se[r] + cs[r] * ss[r] + cn[r] * sn[r]


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _jacobi_sweep(coef, dinv, nx, b, src, out):  # pragma: no cover - compiled
    """``out = D^{-1} (b + O src)``: one Jacobi sweep for ``(I - dt A) x = b`` with
    ``D = 1 - dt a_rr`` and ``O`` the off-diagonal part of ``dt A`` (rows 1..4 of the
    stencil ``coef``); ``src`` and ``out`` padded as in :func:`_stencil_apply`. Returns
    ``||D (out - src)||_1``, the 1-norm of the series term the sweep added.

    Compiled with reassociation allowed (``fastmath={"reassoc"}``) so that the norm's
    sum vectorises; the order is fixed at compile time, the same for every robot and
    thread count.
    """
    m = b.size
    c0, cw, ce, cs, cn = coef[0], coef[1], coef[2], coef[3], coef[4]
    sc, sw, se = src[nx : nx + m], src[nx - 1 : nx - 1 + m], src[nx + 1 : nx + 1 + m]
    ss, sn = src[:m], src[2 * nx : 2 * nx + m]
    oc = out[nx : nx + m]
    change = 0.0
    for r in range(m):
        t = b[r] + cw[r] * sw[r] + ce[r] * se[r] + cs[r] * ss[r] + cn[r] * sn[r]
        oc[r] = dinv[r] * t
        change += abs(t - (1.0 - c0[r]) * sc[r])
    return change


@numba.njit(cache=True, parallel=True, nogil=True)
def _density_filter_stencil(
    x, d, y, coef, dinv, sqcoef, nx, q, max_sweeps, qk, rk, r_floor, chunk
):  # pragma: no cover - compiled
    """Per robot ``i`` (rows), in place, the density part of ``LocalFilters.step``:

    x^- = (I - dt A)^{-1} x     by Jacobi sweeps from D^{-1} x (see
                                :func:`jacobi_sweeps`), stopping at the first whose
                                remainder bound ``q / (1 - q) ||term||_1 <= 1e-15
                                ||x||_1`` holds, at most ``max_sweeps`` (none when
                                ``max_sweeps < 0``: ``x`` is predicted already),
    d^- = (F1 o F1) d + q dt k,
    r = r_scale k max(y, r_floor),  d = 1 / (1/d^- + 1/r),  x = x^- + d / r (y - x^-),

    with ``dt A`` and ``F1 o F1`` as 5-point stencils (``coef``, ``sqcoef``, see
    :func:`stencil_coefficients`) and ``dinv = 1 / (1 - dt a_rr)``. Robots in fixed
    chunks (buffers reused); each robot's arithmetic depends on its own data only, so
    the result does not depend on the number of threads.
    """
    n, m = x.shape
    nch = (n + chunk - 1) // chunk
    ratio = q / (1.0 - q)
    for ch in numba.prange(nch):
        pa = np.zeros(m + 2 * nx)
        pb = np.zeros(m + 2 * nx)
        pd = np.zeros(m + 2 * nx)
        tmp = np.empty(m)
        dc = pd[nx : nx + m]
        for i in range(ch * chunk, min(n, (ch + 1) * chunk)):
            xi, di, yi = x[i], d[i], y[i]
            src, dst = pa, pb
            xc = src[nx : nx + m]
            norm = 0.0
            for r in range(m):
                dc[r] = di[r]
                xc[r] = xi[r] * dinv[r] if max_sweeps >= 0 else xi[r]
                norm += abs(xi[r])
            term = norm  # ||y_0||_1 = ||x||_1
            k = 0
            while k < max_sweeps and ratio * term > 1e-15 * norm:
                term = _jacobi_sweep(coef, dinv, nx, xi, src, dst)
                src, dst = dst, src
                k += 1
            xc = src[nx : nx + m]
            _stencil_apply(sqcoef, nx, pd, tmp)
            for c in range(m):
                # d = 1 / (1/d^- + 1/r) = d^- r / (d^- + r), gain d / r = d^- / (d^- + r)
                dm = tmp[c] + qk
                rr = rk * max(yi[c], r_floor)
                inv = 1.0 / (dm + rr)
                di[c] = dm * rr * inv
                xi[c] = xc[c] + dm * inv * (yi[c] - xc[c])


def jacobi_ratio(coef: np.ndarray) -> float:
    """``q = max_r dt |a_rr| / (1 + dt |a_rr|)``, the contraction of the Jacobi sweeps
    (see :func:`jacobi_sweeps`); ``coef`` from :func:`stencil_coefficients`.
    """
    c0 = coef[0]
    return float(np.max(-c0 / (1.0 - c0), initial=0.0))


def jacobi_sweeps(coef: np.ndarray) -> int:
    """A priori number of Jacobi sweeps ``K`` for ``(I - dt A) x = b`` to a remainder
    below ``1e-15 ||b||_1``.

    With ``D = diag(1 - dt a_rr)`` (``>= 1``) and ``O`` the off-diagonal part of ``dt
    A`` (``>= 0``, column ``r`` summing to ``dt |a_rr|`` since the columns of ``A`` sum
    to zero), ``y = D x`` solves ``y = b + O D^{-1} y``, whose iteration matrix has
    1-norm ``q = max_r dt |a_rr| / (1 + dt |a_rr|) < 1``. ``K`` sweeps from ``y_0 = b``
    sum the series to ``k = K``; the remainder is at most ``q^{K+1} / (1 - q) ||b||_1``
    (``series_terms(q)``), and ``|x - x_K| <= |y - y_K|`` as ``D >= 1``. About half the
    Neumann terms of ``sum (dt A)^k`` (whose ratio is ``rho = 2 max dt |a_rr|``).

    A posteriori: the ``k``-th term ``T^k b`` bounds the rest by ``q / (1 - q)
    ||T^k b||_1`` (each further term shrinks by ``q`` at least), so the filter stops
    as soon as that is below ``1e-15 ||b||_1``, never later than ``K``.
    """
    return series_terms(jacobi_ratio(coef))


def stencil_coefficients(grid: Grid, a: sp.csr_matrix, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The 5-point stencils of ``dt A`` and of ``F1 o F1`` (``F1 = I + dt A``), each
    ``(5, M)`` with rows ``[centre, west, east, south, north]`` (west = cell ``r - 1``,
    south = cell ``r - nx``); entries for neighbours beyond the walls are 0.

    ``(F1 o F1) d`` is the diagonal of ``F1 diag(d) F1^T``: coefficients ``(dt a_rc)^2``
    off the diagonal and ``(dt a_rr)^2 + 1 + 2 dt a_rr`` on it (as
    :func:`harness.estimators.filters.local.squared_transition`).

    Raises:
        ValueError: if ``A`` couples cells that are not grid neighbours.
    """
    a = a.tocsr()
    m, nx = grid.size, grid.nx
    rows = np.repeat(np.arange(m), np.diff(a.indptr))
    cols = a.indices.astype(np.int64)
    dj, di = cols // nx - rows // nx, cols % nx - rows % nx
    slot = np.select(
        [(di == 0) & (dj == 0), (di == -1) & (dj == 0), (di == 1) & (dj == 0),
         (di == 0) & (dj == -1), (di == 0) & (dj == 1)],
        [0, 1, 2, 3, 4], default=-1,
    )  # fmt: skip
    if (slot < 0).any():
        raise ValueError("A is not a 5-point operator on the grid")
    coef = np.zeros((5, m))
    np.add.at(coef, (slot, rows), dt * a.data)
    sq = coef**2
    sq[0] += 1.0 + 2.0 * coef[0]
    return coef, sq


def density_step(
    grid: Grid, dt: float, measurement: MeasurementModel, x: np.ndarray, d: np.ndarray,
    y: np.ndarray, a: sp.csr_matrix, max_sweeps: int = ROBOT_MAX_SWEEPS,
) -> np.ndarray:  # fmt: skip
    """Every robot's density predict under ``A`` (CSR, sorted indices) and update with
    its observation ``y`` ``(N, M)``: ``d`` in place, the estimates in place in ``x`` or,
    after the sparse-LU predict, in a new array; returns the estimates.
    """
    s, g = measurement.settings, grid
    k, _ = measurement.constants
    coef, sqcoef = stencil_coefficients(g, a, dt)
    sweeps = jacobi_sweeps(coef)
    if sweeps > max_sweeps:  # sparse LU (as implicit_solve), then no sweeps
        x = RowSolver(sp.identity(g.size, format="csr") - dt * a).solve_rows(x)
        sweeps = -1
    q = s.process_noise * dt
    _density_filter_stencil(
        x, d, y, coef, 1.0 / (1.0 - coef[0]), sqcoef, g.nx,
        jacobi_ratio(coef), sweeps, q * k, s.r_scale * k, s.r_floor, 16,
    )  # fmt: skip
    return x


def density_filter_reference(
    x: np.ndarray, d: np.ndarray, y: np.ndarray, a: sp.csr_matrix, dt: float,
    measurement: MeasurementModel,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Plain numpy statement of :func:`density_step` for rows ``(N, M)``: the density
    part of ``LocalFilters.step`` with the centralised filter's functions (scipy
    products, :func:`harness.estimators.filters.local.squared_transition`, the measurement model's
    variances).
    """
    s = measurement.settings
    k, _ = measurement.constants
    xm = implicit_solve(a, dt, x.T).T
    dm = squared_transition(a, dt, d.T).T + s.process_noise * dt * k
    r = measurement.density_variance(y).reshape(y.shape)
    dp = 1.0 / (1.0 / dm + 1.0 / r)
    return xm + dp / r * (y - xm), dp
