"""The paper's errors at every step: the observer ``metrics`` (the ``/metrics`` topic of
the log).

All L2 norms are :meth:`harness.grid.Grid.l2`, ``(dx dy sum f^2)^(1/2)``.

The field metrics (:func:`metrics`, observer ``metrics``, :class:`FieldMetrics`) compare
the estimates and the mean-field density ``p`` (the ``meanfield`` plant's state; with
robots the loop's deterministic ``N -> infinity`` limit ``p_inf``) with the target.
Where the robots are is the observer ``swarm`` (:mod:`harness.observers.swarm`).

``phat_smoothed_target_l2`` = ``||p_hat - K_h p_*||`` (every step) is the Fig. 2
quantity for a debiased loop, whose estimates settle on ``K_h p_*``, not ``p_*``.

A moving target (``target=moving``, :mod:`harness.targets.moving`): every metric compares with
the target at the step's time, ``p_*(t)`` (:class:`harness.targets.moving.TargetPath`), so
``phi_l2`` is the tracking error. The finite-N floors are those of ``p_*(0)``
(:class:`harness.observers.swarm.SwarmTruth`).

Which keys the log carries, and in which order, is the log's contract
(:data:`harness.observers.log.METRIC_KEYS`).
"""

from __future__ import annotations

from harness.grid import Grid
from harness.observers.base import RunContext, Status
from harness.observers.theory import lyapunov, poincare_constant
from harness.parameters import number
from harness.protocols import Control, Estimator, carries_traces, law_record
from harness.records import StepRecord
from harness.targets.densities import Target
from harness.targets.moving import TargetPath

FIELD_KEYS = (
    "t",
    "phi_l2",
    "phat_target_l2",
    "eps_l2",
    "eps_g_l2",
    "kde_l2",
    "lyapunov",
    "mass",
    "trace_P",
    "trace_Q",
    "trace_P_grad",
    "trace_Q_grad",
)
"""The field metrics (:func:`metrics`), in log order."""


TRACE_KEYS = ("trace_P", "trace_Q", "trace_P_grad", "trace_Q_grad")
"""The filters' covariance traces among :data:`FIELD_KEYS` (None without filters)."""


def metrics(grid: Grid, target: Target, rec: StepRecord) -> dict[str, float | None]:
    """The per-step metrics:

    ``t`` (s); ``phi_l2`` = ``||p - p_*||`` and ``phat_target_l2`` = ``||p_hat - p_*||``
    (1 / length); ``eps_l2`` = ``||p_hat - p||`` (1 / length); ``eps_g_l2`` =
    ``||q_hat - G p||`` (1 / length^2); ``kde_l2`` = ``||p_KDE - p||`` (1 / length, None
    without a measurement); ``lyapunov`` = ``1/2 int (p - p_*)^2 / p_*`` (1 /
    length^2); ``mass`` = ``int p`` (1); ``trace_P``, ``trace_Q`` (density filter, 1 /
    length^2) and ``trace_P_grad``, ``trace_Q_grad`` (gradient filter, 1 / length^4),
    None without filters. ``p`` is the plant's mean-field density. On a domain with
    obstacles (``target.free``) ``G`` is free space's gradient (closed faces reflect,
    :meth:`harness.domains.base.FreeSpace.gradient`) and the Lyapunov function sums
    over the free cells (``p_*`` is 0 on the blocked ones).
    """
    est = rec.estimate
    p = rec.p_true
    free = target.free
    gradient = grid.gradient if free is None else free.gradient
    return {
        "t": rec.t,
        "phi_l2": grid.l2(p - target.p),
        "phat_target_l2": grid.l2(est.p_hat - target.p),
        "eps_l2": grid.l2(est.p_hat - p),
        "eps_g_l2": grid.l2(est.q_hat - gradient(p)),
        "kde_l2": None if rec.measurement is None else grid.l2(rec.measurement.p - p),
        "lyapunov": lyapunov(grid, p, target.p, free),
        "mass": grid.integrate(p),
        "trace_P": est.trace_P,
        "trace_Q": est.trace_Q,
        "trace_P_grad": est.trace_P_grad,
        "trace_Q_grad": est.trace_Q_grad,
    }


class FieldMetrics:
    """The field metrics of every step (:func:`metrics`; observer ``metrics``), and in
    the ``theory`` record the ``p_*``-weighted Poincare constant ``poincare_lambda``
    (1 / length^2, :func:`harness.observers.theory.poincare_constant`) and, for laws with a gain
    ``alpha``, the exact-estimate decay rate ``rate_exact`` = ``(alpha + sigma) lambda``
    (1 / s); for a law that says what it uses (its ``uses``, a phrase such as
    ``"estimate, gradient estimate, target score"``) and whether it divides by a
    density estimate (``divides_by_density``), ``law_uses`` and
    ``law_divides_by_density`` (``yes`` | ``no``).

    Args:
        grid, target, control: Run-time arguments.
        sigma: The robots' noise intensity (length^2 / s), for ``rate_exact``.
        estimator: The run's estimator (run-time argument): what this observer gives
            at every step (``gives``) depends on it. None (an observer built alone):
            every field metric.
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)

    def __init__(
        self,
        grid: Grid,
        target: Target,
        control: Control,
        sigma: float,
        estimator: Estimator | None = None,
    ) -> None:
        self.grid, self.target, self.control = grid, target, control
        self.gives: tuple[str, ...] = FIELD_KEYS
        if estimator is not None:
            absent = set() if estimator.uses_kde else {"kde_l2"}
            if not carries_traces(estimator):
                absent |= set(TRACE_KEYS)
            self.gives = tuple(k for k in FIELD_KEYS if k not in absent)
        self.sigma = number("sigma", sigma, 0.0)
        self.path = TargetPath(target)

    def initialize(self, run: RunContext) -> None:
        """``poincare_lambda`` and ``rate_exact`` into the theory record."""
        lam = poincare_constant(self.grid, self.target.p, self.target.free)
        run.theory["poincare_lambda"] = repr(lam)
        law = law_record(self.control)
        if "alpha" in law:
            run.theory["rate_exact"] = repr((law["alpha"] + self.sigma) * lam)
        if "uses" in law:
            run.theory["law_uses"] = law["uses"]
        if "divides_by_density" in law:
            run.theory["law_divides_by_density"] = "yes" if law["divides_by_density"] else "no"

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """The step's field metrics, against the target at the step's time."""
        values.update(metrics(self.grid, self.path.at(rec.t), rec))

    def finalize(self, status: Status) -> None:
        """Nothing to close."""
