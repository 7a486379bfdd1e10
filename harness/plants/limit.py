"""The loop's deterministic ``N -> infinity`` limit ``p_inf``: the reference a run with
robots is measured against.

A run with ``N`` robots measured by their KDE has, as ``N -> infinity``, a deterministic
limit: the Fokker-Planck density (eq. ``FP equation``) started from ``p_0`` and moved by
the same control law fed the estimates a noise-free KDE of it would give, ``K_h * p_inf``
and its gradient (:class:`harness.estimators.smoothing.Smoother`, with the plant's own
bandwidth and wall images). Step ``n -> n + 1``, the law's command held over the step as
the robots' is:

    v_n       = law(t_n; K_h * p_inf(t_n), grad K_h * p_inf(t_n), density p_inf(t_n))
    p_inf^{n+1} = FP step of p_inf^n under v_n  (:meth:`harness.fokker_planck.FokkerPlanck.step`)

The Fokker-Planck density under the velocity the robots *receive* would be no reference:
that velocity is computed from the swarm's own fluctuations, so such a density drifts
away from the swarm. The loop (:class:`harness.loop.ClosedLoop`) advances the limit
after the robots and measures the paper's errors ``Phi = p - p_*``, ``eps = p_hat - p``
against it (``p = p_inf``). A law without a mean-field form (its ``needs_robots``) has no
limit: the run is measured against the robots' histogram (the plant's ``density``).
"""

from __future__ import annotations

import numpy as np

from harness.estimators.smoothing import Smoother
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.meanfield import initial_density
from harness.protocols import Control, Plant, kernel, needs_robots, require_field
from harness.records import ControlInput, Estimate
from harness.targets.densities import Density


class Limit:
    """The ``N -> infinity`` limit ``p_inf`` of a run with robots (module docstring).

    Args:
        grid: The grid.
        model: The run's Fokker-Planck model.
        init: The initial density ``p_0``.
        control: The run's law; it must give a velocity field.
        bandwidth: The KDE bandwidth ``h > 0`` (length) of the plant's measurement.
        mirror: Whether that KDE has wall images.

    Attributes:
        density: ``p_inf`` ``(ny, nx)`` (1 / length^2) at the current time.
    """

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        init: Density,
        control: Control,
        bandwidth: float,
        mirror: bool,
    ) -> None:
        require_field(
            control, "for the N -> infinity limit of a run with robots (it moves by the field)"
        )
        self.grid, self.model, self.init, self.control = grid, model, init, control
        self.smoother = Smoother(grid, bandwidth, mirror, free=model.free)
        self.density = initial_density(init, grid, getattr(model, "free", None))
        self.t = 0.0

    @classmethod
    def of(
        cls, plant: Plant, control: Control, grid: Grid, model: FokkerPlanck, init: Density
    ) -> Limit | None:
        """The limit of a run: for a plant with robots measured by a KDE
        (:func:`harness.protocols.kernel`) and a law with a mean-field form; None
        otherwise (no robots: the plant's density is the mean field itself).

        Raises:
            harness.parameters.Incompatible: for a law with a mean-field form but
                without a velocity field.
        """
        measured = kernel(plant)
        if not plant.has_robots or measured is None or needs_robots(control):
            return None
        return cls(grid, model, init, control, *measured)

    def start(self) -> None:
        """``p_inf = p_0`` on the grid at ``t = 0`` (restricted to free space on a domain
        with obstacles).
        """
        self.density = initial_density(self.init, self.grid, getattr(self.model, "free", None))
        self.t = 0.0

    def advance(self, dt: float) -> np.ndarray:
        """One step of ``dt`` (s) under the law's field of ``p_inf``'s own noise-free KDE
        (module docstring); returns the new ``p_inf``.
        """
        estimate = Estimate(*self.smoother(self.density))
        command = self.control(ControlInput(self.t, estimate, density=self.density))
        assert command.field is not None
        self.density = self.model.step(self.density, command.field, dt)
        self.t += dt
        return self.density
