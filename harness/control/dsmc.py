"""``control=dsmc``: a decentralised state-dependent Markov chain on the grid's cells
(after Uzun, Üre and Açıkmeşe's DSMC), rebuilt every period from the estimated cell
masses, whose expected distribution obeys a linear consensus on the ratios ``m / v``
and whose matrix is the identity at the target.

Source: S. Uzun, N. K. Üre, B. Açıkmeşe, "Decentralized state-dependent Markov chain
synthesis with an application to swarm guidance", arXiv 2012.02303. What was retrieved
of it: its abstract and summaries. The Markov matrix ``M(k)`` is a function of the
current distribution through local errors only (each bin's column from its own and its
neighbours' errors), column-stochastic, with transitions only along the allowed
edges; it comes from a state-dependent consensus protocol, converges exponentially to
the desired distribution from every start, moves as few agents as it can, and tends to
the identity as the distribution reaches the target; a modified DSMC adds shortest
paths for bins that do not border a deficit. **The paper's equations were not
retrieved**: the matrix below is this project's own construction with those
properties (:func:`consensus_columns`), not the paper's ``M(k)``, and it carries no
equation numbers of the paper. It differs from ``control=psg_feedback``
(:class:`harness.control.guidance.FeedbackGuidance`), which sends each cell's excess to
the neighbours' deficits and relays by hop counts: here mass flows between every pair of
neighbouring cells from the higher ratio ``m / v`` to the lower, so the expected
distribution follows a linear consensus whose rate is known in closed form.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from harness.control.guidance import ROUND_OFF, FeedbackGuidance

MAX_DEGREE = 4
"""Neighbours a cell has at most (the 4-neighbourhood): the ``4`` in ``w_ij / 4``."""

TINY_MASS = 1e-300
"""Floor of a target mass in the ratio ``m / v``: a cell the target leaves empty has a
huge ratio, so all its robots move out (:func:`consensus_columns`)."""


def consensus_columns(
    m: np.ndarray, v: np.ndarray, cells: np.ndarray, exists: np.ndarray, gain: float
) -> np.ndarray:
    """The chain at each cell's candidates, ``P[j, k] = M_{cells[j, k], j}``, shape
    ``(M, 5)``, for the cell masses ``m`` and the target masses ``v`` (flat, each of sum
    1; dimensionless).

    With the ratios ``r_j = m_j / v_j`` (``v_j`` floored at :data:`TINY_MASS`), the
    weight ``w_ij = min(v_i, v_j)`` of an edge and the gain ``kappa`` in ``(0, 1]``, the
    expected mass that moves from cell ``j`` to its neighbour ``i`` in one period is

        F_ij = (kappa / 4) w_ij (r_j - r_i)^+,

    so a robot in ``j`` moves to ``i`` with the probability

        M_ij = F_ij / m_j  (i ~ j),     M_jj = 1 - sum_{i ~ j} M_ij,

    (``M_ij = 0`` where ``m_j = 0``, the column then the identity's). Each entry reads only
    the two cells' masses and targets: decentralised on the 4-neighbourhood.

    * Nonnegative and column-stochastic: ``F_ij <= (kappa / 4) w_ij r_j <= (kappa / 4)
      m_j`` (as ``w_ij <= v_j``), so ``sum_{i ~ j} M_ij <= kappa d_j / 4 <= kappa <= 1``
      and ``M_jj >= 1 - kappa >= 0``.
    * Identity at the target: ``m = v`` gives ``r = 1`` in every cell with ``v > 0``, so
      every ``F_ij = 0`` and ``M = I``. Conversely, if no mass moves, ``r`` is constant
      on each connected component, hence ``m = v`` on the grid.
    * Moves only downhill: mass goes from the higher ratio to the lower, never both ways
      on an edge; a cell above its target only sends, one below it only receives, as
      long as its neighbours are on the other side.

    A ratio drop ``r_j - r_i`` of at most ``ROUND_OFF`` counts as none (ratios equal up
    to round-off), so an estimate equal to the target gives the identity exactly.
    """
    floored = np.maximum(v, TINY_MASS)
    ratio = m / floored
    weight = np.minimum(floored[:, None], floored[cells[:, 1:]])
    drop = ratio[:, None] - ratio[cells[:, 1:]]
    moving = exists[:, 1:] & (drop > ROUND_OFF)
    flow = np.where(moving, 0.25 * gain * weight * drop, 0.0)
    out = np.zeros(cells.shape)
    np.divide(flow, m[:, None], out=out[:, 1:], where=(m[:, None] > 0) & moving)
    out[:, 0] = 1.0 - out[:, 1:].sum(axis=1)
    return out


def consensus_rate(v: np.ndarray, cells: np.ndarray, exists: np.ndarray, gain: float) -> float:
    """The contraction factor ``rho`` per period of the expected distribution under
    :func:`consensus_columns` (``v`` flat, positive, sum 1).

    The expected masses evolve as ``m <- M(m) m``. The net flow on the edge ``i ~ j`` is
    ``F_ij - F_ji = (kappa / 4) w_ij (r_j - r_i)`` (only one of the two is nonzero), so
    with ``V = diag(v)`` and the weighted Laplacian ``L`` of the weights ``w``,

        V r(k+1) = V r(k) - (kappa / 4) L r(k),   r(k+1) = (I - S) r(k),
        S = (kappa / 4) V^{-1} L:

    the state-dependent chain makes a *linear* consensus of the ratios. ``S`` is
    self-adjoint in ``<a, b>_V = sum v a b`` (``V S = (kappa / 4) L`` is symmetric),
    with eigenvalue 0 on the constants, and ``r(k) - 1`` stays ``V``-orthogonal to the
    constants (``<r - 1, 1>_V = sum m - sum v = 0``). Hence

        ||r(k) - 1||_V <= rho^k ||r(0) - 1||_V,   rho = max(|1 - mu_2|, |1 - mu_max|),

    ``mu_2``, ``mu_max`` the second-smallest and largest eigenvalues of ``S`` (real,
    ``0 <= mu <= 2 kappa`` by Gershgorin, as ``sum_i w_ij <= 4 v_j``); and since ``sum
    v = 1``, ``||m(k) - v||_1 = sum v |r - 1| <= ||r(k) - 1||_V``. ``rho < 1`` on a
    connected grid with ``v > 0`` (``mu_2 > 0``). Dense eigenvalues: for small grids
    (tests, docs), ``O(M^3)``.
    """
    n = v.size
    laplacian = np.zeros((n, n))
    for k in range(1, cells.shape[1]):
        j = np.flatnonzero(exists[:, k])
        i = cells[j, k]
        w = np.minimum(v[i], v[j])
        laplacian[i, j] -= w
        laplacian[j, j] += w
    scale = 1.0 / np.sqrt(v)
    sym = 0.25 * gain * scale[:, None] * laplacian * scale[None, :]  # V^-1/2 L V^-1/2
    mu = np.linalg.eigvalsh(0.5 * (sym + sym.T))
    return float(max(abs(1.0 - mu[1]), abs(1.0 - mu[-1])))


class ConsensusGuidance(FeedbackGuidance):
    """DSMC-style guidance (``control=dsmc``): every period each robot moves to a
    neighbouring cell with the probability of the state-dependent chain of
    :func:`consensus_columns`, built from the estimated cell masses.

    Source: Uzun, Üre and Açıkmeşe, arXiv 2012.02303 (DSMC). Their equations were not
    retrieved (module docstring): the matrix is this project's construction with the
    properties the paper states (state-dependent through local errors, column-stochastic,
    transitions only between neighbours, exponential convergence, ``M -> I`` at the
    target), not the paper's ``M(k)``. Choices where the design is free:

    * bins: the grid's cells; neighbourhood: the 4 neighbours (on free space, those
      through open faces, :func:`harness.control.guidance.neighbour_table`);
    * the distribution each robot's chain reads: the run's estimate ``p_hat`` as cell
      masses ``m_hat_j = max(p_hat_j, 0) |cell| / sum`` (every robot reads the same
      estimate; the column of cell ``j`` needs only ``m_hat`` and ``v`` at ``j`` and its
      neighbours); with ``debias`` the target masses are those of ``K_h * p_*``;
    * the local error: the ratio ``m_hat_j / v_j`` (``1`` at the target), compared
      between neighbours; ``gain`` ``kappa`` scales every move;
    * the period ``T``: every robot draws once per period; a robot that moves heads for a
      point drawn uniformly in its new cell, one that stays holds
      (:class:`harness.control.guidance.FeedbackGuidance`).

    Properties (``tests/test_new_laws.py``): each column is nonnegative and sums to 1;
    ``M = I`` at the target (the robots stop); with exact masses the expected
    distribution follows the linear consensus of :func:`consensus_rate`, converging to
    ``v`` from every start at the rate ``rho`` per period in ``||r - 1||_V``, a bound on
    ``||m - v||_1``. The consensus is diffusive (nearest-neighbour moves of bounded
    probability): ``1 - rho`` falls as ``1 / n^2`` on an ``n x n`` grid (at ``kappa =
    0.5`` and a uniform target, about ``0.0014`` per period on 30 x 30, a relaxation time
    of some 730 periods), slower than ``psg_feedback``'s transport straight to the
    deficits and of the order of ``psg``'s Metropolis chain, but it never moves robots
    into an over-full cell, nor back and forth.

    Inputs: the estimate ``p_hat`` at the start of each period and the robots' cells. A
    density in a denominator: ``m_hat_j`` in ``M_ij = F_ij / m_hat_j``, bounded (``F_ij
    <= kappa m_hat_j / 4``), and ``v_j`` (the target's) in the ratio. Estimation errors
    enter as errors of the ratios: at the target a relative error ``delta`` of the
    estimate moves a fraction ``kappa delta / 4`` per neighbour per period, so the swarm
    churns at that rate; with the noise ``sigma``, holding robots diffuse and the chain
    returns the mass at the rate ``1 - rho``, a balance whose bias was not derived.
    ``needs_robots``: no mean-field form (the chain moves robots); a static target only.

    Args:
        target: The target on the grid (run-time argument).
        gain: ``kappa`` in ``(0, 1]``; ``kappa <= 1/2`` keeps every ``M_jj >= 1/2`` (a
            lazy chain, ``rho = 1 - mu_2``, no oscillation).
        period: ``T > 0`` (s) between decisions.
        seed: The run's seed; the law draws from ``np.random.default_rng([seed, 4])``.
        v_max: Speed cap (length / s), or None.
        debias, bandwidth, mirror: As :class:`harness.control.guidance.FeedbackGuidance`.
    """

    uses: ClassVar[str] = "positions, estimate, target cell masses"
    divides_by_density: ClassVar[bool] = True  # m_hat_j in M_ij, bounded (class docstring)

    def columns(self, p_hat: np.ndarray) -> np.ndarray:
        """The chain at the candidates, ``(M, 5)``, for the estimate ``p_hat``: the
        identity's when it has no positive mass, else :func:`consensus_columns` of its
        cell masses.
        """
        m = self.estimated_masses(p_hat)
        if m is None:
            out = np.zeros(self.cells.shape)
            out[:, 0] = 1.0
            return out
        return self.columns_of_masses(m)

    def columns_of_masses(self, m: np.ndarray) -> np.ndarray:
        """:func:`consensus_columns` for the cell masses ``m`` (flat, sum 1)."""
        return consensus_columns(m, self.masses.ravel(), self.cells, self.exists, self.gain)
