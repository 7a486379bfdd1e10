"""Per-robot fast filters: every robot filters its own tracked observation.

Each robot runs the fast filters of :mod:`harness.filters.local` (derivations there) on
what consensus tracks for it (:mod:`harness.decentralised.consensus`): the density part
``y_i = z_i`` with the centralised KDE's noise (the swarm's ``N`` and ``h`` set ``k``,
``k_g``), vectorised over robots (arrays ``(N, M)``, one robot per row):

* the density filter, compiled over robots (:mod:`harness.decentralised.density`: the
  exact state transition by Jacobi sweeps on the 5-point stencil of ``A``, variances by
  ``F1 o F1``, the diagonal update with ``R = r_scale k diag(max(y_i, r_floor))``);
* the gradient estimate of the option ``gradient``
  (:mod:`harness.decentralised.gradient`): the grid gradient of the robot's own density
  estimate, or a gradient filter per robot on the tracked analytic kernel gradient.

The robots' filters keep every grid mode (no band limit: a per-robot DCT would cost
``O(N M log M)`` per step).

The applied ``A`` is the Fokker-Planck matrix of the velocity the robots are modelled to
follow; in the decentralised loop every robot moves on its own field, and the filters
take whatever ``A`` the caller supplies (it is the filters' model, shared by all).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from harness.decentralised.density import ROBOT_MAX_SWEEPS, density_step
from harness.decentralised.gradient import GRADIENTS, RobotGradient
from harness.decentralised.poisson import BatchedPoisson
from harness.filters.common import FilterSettings, MeasurementModel
from harness.grid import Grid


class RobotFilters:
    """Per-robot fast filters (:class:`harness.filters.local.LocalFilters`, vectorised
    over robots): density estimates ``x`` and variances ``d`` of shape ``(N, M)``, and
    the gradient estimate of the option ``gradient`` (:attr:`gradient`).

    Args:
        grid: The grid.
        dt: Step (s).
        measurement: The swarm's KDE measurement model (``N``, ``h``, settings): each
            robot's tracked observation has the centralised KDE's noise.
        gradient: A key of :data:`~harness.decentralised.gradient.GRADIENTS`: ``"grid"``
            (``q_hat_i = G p_hat_i``) or ``"filter"``.
    """

    def __init__(
        self, grid: Grid, dt: float, measurement: MeasurementModel, gradient: str = "grid"
    ) -> None:
        if gradient not in GRADIENTS:
            names = " or ".join(repr(name) for name in GRADIENTS)
            raise ValueError(f"gradient must be {names}, got {gradient!r}")
        self.grid, self.dt, self.measurement = grid, dt, measurement
        self.settings: FilterSettings = measurement.settings
        self.poisson = BatchedPoisson(grid)
        self.gradient: RobotGradient = GRADIENTS[gradient](grid, dt, measurement, self.poisson)
        self.max_sweeps = ROBOT_MAX_SWEEPS
        self.x: np.ndarray | None = None
        self.d: np.ndarray | None = None

    def initialize(self, y: np.ndarray, y_g: np.ndarray | None = None) -> None:
        """``x0 = y``, ``P0 = initial_variance k``; the gradient as in ``LocalFilters``.

        Args:
            y: Observations ``(N, M)`` (1 / length^2).
            y_g: Gradient observations ``(N, 2M)`` (1 / length^3), when the gradient
                option tracks them.
        """
        s, g = self.settings, self.grid
        k, _ = self.measurement.constants
        n = y.shape[0]
        self.x = np.array(y, dtype=float)
        self.d = np.full((n, g.size), s.initial_variance * k)
        self.gradient.initialize(y_g)

    def step(self, y: np.ndarray, a: sp.csr_matrix, y_g: np.ndarray | None = None) -> None:
        """Predict under ``A`` and update with the observations (in place)."""
        assert self.x is not None and self.d is not None, "call initialize first"
        a = a.tocsr()
        a.sort_indices()
        y = np.ascontiguousarray(y, dtype=float)
        self.x = density_step(
            self.grid, self.dt, self.measurement, self.x, self.d, y, a, self.max_sweeps
        )
        self.gradient.step(y, a, y_g)

    @property
    def q_hat(self) -> np.ndarray:
        """Gradient estimates ``(N, 2M)``: ``G x_g,i`` (filter) or ``G p_hat_i`` (grid)."""
        assert self.x is not None
        return self.gradient.q_hat(self.x)
