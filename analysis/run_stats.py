"""The statistics of one run, from its log: what each row of a sweep's CSV holds.

Tail statistics use the last ``tail`` fraction of the run (a declared or given
fraction, :mod:`analysis.declaration`). Norms in 1/length, rates in 1/s:

* ``phi_tail_mean``, ``phi_tail_sup``, ``phat_tail_mean``, ``eps_tail_mean``,
  ``eps_g_tail_mean`` over the tail; ``phi_sup``, ``eps_sup``, ``eps_g_sup`` over the
  whole run; ``rate_fit``, the least-squares slope of ``-log ||Phi||`` over the second
  half of the run (:func:`decay_rate`); ``rate_theory`` from the log's ``theory`` record;
  ``t_end`` (s), the last logged time.
* Swarm statistics (1/length, ``swarm_w2`` in length; NaN without robots):
  ``swarm_tail_mean``, ``est_swarm_tail_mean``, ``limit_swarm_tail_mean``,
  ``limit_target_tail_mean`` (tail means of the metrics of the same names without
  ``_l2``), ``swarm_w2_last`` (the last evaluated ``swarm_w2``), the floors
  ``swarm_floor_mean``/``_lo``/``_hi`` and ``swarm_w2_floor_mean``/``_lo``/``_hi`` from
  the ``theory`` record, ``swarm_ratio`` = ``swarm_tail_mean / swarm_floor_mean``,
  ``swarm_w2_tail_mean`` (the tail mean of the evaluated ``swarm_w2``, length) and
  ``swarm_w2_ratio`` = ``swarm_w2_tail_mean / swarm_w2_floor_mean``.
* ``ms_per_step``, the run's wall time per step (ms, from the ``status`` record's
  ``wall_s`` and the number of steps; set by :func:`analysis.rows.analyse`).
* Decentralised statistics (NaN for other runs, :data:`NETWORK_STATS`):
  ``central_gap_tail_mean``, ``consensus_tail_mean`` (1/length), ``messages_tail_mean``
  (messages per robot per step), ``bytes_tail_mean`` (bytes per robot per step),
  ``message_bytes_tail_mean`` (bytes of the largest message), ``disagreement_tail_mean``
  (length / s), ``degree_tail_mean``, ``components_tail_mean``,
  ``connectivity_tail_mean``.
* Motion statistics (:func:`motion_stats`): ``effort_integral`` (length^2 / s),
  ``speed_tail_mean`` (length / s), ``settling_time`` (s; ``inf``: never settled),
  ``tracking_tail_mean`` (length / s) and ``age_tail_mean`` (s).
* Start-region statistics (a domain with obstacles, :func:`start_stats`; NaN for other
  runs), dimensionless unless said: ``start_target_mass`` (``p_*``'s mass in the
  support of the initial density), ``start_fraction_tail_mean`` (the tail mean of the
  robots' fraction there), ``start_excess_tail_mean`` (the tail mean of that fraction
  less the target's mass) and ``start_half_time`` (s; ``inf``: never), the first time
  the excess is at most half its value at the start.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from analysis.load import RunLog

START_STATS = (
    "start_target_mass",
    "start_fraction_tail_mean",
    "start_excess_tail_mean",
    "start_half_time",
)
"""The start-region statistics (:func:`start_stats`)."""

STATS = (
    "phi_tail_mean",
    "phi_tail_sup",
    "phi_sup",
    "phat_tail_mean",
    "eps_tail_mean",
    "eps_g_tail_mean",
    "eps_sup",
    "eps_g_sup",
    "rate_fit",
    "rate_theory",
    "t_end",
    "swarm_tail_mean",
    "est_swarm_tail_mean",
    "limit_swarm_tail_mean",
    "limit_target_tail_mean",
    "swarm_w2_last",
    "swarm_floor_mean",
    "swarm_floor_lo",
    "swarm_floor_hi",
    "swarm_w2_floor_mean",
    "swarm_w2_floor_lo",
    "swarm_w2_floor_hi",
    "swarm_ratio",
    "swarm_w2_tail_mean",
    "swarm_w2_ratio",
    "ms_per_step",
    "central_gap_tail_mean",
    "consensus_tail_mean",
    "messages_tail_mean",
    "bytes_tail_mean",
    "message_bytes_tail_mean",
    "disagreement_tail_mean",
    "degree_tail_mean",
    "components_tail_mean",
    "connectivity_tail_mean",
    "effort_integral",
    "speed_tail_mean",
    "settling_time",
    "tracking_tail_mean",
    "age_tail_mean",
    *START_STATS,
)
"""Every statistic of a run, in the order of the CSV's columns."""

LOG_SCALE = frozenset(
    {
        "phi_tail_mean", "phi_tail_sup", "phi_sup", "phat_tail_mean", "eps_tail_mean",
        "eps_g_tail_mean", "eps_sup", "eps_g_sup", "swarm_tail_mean", "est_swarm_tail_mean",
        "limit_swarm_tail_mean", "limit_target_tail_mean", "swarm_w2_last",
        "swarm_floor_mean", "swarm_floor_lo", "swarm_floor_hi", "swarm_w2_floor_mean",
        "swarm_w2_floor_lo", "swarm_w2_floor_hi", "swarm_ratio", "swarm_w2_tail_mean",
        "swarm_w2_ratio", "ms_per_step", "central_gap_tail_mean", "consensus_tail_mean",
        "message_bytes_tail_mean", "disagreement_tail_mean", "effort_integral",
        "speed_tail_mean", "tracking_tail_mean", "wall_s",
    }
)  # fmt: skip
"""Statistics that are positive quantities (norms, distances, their ratios to the floors,
effort, speeds, wall times): summarised over seeds by geometric means with intervals on
the log scale (:func:`analysis.stats.geometric_ci`). The rest are means: the fitted and
theoretical rates (signed), ``t_end``, counts that may be 0 (messages, bytes, degree,
components), the algebraic connectivity (0 on a disconnected graph), the command's age
(0 without a link) and the start region's fractions."""

CENSORED = {"settling_time": "t_end", "start_half_time": "t_end"}
"""Times to an event, ``inf`` for a run that ended first, each with the statistic holding
the run's end: summarised by Kaplan-Meier medians with those runs censored at their end
(:func:`analysis.stats.km_median`)."""


def decay_rate(t: np.ndarray, phi: np.ndarray) -> float:
    """Least-squares slope of ``-log phi`` over the second half of the run (1 / s)."""
    keep = (t >= t[-1] / 2) & np.isfinite(phi) & (phi > 0)
    if keep.sum() < 3:
        return math.nan
    slope = np.polyfit(t[keep], np.log(phi[keep]), 1)[0]
    return float(-slope)


class SweepWarning(UserWarning):
    """A log whose metadata or metrics are not what this project writes."""


def _stat(fn: Any, values: np.ndarray) -> float:
    """``fn(values)`` over the finite entries; NaN when there are none."""
    finite = values[np.isfinite(values)]
    return float(fn(finite)) if finite.size else math.nan


def job_stats(run: RunLog, tail: float) -> dict[str, float]:
    """The statistics of one run (see the module docstring); NaN for a statistic whose
    metric the log lacks, and a :class:`SweepWarning` for metadata that is not a number.
    """
    m = run.metrics
    t = m["t"]
    last = t >= t[-1] * (1 - tail)
    missing = np.full(t.shape, np.nan)

    def col(key: str) -> np.ndarray:
        return m.get(key, missing)

    theory = run.metadata.get("theory", {})
    rate_theory = number(theory.get("rate_exact", "nan"))
    if "rate_exact" in theory and not math.isfinite(rate_theory):
        warnings.warn(
            f"{run.path}: theory record rate_exact={theory.get('rate_exact')!r} is not a "
            "number; rate_theory is NaN",
            SweepWarning,
            stacklevel=2,
        )
    return {
        "phi_tail_mean": _stat(np.mean, col("phi_l2")[last]),
        "phi_tail_sup": _stat(np.max, col("phi_l2")[last]),
        "phi_sup": _stat(np.max, col("phi_l2")),
        "phat_tail_mean": _stat(np.mean, col("phat_target_l2")[last]),
        "eps_tail_mean": _stat(np.mean, col("eps_l2")[last]),
        "eps_g_tail_mean": _stat(np.mean, col("eps_g_l2")[last]),
        "eps_sup": _stat(np.max, col("eps_l2")),
        "eps_g_sup": _stat(np.max, col("eps_g_l2")),
        "rate_fit": decay_rate(t, col("phi_l2")),
        "rate_theory": rate_theory,
        "t_end": float(t[-1]),
        **swarm_stats(run, last),
    }


def swarm_stats(run: RunLog, last: np.ndarray) -> dict[str, float]:
    """The swarm statistics of one run (NaN without robots)."""
    m, theory = run.metrics, run.metadata.get("theory", {})

    def tail_mean(key: str) -> float:
        values = m.get(key, np.array([]))[last] if key in m else np.array([])
        values = values[np.isfinite(values)]
        return float(values.mean()) if values.size else math.nan

    w2 = m.get("swarm_w2", np.array([]))
    w2 = w2[np.isfinite(w2)]
    out = {
        "swarm_tail_mean": tail_mean("swarm_l2"),
        "est_swarm_tail_mean": tail_mean("est_swarm_l2"),
        "limit_swarm_tail_mean": tail_mean("limit_swarm_l2"),
        "limit_target_tail_mean": tail_mean("limit_target_l2"),
        "swarm_w2_last": float(w2[-1]) if w2.size else math.nan,
    }
    for name, key in (("swarm_floor", "swarm_l2_floor"), ("swarm_w2_floor", "swarm_w2_floor")):
        for part in ("mean", "lo", "hi"):
            out[f"{name}_{part}"] = number(theory.get(f"{key}_{part}"))
    out["swarm_ratio"] = out["swarm_tail_mean"] / out["swarm_floor_mean"]
    out["swarm_w2_tail_mean"] = tail_mean("swarm_w2")
    out["swarm_w2_ratio"] = out["swarm_w2_tail_mean"] / out["swarm_w2_floor_mean"]
    for name, key in NETWORK_STATS.items():
        out[name] = tail_mean(key)
    out.update(motion_stats(run, last, out["swarm_floor_mean"]))
    out.update(start_stats(run, last))
    return out


START_HALF = 0.5
"""``start_half_time`` is the first time the start region's excess is at most this
fraction of its value at the start."""


def start_stats(run: RunLog, last: np.ndarray) -> dict[str, float]:
    """How the swarm leaves the region where it started (a domain with obstacles: the
    metrics ``start_fraction`` and ``start_target_mass`` of
    :class:`harness.observers.swarm_metrics.StartRegion`), dimensionless: the target's
    mass in the region ``start_target_mass`` (its last evaluated value), the tail mean of
    the robots' fraction there ``start_fraction_tail_mean``, the tail mean of the excess
    ``start_fraction - start_target_mass`` (``start_excess_tail_mean``; 0 when the region
    holds the target's share, positive when robots are left behind), and
    ``start_half_time`` (s): the first evaluated time at which the excess is at most
    :data:`START_HALF` times its first evaluated value (``inf`` when it never is; NaN
    when the first excess is not positive). All NaN without the metrics.
    """
    m = run.metrics
    out = dict.fromkeys(START_STATS, math.nan)
    if "start_fraction" not in m or "start_target_mass" not in m:
        return out
    t, fraction, mass = m["t"], m["start_fraction"], m["start_target_mass"]
    seen = np.flatnonzero(np.isfinite(fraction) & np.isfinite(mass))
    if not seen.size:
        return out
    excess = fraction - mass
    out["start_target_mass"] = float(mass[seen[-1]])
    out["start_fraction_tail_mean"] = _stat(np.mean, fraction[last])
    out["start_excess_tail_mean"] = _stat(np.mean, excess[last])
    first = excess[seen[0]]
    if first > 0:
        below = seen[excess[seen] <= START_HALF * first]
        out["start_half_time"] = float(t[below[0]]) if below.size else math.inf
    return out


SETTLING_FACTOR = 1.5
"""``settling_time`` is the first time ``swarm_l2 <= SETTLING_FACTOR`` times the mean of
its finite-N floor."""


def motion_stats(run: RunLog, last: np.ndarray, floor_mean: float) -> dict[str, float]:
    """What a law costs and how fast it settles: ``effort_integral`` = ``int effort dt``
    (length^2 / s, trapezoids over the logged steps), ``speed_tail_mean`` (the tail mean
    of ``mean_speed``, length / s: motion at steady state), and ``settling_time`` (s): the
    first time ``swarm_l2 <= SETTLING_FACTOR floor_mean``, ``inf`` when it never is (NaN
    without robots or without a floor); ``tracking_tail_mean`` (length / s) and
    ``age_tail_mean`` (s), the tail means of ``tracking_error`` and ``command_age``.
    """
    m = run.metrics
    t = m["t"]
    out = {"effort_integral": math.nan, "speed_tail_mean": math.nan, "settling_time": math.nan}
    for name, key in (("tracking_tail_mean", "tracking_error"), ("age_tail_mean", "command_age")):
        out[name] = _stat(np.mean, m[key][last]) if key in m else math.nan
    effort = m.get("effort")
    if effort is not None and np.isfinite(effort).all():
        out["effort_integral"] = float(np.sum(0.5 * (effort[1:] + effort[:-1]) * np.diff(t)))
    speed = m.get("mean_speed")
    if speed is not None:
        out["speed_tail_mean"] = _stat(np.mean, speed[last])
    swarm = m.get("swarm_l2")
    if swarm is not None and math.isfinite(floor_mean) and np.isfinite(swarm).any():
        settled = np.flatnonzero(np.isfinite(swarm) & (swarm <= SETTLING_FACTOR * floor_mean))
        out["settling_time"] = float(t[settled[0]]) if settled.size else math.inf
    return out


NETWORK_STATS = {
    "central_gap_tail_mean": "central_gap_l2",
    "consensus_tail_mean": "consensus_l2",
    "messages_tail_mean": "messages",
    "bytes_tail_mean": "bytes",
    "message_bytes_tail_mean": "message_bytes",
    "disagreement_tail_mean": "command_disagreement",
    "degree_tail_mean": "mean_degree",
    "components_tail_mean": "components",
    "connectivity_tail_mean": "algebraic_connectivity",
}
"""Tail means of the decentralised loop's metrics (NaN for other runs)."""


def number(text: Any) -> float:
    """``text`` as a float; NaN when it is not a number."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan
