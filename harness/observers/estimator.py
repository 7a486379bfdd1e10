"""``estimator``: the numbers an estimator publishes (``Estimate.metrics``), into the step's
values.
"""

from __future__ import annotations

from harness.observers.base import RunContext, Status
from harness.protocols import Estimator, publishes
from harness.records import StepRecord


class EstimatorMetrics:
    """The numbers the estimator publishes (``Estimate.metrics``), added to the step's
    values as they are (units: the estimator's docstring; the decentralised loop's are
    listed in ``docs`` under the log contract).

    Args:
        estimator: The run's estimator; what it declares it publishes
            (:func:`harness.protocols.publishes`) is what this observer gives, so the
            builder refuses a guard that requires a network metric of an estimator that
            has none. Without it (an observer built alone), it gives nothing it can
            promise.
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)

    def __init__(self, estimator: Estimator | None = None) -> None:
        self.gives: tuple[str, ...] = () if estimator is None else publishes(estimator)

    def initialize(self, run: RunContext) -> None:
        """Nothing to prepare."""

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Copy the estimate's published numbers."""
        values.update({key: float(v) for key, v in rec.estimate.metrics.items()})

    def finalize(self, status: Status) -> None:
        """Nothing to close."""
