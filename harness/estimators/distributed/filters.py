"""Per-robot fast filters: every robot filters its own tracked observation.

Each robot runs the fast density filter of :mod:`harness.estimators.filters.local` (derivations
there) on what consensus tracks for it (:mod:`harness.estimators.distributed.consensus`), ``y_i =
z_i``, with the centralised KDE's noise (the swarm's ``N`` and ``h`` set ``k``),
vectorised over robots (arrays ``(N, M)``, one robot per row) and compiled over robots
(:mod:`harness.estimators.distributed.density`: the exact state transition by Jacobi sweeps on
the 5-point stencil of ``A``, variances by ``F1 o F1``, the diagonal update with ``R =
r_scale k diag(max(y_i, r_floor))``). A robot's gradient estimate is the central
differences of its own density estimate, which the law takes at the robot's cells
(:func:`harness.control.own_estimates.own_velocities`).

The robots' filters keep every grid mode (no band limit: a per-robot DCT would cost
``O(N M log M)`` per step).

The applied ``A`` is the Fokker-Planck matrix of the velocity the robots are modelled to
follow; in the decentralised loop every robot moves on its own field, and the filters
take whatever ``A`` the caller supplies (it is the filters' model, shared by all).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.density import ROBOT_MAX_SWEEPS, density_step
from harness.estimators.filters.common import FilterSettings, MeasurementModel
from harness.grid import Grid


class RobotFilters:
    """Per-robot fast density filters (the density filter of
    :class:`harness.estimators.filters.local.LocalFilters`, vectorised over robots): density
    estimates ``x`` and variances ``d`` of shape ``(N, M)``.

    Args:
        grid: The grid.
        dt: Step (s).
        measurement: The swarm's KDE measurement model (``N``, ``h``, settings): each
            robot's tracked observation has the centralised KDE's noise.
    """

    def __init__(self, grid: Grid, dt: float, measurement: MeasurementModel) -> None:
        self.grid, self.dt, self.measurement = grid, dt, measurement
        self.settings: FilterSettings = measurement.settings
        self.max_sweeps = ROBOT_MAX_SWEEPS
        self.x: np.ndarray | None = None
        self.d: np.ndarray | None = None

    def initialize(self, y: np.ndarray) -> None:
        """``x0 = y``, ``P0 = initial_variance k``.

        Args:
            y: Observations ``(N, M)`` (1 / length^2).
        """
        s, g = self.settings, self.grid
        k, _ = self.measurement.constants
        n = y.shape[0]
        self.x = np.array(y, dtype=float)
        self.d = np.full((n, g.size), s.initial_variance * k)

    def step(self, y: np.ndarray, a: sp.csr_matrix) -> None:
        """Predict under ``A`` and update with the observations (in place)."""
        assert self.x is not None and self.d is not None, "call initialize first"
        a = a.tocsr()
        a.sort_indices()
        y = np.ascontiguousarray(y, dtype=float)
        self.x = density_step(
            self.grid, self.dt, self.measurement, self.x, self.d, y, a, self.max_sweeps
        )
