"""The per-step metrics of a run (the ``/metrics`` topic of the log).

All L2 norms are :meth:`harness.grid.Grid.l2`, ``(dx dy sum f^2)^(1/2)``.
"""

from __future__ import annotations

from harness.densities import Target
from harness.grid import Grid
from harness.records import StepRecord
from harness.theory import lyapunov

METRIC_KEYS = (
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
"""The keys of :func:`metrics`, in log order."""

ALWAYS_NUMBERS = ("t", "phi_l2", "phat_target_l2", "eps_l2", "eps_g_l2", "lyapunov", "mass")
"""Keys that are never null."""


def metrics(grid: Grid, target: Target, rec: StepRecord) -> dict[str, float | None]:
    """The per-step metrics:

    ``t`` (s); ``phi_l2`` = ``||p - p_*||`` and ``phat_target_l2`` = ``||p_hat - p_*||``
    (1 / length); ``eps_l2`` = ``||p_hat - p||`` (1 / length); ``eps_g_l2`` =
    ``||q_hat - G p||`` (1 / length^2); ``kde_l2`` = ``||p_KDE - p||`` (1 / length, None
    without a measurement); ``lyapunov`` = ``1/2 int (p - p_*)^2 / p_*`` (1 /
    length^2); ``mass`` = ``int p`` (1); ``trace_P``, ``trace_Q`` (density filter, 1 /
    length^2) and ``trace_P_grad``, ``trace_Q_grad`` (gradient filter, 1 / length^4),
    None without filters. ``p`` is the plant's mean-field density.
    """
    est = rec.estimate
    p = rec.p_true
    return {
        "t": rec.t,
        "phi_l2": grid.l2(p - target.p),
        "phat_target_l2": grid.l2(est.p_hat - target.p),
        "eps_l2": grid.l2(est.p_hat - p),
        "eps_g_l2": grid.l2(est.q_hat - grid.gradient(p)),
        "kde_l2": None if rec.measurement is None else grid.l2(rec.measurement.p - p),
        "lyapunov": lyapunov(grid, p, target.p),
        "mass": grid.integrate(p),
        "trace_P": est.trace_P,
        "trace_Q": est.trace_Q,
        "trace_P_grad": est.trace_P_grad,
        "trace_Q_grad": est.trace_Q_grad,
    }
