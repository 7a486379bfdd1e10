"""The closed loop of the paper's block diagram, one step at a time.

    plant --measurement--> estimator --estimate--> control
      ^                                               |
      +------ command (a field, robots' velocities) <-+

Step ``n -> n + 1`` (the command ``u_n`` was computed at ``t_n`` and is held over the
step):

1. the plant moves under ``u_n`` (:meth:`harness.protocols.Plant.advance`), with the
   Fokker-Planck matrix ``A(v_n)`` of the command's field assembled once and shared
   with the estimator (None for a law without a field);
2. the plant is measured at ``t_{n+1}`` (only when the estimator uses a measurement);
3. the estimator predicts under ``v_n`` and updates with the measurement;
4. the control gives ``u_{n+1}`` from what it uses (:class:`~harness.records.ControlInput`:
   the time, the estimate, the robots' positions as observed, or without robots the
   mean-field density that stands for them; for a moving target, ``p_*(t_{n+1})`` and
   ``d_t p_*`` there, :class:`harness.targets.moving.TargetPath`).

Errors are measured against the plant's mean-field density ``p`` (notes section 5):
``Phi = p - p_*``, ``eps = p_hat - p`` and ``eps_g = q_hat - grad p``, the states of the
paper's interconnected system (eqs. ``tracking error equation`` and ``interconnected
system``); see :mod:`harness.observers.metrics`.
"""

from __future__ import annotations

import numpy as np

from harness.fokker_planck import FokkerPlanck, NumericalError
from harness.protocols import Control, Estimator, Plant
from harness.records import Command, ControlInput, Estimate, Measurement, StepInput, StepRecord
from harness.targets.densities import Target
from harness.targets.moving import TargetPath


def observed(plant: Plant) -> np.ndarray | None:
    """The robots' positions as the estimator and the law see them: the plant's
    ``observed`` (with its localisation noise) when it has one, else its positions.
    """
    return getattr(plant, "observed", plant.positions)


class ClosedLoop:
    """Plant, estimator and control, advanced by :meth:`step`.

    Args:
        plant: The plant.
        estimator: The estimator.
        control: The control law.
        model: The Fokker-Planck model ``A(v)`` shared by the plant and the filters.
        dt: Step (s).
        rng: The run's random generator (robots, synthetic noise).
        mass_drift: Largest relative change of ``int p`` from its start before the run
            counts as diverged (1).
        target: The run's target at ``t = 0``; when it moves (:func:`harness.targets.moving.moves`)
            the law is given ``p_*(t)`` and ``d_t p_*`` at every step. None, or a static
            target: the law's own target (the control input carries none).
    """

    def __init__(
        self,
        plant: Plant,
        estimator: Estimator,
        control: Control,
        model: FokkerPlanck,
        dt: float,
        rng: np.random.Generator,
        mass_drift: float = 1e-6,
        target: Target | None = None,
    ) -> None:
        self.plant, self.estimator, self.control = plant, estimator, control
        self.model, self.dt, self.rng = model, dt, rng
        self.grid = model.grid
        self.mass_drift = mass_drift
        self.mass0 = float("nan")
        self.n = 0
        self.command: Command | None = None
        self.path = None if target is None else TargetPath(target)

    @property
    def t(self) -> float:
        """Current time ``n dt`` (s)."""
        return self.n * self.dt

    def _measure(self) -> Measurement | None:
        return self.plant.measure(self.rng) if self.estimator.uses_kde else None

    def _control(self, est: Estimate) -> Command:
        if not (np.isfinite(est.p_hat).all() and np.isfinite(est.q_hat).all()):
            raise NumericalError("the estimate became non-finite")
        seen = observed(self.plant)
        density = self.plant.density if seen is None else None
        if self.path is not None and self.path.moves:
            t = self.t
            inp = ControlInput(t, est, seen, density, self.path.at(t), self.path.rate(t))
        else:
            inp = ControlInput(self.t, est, seen, density)
        command = self.control(inp)
        if not command.is_finite():
            raise NumericalError("the command became non-finite")
        return command

    def _input(self, meas: Measurement | None, command: Command | None, a) -> StepInput:
        return StepInput(
            self.t,
            None if meas is None else meas.p,
            None if meas is None else meas.grad,
            None if command is None else command.field,
            a,
            self.plant.density,
            observed(self.plant),
        )

    def start(self) -> StepRecord:
        """Start the plant, measure and estimate at ``t = 0`` and compute ``u_0``."""
        self.plant.start(self.rng)
        self.mass0 = self.grid.integrate(self.plant.density)
        meas = self._measure()
        est = self.estimator.initialize(self._input(meas, None, None))
        self.command = self._control(est)
        return self._record(meas, est)

    def step(self) -> StepRecord:
        """Advance by one step (see the module docstring)."""
        assert self.command is not None, "call start first"
        command = self.command
        a = None if command.field is None else self.model.matrix(command.field)
        self.plant.advance(command, a, self.dt, self.rng)
        mass = self.grid.integrate(self.plant.density)
        if abs(mass - self.mass0) > self.mass_drift * self.mass0:
            raise NumericalError(f"mass drifted from {self.mass0:.15g} to {mass:.15g}")
        self.n += 1
        meas = self._measure()
        est = self.estimator.step(self._input(meas, command, a))
        self.command = self._control(est)
        return self._record(meas, est)

    def _record(self, meas: Measurement | None, est: Estimate) -> StepRecord:
        assert self.command is not None
        return StepRecord(
            step=self.n,
            t=self.t,
            p_true=self.plant.density,
            measurement=meas,
            estimate=est,
            command=self.command,
            positions=self.plant.positions,
            headings=getattr(self.plant, "headings", None),
        )
