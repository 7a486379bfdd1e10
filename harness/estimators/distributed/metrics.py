"""How far the robots' estimates are from each other and from the centralised one, and
the network figures the decentralised estimator publishes as its metrics
(:data:`NETWORK_KEYS`) beside the fields it publishes (:data:`FIELD_NAMES`).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.graph import n_components
from harness.grid import Grid

NETWORK_KEYS = (
    "consensus_l2",
    "central_gap_l2",
    "messages",
    "bytes",
    "message_bytes",
    "mean_degree",
    "components",
    "algebraic_connectivity",
)
"""The decentralised estimator's per-step metrics (:func:`network_figures`), in log order
(the last keys of :data:`harness.observers.log.METRIC_KEYS`)."""

FIELD_NAMES = ("p_hat_central", "p_hat_robot")
"""The density fields the decentralised estimator publishes (``Estimate.fields``): the
centralised reference's estimate and robot ``estimator.robot``'s, logged as
``/fields/<name>``."""


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


def network_figures(
    grid: Grid, p_hat: np.ndarray, p_central: np.ndarray, adjacency: sp.csr_matrix,
    counts: dict[str, float], connectivity: float,
) -> dict[str, float]:  # fmt: skip
    """The decentralised loop's per-step metrics:

    ``consensus_l2`` = mean over robots of ``||p_hat_i - mean_j p_hat_j||`` (1 / length);
    ``central_gap_l2`` = mean over robots of ``||p_hat_i - p_hat_central||`` (1 / length),
    against the centralised filters run alongside; ``messages`` = messages per robot per
    step (one message: what one robot sends one neighbour in one exchange,
    :mod:`harness.estimators.distributed.consensus`); ``bytes`` = bytes per robot per step (8 per
    float64 value sent); ``message_bytes`` = bytes of the largest message; ``mean_degree``
    (neighbours per robot); ``components``
    (connected components of the communication graph); ``algebraic_connectivity`` =
    ``lambda_2`` of the graph Laplacian (1; 0 when disconnected), as the caller gives it
    (the estimator evaluates it every ``estimator.connectivity_every`` steps and holds
    it in between).

    Args:
        grid: The grid.
        p_hat: The robots' density estimates ``(N, M)``.
        p_central: The centralised reference's estimate.
        adjacency: The step's communication graph.
        counts: ``messages``, ``bytes``, ``message_bytes`` and ``mean_degree`` per robot
            per step
            (:meth:`harness.estimators.distributed.estimator.RobotEstimators.communication`).
        connectivity: The graph's algebraic connectivity (evaluated by the caller, who
            may hold it between evaluations).

    Returns:
        ``consensus_l2``, ``central_gap_l2``, ``messages``, ``bytes``,
        ``message_bytes``, ``mean_degree``, ``components`` and
        ``algebraic_connectivity``.
    """
    spread, gap = estimate_spread(grid, p_hat, p_central)
    values = (
        spread,
        gap,
        counts["messages"],
        counts["bytes"],
        counts["message_bytes"],
        counts["mean_degree"],
        float(n_components(adjacency)),
        connectivity,
    )
    return dict(zip(NETWORK_KEYS, values, strict=True))
