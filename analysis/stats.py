"""Per-point means and Student-t confidence intervals over seeds.

A sweep writes one row per job (a dict: the overrides as columns, the job's
statistics as numbers). Jobs that differ only in their seed are repetitions of one
point; :func:`aggregate` groups the rows by the keys that define a point and gives,
for every metric, the mean over the seeds and its confidence interval

    mean +- t_{1 - a/2, n - 1} s / sqrt(n),     a = 1 - level,

with ``s`` the sample standard deviation (``ddof = 1``) and ``t_{q, n - 1}`` the
Student quantile with ``n - 1`` degrees of freedom: the exact interval for the mean
of ``n`` independent normal values of unknown variance. Missing values (None, NaN,
unparsable strings: failed or diverged jobs) are dropped and counted out of ``n``;
with ``n < 2`` the interval is undefined (NaN).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
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
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    x = np.array([_as_float(v) for v in values], dtype=float)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return MeanCI(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n < 2:
        return MeanCI(mean, math.nan, math.nan, 1)
    half = float(student_t.ppf(0.5 + level / 2, n - 1) * x.std(ddof=1) / math.sqrt(n))
    return MeanCI(mean, mean - half, mean + half, n)


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
) -> list[dict[str, Any]]:
    """Aggregate per-job rows into one row per point.

    Args:
        rows: Per-job rows (e.g. the rows of ``analysis.sweep``'s per-job CSV).
        point_keys: Columns that define a point (e.g. ``["agents.n", "kde.debias"]``;
            not the seed). A row without a key counts as the value None for it.
        metric_keys: Columns to aggregate.
        level: Confidence level.

    Returns:
        One dict per point, in order of first appearance: the point's key values, then
        for every metric ``m``: ``m_mean``, ``m_ci_low``, ``m_ci_high`` and ``m_n`` (the
        number of finite values), and ``jobs``, the number of rows of the point.
    """
    groups: dict[tuple[Any, ...], list[Mapping[str, Any]]] = {}
    for row in rows:
        groups.setdefault(tuple(_hashable(row.get(k)) for k in point_keys), []).append(row)
    out = []
    for members in groups.values():
        agg: dict[str, Any] = {k: members[0].get(k) for k in point_keys}
        agg["jobs"] = len(members)
        for m in metric_keys:
            ci = mean_ci((r.get(m) for r in members), level)
            agg[f"{m}_mean"] = ci.mean
            agg[f"{m}_ci_low"] = ci.low
            agg[f"{m}_ci_high"] = ci.high
            agg[f"{m}_n"] = ci.n
        out.append(agg)
    return out
