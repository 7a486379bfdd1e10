"""Observers: what watches a run's steps and never steers it.

The run (:func:`harness.runs.run.run`) is a straight line: build, initialise the
observers, step the trajectory (:func:`harness.loop.trajectory`), which hands every
step's record to each observer in its config order, finalise. Each observer is a
component of the config group ``observers`` (``conf/observers/``: one YAML per observer,
``_target_`` plus its own parameters, its cadence among them), composed into one dict by
``conf/observers/default.yaml``:

    metrics   field metrics, the paper's errors (:mod:`harness.observers.metrics`)
    swarm     where the robots are (:mod:`harness.observers.swarm`)
    motion    how much the robots move (:mod:`harness.observers.motion`)
    estimator the numbers the estimator publishes (:mod:`harness.observers.estimator`)
    guard     the divergence guard (:mod:`harness.observers.guard`)
    live      the live view over Foxglove's WebSocket protocol (:mod:`harness.observers.live`)
    log       the MCAP log (:mod:`harness.observers.log`)
    progress  the progress bar (:mod:`harness.observers.progress`)

An observer implements :class:`Observer`: ``initialize(run)`` before the loop starts,
``handle(record, values)`` after the start and after every step, ``finalize(status)``
at the end, whatever happened. ``values`` is the step's dict of numbers, which the
observers before fill and the ones after read: the metric observers add their keys, the
guard checks them, the logger writes them. Observers that compute come before those that
show; those that only compute say so (``computes = True``, :func:`computes`), and an
in-memory simulation (:func:`harness.api.simulate`) runs just them. An observer that
computes says which metrics it adds (``gives``) and which of them only at a cadence
(``at_cadence``), one that reads metrics it must have at every step says which
(``needs``: the guard's ``required``, the logger's always-numbers): a run whose observers
need a metric that no observer before them gives at every step is refused before it
starts. A run writes its log through the observer that says so
(``writes_log``); a run without one is refused (:func:`harness.runs.run.check_writes_log`).
An observer that acts every so many steps keeps a :class:`Cadence`. Run-time arguments
an observer's constructor may name (the builder passes the ones it names): ``grid``, ``target``,
``control``, ``plant``, ``limit`` (the loop's ``N -> infinity`` limit, or None),
``steps`` (the run's last step) and ``identity`` (:class:`harness.protocols.Identity`).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

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
        window: The window in which a stop request is honoured: an observer enters it
            around each piece of a long computation (each draw of the finite-N floors),
            and it raises to stop the run when a stop was requested (SIGINT, SIGTERM or
            SIGHUP), or at once on a second request while inside. A run's is its stop
            request's (:meth:`harness.runs.run.StopRequest.window`); by default it does
            nothing.
    """

    out_dir: Path
    theory: dict[str, str] = field(default_factory=dict)
    publishers: list[Any] = field(default_factory=list)
    exclusive: bool = True
    # a factory, so that no class attribute holds nullcontext (the reference would list it)
    window: Callable[[], AbstractContextManager[object]] = field(
        default_factory=lambda: nullcontext
    )


@dataclass(frozen=True)
class Status:
    """How a run ended: ``state`` (``completed`` | ``aborted`` | ``diverged``), the
    ``reason`` and the run's wall time ``wall_s`` (s).
    """

    state: str
    reason: str
    wall_s: float


@dataclass(frozen=True)
class Cadence:
    """The steps at which an observer acts: every ``every`` steps from the start, and the
    run's last step.

    Args:
        every: Steps between two (``>= 1``, checked by the observer that names it).
        last: The run's last step.
    """

    every: int
    last: int

    def due(self, step: int) -> bool:
        """Whether the observer acts at ``step``: ``step mod every = 0`` or the last."""
        return step % self.every == 0 or step == self.last


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


def computes(observer: Observer) -> bool:
    """Whether ``observer`` only computes (its optional ``computes``): it adds to the
    step's values and writes or shows nothing, so an in-memory simulation runs it.
    """
    return bool(getattr(observer, "computes", False))


def gives(observer: Observer) -> frozenset[str] | None:
    """The metric names ``observer`` adds to a step's values (its optional ``gives``);
    none for an observer that only shows or writes (not :func:`computes`), None (it does
    not say) for one that computes without saying what.
    """
    names = getattr(observer, "gives", None)
    if names is None:
        return None if computes(observer) else frozenset()
    return frozenset(names)


def at_cadence(observer: Observer) -> dict[str, str]:
    """The metrics of :func:`gives` that ``observer`` adds only at a cadence (a number at
    some steps, null at the others), each with the parameter that sets the cadence (its
    optional ``at_cadence``: the swarm observer's ``{"swarm_l2": "every", ...}`` when
    ``every`` is above 1); the others it gives are there at every step.
    """
    return {str(k): str(v) for k, v in dict(getattr(observer, "at_cadence", None) or {}).items()}


def needs(observer: Observer) -> dict[str | None, tuple[str, ...]]:
    """The metric names ``observer`` must find in every step's values, filled by the
    observers before it at every step (:func:`at_cadence`), by the parameter that names
    them (its optional ``needs``: the divergence guard's ``{"required": (...)}``), or
    ``None`` for metrics it needs whatever its parameters (the logger's
    ``{None: ALWAYS_NUMBERS}``, the log contract's); empty for an observer that needs none.
    """
    raw = dict(getattr(observer, "needs", None) or {})
    return {None if k is None else str(k): tuple(v) for k, v in raw.items()}


def writes_log(observer: Observer) -> bool:
    """Whether ``observer`` writes the run's log, ``run.mcap`` (its optional ``writes_log``:
    the logger, :class:`harness.observers.log.McapLogger`).
    """
    return bool(getattr(observer, "writes_log", False))


def seconds(observer: Observer) -> float:
    """The wall time (s) ``observer`` spent on the steps, when it keeps it (its optional
    ``seconds``; the logger does), else 0.
    """
    return float(getattr(observer, "seconds", 0.0))


def disk_bytes(observer: Observer, robots: int) -> tuple[int, str] | None:
    """What ``observer`` says it will write (its optional ``disk_bytes(robots)``): an
    upper estimate in bytes and the parameter that sets most of it, for a run with
    ``robots`` robots; None for an observer that writes no file.
    """
    estimate = getattr(observer, "disk_bytes", None)
    return None if estimate is None else estimate(robots)


def probe(observer: Observer) -> None:
    """``observer``'s optional ``probe()``: a check, before a sweep's job starts, that it
    can start (the live view's port), raising what ``initialize`` would.
    """
    check = getattr(observer, "probe", None)
    if check is not None:
        check()
