"""Dynamic average consensus: every robot tracks the swarm's KDE from its own kernel.

The KDE is the mean of the robots' kernels ``phi_i`` (:mod:`harness.estimators.distributed.robot_kde`),
so each robot can track it from its own kernel and messages from its neighbours in the
communication graph (:mod:`harness.estimators.distributed.graph`: adjacency ``A``, Laplacian ``L``,
eigenvalues ``0 = lambda_1 <= lambda_2 <= ... <= lambda_N``); Zheng and Lin, arXiv
2009.05366 / 2106.05318.

Dynamic average consensus (first-order form). Each robot keeps ``z_i`` (a field of ``M``
cells, its estimate of the KDE). With ``W_t = I - eps_t L_t`` and ``m`` rounds per step,

    z_i(0)     = [W_0^{m_0} phi(0)]_i,
    z(t + 1)   = W_{t+1}^m ( z(t) + phi(t + 1) - phi(t) )                          (DAC)

(rows are robots; ``phi(t)`` the ``N x M`` matrix of the robots' kernels at ``X(t)``;
``m_0`` the ``initial_rounds``, by default ``m``: with ``m_0 >> 1`` the robots agree
before they start moving). Robot ``i`` needs ``z_j`` of its neighbours once per round:
one message of ``M`` floats per neighbour per round.

*Computing* ``W z``. All off-diagonal weights equal ``eps``, so ``(W z)_i = w_ii z_i +
eps S_i`` with the neighbour sum ``S_i``; visiting the robots along a Hilbert curve
(:func:`harness.estimators.distributed.graph.spatial_order`), consecutive robots have nearly the
same neighbours and ``S_i`` is the preceding robot's sum corrected by the symmetric
difference of the two neighbourhoods (:func:`_mix_uniform`, restarted every 64 robots):
about ``4 r delta`` times the robot density row operations instead of ``deg_i``
(``delta`` the step along the curve).

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

*Proportional-integral form* (``estimator.consensus: pi``; Freeman, Yang and Lynch,
"Stability and convergence properties of dynamic average consensus estimators", CDC
2006, in the input-difference form of Kia et al., "Tutorial on dynamic average
consensus", IEEE Control Systems 39(3), 2019). A second state ``w`` per robot (same
shape as ``z``, ``w(0) = 0``) integrates the disagreement. With ``L_eps = eps L = I - W``
and gains ``k_P``, ``k_I``, each step adds the input's change and runs ``m`` rounds of

    v       = z + (phi(t + 1) - phi(t)) / m      (the input's change, split over the rounds)
    z'      = v - k_P L_eps v - k_I L_eps w                                          (PI)
    w'      = w + k_I L_eps z'

``1^T L_eps = 0``, so ``1^T z`` changes only by the input's change: the invariant above
holds as for the first-order form (with one round per step, the PI form with ``k_I = 0``,
``k_P = 1`` is it).
*Ramps.* For a constant input change ``phi(t + 1) - phi(t) = c`` (robots moving at
constant velocity, to first order) the first-order form settles at the lag
``e_* = (I - W^m)^+ W^m Pi c``, which the smallest eigenvalues of ``L`` amplify as
``1 / (m eps lambda_2)``. In the PI form every round of a step is then the same affine
map (each adds ``c / m``), and its fixed point needs ``w' = w``, i.e. ``L_eps z' = 0``:
the robots agree after every round (``e = 0``), and ``k_I L_eps w = (I - k_P L_eps) Pi c
/ m`` absorbs the ramp. So the PI form tracks a ramp with zero steady error (tested
against the first-order lag formula). *Stability.* On the eigenvector of ``L_eps`` with eigenvalue
``mu`` in ``(0, 2)`` one round maps ``(e, w)`` by ``[[1 - a, -b], [b (1 - a), 1 - b^2]]``
with ``a = k_P mu``, ``b = k_I mu``: determinant ``1 - a``, trace ``2 - a - b^2``. Both
eigenvalues lie inside the unit circle (Jury) iff ``|1 - a| < 1`` and ``b^2 < 4 - 2 a``,
true for every ``mu < 2`` when ``0 < k_P <= 1`` and ``k_I^2 <= 1 - k_P``. The harness sets
``k_P = 1 - k_I^2`` with ``k_I = estimator.integral_gain`` in ``(0, 1)`` (default 0.5,
``k_P = 0.75``): stable on every *fixed* graph the gain rule below admits. The graph of
the loop changes every step, and the round map is not a contraction (its largest
singular value is 1.14 at ``k_I = 0.5``), so stability under switching is not proved by
this; random switching radius graphs stayed stable in simulation. For small ``mu`` the
two rates per round are about ``k_P mu`` and ``k_I^2 mu / k_P``. *ISS* (fixed graph).
The error ``(e, w)`` obeys a stable linear recursion driven by ``Pi Delta phi``, so it is
bounded by a constant times ``sup ||Pi (Delta phi - Delta phi_prev)||`` (the input's
change of change) plus a decaying transient: a constant drift costs nothing, but white
increments (the robots' noise) cost more than in the first-order form, about 1.3 to 2
times its variance per mode at ``k_I = 0.5`` (from ``mu -> 0`` to ``mu = 0.5``), because
the slow mode keeps them longer. *Cost.* A round needs two
exchanges: ``(v, w)`` to compute ``z'``, then ``z'`` to update ``w``; three fields per
neighbour per round against one.

Messages. A *message* is what one robot sends one neighbour in one exchange: ``C``
float64 values per field, ``C = M`` grid values or ``C = K`` band coefficients
(``estimator.messages: band``, :mod:`harness.estimators.distributed.band`). Per robot per step
the first-order form sends ``m deg_i`` messages of ``C`` values, the PI form ``2 m
deg_i`` messages (``(v, w)`` of ``2 C`` values, then ``z'`` of ``C``);
:func:`message_counts` reports the means over robots (with a broadcast medium one
transmission per exchange would do).

The compiled loops state their plain numpy equivalents in their docstrings; tests
compare.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.band import BandMessages
from harness.estimators.distributed.graph import canonical_csr, laplacian, spatial_order
from harness.estimators.distributed.robot_kde import kernel_factors
from harness.grid import Grid


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


FORMS = ("first_order", "pi")
"""The consensus forms: eq. ``DAC`` and eq. ``PI`` of the module docstring."""


class DynamicAverageConsensus:
    """Dynamic average consensus on the robots' kernels: the first-order form (eq.
    ``DAC`` in the module docstring) or the proportional-integral form (eq. ``PI``),
    on grid fields or on the band's coefficients (:mod:`harness.estimators.distributed.band`).

    State ``z`` of shape ``(N, C)``: ``C = M`` grid values, or ``C = K`` band
    coefficients; the PI form keeps ``w`` of the same shape.

    Args:
        grid: The grid.
        bandwidth: Kernel bandwidth ``h`` (length).
        rounds: Consensus rounds per step ``m >= 1``.
        gain: ``eps = gain / (1 + d_max)``, ``0 < gain <= 1``.
        initial_rounds: Rounds ``m_0 >= 0`` at ``t = 0``, before the first estimate:
            ``z(0) = W_0^{m_0} phi(0)`` (default ``m``). With one round per step each
            robot's first estimate is nearly its own kernel; ``m_0`` rounds bring the
            disagreement down by ``rho^{m_0}`` before the robots start moving.
        chunk: Robots per chunk of the neighbour-sum product (:func:`_mix_uniform`).
        form: ``"first_order"`` or ``"pi"`` (:data:`FORMS`).
        integral_gain: ``k_I`` in ``(0, 1)`` of the PI form (``k_P = 1 - k_I^2``).
        band: Exchange band coefficients (``None``: grid fields).
    """

    def __init__(
        self,
        grid: Grid,
        bandwidth: float,
        rounds: int = 1,
        gain: float = 1.0,
        initial_rounds: int | None = None,
        chunk: int = 64,
        form: str = "first_order",
        integral_gain: float = 0.5,
        band: BandMessages | None = None,
    ) -> None:
        if rounds < 1:
            raise ValueError(f"consensus rounds must be >= 1, got {rounds}")
        initial_rounds = rounds if initial_rounds is None else int(initial_rounds)
        if initial_rounds < 0:
            raise ValueError(f"initial rounds must be >= 0, got {initial_rounds}")
        if form not in FORMS:
            raise ValueError(f"consensus form must be one of {', '.join(FORMS)}, got {form!r}")
        if not 0 < integral_gain < 1:
            raise ValueError(f"integral gain must be in (0, 1), got {integral_gain}")
        self.grid, self.bandwidth = grid, bandwidth
        self.rounds, self.gain = int(rounds), gain
        self.initial_rounds, self.chunk = initial_rounds, int(chunk)
        self.form, self.band = form, band
        self.k_i = float(integral_gain) if form == "pi" else 0.0
        self.k_p = 1.0 - self.k_i**2
        self.columns = band.size if band is not None else grid.size
        self.z: np.ndarray | None = None
        self.w: np.ndarray | None = None
        self._buf: np.ndarray | None = None
        self._factors: tuple[np.ndarray, ...] | None = None
        self._coef: np.ndarray | None = None
        self.eps = 0.0

    @property
    def exchanges(self) -> int:
        """Exchanges per round: 1 (first order) or 2 (PI: ``(v, w)``, then ``z'``)."""
        return 2 if self.form == "pi" else 1

    @property
    def floats_per_round(self) -> int:
        """Float64 values a robot sends one neighbour per round: ``C`` or ``3 C``."""
        return 3 * self.columns if self.form == "pi" else self.columns

    @property
    def message_bytes(self) -> int:
        """Bytes of the largest message: ``8 C`` (first order) or ``16 C`` (PI)."""
        return 8 * self.columns * (2 if self.form == "pi" else 1)

    def _increment(
        self,
        factors: tuple[np.ndarray, ...],
        old: tuple[np.ndarray, ...] | None,
        into: np.ndarray | None = None,
    ) -> np.ndarray:
        """``phi(t + 1) - phi(t)`` (``phi(0)`` when ``old`` is None), ``(N, C)``; on grid
        fields added in place to ``into`` when given (no ``N C`` temporary), and ``into``
        returned.
        """
        kx, _, ky, _ = factors
        if self.band is not None:  # the coefficients' change, C_y ky_i (C_x kx_i)^T
            coef = self.band.kernels(kx, ky)
            delta = coef if self._coef is None or old is None else coef - self._coef
            self._coef = coef
            return delta
        delta = np.zeros((kx.shape[0], self.columns)) if into is None else into
        if old is None:  # the old kernels' values are unused (sign 0)
            _add_kernel_increment(delta, ky, kx, ky, kx, 0.0)
        else:
            okx, _, oky, _ = old
            _add_kernel_increment(delta, ky, kx, oky, okx, -1.0)
        return delta

    def _mixer(self, w: sp.csr_matrix, positions: np.ndarray):
        """``x -> W x`` into a new array: by neighbour sums along a space-filling curve
        (:func:`_mix_uniform`) when ``W``'s off-diagonal entries are all equal (always
        for :func:`consensus_weights`), by the general sparse product otherwise.
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
                _mix_uniform(w.indptr, w.indices, w.data, eps, order, self.chunk, x, out)
            else:
                _spmm(w.indptr, w.indices, w.data, x, out)
            return out

        return mix

    def _mix(
        self, w: sp.csr_matrix, rounds: int, positions: np.ndarray, delta: np.ndarray | None
    ) -> None:
        """Add the input's change ``delta`` and run ``rounds`` rounds: eq. ``DAC`` (``z <-
        W^m (z + delta)``), or eq. ``PI`` with ``delta / m`` added before each round (so
        that every round of a step is the same map under a ramp, and its fixed point
        agrees after every round; the whole change is in ``z`` by the step's end).
        ``delta`` None: the first-order form's change is in ``z`` already.
        """
        assert self.z is not None and self._buf is not None
        mix = self._mixer(w, positions)
        if self.form == "first_order":
            if delta is not None:
                self.z += delta
            for _ in range(rounds):
                mix(self.z, self._buf)
                self.z, self._buf = self._buf, self.z
            return
        assert self.w is not None and delta is not None
        if rounds == 0:
            self.z += delta
            return
        c = self.columns
        for _ in range(rounds):
            v = self.z + delta / rounds
            both = mix(np.concatenate([v, self.w], axis=1))  # exchange (v, w)
            # z' = v - k_P L_eps v - k_I L_eps w,  with L_eps x = x - W x
            z_new = v - self.k_p * (v - both[:, :c]) - self.k_i * (self.w - both[:, c:])
            # w' = w + k_I L_eps z'  (exchange z')
            self.w = self.w + self.k_i * (z_new - mix(z_new))
            self.z = z_new

    def kde(self) -> tuple[np.ndarray, np.ndarray]:
        """The exact KDE of the current positions, ``(p, grad p)`` of shapes ``(ny, nx)``
        and ``(2, ny, nx)``: the mean of the robots' kernels, from the factors the last
        step computed (:meth:`harness.estimators.kde.KDE.exact` without evaluating them again).
        """
        assert self._factors is not None, "call initialize first"
        kx, dkx, ky, dky = self._factors
        n = kx.shape[0]
        return ky.T @ kx / n, np.stack([ky.T @ dkx / n, dky.T @ kx / n])

    def observation(self) -> np.ndarray:
        """What each robot's filter observes, ``(N, M)`` grid fields: ``z`` itself, or
        the band-limited fields ``Pi F_i`` its coefficients stand for.
        """
        assert self.z is not None, "call initialize first"
        return self.z if self.band is None else self.band.fields(self.z)

    def initialize(self, positions: np.ndarray, w: sp.csr_matrix) -> np.ndarray:
        """``z(0) = W^{m_0} phi(0)`` (``m_0`` initial rounds of the form; ``w(0) = 0``);
        returns the robots' observations (:meth:`observation`).
        """
        n = positions.shape[1]
        self.z = np.zeros((n, self.columns))
        self.w = np.zeros_like(self.z) if self.form == "pi" else None
        self._buf = np.empty_like(self.z)
        self._coef = None
        self._factors = kernel_factors(self.grid, positions, self.bandwidth)
        self._mix(w, self.initial_rounds, positions, self._increment(self._factors, None))
        return self.observation()

    def step(self, positions: np.ndarray, w: sp.csr_matrix) -> np.ndarray:
        """Add the kernels' change, then ``m`` rounds; returns the observations."""
        assert self.z is not None and self._factors is not None, "call initialize first"
        factors = kernel_factors(self.grid, positions, self.bandwidth)
        if self.form == "first_order" and self.band is None:  # straight into z
            self._increment(factors, self._factors, into=self.z)
            delta = None
        else:
            delta = self._increment(factors, self._factors)
        self._factors = factors
        self._mix(w, self.rounds, positions, delta)
        return self.observation()

    def reference_step(
        self,
        z: np.ndarray,
        phi_new: np.ndarray,
        phi_old: np.ndarray,
        w: sp.csr_matrix,
        integral: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Plain statement of :meth:`step` (scipy): ``W^m (z + phi_new - phi_old)``, or
        ``m`` rounds of eq. ``PI`` from ``(z, integral)`` with ``(phi_new - phi_old) / m``
        added before each; returns ``(z, w)`` (``w`` None for the first-order form).
        """
        delta = phi_new - phi_old
        if self.form == "first_order":
            out = z + delta
            for _ in range(self.rounds):
                out = w @ out
            return out, None
        out, acc = z, (np.zeros_like(z) if integral is None else integral)

        def lap(x: np.ndarray) -> np.ndarray:
            return x - w @ x

        for _ in range(self.rounds):
            v = out + delta / self.rounds
            out_new = v - self.k_p * lap(v) - self.k_i * lap(acc)
            acc = acc + self.k_i * lap(out_new)
            out = out_new
        return out, acc


def message_counts(
    adj: sp.csr_matrix, rounds: int, floats_per_round: int, exchanges: int = 1
) -> dict[str, float]:
    """Communication per robot per step (means over robots; see the module docstring).

    Args:
        adj: The step's communication graph.
        rounds: Rounds per step.
        floats_per_round: Float64 values a robot sends one neighbour in one round.
        exchanges: Messages per neighbour per round.

    Returns:
        ``messages`` (messages / robot / step), ``floats`` (float64 values / robot /
        step), ``bytes`` (bytes / robot / step) and ``mean_degree``.
    """
    deg = float(adj.nnz) / adj.shape[0]
    return {
        "messages": rounds * exchanges * deg,
        "floats": rounds * deg * floats_per_round,
        "bytes": 8.0 * rounds * deg * floats_per_round,
        "mean_degree": deg,
    }
