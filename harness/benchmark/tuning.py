"""Each law tuned to its best, per scenario, and the points its verdict re-runs.

**Objectives.** A trial is a law's gains run on every tuning seed; its two objectives,
both minimised, are the geometric means over those seeds of

* ``swarm_ratio``: the tail mean of ``swarm_l2``, the robots' KDE against ``K_h * p_*``,
  over its finite-N floor (the same norm for N robots drawn independently from
  ``p_*``; 1 is as good as N independent draws), dimensionless;
* ``effort_integral``: ``int_0^T (1/N) sum_i |u_i|^2 dt``, the robots' mean squared
  commanded speed integrated over the run (length^2 / s).

A run that did not complete (diverged, refused, killed) fails its trial: the trial is
told ``FAIL`` with the reason and never counts for a front.

**Samplers.** A law with one gain is tuned on a declared grid, enqueued in the study
in order: ``trials`` values spread over its range, geometrically on a log scale,
or at most ``trials`` of its listed values, evenly picked. A law with several gains is
tuned by Optuna's multi-objective TPE sampler (``TPESampler(multivariate=True)``), its
first ``min(trials, 5)`` trials drawn at random. A law with no gain runs its default
only. Every study's sampler is seeded from the tier's ``sampler_seed`` and the study's
name, so a benchmark repeats.

**Storage and resumption.** The trials live in Optuna's SQLite storage
``OUT/tuning.db``, one study per scenario and law (``ring/paper``). A trial is asked,
its point written, its runs made by a Hydra multirun and read back from their logs, and
only then told; a benchmark killed in between leaves the trial ``RUNNING``, and the next
start re-runs that trial's point (whose finished runs the multirun skips) instead of
asking a new one. A finished trial is never run again.

**Chosen points** (:func:`choose`), among the law's completed trials and its default
gains (run on the tuning seeds like a trial):

* ``best``: least ``swarm_ratio`` (ties: least effort);
* ``matched``: least ``swarm_ratio`` with effort at most the scenario's budget, the
  effort of the tier's ``budget_law`` at its default gains (none when no point of the
  law spends that little);
* ``default``: the law's default gains.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.benchmark.space import Gain, distributions

OBJECTIVES = ("swarm_ratio", "effort_integral")
"""The two objectives of a trial (module docstring), both minimised."""

DEFAULT = "default"
"""The tag of a law's default gains among its candidates and points."""

RANDOM_START = 5
"""Trials of a several-gain law drawn at random before TPE models the front."""


def study_name(scenario: str, law: str) -> str:
    """The Optuna study of a law in a scenario: ``SCENARIO/LAW``."""
    return f"{scenario}/{law}"


def sampler_seed(base: int, scenario: str, law: str) -> int:
    """A study's sampler seed: the tier's ``base`` and the study's name (CRC-32)."""
    return (base * 1_000_003 + zlib.crc32(study_name(scenario, law).encode())) % 2**32


def grid_values(gain: Gain, trials: int) -> list[Any]:
    """The grid a one-gain law is tuned on: ``trials`` values over a range, or at most
    ``trials`` of a list, evenly picked with both ends kept.
    """
    if gain.values is None:
        return gain.grid(trials)
    values = list(gain.values)
    if len(values) <= trials:
        return values
    picks = np.unique(np.round(np.linspace(0, len(values) - 1, trials)).astype(int))
    return [values[i] for i in picks]


def make_sampler(gains: Sequence[Gain], trials: int, seed: int) -> Any:
    """The sampler of a study (module docstring)."""
    import optuna

    if len(gains) == 1:  # its grid is enqueued (open_study); nothing is sampled
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(
        seed=seed, multivariate=True, n_startup_trials=min(trials, RANDOM_START)
    )


def trial_budget(gains: Sequence[Gain], trials: int) -> int:
    """How many trials a study runs: none without gains, the grid's size for one gain,
    ``trials`` for several.
    """
    if not gains:
        return 0
    if len(gains) == 1:
        return len(grid_values(gains[0], trials))
    return trials


@dataclass(frozen=True)
class Outcome:
    """A point's runs on its seeds, summarised.

    Attributes:
        values: The objectives (:data:`OBJECTIVES`) as geometric means over the seeds,
            or None when a run failed.
        reason: Why the point failed (empty when it did not).
        per_seed: Every run's statistics by seed (the objectives, ``settling_time``,
            ``t_end``, ``ms_per_step``).
    """

    values: tuple[float, float] | None
    reason: str = ""
    per_seed: dict[int, dict[str, float]] = field(default_factory=dict)


def summarise(rows: Mapping[int, Mapping[str, Any]]) -> Outcome:
    """The outcome of a point from its runs' rows by seed (:func:`analysis.rows.job_row`
    rows, or ``{"state": ..., "reason": ...}`` for a run without a log).
    """
    per_seed: dict[int, dict[str, float]] = {}
    logs: dict[str, list[float]] = {k: [] for k in OBJECTIVES}
    for seed, row in sorted(rows.items()):
        state = str(row.get("state", ""))
        if state != "completed":
            why = row.get("reason") or state or "no run"
            return Outcome(None, f"seed {seed}: {why}", per_seed)
        stats = {
            k: _float(row.get(k)) for k in (*OBJECTIVES, "settling_time", "t_end", "ms_per_step")
        }
        per_seed[seed] = stats
        for k in OBJECTIVES:
            if not (math.isfinite(stats[k]) and stats[k] > 0):
                return Outcome(None, f"seed {seed}: {k} = {stats[k]!r}", per_seed)
            logs[k].append(math.log(stats[k]))
    if not per_seed:
        return Outcome(None, "no run", per_seed)
    a, b = (float(math.exp(np.mean(logs[k]))) for k in OBJECTIVES)
    return Outcome((a, b), "", per_seed)


def _float(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


@dataclass(frozen=True)
class Candidate:
    """A point a law could be judged at: a completed trial or the default gains.

    Attributes:
        tag: ``tNNN`` for trial ``NNN``, ``default`` for the default gains.
        gains: The gains (empty for the default: the law's YAML as it is).
        error: ``swarm_ratio`` over the tuning seeds (geometric mean).
        effort: ``effort_integral`` over the tuning seeds (geometric mean, length^2 / s).
    """

    tag: str
    gains: dict[str, Any]
    error: float
    effort: float


def front(candidates: Sequence[Candidate]) -> list[Candidate]:
    """The candidates no other one beats in both error and effort (the Pareto front),
    sorted by effort.
    """
    out = []
    for c in candidates:
        dominated = any(
            (o.error <= c.error and o.effort <= c.effort)
            and (o.error < c.error or o.effort < c.effort)
            for o in candidates
        )
        if not dominated:
            out.append(c)
    return sorted(out, key=lambda c: (c.effort, c.error))


def choose(candidates: Sequence[Candidate], budget: float | None) -> dict[str, Candidate]:
    """The chosen points of a law (module docstring): ``best``, ``matched`` (when a
    candidate's effort is within ``budget``, length^2 / s) and ``default`` (when the
    default gains completed).
    """
    out: dict[str, Candidate] = {}
    if not candidates:
        return out
    out["best"] = min(candidates, key=lambda c: (c.error, c.effort))
    if budget is not None and math.isfinite(budget):
        within = [c for c in candidates if c.effort <= budget]
        if within:
            out["matched"] = min(within, key=lambda c: (c.error, c.effort))
    for c in candidates:
        if c.tag == DEFAULT:
            out["default"] = c
    return out


def open_study(storage: str, scenario: str, law: str, gains: Sequence[Gain], plan: Any) -> Any:
    """The Optuna study of ``law`` in ``scenario`` in ``storage`` (created or loaded),
    with its sampler (module docstring).
    """
    import optuna

    seed = sampler_seed(plan.sampler_seed, scenario, law)
    study = optuna.create_study(
        storage=storage,
        study_name=study_name(scenario, law),
        directions=["minimize", "minimize"],
        sampler=make_sampler(gains, plan.trials, seed),
        load_if_exists=True,
    )
    if len(gains) == 1:  # the grid, in order; a value already tried is not enqueued again
        for value in grid_values(gains[0], plan.trials):
            study.enqueue_trial({gains[0].name: value}, skip_if_exists=True)
    return study


def ask(study: Any, gains: Sequence[Gain]) -> tuple[Any, dict[str, Any], bool]:
    """The trial to run next, its gains and whether it is the study's unfinished trial
    from a killed benchmark (whose point is run again), else a new one.
    """
    import optuna
    from optuna.trial import TrialState

    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    if running:
        frozen = running[0]
        return optuna.trial.Trial(study, frozen._trial_id), dict(frozen.params), True
    trial = study.ask(distributions(gains))
    return trial, dict(trial.params), False


def tell(study: Any, trial: Any, outcome: Outcome) -> None:
    """Record a trial's outcome (its per-seed statistics as user attributes)."""
    from optuna.trial import TrialState

    trial.set_user_attr("per_seed", {str(k): v for k, v in outcome.per_seed.items()})
    if outcome.values is None:
        trial.set_user_attr("reason", outcome.reason)
        study.tell(trial, state=TrialState.FAIL)
    else:
        study.tell(trial, list(outcome.values))


def done(study: Any) -> int:
    """The study's finished trials (completed or failed)."""
    from optuna.trial import TrialState

    return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.FAIL)))


def candidates(study: Any, default: Outcome | None) -> list[Candidate]:
    """The study's completed trials and the default gains' outcome as candidates."""
    from optuna.trial import TrialState

    out = []
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        out.append(Candidate(f"t{t.number:03d}", dict(t.params), t.values[0], t.values[1]))
    if default is not None and default.values is not None:
        out.append(Candidate(DEFAULT, {}, *default.values))
    return out
