"""Observers: what watches a run's steps and never steers it.

The run (:func:`harness.run.run`) is a straight line: build, initialise the observers,
step the loop and hand every step's record to each observer in its config order,
finalise. Each observer is a component of the config group ``observers``
(``conf/observers/``: one YAML per observer, ``_target_`` plus its own parameters, its
cadence among them), composed into one dict by ``conf/observers/default.yaml``:

    metrics   field metrics, the paper's errors (:class:`harness.metrics.FieldMetrics`)
    swarm     where the robots are (:class:`harness.metrics.SwarmTruth`)
    estimator the numbers the estimator publishes (:class:`EstimatorMetrics`)
    guard     the divergence guard (:class:`DivergenceGuard`)
    live      the live view over Foxglove's WebSocket protocol (:class:`harness.live.LiveView`)
    log       the MCAP log (:class:`harness.mcap_log.McapLogger`)
    progress  the progress bar (:class:`ProgressBar`)

An observer implements :class:`Observer`: ``initialize(run)`` before the loop starts,
``handle(record, values)`` after the start and after every step, ``finalize(status)``
at the end, whatever happened. ``values`` is the step's dict of numbers, which the
observers before fill and the ones after read: the metric observers add their keys, the
guard checks them, the logger writes them. Observers that compute come before those that
show; those that only compute say so (``computes = True``), and an in-memory
simulation (:func:`harness.api.simulate`) runs just them. Run-time arguments an
observer's constructor may name (the builder passes the ones
it names): ``grid``, ``target``, ``control``, ``plant``, ``steps`` (the run's last
step) and ``identity`` (:class:`harness.identity.RunIdentity`).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from tqdm.auto import tqdm

from harness.components import ParameterError, integer, require
from harness.fokker_planck import NumericalError
from harness.records import StepRecord


@dataclass
class RunContext:
    """What the observers share during a run.

    Attributes:
        out_dir: The run directory.
        theory: The ``theory`` record (string values), which observers fill in
            ``initialize`` and at the start record; the logger writes it with its first
            step.
        publishers: Live servers the logger hands every message it writes.
        exclusive: Whether the log must be a new file (created exclusively: an
            existing one, even one another process created a moment before, is refused
            by the open itself); False replaces it.
    """

    out_dir: Path
    theory: dict[str, str] = field(default_factory=dict)
    publishers: list[Any] = field(default_factory=list)
    exclusive: bool = True


@dataclass(frozen=True)
class Status:
    """How a run ended: ``state`` (``completed`` | ``aborted`` | ``diverged``), the
    ``reason`` and the run's wall time ``wall_s`` (s).
    """

    state: str
    reason: str
    wall_s: float


@runtime_checkable
class Observer(Protocol):
    """Sees each step of a run; never steers it (module docstring)."""

    def initialize(self, run: RunContext) -> None:
        """Before the loop starts (open files, start servers, compute fixed numbers)."""
        ...

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """After the start (``rec.step == 0``) and after every step."""
        ...

    def finalize(self, status: Status) -> None:
        """At the end, whatever happened (also after an exception)."""
        ...


class EstimatorMetrics:
    """The numbers the estimator publishes (``Estimate.metrics``), added to the step's
    values as they are (units: the estimator's docstring; the decentralised loop's are
    listed in ``docs`` under the log contract).
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)

    def initialize(self, run: RunContext) -> None:
        """Nothing to prepare."""

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Copy the estimate's published numbers."""
        values.update({key: float(v) for key, v in rec.estimate.metrics.items()})

    def finalize(self, status: Status) -> None:
        """Nothing to close."""


class DivergenceGuard:
    """Ends the run as diverged when a number of the step is NaN or infinite, or
    missing where it may not be.

    Args:
        required: Keys that must be numbers at every step; None for the log contract's
            (:data:`harness.mcap_log.ALWAYS_NUMBERS`).
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)

    def __init__(self, required: list[str] | tuple[str, ...] | None = None) -> None:
        if required is None:
            from harness.mcap_log import ALWAYS_NUMBERS

            required = ALWAYS_NUMBERS
        ok = isinstance(required, (list, tuple)) and all(isinstance(k, str) for k in required)
        require(ok, "required", required, "a list of metric names, or null")
        self.required = tuple(required)

    def initialize(self, run: RunContext) -> None:
        """Nothing to prepare."""

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Raise :class:`~harness.fokker_planck.NumericalError` for a bad number."""
        for key in self.required:
            if values.get(key) is None:
                raise NumericalError(f"metric {key} is missing")
        for key, value in values.items():
            if value is not None and not math.isfinite(float(value)):
                raise NumericalError(f"metric {key} became non-finite ({value})")

    def finalize(self, status: Status) -> None:
        """Nothing to close."""


PROGRESS = {"auto": None, "on": True, "off": False}
"""Values of the progress bar's ``show`` (``log.progress``): ``auto`` shows it on a
terminal."""


class ProgressBar:
    """A progress bar on standard error (tqdm) with the time and ``||p_hat - p_*||``.

    Args:
        steps: The run's last step (run-time argument).
        show: ``auto`` (on a terminal) | ``on`` | ``off``.
        every: Steps between updates.
    """

    def __init__(self, steps: int, show: str = "auto", every: int = 50) -> None:
        if show not in PROGRESS:
            raise ParameterError("show", show, f"one of {', '.join(PROGRESS)}")
        self.steps, self.show = steps, PROGRESS[show]
        self.every = integer("every", every, 1)
        self.bar: Any = None

    def initialize(self, run: RunContext) -> None:
        """Open the bar."""
        disable = (not sys.stderr.isatty()) if self.show is None else not self.show
        self.bar = tqdm(total=self.steps, unit="step", disable=disable)

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Update every ``every`` steps and at the last."""
        if rec.step == 0 or not (rec.step % self.every == 0 or rec.step == self.steps):
            return
        err = values.get("phat_target_l2")
        text = f"t={rec.t:.2f} s" + ("" if err is None else f" |p_hat-p*|={err:.3e}")
        self.bar.set_postfix_str(text, refresh=False)
        self.bar.update(rec.step - self.bar.n)

    def finalize(self, status: Status) -> None:
        """Close the bar."""
        if self.bar is not None:
            self.bar.close()
