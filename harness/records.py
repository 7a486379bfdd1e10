"""Records passed between the loop's components and its observers.

Kept apart from the loop so that observers (metrics, the MCAP logger) and components
(plants, estimators) share them without importing :mod:`harness.loop`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from harness.velocity import VelocityField


@dataclass(frozen=True)
class Measurement:
    """What a plant lets the estimator measure at one time.

    Attributes:
        p: Measured density ``(ny, nx)`` (1 / length^2): the KDE of the robots, or the
            mean-field density plus synthetic KDE-like noise.
        grad: Measured gradient ``(2, ny, nx)`` (1 / length^3).
    """

    p: np.ndarray
    grad: np.ndarray


@dataclass(frozen=True)
class StepInput:
    """What an estimator may use at time ``t`` (s).

    Attributes:
        t: Time (s).
        p_kde: Measured density ``(ny, nx)`` (1 / length^2), None for estimators that
            take no measurement.
        grad_kde: Measured gradient ``(2, ny, nx)`` (1 / length^3), or None.
        v_applied: Velocity applied over the last interval (None at ``t = 0``).
        a: ``A(v_applied)``, the Fokker-Planck matrix (None at ``t = 0``).
        p_true: The plant's mean-field density ``(ny, nx)``; only ``exact`` and
            ``injected`` read it.
        positions: Robot positions ``(2, N)`` (None without robots).
    """

    t: float
    p_kde: np.ndarray | None
    grad_kde: np.ndarray | None
    v_applied: VelocityField | None
    a: sp.csr_matrix | None
    p_true: np.ndarray
    positions: np.ndarray | None = None


@dataclass(frozen=True)
class RobotEstimates:
    """The robots' own estimates in a decentralised loop (``estimator=distributed``).

    Attributes:
        p_hat: Robot ``i``'s density estimate in row ``i``, ``(N, M)`` (1 / length^2),
            cells in C order of the grid.
        q_hat: Gradient estimates ``(N, 2M)`` (``x`` block then ``y`` block, 1 /
            length^3), or None when each robot takes the grid gradient of its own
            ``p_hat_i`` (the law evaluates that at the robot's cells).
        p_central: The centralised filter's density estimate ``(ny, nx)`` on the same
            measurements, run alongside as the reference; never used for control.
        robot: The index of the robot whose estimate is logged as a field.
        network: The step's graph and communication figures (see
            :func:`harness.metrics.network_metrics`): ``consensus_l2``,
            ``central_gap_l2``, ``messages``, ``mean_degree``, ``components``,
            ``algebraic_connectivity``.

    ``p_hat`` and ``q_hat`` are the filters' own state arrays (a copy would cost ``N M``
    values per step), like ``StepRecord.positions``: valid until the next step, which
    overwrites them in place. Observers that keep them must copy.
    """

    p_hat: np.ndarray
    q_hat: np.ndarray | None
    p_central: np.ndarray
    robot: int
    network: dict[str, float]


@dataclass(frozen=True)
class Estimate:
    """Estimates and diagnostics.

    Attributes:
        p_hat: Density estimate ``(ny, nx)`` (1 / length^2).
        q_hat: Gradient estimate ``(2, ny, nx)`` (1 / length^3).
        trace_P: L2 trace of the density filter's covariance (1 / length^2), or None.
        trace_Q: L2 trace of its process noise per step (1 / length^2), or None.
        trace_P_grad: Same for the gradient filter (1 / length^4), or None.
        trace_Q_grad: Same for the gradient filter (1 / length^4), or None.
        robots: Each robot's own estimates when every robot moves on its own
            (``estimator=distributed``; ``p_hat`` and ``q_hat`` are then the robots'
            means), else None.
    """

    p_hat: np.ndarray
    q_hat: np.ndarray
    trace_P: float | None = None
    trace_Q: float | None = None
    trace_P_grad: float | None = None
    trace_Q_grad: float | None = None
    robots: RobotEstimates | None = None


@dataclass(frozen=True)
class StepRecord:
    """Everything the observers may see after a step (or at ``t = 0``).

    ``positions`` is None without robots; ``measurement`` is None when the estimator
    takes none (``exact``, ``injected``).
    """

    step: int
    t: float
    p_true: np.ndarray
    measurement: Measurement | None
    estimate: Estimate
    velocity: VelocityField
    positions: np.ndarray | None
