"""Analyse a sweep from its logs: a tidy CSV and the study's figures.

    python -m analysis.sweep SWEEP_DIR [--out DIR] [--tail 0.25]

Reads every job directory below ``SWEEP_DIR`` that holds a ``run.mcap``, and only the
log: its ``config`` record (the resolved config), its ``status`` and ``theory`` records
and its ``/metrics``. Writes ``sweep.csv`` (one row per job; every config key whose
value differs between the jobs is a column) and the figure the study declares.

Declaration. A study preset (``conf/experiment/*.yaml``) declares its analysis in a
top-level ``analysis`` block, which every job logs with its config::

    analysis:
      figure: iss_gain                    # a name of FIGURES
      primary: [law, estimator.delta]     # the keys the study varies (besides seed)
      tail: 0.25                          # tail fraction of each run

``primary`` (default: every varied key but ``seed``) lists the keys that make the
study's points, ``law`` standing for the control law's class (the logged
``control._target_``); jobs that differ in any other key (but ``seed``) are more than
one sweep, and the analysis refuses them. ``tail`` (default 0.25) is the fraction of
each run the tail statistics use; ``--tail`` overrides it. The figures
(:data:`FIGURES`), each drawing against the primary keys it names:

* ``iss_gain`` (``law``, ``estimator.delta``; ``iss_gain.png/.pdf``): the tail supremum
  of ``||Phi|| = ||p - p_*||`` against the supremum of ``||eps||``, one curve per
  control law, with the fitted linear gain;
* ``debias_n`` (``agents.n``, ``kde.debias``; ``debias_n.png/.pdf``): ``swarm_l2`` and
  ``swarm_w2`` with their finite-N floors against N, the paper's loop against the
  debiased loop, and ``||p_hat - p_*||`` beside them;
* ``agents_n`` (``agents.n``; ``agents_n.png/.pdf``): tail means of ``||p_hat -
  p_*||``, ``swarm_l2`` (with its floor) and the decomposition terms against N;
* ``distributed_r`` (``estimator.radius``; ``distributed_r.png/.pdf``): the
  decentralised loop's ``central_gap_l2`` and ``consensus_l2``, ``swarm_l2`` with its
  floor and the mean estimate's ``||p_hat - p_*||``, and the messages and components,
  against the radius;
* ``conv_grid_agents`` (``grid.n``; ``conv_grid_agents.png/.pdf``): tail ``||p_hat -
  p_*||``, ``swarm_l2`` and the decomposition terms against n, and the wall time per
  step;
* ``laws_n``, ``laws_iss``, ``heat_floor``, ``laws_noise``: the law studies
  (:mod:`analysis.laws`);
* ``robots`` (``plant._target_``, ``law``) and ``link`` (``link.period``,
  ``link.latency``, ``link.loss``): the robot and link studies (:mod:`analysis.robots`);
* ``convergence`` (``convergence.png/.pdf``): ``||Phi||`` curves overlaid, labelled by
  the first varied key, and the fitted exponential rates next to the theoretical
  ``(alpha + sigma) lambda``. The generic figure: a sweep without a declaration (one
  typed on the command line) gets it.

An unknown figure name or declaration key, or jobs that declare different analyses, stop
the analysis with one line (exit status 2).

Statistics (the CSV's columns; norms in 1/length, rates in 1/s): ``phi_tail_mean``,
``phi_tail_sup``, ``phat_tail_mean``, ``eps_tail_mean``, ``eps_g_tail_mean`` over the
last ``tail`` fraction of the run; ``phi_sup``, ``eps_sup``, ``eps_g_sup`` over the
whole run;
``rate_fit``, the least-squares slope of ``-log ||Phi||`` over the second half of the
run; ``rate_theory`` from the log's ``theory`` record; ``wall_s`` (s) from its ``status``
record. Swarm statistics (1/length, ``swarm_w2`` in length; empty without robots):
``swarm_tail_mean``, ``est_swarm_tail_mean``, ``limit_swarm_tail_mean``,
``limit_target_tail_mean`` (tail means of the metrics of the same names without
``_l2``), ``swarm_w2_last`` (the last evaluated ``swarm_w2``), the floors
``swarm_floor_mean``/``_lo``/``_hi`` and ``swarm_w2_floor_mean``/``_lo``/``_hi`` from the
``theory`` record, ``swarm_ratio`` = ``swarm_tail_mean / swarm_floor_mean``,
``swarm_w2_tail_mean`` (the tail mean of the evaluated ``swarm_w2``, length) and
``swarm_w2_ratio`` = ``swarm_w2_tail_mean / swarm_w2_floor_mean``;
``ms_per_step``, the run's wall time per step (ms, from ``wall_s`` and the number of steps).
Decentralised statistics (empty for other runs): ``central_gap_tail_mean``,
``consensus_tail_mean`` (1/length), ``messages_tail_mean`` (messages per robot per step),
``bytes_tail_mean`` (bytes per robot per step), ``message_bytes_tail_mean`` (bytes of the
largest message), ``disagreement_tail_mean`` (length / s),
``degree_tail_mean``, ``components_tail_mean``, ``connectivity_tail_mean`` (tail means
of ``central_gap_l2``, ``consensus_l2``, ``messages``, ``bytes``, ``message_bytes``,
``command_disagreement``, ``mean_degree``, ``components``, ``algebraic_connectivity``).
Motion statistics (:func:`motion_stats`): ``effort_integral`` (length^2 / s),
``speed_tail_mean`` (length / s), ``settling_time`` (s; ``inf``: never settled),
``tracking_tail_mean`` (length / s) and ``age_tail_mean`` (s), the tail means of the
robots' ``tracking_error`` and ``command_age``.

Seeds. Rows that differ only in ``seed`` are one point: ``sweep_aggregated.csv`` has one
row per point with, for every statistic ``s``, ``s_mean``, ``s_ci_low``, ``s_ci_high``
(95 % Student-t confidence interval of the mean over the seeds) and ``s_n``, and
``jobs``; the figures draw these means with their intervals as error bars.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from analysis.configs import component, flatten, logged_config
from analysis.load import LogError, LogWarning, load_run
from analysis.output import atomic_path
from analysis.plotting import save_figure
from analysis.stats import aggregate

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
)


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


def job_stats(run, tail: float) -> dict[str, float]:
    """The statistics of one run (see the module docstring); NaN for a statistic whose
    metric the log lacks, and a :class:`SweepWarning` for metadata that is not a number.
    """
    m = run.metrics
    t = m["t"]
    last = t >= t[-1] * (1 - tail)
    missing = np.full(t.shape, np.nan)

    def col(key):
        return m.get(key, missing)

    theory = run.metadata.get("theory", {})
    rate_theory = _float(theory.get("rate_exact", "nan"))
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


def swarm_stats(run, last: np.ndarray) -> dict[str, float]:
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
            out[f"{name}_{part}"] = _float(theory.get(f"{key}_{part}"))
    out["swarm_ratio"] = out["swarm_tail_mean"] / out["swarm_floor_mean"]
    out["swarm_w2_tail_mean"] = tail_mean("swarm_w2")
    out["swarm_w2_ratio"] = out["swarm_w2_tail_mean"] / out["swarm_w2_floor_mean"]
    for name, key in NETWORK_STATS.items():
        out[name] = tail_mean(key)
    out.update(motion_stats(run, last, out["swarm_floor_mean"]))
    return out


SETTLING_FACTOR = 1.5
"""``settling_time`` is the first time ``swarm_l2 <= SETTLING_FACTOR`` times the mean of
its finite-N floor."""


def motion_stats(run, last: np.ndarray, floor_mean: float) -> dict[str, float]:
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


def mixed(rows: list[dict[str, Any]], primary: list[str]) -> list[str]:
    """Varied config keys that the ``primary`` keys do not explain: keys taking more than
    one value among jobs that agree on every primary key. Non-empty means the directory
    holds more than one sweep.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(
            repr([value(r, k) if k != "law" else r.get("law") for k in primary]), []
        ).append(r)
    out = []
    for key in varied(rows):
        if key in primary or key == "seed":
            continue
        if any(len({repr(value(r, key)) for r in g}) > 1 for g in groups.values()):
            out.append(key)
    return out


class MetricSeries(dict):
    """A run's metric arrays, where a metric the log lacks (a foreign or older log) reads
    as NaN at every time, so the figures draw what there is.
    """

    def __missing__(self, key: str) -> np.ndarray:
        return np.full(len(self.get("t", ())), np.nan)


def code_of(provenance: dict[str, str]) -> str:
    """The code a log was made by, from its ``provenance`` record: ``code_sha256`` (the
    commit, the diff's hash and the package versions), else the commit with ``+dirty``
    (logs from before the hash was recorded), else ``unknown``.
    """
    if provenance.get("code_sha256"):
        return str(provenance["code_sha256"])[:12]
    commit = str(provenance.get("git_commit", "unknown"))[:12]
    return commit + ("+dirty" if provenance.get("git_dirty") == "true" else "")


def mixed_code(rows: list[dict[str, Any]]) -> dict[str, int]:
    """The codes (:func:`code_of`) of the rows with their job counts, when more than one
    made them (empty otherwise): such logs are not one study.
    """
    counts: dict[str, int] = {}
    for r in rows:
        if "code" in r:
            counts[r["code"]] = counts.get(r["code"], 0) + 1
    return counts if len(counts) > 1 else {}


def analyse(
    sweep_dir: Path, tail: float | None = None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows of the CSV and the decoded metrics per job directory.

    Each row holds the job's directory, state, statistics, wall time, the short name
    of its control law (``law``) and its whole flattened config; :func:`varied` then
    picks the config keys that differ between jobs. The tail statistics use ``tail``,
    else the tail the job's declaration gives (:func:`declaration`), else 0.25.

    Raises:
        DeclarationError: for a job whose declaration is not one this module reads.
    """
    rows, series = [], {}
    for log_path in sorted(sweep_dir.glob("*/run.mcap")):
        job_dir = log_path.parent
        row: dict[str, Any] = {"dir": job_dir.name}
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LogWarning)
                run = load_run(log_path, topics={"/metrics"})
        except LogError as err:
            row["state"] = f"unreadable: {err}"
            rows.append(row)
            continue
        if run.recovery is not None:  # damaged or cut short: say so, whatever its status says
            row["recovery"] = run.recovery
            warnings.warn(f"{log_path}: {run.recovery}", SweepWarning, stacklevel=2)
        if run.foreign is not None:  # values read as NaN: say so
            warnings.warn(f"{log_path}: {run.foreign}", SweepWarning, stacklevel=2)
        flat = flatten(logged_config(run))
        row.update({CONFIG_PREFIX + k: v for k, v in flat.items()})
        row["code"] = code_of(run.metadata.get("provenance", {}))
        row["law"] = component(flat, "control")
        theory = run.metadata.get("theory", {})
        row["law_uses"] = theory.get("law_uses", "")
        row["law_divides_by_density"] = theory.get("law_divides_by_density", "")
        row["state"] = run.state if run.recovery is None else f"damaged ({run.state})"
        row["wall_s"] = _float(run.metadata.get("status", {}).get("wall_s"))
        if "t" in run.metrics and len(run.metrics["t"]) > 2:
            job_tail = tail if tail is not None else declaration(flat).tail
            row.update(job_stats(run, job_tail))
            steps = len(run.metrics["t"]) - 1
            row["ms_per_step"] = 1e3 * row["wall_s"] / steps
            series[job_dir.name] = MetricSeries(run.metrics)
        rows.append(row)
    return rows, series


def _float(text: Any) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


CONFIG_PREFIX = "cfg:"
"""Prefix of the config columns in the rows (dropped in the CSV header)."""


def varied(rows: list[dict[str, Any]]) -> list[str]:
    """Config keys (without the prefix) whose values differ between the rows, leaving
    out the logging and progress keys, the observers' nodes (their values are the
    public keys', such as ``observers.swarm.seed: ${seed}``) and a component's copy of
    the seed (a key equal to ``seed`` in every row that has it, such as
    ``control.seed: ${seed}``).
    """
    keys = sorted({k for r in rows for k in r if k.startswith(CONFIG_PREFIX)})
    out = []
    for k in keys:
        key = k[len(CONFIG_PREFIX) :]
        if key.startswith(("log.", "observers.")) or _copies_seed(rows, k):
            continue
        if len({repr(r.get(k)) for r in rows}) > 1:
            out.append(key)
    return out


def _copies_seed(rows: list[dict[str, Any]], column: str) -> bool:
    """Whether the config column ``column`` (a key other than ``seed``) holds the row's
    seed wherever it is set.
    """
    seed = CONFIG_PREFIX + "seed"
    if column == seed:
        return False
    found = [r for r in rows if r.get(column) is not None]
    return bool(found) and all(r.get(column) == r.get(seed) for r in found)


def value(row: dict[str, Any], key: str) -> Any:
    """The row's config value at ``key``."""
    return row.get(CONFIG_PREFIX + key)


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    """Tidy CSV: the varied config keys, the law, then the fixed columns."""
    keys = varied(rows)
    fixed = ["dir", "state", *STATS, "wall_s", "recovery"]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[*keys, "law", *fixed], restval="")
        writer.writeheader()
        for r in rows:
            out = {k: value(r, k) for k in keys}
            out["law"] = r.get("law", "")
            out.update({k: r.get(k, "") for k in fixed})
            writer.writerow(out)


def iss_figure(rows, out: Path) -> tuple[list[Path], dict[str, float]]:
    """Tail sup ||Phi|| against sup ||eps||, per control law, with fitted gains."""
    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    gains: dict[str, float] = {}
    groups: dict[str, list] = {}
    for r in rows:
        if "phi_tail_sup" in r:
            groups.setdefault(r.get("law") or "law", []).append(r)
    for law, group in sorted(groups.items()):
        group.sort(key=lambda r: float(value(r, "estimator.delta") or 0))
        x = np.array([r["eps_sup"] for r in group])
        y = np.array([r["phi_tail_sup"] for r in group])
        pos = x > 1e-12
        (line,) = ax.loglog(x[pos], y[pos], "o-", label=law)
        if pos.sum() >= 2:
            gains[law] = float(np.linalg.lstsq(x[pos, None], y[pos], rcond=None)[0][0])
            xs = np.geomspace(x[pos].min(), x[pos].max(), 20)
            ax.loglog(
                xs,
                gains[law] * xs,
                ":",
                color=line.get_color(),
                label=rf"fit $\gamma$ = {gains[law]:.3g}",
            )
        if (~pos).any():
            ax.axhline(
                y[~pos].max(), color=line.get_color(), ls="--", lw=0.8, label=f"{law}, no error"
            )
    ax.set_xlabel(r"$\sup_t \|\epsilon\|_{L^2}$ (1/length)")
    ax.set_ylabel(r"tail $\sup \|\Phi\|_{L^2}$ (1/length)")
    ax.set_title("ISS gain: tracking error against estimation error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, out, "iss_gain"), gains


DECOMPOSITION = {
    "phat_tail_mean": r"$\|\hat p - p_*\|$",
    "swarm_tail_mean": r"$\|K_h\mu_N - K_h p_*\|$ (robots)",
    "est_swarm_tail_mean": r"$\|\hat p - K_h\mu_N\|$ (estimator)",
    "limit_swarm_tail_mean": r"$\|K_h\mu_N - K_h p_\infty\|$ (finite N)",
    "limit_target_tail_mean": r"$\|K_h p_\infty - K_h p_*\|$ (limit loop)",
}
"""The statistics the agent-level figures draw against N or n, with their labels."""


def agents_figure(rows, out: Path) -> list[Path]:
    """Tail errors against the number of robots: means over the seeds with 95 % CIs."""
    agg = sorted(points(rows), key=lambda a: a["agents.n"])
    n = np.array([a["agents.n"] for a in agg], dtype=float)
    fig, ax = plt.subplots(figsize=(6.5, 4.8), constrained_layout=True)
    for stat, label in DECOMPOSITION.items():
        _errorbar(ax, n, agg, stat, label=label)
    _band(ax, n, agg, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("robots N")
    ax.set_ylabel("tail mean (1/length)")
    ax.set_title("errors against swarm size (mean over seeds, 95 % CI)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return save_figure(fig, out, "agents_n")


def points(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per point (the varied config keys but ``seed``): mean and 95 % CI of
    every statistic over the seeds (:func:`analysis.stats.aggregate`).
    """
    keys = [k for k in varied(rows) if k != "seed"]
    flat = [{**{k: value(r, k) for k in keys}, "law": r.get("law", ""), **r} for r in rows]
    done = [r for r in flat if r.get("state") == "completed"]
    return aggregate(done, [*keys, "law"], [*STATS, "wall_s"])


def write_points(agg: list[dict[str, Any]], path: Path) -> None:
    """``sweep_aggregated.csv``."""
    if not agg:
        return
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(agg[0]))
        writer.writeheader()
        writer.writerows(agg)


def _errorbar(ax, x, agg, stat: str, **kwargs) -> None:
    """Means of ``stat`` with their 95 % intervals as error bars (log-log)."""
    mean = np.array([a[f"{stat}_mean"] for a in agg], dtype=float)
    low = np.array([a[f"{stat}_ci_low"] for a in agg], dtype=float)
    high = np.array([a[f"{stat}_ci_high"] for a in agg], dtype=float)
    err = np.vstack(
        [
            mean - np.where(np.isfinite(low), low, mean),
            np.where(np.isfinite(high), high, mean) - mean,
        ]
    )
    ax.errorbar(x, mean, yerr=np.clip(err, 0, None), capsize=3, marker="o", **kwargs)


def _band(ax, x, agg, stat: str, color: str, label: str) -> None:
    """A statistic's floor: mean line and the 95 % band of N independent robots."""
    mean = np.array([a[f"{stat}_mean_mean"] for a in agg], dtype=float)
    lo = np.array([a[f"{stat}_lo_mean"] for a in agg], dtype=float)
    hi = np.array([a[f"{stat}_hi_mean"] for a in agg], dtype=float)
    ax.fill_between(x, lo, hi, color=color, alpha=0.15, lw=0)
    ax.plot(x, mean, ":", color=color, label=label)


def debias_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """``swarm_l2``, ``swarm_w2`` (with floors) and ``||p_hat - p_*||`` against N, for
    the paper's loop and the debiased loop, means over the seeds with 95 % CIs.
    """
    agg = points(rows)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), constrained_layout=True)
    colors = {False: "C3", True: "C0"}
    for debias in (False, True):
        group = sorted(
            (a for a in agg if bool(a.get("kde.debias")) is debias), key=lambda a: a["agents.n"]
        )
        if not group:
            continue
        n = np.array([a["agents.n"] for a in group], dtype=float)
        name = "debiased" if debias else "paper"
        c = colors[debias]
        _errorbar(axes[0], n, group, "swarm_tail_mean", color=c, label=f"{name} loop")
        if not debias:
            _band(axes[0], n, group, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
            _band(axes[1], n, group, "swarm_w2_floor", "0.4", "floor: N robots drawn from $p_*$")
        _errorbar(axes[1], n, group, "swarm_w2_last", color=c, label=f"{name} loop")
        _errorbar(axes[2], n, group, "phat_tail_mean", color=c, label=f"{name} loop")
    titles = (
        r"where the robots are: $\|K_h\mu_N - K_h p_*\|$",
        r"transport $W_2(\mu_N, p_*)$: exact to N = 4096, sliced above",
        r"the paper's Fig. 2 quantity $\|\hat p - p_*\|$",
    )
    units = ("1/length", "length", "1/length")
    for ax, title, unit in zip(axes, titles, units, strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("robots N")
        ax.set_ylabel(f"tail mean ({unit})")
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    return save_figure(fig, out, "debias_n")


def grid_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Agent loop against grid size: tail errors and wall time per step, means over the
    seeds with 95 % CIs.
    """
    agg = sorted(points(rows), key=lambda a: a["grid.n"])
    n = np.array([a["grid.n"] for a in agg], dtype=float)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11.5, 4.4), constrained_layout=True)
    for stat, label in DECOMPOSITION.items():
        _errorbar(ax0, n, agg, stat, label=label)
    _band(ax0, n, agg, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
    ax0.set_yscale("log")
    ax0.set_ylabel("tail mean (1/length)")
    ax0.set_title("tail errors against grid size")
    _errorbar(ax1, n, agg, "ms_per_step", color="k", label="wall time per step")
    ax1.set_yscale("log")
    ax1.set_ylabel("ms per step")
    ax1.set_title("cost against grid size")
    for ax in (ax0, ax1):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("cells per side n")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, out, "conv_grid_agents")


def network_figure(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Decentralised loop against the communication radius: the robots' gap to the
    centralised filter and their disagreement; where the robots are (with the finite-N
    floor) and the mean estimate's error; the communication each robot pays. Means over
    the seeds with 95 % CIs; the radius axis is linear below 0.01 (``r = 0``: no
    neighbours) and logarithmic above.
    """
    agg = sorted(points(rows), key=lambda a: a["estimator.radius"])
    r = np.array([a["estimator.radius"] for a in agg], dtype=float)
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4), constrained_layout=True)
    _errorbar(axes[0], r, agg, "central_gap_tail_mean", color="C3",
              label=r"$\mathrm{mean}_i\,\|\hat p_i - \hat p_{\mathrm{central}}\|$")  # fmt: skip
    _errorbar(axes[0], r, agg, "consensus_tail_mean", color="C0",
              label=r"$\mathrm{mean}_i\,\|\hat p_i - \bar{\hat p}\|$ (disagreement)")  # fmt: skip
    axes[0].set_title("robots' estimates against the centralised filter")
    axes[0].set_ylabel("tail mean (1/length)")
    _errorbar(axes[1], r, agg, "swarm_tail_mean", color="k",
              label=r"$\|K_h\mu_N - K_h p_*\|$ (robots)")  # fmt: skip
    _errorbar(axes[1], r, agg, "phat_tail_mean", color="C2",
              label=r"$\|\bar{\hat p} - p_*\|$ (mean estimate)")  # fmt: skip
    _band(axes[1], r, agg, "swarm_floor", "0.4", "floor: N robots drawn from $p_*$")
    axes[1].set_title("where the robots are (complete graph = centralised loop)")
    axes[1].set_ylabel("tail mean (1/length)")
    _errorbar(axes[2], r, agg, "messages_tail_mean", color="C1",
              label="messages per robot per step")  # fmt: skip
    _errorbar(axes[2], r, agg, "components_tail_mean", color="C4",
              label="connected components")  # fmt: skip
    axes[2].set_title("communication")
    axes[2].set_ylabel("tail mean (1)")
    for ax in axes:
        ax.set_xscale("symlog", linthresh=0.01)
        ax.set_yscale("log")
        ax.set_xlabel("communication radius r (length)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[2].set_yscale("symlog", linthresh=1.0)  # r = 0 sends no messages
    return save_figure(fig, out, "distributed_r")


def _label(row: dict[str, Any], key: str) -> str:
    v = value(row, key)
    return row["dir"] if v is None else str(v)


def convergence_figure(rows, series, varied: list[str], out: Path) -> list[Path]:
    """||Phi|| curves overlaid and fitted against theoretical rates."""
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    label_key = varied[0] if varied else "dir"
    done = [r for r in rows if r["dir"] in series]
    for r in done:
        m = series[r["dir"]]
        ax0.semilogy(m["t"], m["phi_l2"], label=f"{label_key}={_label(r, label_key)}")
    ax0.set_xlabel("t (s)")
    ax0.set_ylabel(r"$\|p - p_*\|_{L^2}$ (1/length)")
    ax0.grid(True, which="both", alpha=0.3)
    ax0.legend(fontsize=8)
    ax0.set_title("convergence curves")
    x = np.arange(len(done))
    ax1.bar(x - 0.2, [r["rate_fit"] for r in done], 0.4, label="measured (fit, second half)")
    ax1.bar(x + 0.2, [r["rate_theory"] for r in done], 0.4, label=r"$(\alpha+\sigma)\lambda$")
    ax1.set_xticks(x, [_label(r, label_key) for r in done])
    ax1.set_xlabel(label_key)
    ax1.set_ylabel("exponential rate (1/s)")
    ax1.legend(fontsize=8)
    ax1.set_title("decay rates")
    return save_figure(fig, out, "convergence")


# --- the declared figure ---------------------------------------------------------------


@dataclass(frozen=True)
class Study:
    """What a figure draws from: the completed jobs' rows (``usable``, with
    statistics), their metrics by job directory, the varied config keys (``seed``
    included), the output directory, the sweep directory and the tail fraction.
    """

    usable: list[dict[str, Any]]
    series: dict[str, Any]
    varied: list[str]
    out: Path
    sweep_dir: Path | None = None
    tail: float = 0.25


def _iss(study: Study) -> list[Path]:
    """:func:`iss_figure`, and the fitted gain of each law."""
    paths, gains = iss_figure(study.usable, study.out)
    for law, g in gains.items():
        print(f"fitted ISS gain ({law}): {g:.4g} (tail sup ||Phi|| per unit sup ||eps||)")
    return paths


def _debias(study: Study) -> list[Path]:
    """:func:`debias_figure`, and ``swarm_l2`` over its floor at each point."""
    paths = debias_figure(study.usable, study.out)
    for a in sorted(points(study.usable), key=lambda a: (a["kde.debias"], a["agents.n"])):
        print(
            f"N = {a['agents.n']}, debias = {a['kde.debias']}: swarm_l2 / floor = "
            f"{a['swarm_ratio_mean']:.3g} (95 % CI {a['swarm_ratio_ci_low']:.3g} to "
            f"{a['swarm_ratio_ci_high']:.3g}, {a['jobs']} seeds)"
        )
    return paths


def _agents(study: Study) -> list[Path]:
    """:func:`agents_figure`."""
    return agents_figure(study.usable, study.out)


def _network(study: Study) -> list[Path]:
    """:func:`network_figure`, and the gap, ``swarm_l2`` and messages at each radius."""
    paths = network_figure(study.usable, study.out)
    for a in sorted(points(study.usable), key=lambda a: a["estimator.radius"]):
        print(
            f"r = {a['estimator.radius']}: central_gap_l2 "
            f"{a['central_gap_tail_mean_mean']:.3g} "
            f"(95 % CI {a['central_gap_tail_mean_ci_low']:.3g} to "
            f"{a['central_gap_tail_mean_ci_high']:.3g}) 1/length, swarm_l2 "
            f"{a['swarm_tail_mean_mean']:.3g} 1/length (floor "
            f"{a['swarm_floor_mean_mean']:.3g}), {a['messages_tail_mean_mean']:.3g} "
            f"messages per robot per step ({a['jobs']} seeds)"
        )
    return paths


def _grid(study: Study) -> list[Path]:
    """:func:`grid_figure`, and the tail error and cost at each grid size."""
    paths = grid_figure(study.usable, study.out)
    for a in sorted(points(study.usable), key=lambda a: a["grid.n"]):
        print(
            f"n = {a['grid.n']}: ||p_hat - p*|| tail {a['phat_tail_mean_mean']:.4g} "
            f"1/length, {a['ms_per_step_mean']:.3g} ms per step ({a['jobs']} seeds)"
        )
    return paths


def _convergence(study: Study) -> list[Path]:
    """:func:`convergence_figure`, and each job's measured and theoretical rates."""
    paths = convergence_figure(study.usable, study.series, study.varied, study.out)
    for r in study.usable:
        print(
            f"{r['dir']}: rate {r['rate_fit']:.4g} 1/s measured, {r['rate_theory']:.4g} 1/s theory"
        )
    return paths


@dataclass(frozen=True)
class Figure:
    """A figure of a study: how to draw it, the primary keys it draws against, and keys
    it tells points apart by beside them (``also``: a point may set them off their
    defaults, e.g. a graph of the ``k`` nearest in a study of radii).
    """

    draw: Callable[[Study], list[Path]]
    needs: tuple[str, ...] = ()
    also: tuple[str, ...] = ()


def _law_figure(name: str, module: str = "laws") -> Callable[[Study], list[Path]]:
    """The figure ``name`` of :mod:`analysis.laws` (or of ``analysis.<module>``),
    imported when it is drawn (those modules draw with this one's helpers).
    """

    def draw(study: Study) -> list[Path]:
        import importlib

        result: list[Path] = getattr(importlib.import_module(f"analysis.{module}"), name)(study)
        return result

    return draw


FRONTIER_KEYS = (
    "estimator.consensus",
    "estimator.share",
    "estimator.messages",
    "estimator.radius",
    "estimator.rounds",
)
"""The keys the ``distributed_frontier`` figure draws against (:mod:`analysis.frontier`)."""

FIGURES: dict[str, Figure] = {
    "iss_gain": Figure(_iss, ("law", "estimator.delta")),
    "laws_n": Figure(_law_figure("draw_laws_n"), ("law", "agents.n")),
    "laws_iss": Figure(_law_figure("draw_laws_iss"), ("law", "estimator.shape", "estimator.delta")),
    "heat_floor": Figure(
        _law_figure("draw_heat_floor"),
        ("control.density_floor", "estimator.shape", "estimator.delta"),
    ),
    "laws_noise": Figure(_law_figure("draw_laws_noise"), ("law", "agents.localisation_noise")),
    "robots": Figure(_law_figure("draw_robots", "robots"), ("plant._target_", "law")),
    "link": Figure(
        _law_figure("draw_link", "robots"), ("link.period", "link.latency", "link.loss")
    ),
    "debias_n": Figure(_debias, ("agents.n", "kde.debias")),
    "agents_n": Figure(_agents, ("agents.n",)),
    "distributed_r": Figure(_network, ("estimator.radius",)),
    "distributed_frontier": Figure(
        _law_figure("draw_frontier", "frontier"),
        FRONTIER_KEYS,
        ("estimator.k_nearest", "estimator.band_limit"),
    ),
    "conv_grid_agents": Figure(_grid, ("grid.n",)),
    "convergence": Figure(_convergence),
}
"""The figures a study can declare (``analysis.figure``), by name."""

GENERIC_FIGURE = "convergence"
"""The figure of a sweep without a declaration."""

DEFAULT_TAIL = 0.25
"""The tail fraction when neither ``--tail`` nor the declaration gives one."""

DECLARATION_BLOCK = "analysis"
"""The config block of the declaration (accepted by the harness, which logs it:
:data:`harness.runs.checks.LOGGED_BLOCKS`)."""

DECLARATION_KEYS = ("figure", "primary", "tail")
"""The keys of a declaration."""


class DeclarationError(ValueError):
    """A declaration this module cannot follow; ``str()`` is the one-line message."""


@dataclass(frozen=True)
class Declaration:
    """A study's declared analysis (see the module docstring).

    Attributes:
        figure: A name of :data:`FIGURES`.
        primary: The keys that make the study's points, or None for every varied key
            but ``seed``.
        tail: The tail fraction in ``(0, 1]``.
    """

    figure: str = GENERIC_FIGURE
    primary: tuple[str, ...] | None = None
    tail: float = DEFAULT_TAIL


def declaration(flat: dict[str, Any]) -> Declaration:
    """The declaration in a job's flattened config (the generic one without a block).

    Raises:
        DeclarationError: for a key that is not one of :data:`DECLARATION_KEYS`, an
            unknown figure name, a ``primary`` that is not a list of keys, or a tail
            outside ``(0, 1]``.
    """
    prefix = DECLARATION_BLOCK + "."
    if DECLARATION_BLOCK in flat:
        raise DeclarationError(
            f"{DECLARATION_BLOCK}={flat[DECLARATION_BLOCK]!r}: a block with "
            f"{', '.join(DECLARATION_KEYS)}"
        )
    block = {k[len(prefix) :]: v for k, v in flat.items() if k.startswith(prefix)}
    if not block:
        return Declaration()
    for key, v in block.items():
        if key not in DECLARATION_KEYS:
            raise DeclarationError(
                f"{prefix}{key}={v!r}: not a key of the analysis declaration "
                f"(one of {', '.join(DECLARATION_KEYS)})"
            )
    figure = block.get("figure")
    if not isinstance(figure, str) or figure not in FIGURES:
        raise DeclarationError(
            f"{prefix}figure={figure!r}: no such figure (one of {', '.join(FIGURES)})"
        )
    primary = block.get("primary")
    if primary is not None and not (
        isinstance(primary, list) and all(isinstance(k, str) for k in primary)
    ):
        raise DeclarationError(f"{prefix}primary={primary!r}: a list of config keys")
    tail = block.get("tail", DEFAULT_TAIL)
    if isinstance(tail, bool) or not isinstance(tail, (int, float)) or not 0 < tail <= 1:
        raise DeclarationError(f"{prefix}tail={tail!r}: a fraction in (0, 1]")
    return Declaration(figure, None if primary is None else tuple(primary), float(tail))


def study_declaration(rows: list[dict[str, Any]]) -> Declaration:
    """The one declaration of the jobs whose config was read.

    Raises:
        DeclarationError: when the jobs declare different analyses, or the declared
            figure draws against a key the primary keys leave out.
    """
    found: dict[Declaration, str] = {}
    for r in rows:
        flat = {k[len(CONFIG_PREFIX) :]: v for k, v in r.items() if k.startswith(CONFIG_PREFIX)}
        if flat:
            found.setdefault(declaration(flat), r["dir"])
    if len(found) > 1:
        jobs = ", ".join(f"{d.figure} ({job})" for d, job in found.items())
        raise DeclarationError(
            f"the jobs declare different analyses: {jobs} "
            "(analyse each sweep from a directory of its own)"
        )
    return next(iter(found), Declaration())


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description="CSV and figures of a sweep, from its logs.")
    parser.add_argument("sweep_dir", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="default: SWEEP_DIR/analysis")
    parser.add_argument(
        "--tail",
        type=float,
        default=None,
        help=f"tail fraction of each run (default: the declared one, else {DEFAULT_TAIL})",
    )
    parser.add_argument(
        "--mixed-code",
        action="store_true",
        help="pool logs made by different code (commit, local changes, package versions)",
    )
    args = parser.parse_args(argv)
    if not args.sweep_dir.is_dir():
        print(f"error: no sweep directory at {args.sweep_dir}", file=sys.stderr)
        return 2
    if args.tail is not None and not 0 < args.tail <= 1:
        print(f"error: --tail must be in (0, 1], got {args.tail}", file=sys.stderr)
        return 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SweepWarning)
        try:
            rows, series = analyse(args.sweep_dir, args.tail)
            study = study_declaration(rows)
        except DeclarationError as err:
            problem: DeclarationError | None = err
        else:
            problem = None
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if problem is not None:
        print(f"error: {args.sweep_dir}: {problem}", file=sys.stderr)
        return 2
    if not rows:
        print(f"error: no run.mcap below {args.sweep_dir}", file=sys.stderr)
        return 2
    codes = mixed_code(rows)
    if codes and not args.mixed_code:
        print(
            f"error: {args.sweep_dir}: the logs were made by different code ("
            + ", ".join(f"{c}: {n} jobs" for c, n in sorted(codes.items()))
            + "; rerun the sweep into the same directory to bring every job to the same "
            "code, or pass --mixed-code)",
            file=sys.stderr,
        )
        return 2
    keys = varied(rows)
    usable = [r for r in rows if "phi_tail_sup" in r]
    figure = FIGURES[study.figure]
    if study.primary is None:  # a sweep of its own axes: every varied key but the seed
        primary = [k for k in keys if k != "seed"]
    else:
        primary = list(study.primary)
    missing = [k for k in figure.needs if k not in primary]
    if missing:
        print(
            f"error: {args.sweep_dir}: analysis.primary={primary!r}: the figure "
            f"{study.figure} draws against {', '.join(missing)} (list it)",
            file=sys.stderr,
        )
        return 2
    extra = mixed(rows, [*primary, *figure.also])
    if extra:
        print(
            f"error: {args.sweep_dir} holds more than one sweep: besides "
            f"{', '.join(primary)} the jobs differ in {', '.join(extra)} "
            "(analyse each sweep from a directory of its own)",
            file=sys.stderr,
        )
        return 2
    out = args.out or args.sweep_dir / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    write_csv(rows, out / "sweep.csv")
    write_points(points(rows), out / "sweep_aggregated.csv")
    written = [out / "sweep.csv", out / "sweep_aggregated.csv"]
    if usable:
        tail = args.tail if args.tail is not None else study.tail
        written += figure.draw(Study(usable, series, keys, out, args.sweep_dir, tail))
    bad = [r for r in rows if r.get("state") != "completed"]
    print(f"{len(rows)} jobs, {len(bad)} not completed")
    for p in written:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
