"""Records passed between the loop's components and its observers.

Kept apart from the loop so that observers (metrics, the MCAP logger) and components
(plants, estimators) share them without importing :mod:`harness.loop`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from harness.velocity import VelocityField, cap_vectors

if TYPE_CHECKING:
    from harness.targets.densities import Target


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
        v_applied: Velocity field applied over the last interval (None at ``t = 0``).
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
    """Each robot's own estimate, when every robot estimates the density on its own.

    Attributes:
        p_hat: Robot ``i``'s density estimate in row ``i``, ``(N, M)`` (1 / length^2),
            cells in C order of the grid.
        q_hat: Gradient estimates ``(N, 2M)`` (``x`` block then ``y`` block, 1 /
            length^3), or None when each robot takes the central differences of its own
            ``p_hat_i`` (a law evaluates them at the robot's cells).
        reference: The centralised reference's density estimate ``(M,)`` (1 /
            length^2) the robots are measured against, or None. A law given it also
            reports the velocities it would command from it at the robots' positions
            (:attr:`Command.reference`).
        order: The order of those central differences, 2 (``G``) or 4 (``G_4``)
            (:func:`harness.grid.grid_gradient`); also used for the reference.

    The arrays may be an estimator's own state (a copy would cost ``N M`` values per
    step), like ``StepRecord.positions``: valid until the next step, which may
    overwrite them in place. Observers that keep them must copy.
    """

    p_hat: np.ndarray
    q_hat: np.ndarray | None
    reference: np.ndarray | None = None
    order: int = 2


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
        robots: Each robot's own estimate, when the robots estimate on their own
            (``p_hat`` and ``q_hat`` are then the robots' means), else None. A law that
            accepts it moves each robot by the law of its own estimate.
        fields: Further density fields ``(ny, nx)`` (1 / length^2) the estimator
            publishes, by name: logged as ``/fields/<name>`` at the field rate, in this
            order (see :mod:`harness.observers.log`).
        metrics: Further per-step numbers the estimator publishes, by name; the log
            writes the ones its contract lists (:data:`harness.observers.log.METRIC_KEYS`).
    """

    p_hat: np.ndarray
    q_hat: np.ndarray
    trace_P: float | None = None
    trace_Q: float | None = None
    trace_P_grad: float | None = None
    trace_Q_grad: float | None = None
    robots: RobotEstimates | None = None
    fields: Mapping[str, np.ndarray] = dc_field(default_factory=dict)
    metrics: Mapping[str, float] = dc_field(default_factory=dict)


@dataclass(frozen=True)
class ControlInput:
    """What a control law may use at time ``t`` (s).

    Attributes:
        t: Time (s).
        estimate: The estimates (and, when the robots estimate on their own, each
            robot's own, ``estimate.robots``).
        positions: Robot positions ``(2, N)`` (length) as the law sees them (with the
            plant's localisation noise), None without robots (the mean-field plant, and
            the loop's ``N -> infinity`` limit).
        density: Without robots, the mean-field density ``(ny, nx)`` (1 / length^2) that
            stands for them (the mean-field plant's state; the loop's limit
            ``p_inf``): a law of the positions evaluates its mean-field form on it.
            None with robots.
        target: The target at ``t``, ``p_*(t)`` (a :class:`harness.targets.densities.Target`),
            when it moves (:mod:`harness.targets.moving`); None for a static target (the law's
            own). A law that follows a moving target uses it in place of its own
            (:class:`harness.control.field.FieldLaw`).
        target_rate: ``d_t p_*`` on the grid at ``t``, ``(ny, nx)`` (1 / (length^2 s)),
            when the target moves, else None.
    """

    t: float
    estimate: Estimate
    positions: np.ndarray | None = None
    density: np.ndarray | None = None
    target: Target | None = None
    target_rate: np.ndarray | None = None


@dataclass(frozen=True)
class Command:
    """A control law's output: a velocity field on the grid, one velocity per robot,
    or both.

    Attributes:
        field: The velocity field (length / s), or None for a law that only moves
            robots. The mean-field plant, the loop's ``N -> infinity`` limit and
            the filters' transport model ``A(v)`` use it.
        robots: Velocities ``(2, N)`` (length / s) the robots move with, or None: the
            robots then move by the field's bilinear interpolant at their positions.
        reference: Velocities ``(2, N)`` (length / s) the law commands at the robots'
            positions from the centralised reference's estimate
            (:attr:`RobotEstimates.reference`, with the robots' central differences),
            or None; compared with ``robots`` by the ``command_disagreement`` metric.
    """

    field: VelocityField | None
    robots: np.ndarray | None = None
    reference: np.ndarray | None = None

    def capped(self, v_max: float | None) -> Command:
        """The command with every speed at most ``v_max`` (length / s; None: itself).

        Each robot's velocity and each cell-centre vector of the field is scaled by
        ``min(1, v_max / |v|)`` (direction kept), and each face-normal value is clipped
        to ``[-v_max, v_max]``; robots that follow the field interpolate capped centres,
        so their speed is at most ``v_max`` too (a convex combination).
        """
        if v_max is None:
            return self
        field = None if self.field is None else self.field.capped(v_max)
        robots = None if self.robots is None else cap_vectors(self.robots, v_max)
        reference = None if self.reference is None else cap_vectors(self.reference, v_max)
        return Command(field, robots, reference)

    def is_finite(self) -> bool:
        """True when every value of the field and of the robots' velocities is finite."""
        ok = self.field is None or self.field.is_finite()
        return ok and (self.robots is None or bool(np.isfinite(self.robots).all()))


@dataclass(frozen=True)
class StepRecord:
    """Everything the observers may see after a step (or at ``t = 0``).

    ``positions`` is None without robots; ``headings`` (unit vectors ``(cos theta,
    sin theta)``, ``(2, N)``) is None for robots without a heading; ``measurement`` is
    None when the estimator takes none (``exact``, ``injected``); ``command`` is the
    control law's output at ``t``, held over the next step.
    """

    step: int
    t: float
    p_true: np.ndarray
    measurement: Measurement | None
    estimate: Estimate
    command: Command
    positions: np.ndarray | None
    headings: np.ndarray | None = None
