"""Plants (config group ``plant``): what moves under the held velocity and what it
lets the estimator measure.

* :class:`Agents` (``plant=agents``): ``N`` robots by eq. ``Langevin equation``
  (:class:`harness.agents.Swarm`), measured by their KDE (:class:`harness.kde.KDE`);
  alongside, the loop's deterministic ``N -> infinity`` limit ``p_inf``: the
  Fokker-Planck density (eq. ``FP equation``) started from ``p_0`` and moved by the
  same control law fed the estimates a noise-free KDE of ``p_inf`` would give,
  ``K_h * p_inf`` and its gradient (:class:`harness.smoothing.Smoother`).
* :class:`MeanField` (``plant=meanfield``): no robots; the state is the Fokker-Planck
  density ``p`` and the measurement is ``p`` plus seeded Gaussian noise with the KDE's
  own variances ``k p`` and ``k_g p`` per cell (notes section 3), for the swarm size and
  bandwidth configured.

Both implement :class:`harness.components.Plant` and share the run's
:class:`~harness.fokker_planck.FokkerPlanck` model. Both need a law with a velocity
field: the mean-field plant moves by it, and the agents plant's limit ``p_inf`` is the
law's field of ``p_inf``'s own noise-free KDE (the Fokker-Planck density under the
*applied* velocity would be no reference: that velocity is computed from the swarm's own
fluctuations, so such a density drifts away from the swarm).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from harness.agents import Swarm, reflect
from harness.components import (
    Control,
    Density,
    MemoryEstimate,
    default_memory,
    flag,
    integer,
    needs_robots,
    number,
    refuse_robot_law,
    require,
    require_field,
)
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.kde import KDE, noise_constants
from harness.records import Command, ControlInput, Estimate, Measurement
from harness.smoothing import Smoother


class Agents:
    """``N`` robots measured by their KDE, with the loop's ``N -> infinity`` limit.

    Args:
        grid, model, init, control: Run-time arguments (grid, Fokker-Planck model,
            ``p_0``, the control law).
        n: Number of robots ``N >= 1``.
        bandwidth: KDE bandwidth ``h > 0`` (length), at most the domain side.
        mirror: Wall images in the KDE.
        method: KDE evaluation, ``auto`` | ``exact`` | ``binned``.
        localisation_noise: Standard deviation ``s`` (length), ``0 <= s <=`` a quarter of
            the domain side, of the localisation error: the estimator and the law see
            ``X_i + s xi_i`` (``xi_i`` standard normal, fresh every step after the robots
            move, from the plant's own stream ``[seed, 3]``, so the robots' own draws are
            those of the run without it; reflected into the domain at the walls), while
            the robots move from their true positions and the swarm metrics use the true
            ones. 0 draws nothing.
        seed: The run's seed, for the localisation error's stream.

    Without a mean-field form of the law (``needs_robots``, a law that moves each
    robot itself, such as a Markov chain or an assignment) there is no limit to
    compute: ``density`` is then the robots' histogram (robots per cell over ``N``
    times the cell area, 1 / length^2), and ``has_limit`` is false.
    """

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        init: Density,
        control: Control,
        n: int,
        bandwidth: float,
        mirror: bool = True,
        method: str = "auto",
        localisation_noise: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.grid, self.model, self.init, self.control = grid, model, init, control
        self.localisation_noise = number("localisation_noise", localisation_noise, 0.0)
        quarter = min(grid.x1 - grid.x0, grid.y1 - grid.y0) / 4
        require(
            self.localisation_noise <= quarter,
            "localisation_noise", localisation_noise, f"at most a quarter of the side, {quarter:g}",
        )  # fmt: skip
        self.seed = integer("seed", seed, 0)
        self._sight = np.random.default_rng([self.seed, 3])
        self.has_limit = not needs_robots(control)
        self.density = init.on_grid(grid)
        self.n = integer("n", n, 1)
        h = number("bandwidth", bandwidth, 0.0, strict=True)
        side = min(grid.x1 - grid.x0, grid.y1 - grid.y0)
        require(h <= side, "bandwidth", bandwidth, f"at most the domain side {side:g}")
        require(method in KDE.METHODS, "method", method, f"one of {', '.join(KDE.METHODS)}")
        self.kde = KDE(grid, h, mirror=flag("mirror", mirror), method=method)
        self.smoother = Smoother(grid, h, mirror)
        self.swarm: Swarm | None = None
        self.resolution: float | None = h  # the KDE resolves no scale below h
        self.t = 0.0

    has_robots = True

    BYTES_PER_ROBOT = 200
    """Per robot: positions, noise and interpolation temporaries (float64, 2 x 8 bytes
    each, about eight of them), the KDE's binning indices and weights, and the logged
    point cloud (float32 x, y, z and its serialised copy)."""

    @classmethod
    def memory_estimate(cls, grid: Grid, n: int = 1, **params: object) -> MemoryEstimate:
        """``BYTES_PER_ROBOT n`` plus the grid arrays (:func:`default_memory`)."""
        robots = n if isinstance(n, int) and n > 0 else 1
        return MemoryEstimate(cls.BYTES_PER_ROBOT * robots + default_memory(grid).nbytes, "n")

    @property
    def positions(self) -> np.ndarray | None:
        """Robot positions ``(2, N)`` (length), None before :meth:`start`."""
        return None if self.swarm is None else self.swarm.positions

    @property
    def observed(self) -> np.ndarray | None:
        """The positions as the estimator and the law see them ``(2, N)`` (length):
        the true ones plus the localisation error (the class docstring).
        """
        if self.localisation_noise > 0 and self.swarm is not None:
            return self._observed
        return self.positions

    def _observe(self) -> None:
        """Draw the localisation error of the current positions (own stream)."""
        if self.localisation_noise > 0:
            assert self.swarm is not None
            g = self.grid
            seen = self.swarm.positions + self.localisation_noise * self._sight.standard_normal(
                self.swarm.positions.shape
            )
            reflect(seen[0], g.x0, g.x1)
            reflect(seen[1], g.y0, g.y1)
            self._observed = seen

    def check(self, control: Control, **parts: object) -> None:
        """The limit ``p_inf`` moves by the law's field: refuse a law without one."""
        require_field(control, "on plant=agents (its N -> infinity limit moves by the field)")

    def start(self, rng: np.random.Generator) -> None:
        """Draw ``N`` robots from ``p_0``."""
        self.swarm = Swarm(self.grid, self.init.sample(self.n, self.grid, rng), self.model.sigma)
        self.t = 0.0
        if not self.has_limit:
            self.density = self.swarm.histogram()
        self._sight = np.random.default_rng([self.seed, 3])  # the stream restarts
        self._observe()

    def advance(
        self, command: Command, a: sp.csr_matrix | None, dt: float, rng: np.random.Generator
    ) -> None:
        """Robots by Euler-Maruyama with reflection under the command (their own
        velocities when it has them, else the field's interpolant); the limit ``p_inf``
        under the law's field of its own noise-free KDE and of ``p_inf`` itself (held
        over the step, like the command), or the robots' histogram without a limit;
        then the localisation error of the new positions.
        """
        assert self.swarm is not None, "call start first"
        if command.robots is not None:
            self.swarm.step_robots(command.robots, dt, rng)
        else:
            assert command.field is not None
            self.swarm.step(command.field, dt, rng)
        if self.has_limit:
            estimate = Estimate(*self.smoother(self.density))
            limit = self.control(ControlInput(self.t, estimate, density=self.density))
            assert limit.field is not None
            self.density = self.model.step(self.density, limit.field, dt)
        else:
            self.density = self.swarm.histogram()
        self.t += dt
        self._observe()

    def measure(self, rng: np.random.Generator) -> Measurement:
        """The KDE of the robots as observed (:attr:`observed`) and its analytic gradient."""
        assert self.swarm is not None, "call start first"
        seen = self.observed
        assert seen is not None
        return Measurement(*self.kde(seen))


class MeanField:
    """The mean-field density, measured with KDE-like noise (no robots).

    Args:
        grid, model, init, control: Run-time arguments (``control`` is not used: the
            density moves under the applied velocity).
        robots: Swarm size ``N >= 1`` whose KDE noise is imitated.
        bandwidth: KDE bandwidth ``h > 0`` (length) whose noise is imitated.
        localisation_noise: Must be 0: without robots there are no positions to
            mislocate.
    """

    positions = None
    observed = None
    has_robots = False
    has_limit = True
    resolution = None  # white noise per cell: grid resolution

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        init: Density,
        control: Control,
        robots: int,
        bandwidth: float,
        localisation_noise: float = 0.0,
    ) -> None:
        noise = number("localisation_noise", localisation_noise, 0.0)
        require(noise == 0, "localisation_noise", localisation_noise, "0 without robots")
        self.grid, self.model = grid, model
        self.density = init.on_grid(grid)
        self.robots = integer("robots", robots, 1)
        self.bandwidth = number("bandwidth", bandwidth, 0.0, strict=True)
        self.k, self.k_g = noise_constants(self.robots, self.bandwidth)

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
        grad = self.grid.gradient(p)
        grad_meas = grad + np.sqrt(self.k_g) * sd * rng.standard_normal((2, *self.grid.shape))
        return Measurement(p_meas, grad_meas)
