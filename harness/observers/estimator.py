"""``estimator``: the numbers an estimator publishes (``Estimate.metrics``), into the step's
values.
"""

from __future__ import annotations

from harness.estimators.distributed.metrics import NETWORK_KEYS
from harness.observers.base import RunContext, Status
from harness.records import StepRecord


class EstimatorMetrics:
    """The numbers the estimator publishes (``Estimate.metrics``), added to the step's
    values as they are (units: the estimator's docstring; the decentralised loop's are
    listed in ``docs`` under the log contract).
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)
    gives = NETWORK_KEYS  # what an estimator may publish (the log's contract)

    def initialize(self, run: RunContext) -> None:
        """Nothing to prepare."""

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Copy the estimate's published numbers."""
        values.update({key: float(v) for key, v in rec.estimate.metrics.items()})

    def finalize(self, status: Status) -> None:
        """Nothing to close."""
