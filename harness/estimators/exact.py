"""``estimator=exact``: the plant's mean-field density as the estimate (theory checks)."""

from __future__ import annotations

from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.records import Estimate, StepInput


class ExactEstimator:
    """``p_hat = p``, ``q_hat = G p`` with the mean-field density ``p`` (theory checks,
    ``estimator=exact``); on free space ``G`` is its gradient
    (:meth:`harness.domains.base.FreeSpace.gradient`, reflecting at closed faces).
    """

    uses_kde = False
    free_space = True

    def __init__(self, grid: Grid, model: FokkerPlanck) -> None:
        self.grid = grid
        self.free = model.free

    def initialize(self, inp: StepInput) -> Estimate:
        """The mean-field density and its grid gradient."""
        if self.free is not None:
            return Estimate(inp.p_true, self.free.gradient(inp.p_true))
        return Estimate(inp.p_true, self.grid.gradient(inp.p_true))

    step = initialize
