"""``guard``: the divergence guard, which ends a run as ``diverged`` at a bad number."""

from __future__ import annotations

import math

from harness.fokker_planck import NumericalError
from harness.observers.base import RunContext, Status
from harness.parameters import require
from harness.records import StepRecord


class DivergenceGuard:
    """Ends the run as diverged when a number of the step is NaN or infinite, or
    missing where it may not be.

    Args:
        required: Keys that must be numbers at every step; None for the log contract's
            (:data:`harness.observers.log.ALWAYS_NUMBERS`).
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)
    gives: tuple[str, ...] = ()  # checks the values, adds none

    def __init__(self, required: list[str] | tuple[str, ...] | None = None) -> None:
        if required is None:
            from harness.observers.log import ALWAYS_NUMBERS

            required = ALWAYS_NUMBERS
        ok = isinstance(required, (list, tuple)) and all(isinstance(k, str) for k in required)
        require(ok, "required", required, "a list of metric names, or null")
        self.required = tuple(required)

    @property
    def needs(self) -> dict[str, tuple[str, ...]]:
        """The metrics that must be numbers at every step, by the parameter naming them
        (:func:`harness.observers.base.needs`): an observer before the guard must give each.
        """
        return {"required": self.required}

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
