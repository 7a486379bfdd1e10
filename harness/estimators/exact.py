"""``estimator=exact``: the plant's mean-field density as the estimate (theory checks)."""

from __future__ import annotations

from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.records import Estimate, StepInput


class ExactEstimator:
    """``p_hat = p``, ``q_hat = G p`` with the mean-field density ``p`` (theory checks,
    ``estimator=exact``).
    """

    uses_kde = False

    def __init__(self, grid: Grid, model: FokkerPlanck) -> None:
        self.grid = grid

    def initialize(self, inp: StepInput) -> Estimate:
        """The mean-field density and its grid gradient."""
        return Estimate(inp.p_true, self.grid.gradient(inp.p_true))

    step = initialize
