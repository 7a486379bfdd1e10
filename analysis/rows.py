"""A sweep's jobs as rows, from their logs alone, and the rows aggregated over seeds.

:func:`analyse` reads every job directory below a sweep directory (:func:`job_dirs`: one
holding a ``run.mcap``, a ``job_status.json`` or a ``.hydra/``; a job whose log is
missing, a dangling link or a link loop is a row ``unreadable: no run log at ...``, not
completed): its ``config`` record (the resolved config, :mod:`analysis.configs`), its
``choices`` record (the option of each config group), its ``status``, ``theory`` and
``provenance`` records and its ``/metrics``. Each row holds the job's directory, state,
statistics (:mod:`analysis.run_stats`), wall time, its whole flattened config under
:data:`CONFIG_PREFIX`, and the option of each config group (under
:data:`OPTION_PREFIX`):

* ``law``: the option of group ``control`` (``paper``, ``heat``, or a law of your own);
* ``plant``, ``estimator``, ``target``, ``init``, ``experiment``, ... : the option of
  each other group, as config keys of their own (a sweep over ``plant=agents,unicycles``
  varies key ``plant``).

The options are read from the log's ``choices`` record, never worked out from a class
name. A log written before the record existed names each group by the class name of its
``_target_`` (``HeatControl``) instead, and the analysis says so in one warning.

Rows that differ only in ``seed`` are one point: :func:`points` gives one row per point
with, for every statistic ``s``, ``s_mean``, ``s_ci_low``, ``s_ci_high`` (its summary
over the seeds with the 95 % interval, by the rule of :mod:`analysis.stats` its kind
asks for: a geometric mean, a Kaplan-Meier median or a mean) and ``s_n``, and
``jobs``.
"""

from __future__ import annotations

import csv
import os
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from analysis.configs import component, flatten, logged_config
from analysis.declaration import declaration
from analysis.load import LogError, LogWarning, RunLog, load_run
from analysis.output import atomic_path
from analysis.run_stats import CENSORED, LOG_SCALE, STATS, SweepWarning, job_stats, number
from analysis.stats import aggregate

CONFIG_PREFIX = "cfg:"
"""Prefix of the config columns in the rows (dropped in the CSV header)."""

OPTION_PREFIX = "option:"
"""Prefix of the config groups' options in the rows (dropped in the CSV header)."""

LAW = "law"
"""The column of the control law: the option of config group ``control``."""

LAW_GROUP = "control"
"""The config group whose option is :data:`LAW`."""

TARGET = "._target_"
"""The suffix of a group's class path in the flattened config."""


class MetricSeries(dict):
    """A run's metric arrays, where a metric the log lacks (a foreign or older log) reads
    as NaN at every time, so the figures draw what there is.
    """

    def __missing__(self, key: str) -> np.ndarray:
        return np.full(len(self.get("t", ())), np.nan)


def options(run: RunLog, flat: dict[str, Any]) -> tuple[dict[str, str], bool]:
    """The option of each config group of ``run``, and whether the log recorded them.

    From the ``choices`` record (:attr:`analysis.load.RunLog.choices`); a group with a
    ``_target_`` (``plant._target_``) that the record does not name, as in every log
    written before the record existed, is named by its class name
    (:func:`analysis.configs.component`).

    Returns:
        ``{group: option}`` and True when every group with a ``_target_`` is named by
        the record.
    """
    chosen = run.choices
    named = dict(chosen)
    recorded = run.has_choices
    for key in flat:
        group = key.removesuffix(TARGET)
        if key.endswith(TARGET) and "." not in group and group not in chosen:
            named[group] = component(flat, group)
            recorded = False
    return named, recorded


LOG_FILE = "run.mcap"
"""A job's log, in its directory."""

JOB_MARKS = (LOG_FILE, "job_status.json", ".hydra")
"""The names of which any one makes a directory below a sweep directory a job's: its log,
the status file the sweep writes (:mod:`harness.runs.status`) and Hydra's record of
the job's config."""


def job_dirs(sweep_dir: Path) -> list[Path]:
    """The job directories right below ``sweep_dir``, sorted: each directory holding an
    entry named as one of :data:`JOB_MARKS`, whatever that entry is (a dangling link or a
    link loop counts; none is followed). A link to a directory is a job directory as the
    directory is, once: entries naming the same directory (a link to another job) count
    as the first of them; a link loop in place of a directory is none.
    """
    found, seen = [], set()
    for entry in sorted(sweep_dir.iterdir()):
        if entry.is_dir() and any(os.path.lexists(entry / mark) for mark in JOB_MARKS):
            where = os.path.realpath(entry)
            if where not in seen:
                seen.add(where)
                found.append(entry)
    return found


def analyse(
    sweep_dir: Path, tail: float | None = None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows of the CSV and the decoded metrics per job directory.

    Each row holds the job's directory, state, statistics, wall time, the option of its
    control law (:data:`LAW`), the options of the other config groups and its whole
    flattened config (module docstring); :func:`varied` then picks the config keys that
    differ between jobs. The tail statistics use ``tail``, else the tail the job's
    declaration gives (:func:`analysis.declaration.declaration`), else 0.25. Logs
    without the ``choices`` record get one :class:`~analysis.run_stats.SweepWarning`.

    Raises:
        analysis.declaration.DeclarationError: for a job whose declaration is not one
            the analysis reads.
    """
    rows, series, unnamed = [], {}, 0
    for job_dir in job_dirs(sweep_dir):
        row, metrics, recorded = job_row(job_dir, tail)
        unnamed += not recorded
        if metrics is not None:
            series[job_dir.name] = metrics
        rows.append(row)
    if unnamed:
        warnings.warn(
            f"{sweep_dir}: {unnamed} of {len(rows)} logs record no option for some config "
            "group (no choices record: written before logs had one); their law and "
            "group columns hold class names (the last part of each _target_)",
            SweepWarning,
            stacklevel=2,
        )
    return rows, series


def job_row(
    job_dir: Path, tail: float | None = None
) -> tuple[dict[str, Any], MetricSeries | None, bool]:
    """One job's row (as :func:`analyse` writes it), its metrics (None when the log
    holds fewer than three steps or cannot be read) and whether the log recorded the
    option of every config group.
    """
    log_path = job_dir / LOG_FILE
    row: dict[str, Any] = {"dir": job_dir.name}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LogWarning)
            run = load_run(log_path, topics={"/metrics"})
    except LogError as err:
        row["state"] = f"unreadable: {err}"
        return row, None, True
    if run.recovery is not None:  # damaged or cut short: say so, whatever its status says
        row["recovery"] = run.recovery
        warnings.warn(f"{log_path}: {run.recovery}", SweepWarning, stacklevel=3)
    if run.foreign is not None:  # values read as NaN: say so
        warnings.warn(f"{log_path}: {run.foreign}", SweepWarning, stacklevel=3)
    flat = flatten(logged_config(run))
    row.update({CONFIG_PREFIX + k: v for k, v in flat.items()})
    named, recorded = options(run, flat)
    row[LAW] = named.pop(LAW_GROUP, "")
    row.update({OPTION_PREFIX + group: option for group, option in named.items()})
    row["code"] = code_of(run.metadata.get("provenance", {}))
    theory = run.metadata.get("theory", {})
    row["law_uses"] = theory.get("law_uses", "")
    row["law_divides_by_density"] = theory.get("law_divides_by_density", "")
    row["state"] = run.state if run.recovery is None else f"damaged ({run.state})"
    row["wall_s"] = number(run.metadata.get("status", {}).get("wall_s"))
    metrics = None
    if "t" in run.metrics and len(run.metrics["t"]) > 2:
        job_tail = tail if tail is not None else declaration(flat).tail
        row.update(job_stats(run, job_tail))
        steps = len(run.metrics["t"]) - 1
        row["ms_per_step"] = 1e3 * row["wall_s"] / steps
        metrics = MetricSeries(run.metrics)
    return row, metrics, recorded


def config_of(row: dict[str, Any]) -> dict[str, Any]:
    """The row's flattened config, as the log records it."""
    return {k[len(CONFIG_PREFIX) :]: v for k, v in row.items() if k.startswith(CONFIG_PREFIX)}


def value(row: Mapping[str, Any], key: str) -> Any:
    """The row's value at key ``key``: a config key, a group's option at the group's name
    (``plant``; a config key of the same name comes first), the law's at :data:`LAW`.
    """
    if key == LAW:
        return row.get(LAW)
    if CONFIG_PREFIX + key in row:
        return row[CONFIG_PREFIX + key]
    return row.get(OPTION_PREFIX + key)


def _keys(rows: list[dict[str, Any]]) -> list[str]:
    """Every config key and group name of the rows, sorted."""
    found = set()
    for r in rows:
        for k in r:
            for prefix in (CONFIG_PREFIX, OPTION_PREFIX):
                if k.startswith(prefix):
                    found.add(k[len(prefix) :])
    return sorted(found)


def varied(rows: list[dict[str, Any]]) -> list[str]:
    """Config keys (without the prefix) whose values differ between the rows, leaving
    out the logging and progress keys, the observers' nodes (their values are the
    public keys', such as ``observers.swarm.seed: ${seed}``), a component's copy of
    the seed (a key equal to ``seed`` in every row that has it, such as
    ``control.seed: ${seed}``) and a group's class path where the group's option names
    it (``plant._target_`` beside ``plant``; ``control._target_`` beside ``law``).
    Only rows whose config was read count: a job without a readable log varies nothing.
    """
    rows = [r for r in rows if any(k.startswith(CONFIG_PREFIX) for k in r)]
    out = []
    for key in _keys(rows):
        if key.startswith(("log.", "observers.")) or _copies_seed(rows, key):
            continue
        if _named_by_option(rows, key):
            continue
        if len({repr(value(r, key)) for r in rows}) > 1:
            out.append(key)
    return out


def _copies_seed(rows: list[dict[str, Any]], key: str) -> bool:
    """Whether config key ``key`` (other than ``seed``) holds the row's seed wherever
    it is set.
    """
    if key == "seed":
        return False
    found = [r for r in rows if value(r, key) is not None]
    return bool(found) and all(value(r, key) == value(r, "seed") for r in found)


def _named_by_option(rows: list[dict[str, Any]], key: str) -> bool:
    """Whether ``key`` is a group's ``_target_`` that takes one value wherever the
    group's option does (the option then says all the class path says).
    """
    group = key.removesuffix(TARGET)
    if not key.endswith(TARGET) or "." in group:
        return False
    option = LAW if group == LAW_GROUP else group
    seen: dict[str, str] = {}
    for r in rows:
        if CONFIG_PREFIX + key not in r:
            continue
        named = repr(value(r, option))
        if seen.setdefault(named, repr(value(r, key))) != repr(value(r, key)):
            return False
    return True


def mixed(rows: list[dict[str, Any]], primary: list[str]) -> list[str]:
    """Varied config keys that the ``primary`` keys do not explain: keys taking more than
    one value among jobs that agree on every primary key. Non-empty means the directory
    holds more than one sweep.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(repr([value(r, k) for k in primary]), []).append(r)
    out = []
    for key in varied(rows):
        if key in primary or key == "seed":
            continue
        if any(len({repr(value(r, key)) for r in g}) > 1 for g in groups.values()):
            out.append(key)
    return out


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


def points(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per point (the varied config keys but ``seed``, and the law): every
    statistic over the seeds with its 95 % interval (:func:`analysis.stats.aggregate`):
    geometric means for the positive ones (:data:`analysis.run_stats.LOG_SCALE`),
    Kaplan-Meier medians for the censored times (:data:`analysis.run_stats.CENSORED`),
    means for the rest.
    """
    keys = [k for k in varied(rows) if k != "seed"]
    flat = [{**{k: value(r, k) for k in keys}, LAW: r.get(LAW, ""), **r} for r in rows]
    done = [r for r in flat if r.get("state") == "completed"]
    return aggregate(done, [*keys, LAW], [*STATS, "wall_s"], log_scale=LOG_SCALE, censored=CENSORED)


def points_with(rows: list[dict[str, Any]], keys: Iterable[str]) -> list[dict[str, Any]]:
    """:func:`points`, each point holding every key of ``keys`` (a key that does not
    vary across the sweep is not among the points' own: its single value is copied in
    from the rows).
    """
    agg = points(rows)
    for key in keys:
        fixed = next((value(r, key) for r in rows if value(r, key) is not None), None)
        for a in agg:
            a.setdefault(key, fixed)
    return agg


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    """``sweep.csv``: the varied config keys, the law, then the fixed columns."""
    keys = varied(rows)
    fixed = ["dir", "state", *STATS, "wall_s", "recovery"]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[*keys, LAW, *fixed], restval="")
        writer.writeheader()
        for r in rows:
            out = {k: value(r, k) for k in keys}
            out[LAW] = r.get(LAW, "")
            out.update({k: r.get(k, "") for k in fixed})
            writer.writerow(out)


def write_points(agg: list[dict[str, Any]], path: Path) -> None:
    """``sweep_aggregated.csv``."""
    if not agg:
        return
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(agg[0]))
        writer.writeheader()
        writer.writerows(agg)
