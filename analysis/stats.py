"""Summaries over seeds, and comparisons of two laws on the same seeds.

A sweep writes one row per job (a dict: the overrides as columns, the job's
statistics as numbers). Jobs that differ only in their seed are repetitions of one
point; :func:`aggregate` groups the rows by the keys that define a point and summarises
every metric over the seeds by one of three rules, chosen by what the metric is:

* **a signed or bounded quantity** (a decay rate, a fraction): the mean and its
  Student-t confidence interval (:func:`mean_ci`),

      mean +- t_{1 - a/2, n - 1} s / sqrt(n),     a = 1 - level,

  with ``s`` the sample standard deviation (``ddof = 1``): the exact interval for the
  mean of ``n`` independent normal values of unknown variance;
* **a positive quantity** (an error norm, a ratio to the floor, effort, a wall time):
  the geometric mean and the same interval on the logarithms (:func:`geometric_ci`),

      exp(m +- t_{1 - a/2, n - 1} s_log / sqrt(n)),   m = mean(log x),

  exact for log-normal values, and never below zero, so it draws on a log axis. A
  point where such a quantity has a value <= 0 is summarised by the mean instead;
* **a time to an event that may not happen within the run** (the settling time, ``inf``
  for a run that ended first): the Kaplan-Meier median with the runs that never reached
  it censored at their end, and the Brookmeyer-Crowley interval (:func:`km_median`), so
  a run that never settled counts instead of being dropped.

Two laws run on the same seeds are compared by :func:`paired_ratio` (the geometric mean
of their per-seed ratios, a t interval on the log ratios and the two-sided p-value of
the paired t-test), several comparisons at once with Holm's step-down correction
(:func:`holm`).

Missing values (None, NaN, unparsable strings: failed or diverged jobs) are dropped and
counted out of ``n``; with ``n < 2`` an interval is undefined (NaN).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np
from scipy.stats import norm
from scipy.stats import t as student_t


@dataclass(frozen=True)
class MeanCI:
    """Mean, confidence interval ``[low, high]`` and the number of values ``n``."""

    mean: float
    low: float
    high: float
    n: int


def _as_float(value: Any) -> float:
    """``value`` as a float, NaN when it is None or not a number."""
    if value is None:
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def mean_ci(values: Iterable[Any], level: float = 0.95) -> MeanCI:
    """Mean and Student-t confidence interval of the finite values in ``values``.

    Args:
        values: Numbers (None, NaN and non-numbers are dropped).
        level: Confidence level in ``(0, 1)``.

    Returns:
        :class:`MeanCI`; ``mean`` is NaN for no values, ``low``/``high`` NaN for fewer
        than two.
    """
    _check_level(level)
    x = _finite(values)
    n = int(x.size)
    if n == 0:
        return MeanCI(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n < 2:
        return MeanCI(mean, math.nan, math.nan, 1)
    half = float(student_t.ppf(0.5 + level / 2, n - 1) * x.std(ddof=1) / math.sqrt(n))
    return MeanCI(mean, mean - half, mean + half, n)


def _finite(values: Iterable[Any]) -> np.ndarray:
    """The finite floats among ``values``."""
    x = np.array([_as_float(v) for v in values], dtype=float)
    return x[np.isfinite(x)]


def _check_level(level: float) -> None:
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")


def geometric_ci(values: Iterable[Any], level: float = 0.95) -> MeanCI:
    """Geometric mean and the Student-t interval of the logarithms (module docstring) of
    the finite values in ``values``, which must be positive; :func:`mean_ci` when one of
    them is not (a geometric mean is then undefined).

    Returns:
        :class:`MeanCI` with ``0 < low <= mean <= high`` when every value is positive.
    """
    _check_level(level)
    x = _finite(values)
    if x.size == 0 or (x <= 0).any():
        return mean_ci(x, level)
    logs = mean_ci(np.log(x), level)
    return MeanCI(math.exp(logs.mean), math.exp(logs.low), math.exp(logs.high), logs.n)


BEYOND = "beyond the run"
"""How a page or table reads a Kaplan-Meier median (or interval end) the runs did not
reach: more than half the seeds (or too many for the interval) ended before the event."""


@dataclass(frozen=True)
class Censored:
    """A Kaplan-Meier median time and its interval.

    Attributes:
        median: The least time at which the estimated fraction still waiting is at most
            1/2; ``inf`` when more than half the runs ended first.
        low: Lower end of the interval (``inf`` like ``median``).
        high: Upper end; ``inf`` when the data cannot bound it.
        events: Runs that reached the event.
        n: Runs counted (reached or censored).
    """

    median: float
    low: float
    high: float
    events: int
    n: int


def km_median(times: Iterable[Any], ends: Iterable[Any], level: float = 0.95) -> Censored:
    """The Kaplan-Meier median of times to an event, right-censored at each run's end.

    A run whose time is finite reached the event then; one whose time is ``inf`` ended
    at its ``ends`` entry without it (censored there); a run with a NaN or missing time,
    or an infinite time without a finite end, is dropped. With ``d_j`` events among the
    ``r_j`` runs still waiting at the ``j``-th distinct event time ``t_j``,

        S(t) = prod_{t_j <= t} (1 - d_j / r_j),
        Var S(t) = S(t)^2 sum_{t_j <= t} d_j / (r_j (r_j - d_j))       (Greenwood),

    the median is the least ``t_j`` with ``S(t_j) <= 1/2`` and the interval (Brookmeyer
    and Crowley, 1982) is the set of event times at which ``|S(t) - 1/2| <= z se(S(t))``,
    ``z`` the normal quantile of ``level``: from the first ``t_j`` with ``S(t_j) <= 1/2
    + z se`` to the first with ``S(t_j) < 1/2 - z se`` (``inf`` when there is none).
    """
    _check_level(level)
    t = np.array([_as_float(v) for v in times], dtype=float)
    e = np.array([_as_float(v) for v in ends], dtype=float)
    if t.shape != e.shape:
        raise ValueError(f"{t.size} times against {e.size} ends")
    event = np.isfinite(t)
    censored = np.isinf(t) & (t > 0) & np.isfinite(e)
    keep = event | censored
    t, e, event = t[keep], e[keep], event[keep]
    n = int(t.size)
    if n == 0:
        return Censored(math.nan, math.nan, math.nan, 0, 0)
    at = np.where(event, t, e)
    z = float(norm.ppf(0.5 + level / 2))
    surv, green = Fraction(1), 0.0  # S exactly: S(t_j) = 1/2 is a tie, not round-off
    median = low = high = math.inf
    for tj in np.unique(at[event]):
        r = int((at >= tj).sum())
        d = int((event & (at == tj)).sum())
        surv *= Fraction(r - d, r)
        green += d / (r * (r - d)) if r > d else math.inf
        se = float(surv) * math.sqrt(green) if math.isfinite(green) else 0.0
        if median == math.inf and surv <= 0.5:
            median = float(tj)
        if low == math.inf and surv <= 0.5 + z * se:
            low = float(tj)
        if high == math.inf and surv < 0.5 - z * se:
            high = float(tj)
    return Censored(median, low, high, int(event.sum()), n)


@dataclass(frozen=True)
class PairedRatio:
    """``a`` against ``b`` on the same seeds.

    Attributes:
        ratio: Geometric mean of the per-seed ratios ``a_i / b_i``.
        low: Lower end of its interval.
        high: Upper end.
        p: Two-sided p-value of the paired t-test of ``mean(log(a_i / b_i)) = 0``.
        n: Seeds with both values finite and positive.
    """

    ratio: float
    low: float
    high: float
    p: float
    n: int


def paired_ratio(a: Sequence[Any], b: Sequence[Any], level: float = 0.95) -> PairedRatio:
    """Compare two positive quantities measured on the same seeds (``a[i]`` and ``b[i]``
    on seed ``i``): the paired t-test on the log ratios, whose interval, exponentiated,
    is that of the geometric mean ratio. Pairs with a missing or non-positive value are
    dropped.
    """
    _check_level(level)
    if len(a) != len(b):
        raise ValueError(f"{len(a)} values against {len(b)}: pairs need the same seeds")
    x = np.array([_as_float(v) for v in a], dtype=float)
    y = np.array([_as_float(v) for v in b], dtype=float)
    keep = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    d = np.log(x[keep]) - np.log(y[keep])
    n = int(d.size)
    if n == 0:
        return PairedRatio(math.nan, math.nan, math.nan, math.nan, 0)
    ci = mean_ci(d, level)
    if n < 2:
        return PairedRatio(math.exp(ci.mean), math.nan, math.nan, math.nan, n)
    sd = float(d.std(ddof=1))
    if sd == 0.0:
        p = 1.0 if ci.mean == 0.0 else 0.0
    else:
        p = float(2 * student_t.sf(abs(ci.mean) / (sd / math.sqrt(n)), n - 1))
    return PairedRatio(math.exp(ci.mean), math.exp(ci.low), math.exp(ci.high), p, n)


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of ``m`` p-values: sorted ascending, the ``k``-th
    (from 0) is multiplied by ``m - k``, made non-decreasing along the order and capped
    at 1; returned in the input order. Rejecting where the adjusted value is at most
    ``alpha`` keeps the family-wise error rate at ``alpha``. NaN stays NaN and does not
    count in ``m``.
    """
    p = np.array(pvalues, dtype=float)
    out = np.full(p.shape, math.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = ok.size
    running = 0.0
    for k, i in enumerate(ok[np.argsort(p[ok], kind="stable")]):
        running = max(running, min(1.0, (m - k) * p[i]))
        out[i] = running
    return out.tolist()


def _hashable(value: Any) -> Any:
    """``value`` as a dictionary key: itself when hashable, else its type and ``repr``
    (a list or mapping in a foreign config).
    """
    try:
        hash(value)
    except TypeError:
        return (type(value).__name__, repr(value))
    return value


def aggregate(
    rows: Iterable[Mapping[str, Any]],
    point_keys: Sequence[str],
    metric_keys: Sequence[str],
    level: float = 0.95,
    log_scale: Collection[str] = (),
    censored: Mapping[str, str] | None = None,
) -> list[dict[str, Any]]:
    """Aggregate per-job rows into one row per point.

    Args:
        rows: Per-job rows (e.g. the rows of ``analysis.sweep``'s per-job CSV).
        point_keys: Columns that define a point (e.g. ``["agents.n", "kde.debias"]``;
            not the seed). A row without a key counts as the value None for it.
        metric_keys: Columns to aggregate.
        level: Confidence level.
        log_scale: Metrics that are positive quantities: geometric means
            (:func:`geometric_ci`).
        censored: Metrics that are times to an event (``inf``: the run ended first),
            each mapped to the column of the run's end: Kaplan-Meier medians
            (:func:`km_median`). The others: means (:func:`mean_ci`).

    Returns:
        One dict per point, in order of first appearance: the point's key values, then
        for every metric ``m``: ``m_mean`` (the mean, geometric mean or median),
        ``m_ci_low``, ``m_ci_high`` and ``m_n`` (the number of finite values; for a
        censored metric the runs that reached the event), and ``jobs``, the number of
        rows of the point.
    """
    censored = dict(censored or {})
    groups: dict[tuple[Any, ...], list[Mapping[str, Any]]] = {}
    for row in rows:
        groups.setdefault(tuple(_hashable(row.get(k)) for k in point_keys), []).append(row)
    out = []
    for members in groups.values():
        agg: dict[str, Any] = {k: members[0].get(k) for k in point_keys}
        agg["jobs"] = len(members)
        for m in metric_keys:
            if m in censored:
                km = km_median(
                    [r.get(m) for r in members], [r.get(censored[m]) for r in members], level
                )
                agg[f"{m}_mean"] = km.median
                agg[f"{m}_ci_low"] = km.low
                agg[f"{m}_ci_high"] = km.high
                agg[f"{m}_n"] = km.events
                continue
            summary = geometric_ci if m in log_scale else mean_ci
            ci = summary((r.get(m) for r in members), level)
            agg[f"{m}_mean"] = ci.mean
            agg[f"{m}_ci_low"] = ci.low
            agg[f"{m}_ci_high"] = ci.high
            agg[f"{m}_n"] = ci.n
        out.append(agg)
    return out
