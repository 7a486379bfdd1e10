"""The closed loop of the paper's block diagram: one step (:class:`ClosedLoop`), and a
run's steps with what watches them (:func:`trajectory`).

    plant --measurement--> estimator --estimate--> control
      ^                                               |
      +------ command (a field, robots' velocities) <-+

Step ``n -> n + 1`` (the command ``u_n`` was computed at ``t_n`` and is held over the
step):

1. the plant moves under ``u_n`` (:meth:`harness.protocols.Plant.advance`), with the
   Fokker-Planck matrix ``A(v_n)`` of the command's field assembled once and shared
   with the estimator (None for a law without a field);
2. the loop's ``N -> infinity`` limit, when the run has one, moves under the law's field
   of its own noise-free estimate (:class:`harness.plants.limit.Limit`);
3. the plant is measured at ``t_{n+1}`` (only when the estimator uses a measurement);
4. the estimator predicts under ``v_n`` and updates with the measurement;
5. the control gives ``u_{n+1}`` from what it uses (:class:`~harness.records.ControlInput`:
   the time, the estimate, the robots' positions as observed, or without robots the
   mean-field density that stands for them; for a moving target, ``p_*(t_{n+1})`` and
   ``d_t p_*`` there, :class:`harness.targets.moving.TargetPath`).

Errors are measured against the mean-field density ``p`` (notes section 5): the limit's
``p_inf`` when the run has one, else the plant's density (the mean-field plant's state;
the robots' histogram for a law without a mean-field form). ``Phi = p - p_*``, ``eps =
p_hat - p`` and ``eps_g = q_hat - grad p`` are the states of the paper's interconnected
system (eqs. ``tracking error equation`` and ``interconnected system``); see
:mod:`harness.observers.metrics`.

:func:`trajectory` is the only place the loop is assembled and stepped: the run
(:func:`harness.runs.run.run`), the Python API (:func:`harness.api.simulate`), the
benchmarks and the tests all consume it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse.linalg as spla
from threadpoolctl import ThreadpoolController

from harness.fokker_planck import FokkerPlanck, NumericalError
from harness.grid import Grid
from harness.observers.base import Observer, computes
from harness.plants.limit import Limit
from harness.protocols import Control, Estimator, Identity, Plant, headings, observed
from harness.records import Command, ControlInput, Estimate, Measurement, StepInput, StepRecord
from harness.targets.densities import Density, Target
from harness.targets.moving import TargetPath

Values = dict[str, float | None]
"""One step's numbers, by name, as the observers fill them (:mod:`harness.observers`)."""


@dataclass(frozen=True)
class Experiment:
    """Everything one run needs, built from a config by :func:`harness.runs.build.build`.

    Attributes:
        grid, target, init, model, plant, estimator, control: The components (``model``
            the Fokker-Planck model ``A(v)`` the plant, the limit and the filters share).
        limit: The loop's ``N -> infinity`` limit, or None (a run without robots, or a
            law without a mean-field form).
        observers: The observers by name, in the order they see each step.
        seed: The run's seed.
        dt: Step (s).
        steps: Number of steps after the start.
        identity: The records that identify the run in its log.
        keys: The public config key of each observer parameter
            (``"observers.live.port" -> "log.live_port"``), for errors raised when the
            run starts.
        spent: Set by :func:`trajectory`: the components keep their state, so an
            experiment runs once.
    """

    grid: Grid
    target: Target
    init: Density
    model: FokkerPlanck
    plant: Plant
    limit: Limit | None
    estimator: Estimator
    control: Control
    observers: dict[str, Observer]
    seed: int
    dt: float
    steps: int
    identity: Identity
    keys: dict[str, str]
    spent: list[bool] = field(default_factory=list, compare=False, repr=False)


class ClosedLoop:
    """Plant, limit, estimator and control of an experiment, advanced by :meth:`step`
    (module docstring).

    Args:
        exp: The experiment.
        rng: The run's random generator (robots, synthetic noise).
        mass_drift: Largest relative change of ``int p`` from its start before the run
            counts as diverged (1).
    """

    def __init__(self, exp: Experiment, rng: np.random.Generator, mass_drift: float = 1e-6):
        self.plant, self.limit = exp.plant, exp.limit
        self.estimator, self.control = exp.estimator, exp.control
        self.model, self.dt, self.rng = exp.model, exp.dt, rng
        self.grid = exp.grid
        self.mass_drift = mass_drift
        self.mass0 = float("nan")
        self.n = 0
        self.command: Command | None = None
        self.path = TargetPath(exp.target)

    @property
    def t(self) -> float:
        """Current time ``n dt`` (s)."""
        return self.n * self.dt

    def _density(self) -> np.ndarray:
        """The mean-field density ``p`` the errors are measured against (module
        docstring).
        """
        return self.plant.density if self.limit is None else self.limit.density

    def _measure(self) -> Measurement | None:
        return self.plant.measure(self.rng) if self.estimator.uses_kde else None

    def _control(self, est: Estimate, density: np.ndarray) -> Command:
        if not (np.isfinite(est.p_hat).all() and np.isfinite(est.q_hat).all()):
            raise NumericalError("the estimate became non-finite")
        seen = observed(self.plant)
        stand_in = density if seen is None else None
        if self.path.moves:
            t = self.t
            inp = ControlInput(t, est, seen, stand_in, self.path.at(t), self.path.rate(t))
        else:
            inp = ControlInput(self.t, est, seen, stand_in)
        command = self.control(inp)
        if not command.is_finite():
            raise NumericalError("the command became non-finite")
        return command

    def _input(
        self, meas: Measurement | None, command: Command | None, a, density: np.ndarray
    ) -> StepInput:
        return StepInput(
            self.t,
            None if meas is None else meas.p,
            None if meas is None else meas.grad,
            None if command is None else command.field,
            a,
            density,
            observed(self.plant),
        )

    def start(self) -> StepRecord:
        """Start the plant (and the limit), measure and estimate at ``t = 0`` and compute
        ``u_0``.
        """
        self.plant.start(self.rng)
        if self.limit is not None:
            self.limit.start()
        density = self._density()
        self.mass0 = self.grid.integrate(density)
        meas = self._measure()
        est = self.estimator.initialize(self._input(meas, None, None, density))
        self.command = self._control(est, density)
        return self._record(meas, est, density)

    def step(self) -> StepRecord:
        """Advance by one step (module docstring)."""
        assert self.command is not None, "call start first"
        command = self.command
        a = None if command.field is None else self.model.matrix(command.field)
        self.plant.advance(command, a, self.dt, self.rng)
        if self.limit is not None:
            self.limit.advance(self.dt)
        density = self._density()
        mass = self.grid.integrate(density)
        if abs(mass - self.mass0) > self.mass_drift * self.mass0:
            raise NumericalError(f"mass drifted from {self.mass0:.15g} to {mass:.15g}")
        self.n += 1
        meas = self._measure()
        est = self.estimator.step(self._input(meas, command, a, density))
        self.command = self._control(est, density)
        return self._record(meas, est, density)

    def _record(self, meas: Measurement | None, est: Estimate, density: np.ndarray) -> StepRecord:
        assert self.command is not None
        return StepRecord(
            step=self.n,
            t=self.t,
            p_true=density,
            measurement=meas,
            estimate=est,
            command=self.command,
            positions=self.plant.positions,
            headings=headings(self.plant),
        )


NUMERICAL_WARNINGS = (spla.MatrixRankWarning, RuntimeWarning)
"""Warnings that are errors while a step computes: a singular factorisation, and
numpy's floating-point warnings (overflow, division by zero, invalid value) raised in
the harness's own modules, as in the test suite; the run then ends ``diverged``."""


@contextmanager
def computing(blas: ThreadpoolController | None = None) -> Iterator[None]:
    """While the harness computes: BLAS on one thread (``blas``, a controller made once
    by a caller that enters this often) and the :data:`NUMERICAL_WARNINGS` as errors.
    Every step of :func:`trajectory` runs inside it, and so do the observers'
    ``initialize`` (the finite-N floors) in a run.
    """
    with (blas or ThreadpoolController()).limit(limits=1), warnings.catch_warnings():
        warnings.simplefilter("error", spla.MatrixRankWarning)
        warnings.filterwarnings("error", category=RuntimeWarning, module="harness")
        yield


def trajectory(
    exp: Experiment,
    observers: Sequence[Observer] = (),
    window: Callable[[], AbstractContextManager[object]] = nullcontext,
    hold: bool = False,
) -> Iterator[tuple[StepRecord, Values]]:
    """Step ``exp`` from ``t = 0`` to its last step: each step's record and the numbers
    ``observers`` filled, ``steps + 1`` of them (the start first).

    While a step computes (the loop's step and every observer's ``handle``) BLAS runs on
    one thread and the :data:`NUMERICAL_WARNINGS` are errors (:func:`computing`), so every
    caller computes the same numbers as a logged run; by default not while the caller
    holds what was yielded. The random stream is ``numpy.random.default_rng(exp.seed)``.

    Args:
        exp: The experiment; it runs once (its components keep their state).
        observers: Observers already initialised (``initialize``), handed each step's
            record in this order; the caller finalises them.
        window: A context manager entered around each step's computation: the loop's
            own and that of the observers that only compute, from the first up to the
            first that writes or shows (the logger is never inside); for example to let
            signals interrupt it. It may raise to stop before the step.
        hold: Keep those guards from the first step to the last, the caller's code
            between steps included: for a caller that does nothing there (a run, a
            benchmark), which then saves entering them at every step (tens of
            microseconds, a quarter of a small loop's step). Hold one trajectory at a
            time: interleaved ones would restore each other's guards out of order.

    Yields:
        ``(record, values)`` per step. A record's arrays may be the components' own
        state (the robots' positions, each robot's estimates), overwritten at the next
        step: copy what you keep.

    Raises:
        ValueError: for an experiment that has run already.
        harness.fokker_planck.NumericalError: at the step where the numbers broke down
            (a non-finite estimate, command or metric, lost mass), as do the numerical
            exceptions of :data:`NUMERICAL_WARNINGS`.
    """
    if exp.spent:
        raise ValueError(
            "this Experiment has run already (its components keep their state): build it again"
        )
    exp.spent.append(True)
    loop = ClosedLoop(exp, np.random.default_rng(exp.seed))
    blas = ThreadpoolController()
    inside = _computing_prefix(observers)
    with computing(blas) if hold else nullcontext():
        for n in range(exp.steps + 1):
            with nullcontext() if hold else computing(blas):
                values: Values = {}
                with window():
                    rec = loop.start() if n == 0 else loop.step()
                    for observer in observers[:inside]:
                        observer.handle(rec, values)
                for observer in observers[inside:]:
                    observer.handle(rec, values)
            yield rec, values


def _computing_prefix(observers: Sequence[Observer]) -> int:
    """How many of ``observers``, from the first, only compute
    (:func:`harness.observers.base.computes`): those :func:`trajectory` hands each record
    inside its window, before the first that writes or shows.
    """
    for i, observer in enumerate(observers):
        if not computes(observer):
            return i
    return len(observers)
