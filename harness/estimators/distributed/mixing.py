"""One round of consensus: the weights ``W = I - eps L`` and the product ``W z``.

Dynamic average consensus (:mod:`harness.estimators.distributed.consensus`) and the agreement
on the law's input (:mod:`harness.estimators.distributed.share`) run rounds ``z <- W z`` on
the robots' states (rows are robots), with ``L`` the Laplacian of the step's
communication graph (:mod:`harness.estimators.distributed.graph`: eigenvalues ``0 = lambda_1
<= lambda_2 <= ... <= lambda_N``).

*Gain.* ``eps = gain / (1 + d_max)`` with ``d_max`` the largest degree of the current
graph and ``0 < gain <= 1`` (default 1). Then every entry of ``W`` is ``>= 0`` (``1 - eps
d_i >= 1 / (1 + d_max)``), ``W`` is doubly stochastic, and Gershgorin (``lambda_N <= 2
d_max``) gives ``|1 - eps lambda_N| < 1``: stable on every graph. On the complete graph
``eps = 1/N`` and ``W = 1 1^T / N``: one round is exact consensus, which the test of
equality with the centralised filter uses. A robot with no neighbours has ``W_ii = 1``
and tracks its own kernel.

*Computing* ``W z``. All off-diagonal weights equal ``eps``, so ``(W z)_i = w_ii z_i +
eps S_i`` with the neighbour sum ``S_i``; visiting the robots along a Hilbert curve
(:func:`harness.estimators.distributed.graph.spatial_order`), consecutive robots have nearly the
same neighbours and ``S_i`` is the preceding robot's sum corrected by the symmetric
difference of the two neighbourhoods (:func:`_mix_uniform`, restarted every 64 robots):
about ``4 r delta`` times the robot density row operations instead of ``deg_i``
(``delta`` the step along the curve).

The compiled loops state their plain numpy equivalents in their docstrings; tests
compare.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.graph import canonical_csr, laplacian, spatial_order


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
    """``W = I - eps L`` with ``eps = gain / (1 + d_max)`` (*Gain* in the module docstring).

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
        return canonical_csr(indptr, indices, data, n), eps
    w = (sp.identity(n, format="csr") - eps * laplacian(adj)).tocsr()
    w.sort_indices()
    return w, eps


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


Mixer = Callable[..., np.ndarray]
"""``x -> W x`` for ``(N, C)`` robot states, into a new array or into ``out``
(:func:`mixer`)."""


def mixer(w: sp.csr_matrix, positions: np.ndarray, chunk: int = 64) -> Mixer:
    """``x -> W x`` into a new array (or into ``out``): by neighbour sums along a
    space-filling curve (:func:`_mix_uniform`, ``chunk`` robots per chunk) when ``W``'s
    off-diagonal entries are all equal (always for :func:`consensus_weights`), by the
    general sparse product otherwise.
    """
    if not w.has_sorted_indices:
        w = w.copy()
        w.sort_indices()
    eps = _uniform_offdiagonal(w.indptr, w.indices, w.data)
    order = spatial_order(positions) if np.isfinite(eps) else None

    def mix(x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        x = np.ascontiguousarray(x)
        out = np.empty_like(x) if out is None else out
        if order is not None:
            _mix_uniform(w.indptr, w.indices, w.data, eps, order, chunk, x, out)
        else:
            _spmm(w.indptr, w.indices, w.data, x, out)
        return out

    return mix
