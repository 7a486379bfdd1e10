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
class Estimate:
    """Estimates and diagnostics.

    Attributes:
        p_hat: Density estimate ``(ny, nx)`` (1 / length^2).
        q_hat: Gradient estimate ``(2, ny, nx)`` (1 / length^3).
        trace_P: L2 trace of the density filter's covariance (1 / length^2), or None.
        trace_Q: L2 trace of its process noise per step (1 / length^2), or None.
        trace_P_grad: Same for the gradient filter (1 / length^4), or None.
        trace_Q_grad: Same for the gradient filter (1 / length^4), or None.
    """

    p_hat: np.ndarray
    q_hat: np.ndarray
    trace_P: float | None = None
    trace_Q: float | None = None
    trace_P_grad: float | None = None
    trace_Q_grad: float | None = None


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
