"""``plant=meanfield``: no robots; the state is the Fokker-Planck density ``p`` (eq. ``FP
equation``) and the measurement is ``p`` plus seeded Gaussian noise with the KDE's own
variances ``k p`` and ``k_g p`` per cell (notes section 3), for the swarm size and
bandwidth configured.

On a domain with obstacles (the model's ``free``) the density starts from ``p_0``
restricted to the free cells (:meth:`harness.domains.base.FreeSpace.restrict`), the
Fokker-Planck step keeps it there, and the measured gradient is free space's
(:meth:`harness.domains.base.FreeSpace.gradient`: reflecting at closed faces). The noise
is ``sqrt(k p)``, so it is 0 on blocked cells, where ``p`` is.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from harness.domains.base import FreeSpace
from harness.estimators.kde import noise_constants
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import integer, number, require
from harness.plants.link import command_link
from harness.protocols import (
    Control,
    refuse_robot_law,
    require_field,
)
from harness.records import Command, Measurement
from harness.targets.densities import Density


class MeanField:
    """``plant=meanfield``: the mean-field density, measured with KDE-like noise (no
    robots).

    Args:
        grid, model, init: Run-time arguments.
        robots: Swarm size ``N >= 1`` whose KDE noise is imitated.
        bandwidth: KDE bandwidth ``h > 0`` (length) whose noise is imitated.
        localisation_noise: Must be 0: without robots there are no positions to
            mislocate.
        link_period, link_latency, link_loss, dt: Must be the ideal link (the
            defaults): without robots there is no one to send commands to.
    """

    positions = None
    has_robots = False

    free_space = True
    """The density lives on the model's free space (module docstring)."""

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        init: Density,
        robots: int,
        bandwidth: float,
        localisation_noise: float = 0.0,
        link_period: float | None = None,
        link_latency: float = 0.0,
        link_loss: float = 0.0,
        dt: float | None = None,
    ) -> None:
        noise = number("localisation_noise", localisation_noise, 0.0)
        require(noise == 0, "localisation_noise", localisation_noise, "0 without robots")
        link = command_link(link_period, link_latency, link_loss, dt, 0)
        if not link.ideal:
            bad = "link_loss" if link_loss else "link_latency" if link_latency else "link_period"
            value = {"link_loss": link_loss, "link_latency": link_latency}.get(bad, link_period)
            require(False, bad, value, "the ideal link on plant=meanfield (it has no robots)")
        self.grid, self.model = grid, model
        self.free = getattr(model, "free", None)
        self.density = initial_density(init, grid, self.free)
        self.robots = integer("robots", robots, 1)
        self.bandwidth = number("bandwidth", bandwidth, 0.0, strict=True)
        self.k, self.k_g = noise_constants(self.robots, self.bandwidth)
        # the swarm's size and the loop's step, as the run's shared keys must give them
        self.copies: dict[str, tuple[str, float]] = {"robots": ("robots", self.robots)}
        if dt is not None:
            self.copies["dt"] = ("dt", link.dt)

    def check(self, control: Control, **parts: object) -> None:
        """The density moves by the law's field of the density: refuse a law without a
        field or without a mean-field form.
        """
        require_field(control, "on plant=meanfield (the density moves by it)")
        refuse_robot_law(control, "on plant=meanfield (it has no robots)")

    def start(self, rng: np.random.Generator) -> None:
        """Nothing to draw: the state is ``p_0`` on the grid."""

    def advance(
        self, command: Command, a: sp.csr_matrix | None, dt: float, rng: np.random.Generator
    ) -> None:
        """The backward-Euler Fokker-Planck step under the command's field."""
        assert command.field is not None
        self.density = self.model.step(self.density, command.field, dt, a)

    def measure(self, rng: np.random.Generator) -> Measurement:
        """``p + sqrt(k p) xi`` and ``G p + sqrt(k_g p) xi_g``, ``xi`` standard normal."""
        p = self.density
        sd = np.sqrt(np.maximum(p, 0.0))
        p_meas = p + np.sqrt(self.k) * sd * rng.standard_normal(self.grid.shape)
        grad = self.grid.gradient(p) if self.free is None else self.free.gradient(p)
        grad_meas = grad + np.sqrt(self.k_g) * sd * rng.standard_normal((2, *self.grid.shape))
        return Measurement(p_meas, grad_meas)


def initial_density(init: Density, grid: Grid, free: FreeSpace | None) -> np.ndarray:
    """``p_0`` on the grid, restricted to the free cells of ``free`` (zero on blocked
    cells, unit mass on the free ones) when given.
    """
    p = init.on_grid(grid)
    return p if free is None else free.restrict(p)
