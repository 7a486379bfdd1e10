"""Distributed density filter and decentralised control (issue 14).

The centralised loop forms one KDE of every position. But the KDE is a mean over robots,

    p_KDE(x) = (1/N) sum_i phi_i(x),        phi_i(x) = K_h(x - X_i)  (with wall images),

so each robot can *track* it from its own kernel ``phi_i`` and messages from its
neighbours (Zheng and Lin, arXiv 2009.05366 / 2106.05318), run the project's fast density
filter on what it tracks, and move by the paper's law evaluated on its own estimate.

Communication graph. Robots ``i != j`` are neighbours when ``|X_i - X_j| <= r`` (radius
graph) or when either is among the other's ``k`` nearest (symmetrised k-nearest graph);
recomputed every step from the positions (``scipy.spatial.cKDTree``). ``A`` is the
symmetric 0/1 adjacency, ``D = diag(deg)``, ``L = D - A`` the graph Laplacian with
eigenvalues ``0 = lambda_1 <= lambda_2 <= ... <= lambda_N``; ``lambda_2 > 0`` iff the
graph is connected (the algebraic connectivity).

Dynamic average consensus (first-order form). Each robot keeps ``z_i`` (``F`` fields of
``M`` cells: its kernel, and with the per-robot gradient filter also the kernel's two
analytic derivatives). With ``W_t = I - eps_t L_t`` and ``m`` rounds per step,

    z_i(0)     = [W_0^{m_0} phi(0)]_i,
    z(t + 1)   = W_{t+1}^m ( z(t) + phi(t + 1) - phi(t) )                          (DAC)

(rows are robots; ``phi(t)`` the ``N x FM`` matrix of the robots' kernels at ``X(t)``;
``m_0`` the ``initial_rounds``, by default ``m``: with ``m_0 >> 1`` the robots agree
before they start moving). Robot ``i`` needs ``z_j`` of its neighbours once per round:
one message of ``F M`` floats per neighbour per round.

*Computing* ``W z``. All off-diagonal weights equal ``eps``, so ``(W z)_i = w_ii z_i +
eps S_i`` with the neighbour sum ``S_i``; visiting the robots along a Hilbert curve,
consecutive robots have nearly the same neighbours and ``S_i`` is the previous robot's
sum corrected by the symmetric difference of the two neighbourhoods
(:func:`_mix_uniform`, restarted every 64 robots): about ``4 r delta`` times the robot
density row operations instead of ``deg_i`` (``delta`` the step along the curve).

*Invariant.* ``L`` is symmetric with zero row and column sums, so ``1^T W = 1^T`` for
every graph and gain: ``1^T z(t + 1) = 1^T z(t) + 1^T phi(t + 1) - 1^T phi(t)``, and by
induction from ``1^T z(0) = 1^T phi(0)``,

    (1/N) sum_i z_i(t) = (1/N) sum_i phi_i(t) = p_KDE(t)     at every step, exactly,

whatever the graph does (it may change, disconnect, reconnect). The robots' mean
observation is the centralised one; consensus only distributes it.

*Error dynamics.* Let ``Pi = I - 1 1^T / N`` and ``e = Pi z`` the disagreement
(``z_i - p_KDE``). ``Pi`` commutes with ``W`` (both are polynomials in symmetric,
constant-preserving operators), so

    e(t + 1) = W^m ( e(t) + Pi (phi(t + 1) - phi(t)) ),
    ||e(t + 1)|| <= rho^m ( ||e(t)|| + ||Pi Delta phi|| ),
    rho = max(|1 - eps lambda_2|, |1 - eps lambda_N|)                (spectral radius on 1^perp).

On a fixed connected graph with a static swarm the error decays geometrically at the
rate ``rho^m`` per step, which is ``(1 - eps lambda_2)^m`` whenever ``eps (lambda_2 +
lambda_N) <= 2`` (always true for the default gain below when the graph is not
bipartite-like; the test uses a ring and checks both). With moving robots the error is
input-to-state stable with respect to the kernels' per-step change: asymptotically
``||e|| <= rho^m / (1 - rho^m) sup ||Pi Delta phi||``. Robots move ``~ 1e-3`` per step
against a bandwidth ``h = 0.04``, so ``Delta phi`` is small and one round per step
already tracks; the disconnected case (``lambda_2 = 0``) keeps the component averages
instead (each component tracks the mean over its members).

*Gain.* ``eps = gain / (1 + d_max)`` with ``d_max`` the largest degree of the current
graph and ``0 < gain <= 1`` (default 1). Then every entry of ``W`` is ``>= 0`` (``1 - eps
d_i >= 1 / (1 + d_max)``), ``W`` is doubly stochastic, and Gershgorin (``lambda_N <= 2
d_max``) gives ``|1 - eps lambda_N| < 1``: stable on every graph. On the complete graph
``eps = 1/N`` and ``W = 1 1^T / N``: one round is exact consensus, which the test of
equality with the centralised filter uses. A robot with no neighbours has ``W_ii = 1``
and tracks its own kernel.

*Why first order, not proportional-integral.* The PI form (Freeman, Yang and Lynch
2006) tolerates arbitrary initial states and robots joining or leaving, at the price of
a second state per robot (twice the memory and the messages) and a slower, oscillatory
transient. Here every robot starts with ``z_i(0) = phi_i(0)`` (it knows its own
position) and the swarm is fixed, so the first-order form keeps the invariant exactly
and its error is the ISS bound above.

Per-robot filters. Each robot runs the density filter of :mod:`harness.filters.local`
on ``y_i = z_i`` (density part): the same predict (exact state transition ``(I - dt
A)^{-1}``, variances by ``F1 o F1``) and diagonal update with ``R = r_scale k
diag(max(y_i, r_floor))``, vectorised over robots (compiled loop, one robot per
iteration, arrays ``(N, M)``). ``A`` is a 5-point operator, applied as fixed-offset
stencils on padded fields (:func:`stencil_coefficients`); the implicit predict is
solved by Jacobi sweeps with an a posteriori stop at a remainder below ``1e-15 ||x||_1``
(:func:`jacobi_sweeps`: ratio ``q ~ rho / 2`` against the Neumann series' ``rho``), by
one sparse LU with triangular solves over robots beyond ``_ROBOT_MAX_SWEEPS``. The
gradient estimate is either

* ``gradient="grid"`` (default): ``q_hat_i = G p_hat_i``, the grid gradient of the
  robot's own density estimate; only the density kernel is tracked (``F = 1``); or
* ``gradient="filter"``: the fast gradient filter per robot on the tracked analytic
  kernel gradient (``F = 3``), with the weighted-Poisson mean update solved by batched
  conjugate gradients, each robot preconditioned by the grid Laplacian's pseudo-inverse
  (dense cosine-transform products over all robots) scaled by its own information
  (:class:`BatchedPoisson`); a robot that does not reach the tolerance stops the run.

The applied ``A`` is the Fokker-Planck matrix of the velocity the robots are modelled to
follow; in the decentralised loop every robot moves on its own field, and the estimator
takes whatever ``A`` the caller supplies (it is the filters' model, shared by all).

Decentralised control. Robot ``i`` moves with the paper's law (eq. ``modified density
feedback law using estimates``) evaluated from its own estimates, at its own position:
the bilinear interpolant at ``X_i`` of the law's cell-centre values built from ``(p_hat_i,
q_hat_i)``, exactly what a centralised robot does with the broadcast field (so with exact
consensus the two loops coincide; only the four cells around ``X_i`` are evaluated).

Messages. A *message* is one vector of ``F M`` float64 values sent by one robot to one
neighbour in one consensus round. Per robot per step that is ``m deg_i`` messages, i.e.
``m deg_i F M`` floats or ``8 m deg_i F M`` bytes; :func:`message_counts` reports the
mean over robots (with a broadcast medium one transmission per round would do).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numba
import numpy as np
import scipy.fft as sfft
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from harness.filters.common import FilterSettings, MeasurementModel
from harness.filters.local import squared_transition
from harness.fokker_planck import _MAX_SERIES_TERMS, NumericalError, _series_terms
from harness.grid import Grid
from harness.kde import _IMAGE_CUTOFF
from harness.velocity import VelocityField

# --------------------------------------------------------------------------------------
# communication graph


@numba.njit(cache=True, nogil=True)
def _sort_rows_unique(indptr, indices, n):  # pragma: no cover - compiled
    """Sort every row of a symmetric CSR pattern (by :func:`_transpose_pattern`), drop
    duplicates and self-loops; returns the compacted ``(indptr, indices)``.
    """
    srt = _transpose_pattern(indptr, indices)
    out_ptr = np.zeros(n + 1, dtype=np.int64)
    out_idx = np.empty(indices.size, dtype=np.int32)
    pos = 0
    for i in range(n):
        last = -1
        for k in range(indptr[i], indptr[i + 1]):
            j = srt[k]
            if j != last and j != i:
                out_idx[pos] = j
                pos += 1
            last = j
        out_ptr[i + 1] = pos
    return out_ptr, out_idx[:pos].copy()


@numba.njit(cache=True, nogil=True)
def _radius_neighbours(px, py, radius):  # pragma: no cover - compiled
    """CSR (rows sorted by :func:`_transpose_pattern`) of the pairs ``i != j`` with
    ``sqrt(dx^2 + dy^2) <= radius``
    (the expression of ``scipy.spatial.distance.cdist``; ``dx^2 + dy^2`` decides unless
    it is within ``1e-12`` of ``radius^2``), by a cell list of square buckets of side
    ``>= radius / 2``: a robot's neighbours are in the 5 x 5 block of buckets around its
    own, less the buckets whose nearest point is farther than ``radius``.
    """
    n = px.size
    x0, y0 = px.min(), py.min()
    ext = max(px.max() - x0, py.max() - y0, 1e-300)
    nb = max(1, min(int(2.0 * ext / max(radius, 1e-300)), 512))  # buckets per side
    side = ext / nb
    reach = min(int(np.ceil(radius / side * (1.0 + 1e-9))), nb)  # buckets on each side
    bx = np.minimum(((px - x0) / side).astype(np.int64), nb - 1)
    by = np.minimum(((py - y0) / side).astype(np.int64), nb - 1)
    bucket = by * nb + bx
    start = np.zeros(nb * nb + 1, dtype=np.int64)
    for i in range(n):
        start[bucket[i] + 1] += 1
    for b in range(nb * nb):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    members = np.empty(n, dtype=np.int64)
    sx = np.empty(n)
    sy = np.empty(n)
    for i in range(n):
        k = fill[bucket[i]]
        members[k], sx[k], sy[k] = i, px[i], py[i]
        fill[bucket[i]] += 1
    r2lo = radius * radius * (1.0 - 1e-12)
    r2hi = radius * radius * (1.0 + 1e-12)
    indptr = np.zeros(n + 1, dtype=np.int64)
    indices = np.empty(max(16 * n, 1024), dtype=np.int32)
    buf = np.empty(n, dtype=np.int64)
    for i in range(n):
        cnt = 0
        xi, yi = px[i], py[i]
        for cy in range(max(by[i] - reach, 0), min(by[i] + reach + 1, nb)):
            # gaps to the bucket, less a margin for the rounding of the bucket bounds
            gy = max(y0 + cy * side - yi, yi - (y0 + (cy + 1) * side)) - 1e-9 * ext
            gy = max(gy, 0.0)
            for cx in range(max(bx[i] - reach, 0), min(bx[i] + reach + 1, nb)):
                gx = max(x0 + cx * side - xi, xi - (x0 + (cx + 1) * side)) - 1e-9 * ext
                gx = max(gx, 0.0)
                if gx * gx + gy * gy > r2hi:  # the whole bucket is out of reach
                    continue
                b = cy * nb + cx
                for k in range(start[b], start[b + 1]):
                    dx = xi - sx[k]
                    dy = yi - sy[k]
                    s = dx * dx + dy * dy
                    if s <= r2lo or (s <= r2hi and np.sqrt(s) <= radius):
                        j = members[k]
                        if j != i:
                            buf[cnt] = j
                            cnt += 1
        pos = indptr[i]
        if pos + cnt > indices.size:
            grown = np.empty(max(2 * indices.size, pos + cnt), dtype=np.int32)
            grown[:pos] = indices[:pos]
            indices = grown
        indices[pos : pos + cnt] = buf[:cnt]
        indptr[i + 1] = pos + cnt
    return indptr, _transpose_pattern(indptr, indices[: indptr[n]])


@numba.njit(cache=True, nogil=True)
def _transpose_pattern(indptr, indices):  # pragma: no cover - compiled
    """Column indices of the transpose of a symmetric pattern (same ``indptr``), which
    come out sorted: rows ``i`` are scattered in increasing order (a counting sort).
    """
    n = indptr.size - 1
    fill = indptr[:-1].copy()
    out = np.empty(indices.size, dtype=np.int32)
    for i in range(n):
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            out[fill[j]] = i
            fill[j] += 1
    return out


@numba.njit(cache=True, nogil=True)
def _symmetric_csr(n, rows, cols):  # pragma: no cover - compiled
    """CSR of the symmetrised edge list ``{(r, c), (c, r)}``: sorted rows, no duplicates,
    no self-loops.
    """
    indptr = np.zeros(n + 1, dtype=np.int64)
    for k in range(rows.size):
        indptr[rows[k] + 1] += 1
        indptr[cols[k] + 1] += 1
    for i in range(n):
        indptr[i + 1] += indptr[i]
    fill = indptr[:-1].copy()
    indices = np.empty(indptr[n], dtype=np.int32)
    for k in range(rows.size):
        indices[fill[rows[k]]] = cols[k]
        fill[rows[k]] += 1
        indices[fill[cols[k]]] = rows[k]
        fill[cols[k]] += 1
    return _sort_rows_unique(indptr, indices, n)


def _csr(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, n: int) -> sp.csr_matrix:
    """A CSR matrix from canonical arrays (sorted rows, no duplicates), unchecked."""
    out = sp.csr_matrix((data, indices.astype(np.int32, copy=False), indptr.astype(np.int32)),
                        shape=(n, n))  # fmt: skip
    out.has_sorted_indices = True
    return out


def communication_graph(
    positions: np.ndarray, radius: float | None = None, k_nearest: int | None = None
) -> sp.csr_matrix:
    """Symmetric 0/1 adjacency of the robots' communication graph, no self-loops.

    Radius graphs come from a compiled cell list (:func:`_radius_neighbours`), k-nearest
    graphs from ``scipy.spatial.cKDTree`` and a compiled symmetrisation; tests compare
    both with brute-force distance matrices.

    Args:
        positions: Robot positions ``(2, N)`` (length).
        radius: Neighbours within this distance (length), inclusive.
        k_nearest: Or: each robot links to its ``k`` nearest, then symmetrised (``i ~ j``
            if either is among the other's ``k`` nearest). Exactly one of the two.

    Returns:
        ``(N, N)`` CSR matrix with sorted indices and float entries 1.
    """
    if (radius is None) == (k_nearest is None):
        raise ValueError("give exactly one of radius and k_nearest")
    pts = np.asarray(positions, dtype=float)
    n = pts.shape[1]
    if radius is not None:
        if not radius >= 0:
            raise ValueError(f"radius must be >= 0, got {radius}")
        if n == 0:
            return sp.csr_matrix((0, 0))
        indptr, indices = _radius_neighbours(
            np.ascontiguousarray(pts[0]), np.ascontiguousarray(pts[1]), float(radius)
        )
    else:
        assert k_nearest is not None
        k = min(int(k_nearest), n - 1)
        if k < 0:
            raise ValueError(f"k_nearest must be >= 0, got {k_nearest}")
        if k == 0:
            rows = cols = np.empty(0, dtype=np.int64)
        else:
            _, idx = cKDTree(pts.T).query(pts.T, k + 1)
            rows = np.repeat(np.arange(n, dtype=np.int64), k)
            cols = idx[:, 1:].ravel().astype(np.int64)  # the first is the robot itself
        indptr, indices = _symmetric_csr(n, rows, cols)
    return _csr(indptr, indices, np.ones(indices.size), n)


def laplacian(adj: sp.csr_matrix) -> sp.csr_matrix:
    """Graph Laplacian ``L = D - A`` (CSR)."""
    deg = np.asarray(adj.sum(axis=1)).ravel()
    return (sp.diags(deg) - adj).tocsr()


def n_components(adj: sp.csr_matrix) -> int:
    """Number of connected components of the graph."""
    return int(csgraph.connected_components(adj, directed=False)[0])


def algebraic_connectivity(adj: sp.csr_matrix, dense_max: int = 400) -> float:
    """``lambda_2(L)``, the second-smallest Laplacian eigenvalue (0 if disconnected).

    Dense ``eigvalsh`` up to ``dense_max`` robots; above, ARPACK in shift-invert mode
    about ``-1e-3`` (the two eigenvalues nearest 0 of ``L``, factorised once).
    """
    n = adj.shape[0]
    if n < 2 or n_components(adj) > 1:
        return 0.0
    lap = laplacian(adj)
    if n <= dense_max:
        return float(np.linalg.eigvalsh(lap.toarray())[1])
    vals = spla.eigsh(lap.tocsc(), k=2, sigma=-1e-3, which="LM", return_eigenvectors=False)
    return float(np.sort(vals)[1])


@numba.njit(cache=True, nogil=True)
def _weights_csr(indptr, indices, eps):  # pragma: no cover - compiled
    """``W = I - eps L`` for a 0/1 adjacency in CSR (sorted rows): each row gets its
    diagonal ``1 - eps deg_i`` inserted in order; off-diagonal entries are ``eps``.
    """
    n = indptr.size - 1
    out_ptr = indptr + np.arange(n + 1)
    out_idx = np.empty(out_ptr[n], dtype=np.int32)
    out_val = np.full(out_ptr[n], eps)
    for i in range(n):
        pos = out_ptr[i]
        placed = False
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if not placed and j > i:
                out_idx[pos] = i
                out_val[pos] = 1.0 - eps * (indptr[i + 1] - indptr[i])
                pos += 1
                placed = True
            out_idx[pos] = j
            pos += 1
        if not placed:
            out_idx[pos] = i
            out_val[pos] = 1.0 - eps * (indptr[i + 1] - indptr[i])
    return out_ptr, out_idx, out_val


def consensus_weights(adj: sp.csr_matrix, gain: float = 1.0) -> tuple[sp.csr_matrix, float]:
    """``W = I - eps L`` with ``eps = gain / (1 + d_max)`` (see the module docstring).

    Compiled (:func:`_weights_csr`) for a canonical 0/1 adjacency, scipy otherwise.

    Returns:
        ``(W, eps)``; ``W`` is symmetric, doubly stochastic and non-negative for
        ``0 < gain <= 1``; its off-diagonal entries all equal ``eps``.
    """
    if not 0 < gain <= 1:
        raise ValueError(f"consensus gain must be in (0, 1], got {gain}")
    n = adj.shape[0]
    canonical = adj.format == "csr" and adj.has_canonical_format and bool(np.all(adj.data == 1.0))
    deg = np.diff(adj.indptr) if canonical else np.asarray(adj.sum(axis=1)).ravel()
    eps = float(gain / (1.0 + (deg.max() if deg.size else 0.0)))
    if canonical:
        indptr, indices, data = _weights_csr(adj.indptr, adj.indices, eps)
        return _csr(indptr, indices, data, n), eps
    w = (sp.identity(n, format="csr") - eps * laplacian(adj)).tocsr()
    w.sort_indices()
    return w, eps


# --------------------------------------------------------------------------------------
# compiled kernels (plain numpy statements in the docstrings; tests compare)


@numba.njit(cache=True, parallel=True, nogil=True)
def _spmm(indptr, indices, data, z, out):  # pragma: no cover - compiled
    """``out = W z`` for CSR ``W`` and dense ``z`` ``(N, F)``: rows in parallel, each
    row's sum in CSR order (deterministic for any thread count).
    """
    n, f = z.shape
    for i in numba.prange(n):
        for c in range(f):
            out[i, c] = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            w = data[k]
            for c in range(f):
                out[i, c] += w * z[j, c]


@numba.njit(cache=True, nogil=True)
def _hilbert_keys(px, py, bits):  # pragma: no cover - compiled
    """Index along a Hilbert curve of order ``bits`` through the bounding box of the
    points (the usual ``xy2d``: quadrant digit, then rotate/reflect the sub-square).
    """
    n = px.size
    side = 1 << bits
    x0, y0 = px.min(), py.min()
    ext = max(px.max() - x0, py.max() - y0, 1e-300)
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        x = min(int((px[i] - x0) / ext * side), side - 1)
        y = min(int((py[i] - y0) / ext * side), side - 1)
        d = 0
        s = side >> 1
        while s > 0:
            rx = 1 if (x & s) > 0 else 0
            ry = 1 if (y & s) > 0 else 0
            d += s * s * ((3 * rx) ^ ry)
            if ry == 0:
                if rx == 1:
                    x = side - 1 - x
                    y = side - 1 - y
                x, y = y, x
            s >>= 1
        keys[i] = d
    return keys


def spatial_order(positions: np.ndarray, bits: int = 10) -> np.ndarray:
    """Robots sorted along a Hilbert curve (consecutive robots are close in space)."""
    pts = np.asarray(positions, dtype=float)
    if pts.shape[1] == 0:
        return np.empty(0, dtype=np.intp)
    keys = _hilbert_keys(np.ascontiguousarray(pts[0]), np.ascontiguousarray(pts[1]), bits)
    return np.argsort(keys, kind="stable")


@numba.njit(cache=True, nogil=True)
def _uniform_offdiagonal(indptr, indices, data):  # pragma: no cover - compiled
    """The common value of all off-diagonal entries of a CSR matrix, or NaN if they
    differ (0 when there are none).
    """
    val = np.nan
    for i in range(indptr.size - 1):
        for k in range(indptr[i], indptr[i + 1]):
            if indices[k] != i:
                if val != val:
                    val = data[k]
                elif data[k] != val:
                    return np.nan
    return 0.0 if val != val else val


@numba.njit(cache=True, nogil=True)
def _symmetric_difference(indices, a0, a1, b0, b1, i, prev, ops, pos, limit):  # pragma: no cover
    """Walk the sorted rows ``a0:a1`` (robot ``i``) and ``b0:b1`` (robot ``prev``) of a
    matrix with diagonal entries: the open neighbourhoods ``N(i) = row(i) - {i}``,
    ``N(prev) = row(prev) - {prev}``. Records their symmetric difference in ``ops``
    from ``pos`` on (``j + 1`` for ``j`` in ``N(i) - N(prev)``, ``-(j + 1)`` for ``j`` in
    ``N(prev) - N(i)``) and returns its size, stopping at ``limit``.
    """
    big = np.iinfo(np.int64).max
    ka, kb, cnt = a0, b0, 0
    while (ka < a1 or kb < b1) and cnt < limit:
        ja = indices[ka] if ka < a1 else big
        jb = indices[kb] if kb < b1 else big
        op = 0
        if ja == jb:  # in both rows: differs only for i itself and prev itself
            if ja == i:
                op = -(ja + 1)
            elif ja == prev:
                op = ja + 1
            ka += 1
            kb += 1
        elif ja < jb:  # only in row(i)
            if ja != i:
                op = ja + 1
            ka += 1
        else:  # only in row(prev)
            if jb != prev:
                op = -(jb + 1)
            kb += 1
        if op != 0:
            ops[pos + cnt] = op
            cnt += 1
    return cnt


@numba.njit(cache=True, nogil=True)
def _add_rows(z, idx, k0, k1, sign, s):  # pragma: no cover - compiled
    """``s += sign sum_{k0 <= k < k1} z[idx[k]]``, four rows per pass over ``s``."""
    f = s.size
    k = k0
    while k + 4 <= k1:
        z1, z2, z3, z4 = z[idx[k]], z[idx[k + 1]], z[idx[k + 2]], z[idx[k + 3]]
        for c in range(f):
            s[c] += sign * ((z1[c] + z2[c]) + (z3[c] + z4[c]))
        k += 4
    while k < k1:
        z1 = z[idx[k]]
        for c in range(f):
            s[c] += sign * z1[c]
        k += 1


@numba.njit(cache=True, parallel=True, nogil=True)
def _mix_uniform(indptr, indices, data, eps, order, chunk, z, out):  # pragma: no cover
    """``out = W z`` for ``W`` whose off-diagonal entries all equal ``eps``:
    ``out_i = w_ii z_i + eps S_i`` with the neighbour sum ``S_i = sum_{j ~ i} z_j``.

    Robots are visited in ``order`` (a space-filling curve) in chunks of ``chunk``; in a
    chunk, ``S_i`` is updated from the previous robot's ``S`` by the symmetric
    difference of their neighbourhoods (``S_i = S_prev + sum_{N(i) - N(prev)} z_j -
    sum_{N(prev) - N(i)} z_j``) whenever that is shorter than ``N(i)``, and summed
    directly otherwise; each chunk starts directly. Rows are added four at a time
    (:func:`_add_rows`). Chunks are fixed, so the result does not depend on the number
    of threads. Rows of ``W`` must be sorted and hold the diagonal.
    """
    n, f = z.shape
    nch = (n + chunk - 1) // chunk
    for ch in numba.prange(nch):
        s = np.zeros(f)
        ops = np.empty(n, dtype=np.int64)
        plus = np.empty(n, dtype=np.int64)
        minus = np.empty(n, dtype=np.int64)
        prev = -1
        for kk in range(ch * chunk, min(n, (ch + 1) * chunk)):
            i = order[kk]
            a0, a1 = indptr[i], indptr[i + 1]
            diag = 0.0
            deg = 0
            for k in range(a0, a1):
                if indices[k] == i:
                    diag = data[k]
                else:
                    deg += 1
            cnt = deg
            if prev >= 0:
                b0, b1 = indptr[prev], indptr[prev + 1]
                cnt = _symmetric_difference(indices, a0, a1, b0, b1, i, prev, ops, 0, deg)
            n_plus = n_minus = 0
            if cnt >= deg:  # direct sum over N(i)
                for c in range(f):
                    s[c] = 0.0
                for k in range(a0, a1):
                    if indices[k] != i:
                        plus[n_plus] = indices[k]
                        n_plus += 1
            else:
                for k in range(cnt):
                    if ops[k] > 0:
                        plus[n_plus] = ops[k] - 1
                        n_plus += 1
                    else:
                        minus[n_minus] = -ops[k] - 1
                        n_minus += 1
            _add_rows(z, plus, 0, n_plus, 1.0, s)
            _add_rows(z, minus, 0, n_minus, -1.0, s)
            zi, oi = z[i], out[i]
            for c in range(f):
                oi[c] = diag * zi[c] + eps * s[c]
            prev = i


@numba.njit(cache=True, parallel=True, nogil=True)
def _add_kernel_increment(z, ky, kx, ky_old, kx_old, sign_old):  # pragma: no cover
    """``z[i] += outer(ky[i], kx[i]) + sign_old outer(ky_old[i], kx_old[i])`` (flattened
    ``(ny, nx)``), i.e. ``z += phi(t+1) - phi(t)`` for ``sign_old = -1``.
    """
    n, ny = ky.shape
    nx = kx.shape[1]
    for i in numba.prange(n):
        for j in range(ny):
            a = ky[i, j]
            b = sign_old * ky_old[i, j]
            base = j * nx
            for c in range(nx):
                z[i, base + c] += a * kx[i, c] + b * kx_old[i, c]


@numba.njit(cache=True, nogil=True)
def _series(indptr, indices, data, x, terms, total, term, tmp):  # pragma: no cover
    """``total = sum_{k <= terms} (dt A)^k x`` (``data`` holds ``dt A``), one robot."""
    m = x.size
    for r in range(m):
        total[r] = x[r]
        term[r] = x[r]
    for _ in range(terms):
        for r in range(m):
            s = 0.0
            for k in range(indptr[r], indptr[r + 1]):
                s += data[k] * term[indices[k]]
            tmp[r] = s
        for r in range(m):
            term[r] = tmp[r]
            total[r] += tmp[r]


@numba.njit(cache=True, nogil=True)
def _sq_apply(indptr, indices, sq, boost, v, out):  # pragma: no cover
    """``out = sq @ v + boost v``: ``(F1 o F1) v`` of ``squared_transition``."""
    for r in range(v.size):
        s = boost[r] * v[r]
        for k in range(indptr[r], indptr[r + 1]):
            s += sq[k] * v[indices[k]]
        out[r] = s


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
                                :func:`jacobi_sweeps`) until the remainder bound
                                ``q / (1 - q) ||term||_1 <= 1e-15 ||x||_1`` holds, at
                                most ``max_sweeps`` (none when ``max_sweeps < 0``:
                                ``x`` is predicted already),
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
    (``_series_terms(q)``), and ``|x - x_K| <= |y - y_K|`` as ``D >= 1``. About half the
    Neumann terms of ``sum (dt A)^k`` (whose ratio is ``rho = 2 max dt |a_rr|``).

    A posteriori: the ``k``-th term ``T^k b`` bounds the rest by ``q / (1 - q)
    ||T^k b||_1`` (each further term shrinks by ``q`` at least), so the filter stops
    as soon as that is below ``1e-15 ||b||_1``, never later than ``K``.
    """
    return _series_terms(jacobi_ratio(coef))


def stencil_coefficients(grid: Grid, a: sp.csr_matrix, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The 5-point stencils of ``dt A`` and of ``F1 o F1`` (``F1 = I + dt A``), each
    ``(5, M)`` with rows ``[centre, west, east, south, north]`` (west = cell ``r - 1``,
    south = cell ``r - nx``); entries for neighbours beyond the walls are 0.

    ``(F1 o F1) d`` is the diagonal of ``F1 diag(d) F1^T``: coefficients ``(dt a_rc)^2``
    off the diagonal and ``(dt a_rr)^2 + 1 + 2 dt a_rr`` on it (as
    :func:`harness.filters.local.squared_transition`).

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


@numba.njit(cache=True, parallel=True, nogil=True)
def _gradient_predict(xg, cg, indptr, indices, adt, sq, boost, terms, qkg):  # pragma: no cover
    """Per robot, in place: ``x_g^- = F x_g`` (series) and, per gradient component,
    ``1/C^- = (F1 o F1)(1/C) + q dt k_g`` (``cg`` rows hold both components, ``(N, 2M)``).
    """
    n, m = xg.shape
    for i in numba.prange(n):
        total = np.empty(m)
        term = np.empty(m)
        tmp = np.empty(m)
        inv = np.empty(m)
        _series(indptr, indices, adt, xg[i], terms, total, term, tmp)
        for c in range(m):
            xg[i, c] = total[c]
        for comp in range(2):
            for c in range(m):
                inv[c] = 1.0 / cg[i, comp * m + c]
            _sq_apply(indptr, indices, sq, boost, inv, tmp)
            for c in range(m):
                cg[i, comp * m + c] = 1.0 / (tmp[c] + qkg)


@numba.njit(cache=True, nogil=True)
def _grad_row(f, nx, ny, dx, dy, out):  # pragma: no cover
    """``out = G f`` for one flattened field (``Grid.gradient``: central differences,
    reflecting ghosts), ``out`` of length ``2M``.
    """
    m = nx * ny
    for j in range(ny):
        jm = max(j - 1, 0)
        jp = min(j + 1, ny - 1)
        for i in range(nx):
            im = max(i - 1, 0)
            ip = min(i + 1, nx - 1)
            out[j * nx + i] = (f[j * nx + ip] - f[j * nx + im]) / (2.0 * dx)
            out[m + j * nx + i] = (f[jp * nx + i] - f[jm * nx + i]) / (2.0 * dy)


@numba.njit(cache=True, nogil=True)
def _grad_t_row(g, nx, ny, dx, dy, out):  # pragma: no cover
    """``out = G^T g`` for one stacked gradient ``g`` (length ``2M``)."""
    m = nx * ny
    for r in range(m):
        out[r] = 0.0
    for j in range(ny):
        jm = max(j - 1, 0)
        jp = min(j + 1, ny - 1)
        for i in range(nx):
            im = max(i - 1, 0)
            ip = min(i + 1, nx - 1)
            a = g[j * nx + i] / (2.0 * dx)
            out[j * nx + ip] += a
            out[j * nx + im] -= a
            b = g[m + j * nx + i] / (2.0 * dy)
            out[jp * nx + i] += b
            out[jm * nx + i] -= b


@numba.njit(cache=True, parallel=True, nogil=True)
def _gradient_rhs(xg, yg, w, nx, ny, dx, dy, out):  # pragma: no cover
    """``out_i = G^T (w_i o (y_g,i - G x_g,i))``: the weighted-Poisson right-hand side."""
    n, m = xg.shape
    for i in numba.prange(n):
        g = np.empty(2 * m)
        _grad_row(xg[i], nx, ny, dx, dy, g)
        for r in range(2 * m):
            g[r] = w[i, r] * (yg[i, r] - g[r])
        _grad_t_row(g, nx, ny, dx, dy, out[i])


@numba.njit(cache=True, parallel=True, nogil=True)
def _lu_solve_columns(lp, li, lx, up, ui, ux, perm_r, perm_c, b, chunks):  # pragma: no cover
    """``x = A^{-1} b`` column by column for ``b`` ``(M, K)`` (columns are robots), from
    SuperLU's factors ``Pr A Pc = L U`` (CSC; ``L`` unit lower): ``c[perm_r] = b``,
    ``c <- L^{-1} c``, ``c <- U^{-1} c``, ``x = c[perm_c]``. Column chunks run in parallel;
    each column's arithmetic is fixed, so the result does not depend on the threads.
    """
    m, k = b.shape
    out = np.empty_like(b)
    step = (k + chunks - 1) // chunks
    for ch in numba.prange(chunks):
        lo = ch * step
        hi = min(k, lo + step)
        if lo >= hi:
            continue
        c = np.empty((m, hi - lo))
        for i in range(m):
            c[perm_r[i], :] = b[i, lo:hi]
        for j in range(m):
            for q in range(lp[j], lp[j + 1]):
                r = li[q]
                if r > j:
                    c[r, :] -= lx[q] * c[j, :]
        for j in range(m - 1, -1, -1):
            diag = 0.0
            for q in range(up[j], up[j + 1]):
                if ui[q] == j:
                    diag = ux[q]
            c[j, :] /= diag
            for q in range(up[j], up[j + 1]):
                r = ui[q]
                if r < j:
                    c[r, :] -= ux[q] * c[j, :]
        for i in range(m):
            out[i, lo:hi] = c[perm_c[i], :]
    return out


class RowSolver:
    """``A^{-1}`` applied to every row of an ``(N, M)`` array: one sparse LU (SuperLU,
    COLAMD), triangular solves compiled and vectorised over robots
    (:func:`_lu_solve_columns`); ``splu(A).solve`` is the reference (tests compare).
    """

    def __init__(self, a: sp.spmatrix, chunks: int | None = None, width: int = 16) -> None:
        lu = spla.splu(sp.csc_matrix(a))
        lo, up = lu.L.tocsc(), lu.U.tocsc()
        lo.sort_indices()
        up.sort_indices()
        self._args = (
            lo.indptr, lo.indices, lo.data, up.indptr, up.indices, up.data,
            lu.perm_r.astype(np.intp), lu.perm_c.astype(np.intp),
        )  # fmt: skip
        self.chunks, self.width = chunks, width

    def solve_rows(self, x: np.ndarray) -> np.ndarray:
        """``A^{-1} x_i`` for every row ``x_i``, shape ``(N, M)``; in ``chunks`` blocks
        of rows, by default blocks of ``width`` rows (a block's work array stays in
        cache).
        """
        b = np.ascontiguousarray(x.T)
        chunks = self.chunks or max(1, -(-b.shape[1] // self.width))
        return np.ascontiguousarray(_lu_solve_columns(*self._args, b, chunks).T)


# --------------------------------------------------------------------------------------
# per-robot kernels


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
    :func:`harness.kde.kernel_1d`: images of the robots within ``cutoff h`` of a
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
    ``(N, nx)``, ``(N, ny)``, ``(N, ny)``, with the wall images of :mod:`harness.kde`.

    Robot ``i``'s kernel on the grid is ``phi_i = outer(ky[i], kx[i])`` (1 / length^2),
    its gradient ``(outer(ky[i], dkx[i]), outer(dky[i], kx[i]))`` (1 / length^3); their
    means over robots are :meth:`harness.kde.KDE.exact`. Compiled with two exponentials
    per robot, axis and image (:func:`_gauss_run`); :func:`harness.kde.kernel_1d` is the
    reference (tests compare).
    """
    g = grid
    pts = np.asarray(positions, dtype=float)
    out = []
    for p, n, d, c, lo, hi in ((pts[0], g.nx, g.dx, g.x, g.x0, g.x1),
                               (pts[1], g.ny, g.dy, g.y, g.y0, g.y1)):  # fmt: skip
        out.append(
            _kernel_factors_1d(
                np.ascontiguousarray(p), float(c[0]), d, n, bandwidth, lo, hi, _IMAGE_CUTOFF
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


# --------------------------------------------------------------------------------------
# dynamic average consensus


class DynamicAverageConsensus:
    """First-order dynamic average consensus on the robots' kernels (eq. DAC in the
    module docstring), state ``z`` of shape ``(N, F M)``.

    Args:
        grid: The grid.
        bandwidth: Kernel bandwidth ``h`` (length).
        gradient: Track the kernel's gradient as well (``F = 3``) or not (``F = 1``).
        rounds: Consensus rounds per step ``m >= 1``.
        gain: ``eps = gain / (1 + d_max)``, ``0 < gain <= 1``.
        initial_rounds: Rounds ``m_0 >= 0`` at ``t = 0``, before the first estimate:
            ``z(0) = W_0^{m_0} phi(0)`` (default ``m``). With one round per step each
            robot's first estimate is nearly its own kernel; ``m_0`` rounds bring the
            disagreement down by ``rho^{m_0}`` before the robots start moving.
        chunk: Robots per chunk of the neighbour-sum product (:func:`_mix_uniform`).
    """

    def __init__(
        self,
        grid: Grid,
        bandwidth: float,
        gradient: bool = False,
        rounds: int = 1,
        gain: float = 1.0,
        initial_rounds: int | None = None,
        chunk: int = 64,
    ) -> None:
        if rounds < 1:
            raise ValueError(f"consensus rounds must be >= 1, got {rounds}")
        initial_rounds = rounds if initial_rounds is None else int(initial_rounds)
        if initial_rounds < 0:
            raise ValueError(f"initial rounds must be >= 0, got {initial_rounds}")
        self.grid, self.bandwidth, self.gradient = grid, bandwidth, gradient
        self.rounds, self.gain = int(rounds), gain
        self.initial_rounds, self.chunk = initial_rounds, int(chunk)
        self.fields = 3 if gradient else 1
        self.z: np.ndarray | None = None
        self._buf: np.ndarray | None = None
        self._factors: tuple[np.ndarray, ...] | None = None
        self.eps = 0.0

    def _increment(self, factors: tuple[np.ndarray, ...], old: tuple[np.ndarray, ...] | None):
        assert self.z is not None
        m = self.grid.size
        kx, dkx, ky, dky = factors
        parts = [(ky, kx)]
        if self.gradient:
            parts += [(ky, dkx), (dky, kx)]
        olds = [(ky, kx)] * len(parts)  # unused values when old is None (sign 0)
        if old is not None:
            okx, odkx, oky, odky = old
            olds = [(oky, okx)] + ([(oky, odkx), (odky, okx)] if self.gradient else [])
        sign = -1.0 if old is not None else 0.0
        for f, ((a, b), (oa, ob)) in enumerate(zip(parts, olds, strict=True)):
            # a column block of z (strided rows): the kernel takes any layout
            _add_kernel_increment(self.z[:, f * m : (f + 1) * m], a, b, oa, ob, sign)

    def _mix(self, w: sp.csr_matrix, rounds: int, positions: np.ndarray) -> None:
        """``z <- W^rounds z``: by neighbour sums along a space-filling curve
        (:func:`_mix_uniform`) when ``W``'s off-diagonal entries are all equal (always
        for :func:`consensus_weights`), by the general sparse product otherwise.
        """
        assert self.z is not None and self._buf is not None
        if not w.has_sorted_indices:
            w = w.copy()
            w.sort_indices()
        eps = _uniform_offdiagonal(w.indptr, w.indices, w.data)
        order = spatial_order(positions) if np.isfinite(eps) else None
        for _ in range(rounds):
            if order is not None:
                _mix_uniform(w.indptr, w.indices, w.data, eps, order, self.chunk, self.z, self._buf)
            else:
                _spmm(w.indptr, w.indices, w.data, self.z, self._buf)
            self.z, self._buf = self._buf, self.z

    def kde(self) -> tuple[np.ndarray, np.ndarray]:
        """The exact KDE of the current positions, ``(p, grad p)`` of shapes ``(ny, nx)``
        and ``(2, ny, nx)``: the mean of the robots' kernels, from the factors the last
        step computed (:meth:`harness.kde.KDE.exact` without evaluating them again).
        """
        assert self._factors is not None, "call initialize first"
        kx, dkx, ky, dky = self._factors
        n = kx.shape[0]
        return ky.T @ kx / n, np.stack([ky.T @ dkx / n, dky.T @ kx / n])

    def initialize(self, positions: np.ndarray, w: sp.csr_matrix) -> np.ndarray:
        """``z(0) = W^{m_0} phi(0)`` (``m_0`` initial rounds); returns ``z`` ``(N, F M)``."""
        n = positions.shape[1]
        self.z = np.zeros((n, self.fields * self.grid.size))
        self._buf = np.empty_like(self.z)
        self._factors = kernel_factors(self.grid, positions, self.bandwidth)
        self._increment(self._factors, None)
        self._mix(w, self.initial_rounds, positions)
        return self.z

    def step(self, positions: np.ndarray, w: sp.csr_matrix) -> np.ndarray:
        """``z <- W^m (z + phi(t+1) - phi(t))``; returns ``z``."""
        assert self.z is not None and self._factors is not None, "call initialize first"
        factors = kernel_factors(self.grid, positions, self.bandwidth)
        self._increment(factors, self._factors)
        self._factors = factors
        self._mix(w, self.rounds, positions)
        return self.z

    def reference_step(
        self, z: np.ndarray, phi_new: np.ndarray, phi_old: np.ndarray, w: sp.csr_matrix
    ) -> np.ndarray:
        """Plain statement of :meth:`step`: ``W^m (z + phi_new - phi_old)`` (scipy)."""
        out = z + phi_new - phi_old
        for _ in range(self.rounds):
            out = w @ out
        return out


# --------------------------------------------------------------------------------------
# per-robot filters


@numba.njit(cache=True, parallel=True, nogil=True)
def _weighted_laplacian_columns(d, c, nx, ny, dx, dy, g, out):  # pragma: no cover
    """``out[:, k] = G^T diag(c[:, k]) G d[:, k]`` for every robot ``k`` (columns), cells
    in rows (robots last, so the inner loops run along contiguous robots). ``g`` is a
    ``(2M, N)`` work array. ``G`` is :meth:`harness.grid.Grid.gradient` (central
    differences, reflecting ghosts: the neighbour beyond a wall is the cell itself);
    ``G^T`` is applied as a gather, so rows run in parallel without races and every
    value is summed in a fixed order.
    """
    m = nx * ny
    n = d.shape[1]
    for j in numba.prange(ny):
        jm = max(j - 1, 0)
        jp = min(j + 1, ny - 1)
        for i in range(nx):
            im = max(i - 1, 0)
            ip = min(i + 1, nx - 1)
            cell = j * nx + i
            for k in range(n):
                g[cell, k] = c[cell, k] * (d[j * nx + ip, k] - d[j * nx + im, k]) / (2.0 * dx)
                g[m + cell, k] = (
                    c[m + cell, k] * (d[jp * nx + i, k] - d[jm * nx + i, k]) / (2.0 * dy)
                )
    for j in numba.prange(ny):
        for i in range(nx):
            cell = j * nx + i
            for k in range(n):
                out[cell, k] = 0.0
            # x: cell i is the right neighbour of i - 1 (and of itself at the right
            # wall), the left neighbour of i + 1 (and of itself at the left wall)
            if i >= 1:
                for k in range(n):
                    out[cell, k] += g[cell - 1, k] / (2.0 * dx)
            if i == nx - 1:
                for k in range(n):
                    out[cell, k] += g[cell, k] / (2.0 * dx)
            if i <= nx - 2:
                for k in range(n):
                    out[cell, k] -= g[cell + 1, k] / (2.0 * dx)
            if i == 0:
                for k in range(n):
                    out[cell, k] -= g[cell, k] / (2.0 * dx)
            if j >= 1:
                for k in range(n):
                    out[cell, k] += g[m + cell - nx, k] / (2.0 * dy)
            if j == ny - 1:
                for k in range(n):
                    out[cell, k] += g[m + cell, k] / (2.0 * dy)
            if j <= ny - 2:
                for k in range(n):
                    out[cell, k] -= g[m + cell + nx, k] / (2.0 * dy)
            if j == 0:
                for k in range(n):
                    out[cell, k] -= g[m + cell, k] / (2.0 * dy)


class BatchedPoisson:
    """Solves ``(G^T diag(c_i) G) delta_i = b_i``, ``sum delta_i = 0``, for every robot
    ``i`` by conjugate gradients, each robot preconditioned with ``S_i^{-1/2} (G^T G)^+
    S_i^{-1/2}``, ``S_i`` the local mean of ``c_i`` that scales the operator's diagonal
    (:meth:`diagonal_weights`).

    ``G^T G`` is diagonal in the orthonormal DCT-II basis, so its pseudo-inverse is two
    transforms; for ``N`` robots on a small grid they are dense products with the
    ``n x n`` DCT matrices over all robots at once. The iteration keeps cells in rows and
    robots in columns, so each product is one large matrix product and the operator a
    compiled pass along contiguous robots (:func:`_weighted_laplacian_columns`). The
    scaling takes out each robot's own range of information (a factor of about 25
    across the domain mid-run); what is left sets the iteration count (about 35 for a
    relative residual of ``1e-10`` mid-run at paper scale, ``python -m
    benchmarks.distributed --gradient-filter``). A robot stops when its residual is
    below ``tol`` relative to ``b_i``; a robot that has not, or whose iteration broke
    down above it, stops the run (:class:`~harness.fokker_planck.NumericalError`). The
    result is reproducible for the same robots; a robot's bits may differ at round-off
    with the batch it is solved in (the blocking of the batched matrix products).
    """

    def __init__(self, grid: Grid, tol: float = 1e-10) -> None:
        from harness.filters.local import _gradient_eigenvalues

        self.grid, self.tol = grid, tol
        self.g = grid.gradient_matrix.tocsr()
        self.gt = self.g.T.tocsr()
        lam = (
            _gradient_eigenvalues(grid.ny, grid.dy)[:, None]
            + _gradient_eigenvalues(grid.nx, grid.dx)[None, :]
        )
        keep = lam > 1e-12 * lam.max()
        self._inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)[:, :, None]
        self._cx = sfft.dct(np.eye(grid.nx), type=2, norm="ortho", axis=0)
        self._cy = sfft.dct(np.eye(grid.ny), type=2, norm="ortho", axis=0)
        # contiguous transposes: the batched products fall back to slow loops otherwise
        self._cx_t = np.ascontiguousarray(self._cx.T)
        self._cy_t = np.ascontiguousarray(self._cy.T)
        self._work: tuple[np.ndarray, ...] | None = None
        self.iterations = 0

    def diagonal_weights(self, c: np.ndarray) -> np.ndarray:
        """``S_i`` ``(N, M)``: per cell, the mean of the four gradient-grid weights that
        enter its diagonal entry of ``G^T diag(c_i) G`` (central differences: ``c_x`` of
        the left and right neighbours, ``c_y`` of the lower and upper ones; a wall cell
        uses itself for the missing one), so that on square cells (``dx = dy``) ``S_i``
        times the unweighted diagonal is the weighted one in the interior. (The plain
        per-cell mean of ``c_i`` needs about 50 rather than 35 iterations mid-run at
        paper scale.) Rows are robots.
        """
        g = self.grid
        n = c.shape[0]
        cx = c[:, : g.size].reshape(n, g.ny, g.nx)
        cy = c[:, g.size :].reshape(n, g.ny, g.nx)
        s = np.empty((n, g.ny, g.nx))
        s[:, :, 1:-1] = cx[:, :, :-2] + cx[:, :, 2:]
        s[:, :, 0] = cx[:, :, 0] + cx[:, :, 1]
        s[:, :, -1] = cx[:, :, -2] + cx[:, :, -1]
        s[:, 1:-1, :] += cy[:, :-2, :] + cy[:, 2:, :]
        s[:, 0, :] += cy[:, 0, :] + cy[:, 1, :]
        s[:, -1, :] += cy[:, -2, :] + cy[:, -1, :]
        return 0.25 * s.reshape(n, g.size)

    def _buffers(self, n: int) -> tuple[np.ndarray, ...]:
        """Work arrays for ``n`` robots (cells by robots), kept between calls."""
        m = self.grid.size
        if self._work is None or self._work[0].shape[1] != n:
            self._work = (np.empty((m, n)), np.empty((m, n)), np.empty((2 * m, n)))
        return self._work

    def pinv_columns(self, r: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``out[:, k] = (G^T G)^+ r[:, k]`` for cells by robots ``(M, N)`` (four dense
        products with the DCT matrices; ``out`` may be ``r``).
        """
        g = self.grid
        n = r.shape[1]
        _, b, _ = self._buffers(n)
        np.matmul(self._cy, r.reshape(g.ny, g.nx * n), out=b.reshape(g.ny, g.nx * n))  # y
        coef = out.reshape(g.ny, g.nx, n)
        np.matmul(self._cx, b.reshape(g.ny, g.nx, n), out=coef)  # x, per row of modes
        coef *= self._inv
        np.matmul(self._cx_t, coef, out=b.reshape(g.ny, g.nx, n))
        np.matmul(self._cy_t, b.reshape(g.ny, g.nx * n), out=out.reshape(g.ny, g.nx * n))
        return out

    def laplacian_pinv(self, r: np.ndarray) -> np.ndarray:
        """``(G^T G)^+ r_i`` for every row of ``r`` ``(N, M)`` (robots in rows)."""
        cols = np.array(r.T, dtype=float, order="C")  # a copy: never a view of r
        return np.ascontiguousarray(self.pinv_columns(cols, cols).T)

    def solve(self, c: np.ndarray, b: np.ndarray, maxiter: int = 500) -> np.ndarray:
        """Zero-mean solutions ``(N, M)`` for information ``c`` ``(N, 2M)``, ``b`` ``(N, M)``
        (robots in rows; the iteration runs on the transposes).

        Raises:
            NumericalError: A robot's residual is not below ``tol`` after ``maxiter``
                iterations (the estimate would not be the filter's).
        """
        g = self.grid
        n = b.shape[0]
        top = np.max(np.abs(b), axis=1)
        if not np.isfinite(top).all():
            raise NumericalError("gradient update: a robot's right-hand side is not finite")
        if not (np.isfinite(c).all() and (c > 0.0).all()):
            raise NumericalError(
                "gradient update: a robot's information is not finite and positive"
            )
        # each robot's right-hand side divided by a power of two near its largest entry
        # (the largest entry scaled into [1, 2)): exact, and its inner products cannot
        # overflow
        unit = np.where(top > 0.0, np.ldexp(1.0, np.frexp(top)[1] - 1), 1.0)
        ct = np.ascontiguousarray(c.T)
        scale = np.ascontiguousarray((1.0 / np.sqrt(self.diagonal_weights(c))).T)
        r = np.array(b.T / unit, dtype=float, order="C")
        _, _, work = self._buffers(n)
        z, ad = np.empty_like(r), np.empty_like(r)

        def precondition() -> None:
            np.multiply(scale, r, out=z)
            self.pinv_columns(z, z)
            np.multiply(z, scale, out=z)

        x = np.zeros_like(r)
        b_norm = np.sqrt(np.einsum("ij,ij->j", r, r))
        active = b_norm > 0.0
        precondition()
        d = z.copy()
        rz = np.einsum("ij,ij->j", r, z)
        its = 0
        while active.any() and its < maxiter:
            its += 1
            _weighted_laplacian_columns(d, ct, g.nx, g.ny, g.dx, g.dy, work, ad)
            curv = np.einsum("ij,ij->j", d, ad)
            # a robot whose preconditioned residual vanished has converged to round-off
            active &= (rz > 0.0) & (curv > 0.0)
            step = np.where(active, rz / np.where(active, curv, 1.0), 0.0)
            x += step * d
            r -= step * ad
            active &= np.sqrt(np.einsum("ij,ij->j", r, r)) > self.tol * b_norm
            if not active.any():
                break
            precondition()
            rz_new = np.einsum("ij,ij->j", r, z)
            beta = np.where(active, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
            d *= beta
            d += z
            rz = rz_new
        self.iterations = its
        # every robot, also one whose iteration stopped on a vanishing r^T z or d^T A d:
        # its residual off the constants (the part of b along them cannot be reduced)
        r -= r.mean(axis=0)
        off = np.sqrt(np.einsum("ij,ij->j", r, r))
        failed = ~(off <= self.tol * b_norm)
        if failed.any():
            raise NumericalError(
                f"gradient update: {int(failed.sum())} robots' Poisson solves did not "
                f"reach the tolerance in {its} iterations"
            )
        x -= x.mean(axis=0)
        x *= unit
        return np.ascontiguousarray(x.T)


_ROBOT_MAX_SWEEPS = 60
"""Above this many Jacobi sweeps the per-robot predict uses one sparse LU and
triangular solves vectorised over robots (a sweep costs about 1/80 of the LU path at
``n = 30``, measured with ``python -m benchmarks.distributed``)."""


class RobotFilters:
    """Per-robot fast filters (:class:`harness.filters.local.LocalFilters`, vectorised
    over robots): density estimates ``x`` and variances ``d`` of shape ``(N, M)``; with
    ``gradient="filter"`` also ``x_g`` ``(N, M)`` and gradient-grid information ``c_g``
    ``(N, 2M)``.

    Args:
        grid: The grid.
        dt: Step (s).
        measurement: The swarm's KDE measurement model (``N``, ``h``, settings): each
            robot's tracked observation has the centralised KDE's noise.
        gradient: ``"grid"`` (``q_hat_i = G p_hat_i``) or ``"filter"``.
    """

    def __init__(
        self, grid: Grid, dt: float, measurement: MeasurementModel, gradient: str = "grid"
    ) -> None:
        if gradient not in ("grid", "filter"):
            raise ValueError(f"gradient must be 'grid' or 'filter', got {gradient!r}")
        self.grid, self.dt, self.measurement, self.gradient = grid, dt, measurement, gradient
        self.settings: FilterSettings = measurement.settings
        self.poisson = BatchedPoisson(grid)
        self.max_sweeps = _ROBOT_MAX_SWEEPS
        self.x: np.ndarray | None = None
        self.d: np.ndarray | None = None
        self.x_g: np.ndarray | None = None
        self.c_g: np.ndarray | None = None

    def initialize(self, y: np.ndarray, y_g: np.ndarray | None = None) -> None:
        """``x0 = y``, ``P0 = initial_variance k``; gradient as in ``LocalFilters``.

        Args:
            y: Observations ``(N, M)`` (1 / length^2).
            y_g: Gradient observations ``(N, 2M)`` (1 / length^3), for ``"filter"``.
        """
        s, g = self.settings, self.grid
        k, k_g = self.measurement.constants
        n = y.shape[0]
        self.x = np.array(y, dtype=float)
        self.d = np.full((n, g.size), s.initial_variance * k)
        if self.gradient == "filter":
            assert y_g is not None
            self.c_g = np.full((n, 2 * g.size), 1.0 / (s.initial_variance * k_g))
            rhs = np.asarray(y_g) @ self.poisson.g  # rows: G^T y_g,i
            fit = self.poisson.solve(np.ones((n, 2 * g.size)), np.ascontiguousarray(rhs))
            self.x_g = fit + 1.0 / g.area

    def step(self, y: np.ndarray, a: sp.csr_matrix, y_g: np.ndarray | None = None) -> None:
        """Predict under ``A`` and update with the observations (in place)."""
        assert self.x is not None and self.d is not None, "call initialize first"
        s, dt, g = self.settings, self.dt, self.grid
        k, k_g = self.measurement.constants
        a = a.tocsr()
        a.sort_indices()
        coef, sqcoef = stencil_coefficients(g, a, dt)
        sweeps = jacobi_sweeps(coef)
        if sweeps > self.max_sweeps:  # sparse LU (as implicit_solve), then no sweeps
            self.x = RowSolver(sp.identity(g.size, format="csr") - dt * a).solve_rows(self.x)
            sweeps = -1
        q = s.process_noise * dt
        y = np.ascontiguousarray(y, dtype=float)
        _density_filter_stencil(
            self.x, self.d, y, coef, 1.0 / (1.0 - coef[0]), sqcoef, g.nx,
            jacobi_ratio(coef), sweeps, q * k, s.r_scale * k, s.r_floor, 16,
        )  # fmt: skip
        if self.gradient == "filter":
            assert self.x_g is not None and self.c_g is not None and y_g is not None
            terms = _series_terms(dt * 2.0 * float(np.max(np.abs(a.diagonal()), initial=0.0)))
            if terms > _MAX_SERIES_TERMS:  # as implicit_solve: sparse LU, then no series
                solver = RowSolver(sp.identity(g.size, format="csr") - dt * a)
                self.x_g = solver.solve_rows(self.x_g)
                terms = 0
            _gradient_predict(
                self.x_g, self.c_g, a.indptr, a.indices, dt * a.data, (dt * a.data) ** 2,
                1.0 + 2.0 * dt * a.diagonal(), terms, q * k_g,
            )  # fmt: skip
            one = 1.0 / (s.r_scale * k_g * np.maximum(y, s.r_floor))
            w_g = np.concatenate([one, one], axis=1)
            self.c_g += w_g
            rhs = np.empty_like(self.x_g)
            yg = np.ascontiguousarray(y_g, dtype=float)
            _gradient_rhs(self.x_g, yg, w_g, g.nx, g.ny, g.dx, g.dy, rhs)
            self.x_g += self.poisson.solve(self.c_g, rhs)

    @property
    def q_hat(self) -> np.ndarray:
        """Gradient estimates ``(N, 2M)``: ``G x_g,i`` (filter) or ``G p_hat_i`` (grid)."""
        src = self.x_g if self.gradient == "filter" else self.x
        assert src is not None
        return np.asarray(src @ self.poisson.gt)


def density_filter_reference(
    x: np.ndarray, d: np.ndarray, y: np.ndarray, a: sp.csr_matrix, dt: float,
    measurement: MeasurementModel,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Plain numpy statement of the density step of :class:`RobotFilters` for rows
    ``(N, M)`` (the density part of ``LocalFilters.step``, with scipy products).
    """
    from harness.fokker_planck import implicit_solve

    s = measurement.settings
    k, _ = measurement.constants
    xm = implicit_solve(a, dt, x.T).T
    dm = squared_transition(a, dt, d.T).T + s.process_noise * dt * k
    r = s.r_scale * k * np.maximum(y, s.r_floor)
    dp = 1.0 / (1.0 / dm + 1.0 / r)
    return xm + dp / r * (y - xm), dp


# --------------------------------------------------------------------------------------
# decentralised control


class CellLaw(Protocol):
    """A control law's cell-centre values at given cells (``Control.at_cells``)."""

    def __call__(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(vx, vy)`` (length / s) at flat ``cells`` from the estimates there."""
        ...


def decentralised_velocities(
    grid: Grid,
    law: CellLaw,
    p_hat: np.ndarray,
    positions: np.ndarray,
    q_hat: np.ndarray | None = None,
) -> np.ndarray:
    """Each robot's velocity from its own estimates at its own position, ``(2, N)``
    (length / time).

    Robot ``i`` evaluates the law's cell-centre values (``law``, a control's
    ``at_cells``; for the paper's law eq. ``modified density feedback law using
    estimates``,

        v_i = -alpha (p_* q_hat_i - p_hat_i grad p_*) / p_*^2 + sigma grad p_* / p_*)

    at the four cell centres around ``X_i`` from ``(p_hat_i, q_hat_i)`` there, and
    interpolates bilinearly as :func:`harness.agents.interpolate` does (nearest values
    beyond the outer centres): what a robot of the centralised loop does with the
    broadcast field, with its own estimate in place of the broadcast one.

    Args:
        law: ``(p, qx, qy, cells) -> (vx, vy)`` at flat cell indices.
        p_hat: Robots' density estimates ``(N, M)`` (1 / length^2).
        positions: ``(2, N)`` (length).
        q_hat: Gradient estimates ``(N, 2M)`` (1 / length^3); None for the grid
            gradient ``G p_hat_i`` (evaluated only at the four cells).
    """
    g = grid
    n = positions.shape[1]
    u = np.clip((positions[0] - g.x0) / g.dx - 0.5, 0.0, g.nx - 1)
    w = np.clip((positions[1] - g.y0) / g.dy - 0.5, 0.0, g.ny - 1)
    i0 = np.minimum(u.astype(np.intp), g.nx - 2)
    j0 = np.minimum(w.astype(np.intp), g.ny - 2)
    fx, fy = u - i0, w - j0
    ci = np.stack([i0, i0 + 1, i0, i0 + 1], axis=1)  # (N, 4): corners 00, 10, 01, 11
    cj = np.stack([j0, j0, j0 + 1, j0 + 1], axis=1)
    cells = cj * g.nx + ci
    rows = np.arange(n)[:, None]
    p = p_hat[rows, cells]
    if q_hat is None:
        ip, im = np.minimum(ci + 1, g.nx - 1), np.maximum(ci - 1, 0)
        jp, jm = np.minimum(cj + 1, g.ny - 1), np.maximum(cj - 1, 0)
        # the grid gradient G (harness.grid.Grid.gradient), reflecting ghost cells
        qx = (p_hat[rows, cj * g.nx + ip] - p_hat[rows, cj * g.nx + im]) / (2 * g.dx)
        qy = (p_hat[rows, jp * g.nx + ci] - p_hat[rows, jm * g.nx + ci]) / (2 * g.dy)
    else:
        qx = q_hat[rows, cells]
        qy = q_hat[rows, g.size + cells]
    vx, vy = law(p, qx, qy, cells)
    out = np.empty((2, n))
    for c, v in enumerate((vx, vy)):
        out[c] = (v[:, 0] + fx * (v[:, 1] - v[:, 0])) * (1 - fy) + (
            v[:, 2] + fx * (v[:, 3] - v[:, 2])
        ) * fy
    return out


def decentralised_velocities_reference(
    grid: Grid,
    control: Callable[[np.ndarray, np.ndarray], VelocityField],
    p_hat: np.ndarray,
    positions: np.ndarray,
    q_hat: np.ndarray | None = None,
) -> np.ndarray:
    """Plain statement of :func:`decentralised_velocities`: per robot the full field of
    ``control`` (a control law on fields) and :func:`harness.agents.interpolate` at
    ``X_i``.
    """
    from harness.agents import interpolate

    out = np.empty((2, positions.shape[1]))
    for i in range(positions.shape[1]):
        p = p_hat[i].reshape(grid.shape)
        q = grid.gradient(p) if q_hat is None else q_hat[i].reshape(2, *grid.shape)
        v = control(p, q)
        out[:, i] = interpolate(grid, v.centres, positions[:, i : i + 1])[:, 0]
    return out


def euler_maruyama_robots(
    grid: Grid,
    positions: np.ndarray,
    velocities: np.ndarray,
    sigma: float,
    dt: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """In place: ``X <- R(X + v_i dt + sqrt(2 sigma dt) xi)`` with per-robot velocities
    ``(2, N)`` (the step of :meth:`harness.agents.Swarm.step_reference`, same draws).
    """
    from harness.agents import reflect

    noise = rng.standard_normal(positions.shape) * np.sqrt(2.0 * sigma * dt)
    positions += velocities * dt + noise
    reflect(positions[0], grid.x0, grid.x1)
    reflect(positions[1], grid.y0, grid.y1)
    return positions


# --------------------------------------------------------------------------------------
# metrics


def consensus_l2(grid: Grid, p_hat: np.ndarray) -> float:
    """Mean over robots of ``||p_hat_i - mean_j p_hat_j||`` (1 / length)."""
    dev = p_hat - p_hat.mean(axis=0)
    return float(np.mean(np.sqrt(np.einsum("ij,ij->i", dev, dev) * grid.cell_area)))


def central_gap_l2(grid: Grid, p_hat: np.ndarray, p_central: np.ndarray) -> float:
    """Mean over robots of ``||p_hat_i - p_hat_central||`` (1 / length)."""
    dev = p_hat - np.asarray(p_central).ravel()
    return float(np.mean(np.sqrt(np.einsum("ij,ij->i", dev, dev) * grid.cell_area)))


@numba.njit(cache=True, parallel=True, nogil=True)
def _row_distances(x, a, b, out_a, out_b):  # pragma: no cover - compiled
    """``out_a[i] = sum_j (x_ij - a_j)^2`` and ``out_b[i]`` likewise with ``b``, one
    pass over ``x`` (parallel over rows).
    """
    n, m = x.shape
    for i in numba.prange(n):
        sa = 0.0
        sb = 0.0
        for j in range(m):
            da = x[i, j] - a[j]
            db = x[i, j] - b[j]
            sa += da * da
            sb += db * db
        out_a[i] = sa
        out_b[i] = sb


def estimate_spread(grid: Grid, p_hat: np.ndarray, p_central: np.ndarray) -> tuple[float, float]:
    """``(consensus_l2, central_gap_l2)`` of :func:`consensus_l2` and
    :func:`central_gap_l2` in one compiled pass over the robots' estimates (tested
    against them).
    """
    x = np.ascontiguousarray(p_hat, dtype=float)
    mean = x.mean(axis=0)
    central = np.ascontiguousarray(p_central, dtype=float).ravel()
    to_mean, to_central = np.empty(x.shape[0]), np.empty(x.shape[0])
    _row_distances(x, mean, central, to_mean, to_central)
    area = grid.cell_area
    return float(np.mean(np.sqrt(to_mean * area))), float(np.mean(np.sqrt(to_central * area)))


def message_counts(adj: sp.csr_matrix, rounds: int, floats_per_message: int) -> dict[str, float]:
    """Communication per robot per step (means over robots; see the module docstring).

    Returns:
        ``messages`` (messages / robot / step), ``floats`` (float64 values / robot /
        step), ``bytes`` (bytes / robot / step) and ``mean_degree``.
    """
    deg = float(adj.nnz) / adj.shape[0]
    msgs = rounds * deg
    return {
        "messages": msgs,
        "floats": msgs * floats_per_message,
        "bytes": 8.0 * msgs * floats_per_message,
        "mean_degree": deg,
    }


# --------------------------------------------------------------------------------------
# the estimator


@dataclass(frozen=True)
class DistributedEstimate:
    """The robots' estimates after a step.

    Attributes:
        p_hat: ``(N, M)`` density estimates (1 / length^2).
        q_hat: ``(N, 2M)`` gradient estimates (1 / length^3), or None (grid gradient,
            computed on demand by :attr:`RobotFilters.q_hat`).
        observation: ``(N, M)`` tracked observations ``z_i`` (density part).
        adjacency: The step's communication graph.
        eps: The step's consensus gain.
    """

    p_hat: np.ndarray
    q_hat: np.ndarray | None
    observation: np.ndarray
    adjacency: sp.csr_matrix
    eps: float


class RobotEstimators:
    """Graph + dynamic average consensus + per-robot fast filters.

    Args:
        grid: The grid.
        dt: Step (s).
        n_robots: ``N`` (each robot knows it; it sets ``k``, ``k_g``).
        bandwidth: KDE bandwidth ``h`` (length).
        settings: Filter settings.
        radius: Communication radius (length), or
        k_nearest: number of nearest neighbours (exactly one of the two).
        rounds: Consensus rounds per step.
        gain: Consensus gain factor in ``(0, 1]``.
        gradient: ``"grid"`` or ``"filter"`` (see the module docstring).
        initial_rounds: Consensus rounds at ``t = 0`` before the first estimate
            (default ``rounds``; see :class:`DynamicAverageConsensus`).
    """

    def __init__(
        self,
        grid: Grid,
        dt: float,
        n_robots: int,
        bandwidth: float,
        settings: FilterSettings,
        radius: float | None = None,
        k_nearest: int | None = None,
        rounds: int = 1,
        gain: float = 1.0,
        gradient: str = "grid",
        initial_rounds: int | None = None,
    ) -> None:
        if (radius is None) == (k_nearest is None):
            raise ValueError("give exactly one of radius and k_nearest")
        self.grid, self.radius, self.k_nearest = grid, radius, k_nearest
        self.consensus = DynamicAverageConsensus(
            grid, bandwidth, gradient=gradient == "filter", rounds=rounds, gain=gain,
            initial_rounds=initial_rounds,
        )  # fmt: skip
        self.filters = RobotFilters(
            grid, dt, MeasurementModel(n_robots, bandwidth, settings), gradient
        )
        self.adjacency: sp.csr_matrix | None = None

    def _graph(self, positions: np.ndarray) -> sp.csr_matrix:
        self.adjacency = communication_graph(positions, self.radius, self.k_nearest)
        w, self.consensus.eps = consensus_weights(self.adjacency, self.consensus.gain)
        return w

    def _split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        m = self.grid.size
        return z[:, :m], (z[:, m:] if self.consensus.gradient else None)

    def _estimate(self, y: np.ndarray) -> DistributedEstimate:
        f = self.filters
        assert f.x is not None and self.adjacency is not None
        q = f.q_hat if f.gradient == "filter" else None
        return DistributedEstimate(f.x, q, y, self.adjacency, self.consensus.eps)

    def initialize(self, positions: np.ndarray) -> DistributedEstimate:
        """Graph, ``z(0)`` and the filters' start from it, at ``t = 0``."""
        z = self.consensus.initialize(positions, self._graph(positions))
        y, y_g = self._split(z)
        self.filters.initialize(np.ascontiguousarray(y), y_g)
        return self._estimate(y)

    def step(self, positions: np.ndarray, a: sp.csr_matrix) -> DistributedEstimate:
        """New graph at the new positions, consensus, then every robot's filter step
        under the model ``A`` (the Fokker-Planck matrix of the last interval).
        """
        z = self.consensus.step(positions, self._graph(positions))
        y, y_g = self._split(z)
        self.filters.step(y, a, y_g)
        return self._estimate(y)

    def memory_bytes(self) -> int:
        """Bytes held in per-robot arrays (consensus state and buffer, filter states)."""
        arrays = [self.consensus.z, self.consensus._buf, self.filters.x, self.filters.d]
        arrays += [self.filters.x_g, self.filters.c_g]
        arrays += list(self.consensus._factors or ())
        return int(sum(a.nbytes for a in arrays if a is not None))
