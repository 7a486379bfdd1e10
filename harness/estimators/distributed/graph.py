"""The robots' communication graph: who talks to whom at each step.

Robots ``i != j`` are neighbours when ``|X_i - X_j| <= r`` (radius graph) or when either
is among the other's ``k`` nearest (symmetrised k-nearest graph); the graph is
recomputed every step from the positions. ``A`` is the symmetric 0/1 adjacency, ``D =
diag(deg)``, ``L = D - A`` the graph Laplacian with eigenvalues ``0 = lambda_1 <=
lambda_2 <= ... <= lambda_N``; ``lambda_2 > 0`` iff the graph is connected (the
algebraic connectivity). How ``L`` enters the consensus, and what ``lambda_2`` and
``lambda_N`` decide there, is derived in :mod:`harness.estimators.distributed.consensus`.

Also here: the canonical CSR helpers the graph and the consensus weights are built
with, and :func:`spatial_order`, the robots sorted along a Hilbert curve (the visiting
order of the consensus product).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree


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


def canonical_csr(
    indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, n: int
) -> sp.csr_matrix:
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
            if either is among the other's ``k`` nearest). With ``radius`` as well: its
            ``k`` nearest among those within ``radius`` (a robot that can hear everyone
            within ``radius`` and talks to its ``k`` nearest), then symmetrised. At
            least one of the two.

    Returns:
        ``(N, N)`` CSR matrix with sorted indices and float entries 1.
    """
    if radius is None and k_nearest is None:
        raise ValueError("give radius, k_nearest or both")
    if radius is not None and not radius >= 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    pts = np.asarray(positions, dtype=float)
    n = pts.shape[1]
    if k_nearest is None:
        assert radius is not None
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
            dist, idx = cKDTree(pts.T).query(pts.T, k + 1)
            rows = np.repeat(np.arange(n, dtype=np.int64), k)
            cols = idx[:, 1:].ravel().astype(np.int64)  # the first is the robot itself
            if radius is not None:  # only those within the radius (inclusive)
                near = dist[:, 1:].ravel() <= radius
                rows, cols = rows[near], cols[near]
        indptr, indices = _symmetric_csr(n, rows, cols)
    return canonical_csr(indptr, indices, np.ones(indices.size), n)


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
    about ``-1e-3`` (the two eigenvalues nearest 0 of ``L``, factorised once), from a
    fixed start vector (ARPACK's own is random: the last bits would differ run to run).
    """
    n = adj.shape[0]
    if n < 2 or n_components(adj) > 1:
        return 0.0
    lap = laplacian(adj)
    if n <= dense_max:
        return float(np.linalg.eigvalsh(lap.toarray())[1])
    start = np.random.default_rng(0).standard_normal(n)
    vals = spla.eigsh(
        lap.tocsc(), k=2, sigma=-1e-3, which="LM", v0=start, return_eigenvectors=False
    )
    return float(np.sort(vals)[1])


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
