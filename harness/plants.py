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

from typing import cast

import numpy as np
import scipy.sparse as sp

from harness.agents import Swarm, reflect
from harness.components import (
    Control,
    Density,
    MemoryEstimate,
    ParameterError,
    default_memory,
    flag,
    integer,
    needs_robots,
    number,
    refuse_robot_law,
    require,
    require_field,
)
from harness.double_integrators import DoubleIntegratorSwarm
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.kde import KDE, noise_constants
from harness.link import Link
from harness.records import Command, ControlInput, Estimate, Measurement
from harness.smoothing import Smoother
from harness.unicycles import UnicycleSwarm


def command_link(
    period: float | None, latency: float, loss: float, dt: float | None, seed: int
) -> Link:
    """The plant's command link (:class:`harness.link.Link`; ``period`` None: every
    step), its refusals named by the plant's keys (``link_period``, ...). Without ``dt``
    only the ideal link is possible.
    """
    if dt is None:
        ideal = period is None and latency == 0 and loss == 0
        require(ideal, "dt", dt, "the step sim.dt, for a link that is not ideal")
    step = 1.0 if dt is None else dt
    try:
        return Link(step if period is None else period, latency, loss, step, seed)
    except ParameterError as err:
        name = "dt" if err.name == "dt" else f"link_{err.name}"
        raise ParameterError(name, err.value, err.allowed) from None


def spread_values(nominal: float, spread: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Per-robot values ``nominal (1 + spread U)``, ``U`` uniform on ``[-1, 1]`` (drawn
    from ``rng``); ``nominal > 0`` and ``0 <= spread < 1`` (checked by the plant's
    constructor), so every value is positive.
    """
    return np.asarray(nominal * (1.0 + spread * rng.uniform(-1.0, 1.0, n)))


def _spread(spread: float) -> float:
    s = number("spread", spread, 0.0)
    require(s < 1, "spread", spread, "below 1 (a relative half-width; values stay positive)")
    return s


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
        seed: The run's seed, for the localisation error's stream and the link's.
        link_period, link_latency, link_loss: The command link (:class:`harness.link.Link`):
            time between broadcasts (s; None: every step), delay to arrival (s) and
            the probability that a robot misses a broadcast. The defaults are the
            ideal link, under which the robots move by the code path of a run without
            one.
        dt: The step (s), which the link's period and latency count in.

    Per step the plant reports ``tracking_error``, the mean over robots of
    ``|velocity applied - velocity commanded|`` (length / s; the commanded velocity is
    the held command at the robot, the applied one its displacement over the step
    without the noise; 0 for these ideal integrators, which apply what they hold), and
    ``command_age``, the mean age of the held commands (s, :class:`harness.link.Link`);
    both None before the first step.

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
        link_period: float | None = None,
        link_latency: float = 0.0,
        link_loss: float = 0.0,
        dt: float | None = None,
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
        self.link = command_link(link_period, link_latency, link_loss, dt, self.seed)
        self.tracking_error: float | None = None
        self.command_age: float | None = None
        self._steps = 0

    has_robots = True

    BYTES_PER_ROBOT = 200
    """Per robot: positions, noise and interpolation temporaries (float64, 2 x 8 bytes
    each, about eight of them), the KDE's binning indices and weights, and the logged
    point cloud (float32 x, y, z and its serialised copy)."""

    @classmethod
    def memory_estimate(cls, grid: Grid, n: int = 1, **params: object) -> MemoryEstimate:
        """``BYTES_PER_ROBOT n`` plus the grid arrays (:func:`default_memory`), plus the
        commands a link holds in flight: up to ``latency / period + 1`` copies of a
        command (a velocity per robot, 16 bytes each, and a field of about 32 bytes per
        cell), named by ``link.latency`` when they are most of it.
        """
        robots = n if isinstance(n, int) and n > 0 else 1
        base = cls.BYTES_PER_ROBOT * robots + default_memory(grid).nbytes
        period = params.get("link_period") or params.get("dt")
        latency = params.get("link_latency") or 0.0
        in_flight = 0.0
        if isinstance(period, (int, float)) and isinstance(latency, (int, float)) and period > 0:
            in_flight = latency / period + 1.0 if latency > 0 or period != params.get("dt") else 0.0
        held = in_flight * (16.0 * robots + 32.0 * grid.size)
        if not np.isfinite(held) or held > 1e18:
            held = 1e18  # a latency no run reaches: refused as more than any machine has
        return MemoryEstimate(int(base + held), "link_latency" if held > base else "n")

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

    headings: np.ndarray | None = None
    """Robot headings as unit vectors ``(cos theta, sin theta)``, ``(2, N)``, for robots
    that have one, else None."""

    def _robots(self, positions: np.ndarray) -> Swarm:
        """The robots at ``positions`` ``(2, N)``: ideal integrators here."""
        return Swarm(self.grid, positions, self.model.sigma)

    def start(self, rng: np.random.Generator) -> None:
        """Draw ``N`` robots from ``p_0``."""
        self.swarm = self._robots(self.init.sample(self.n, self.grid, rng))
        self.link.start(self.n)
        self.tracking_error = self.command_age = None
        self._steps = 0
        self.t = 0.0
        if not self.has_limit:
            self.density = self.swarm.histogram()
        self._sight = np.random.default_rng([self.seed, 3])  # the stream restarts
        self._observe()

    def move_robots(self, command: Command, dt: float, rng: np.random.Generator) -> None:
        """The command through the link and the robots over the step under what each
        holds; sets ``tracking_error``.
        """
        assert self.swarm is not None, "call start first"
        self.link.transmit(command, self._steps)
        if self.link.ideal and type(self.swarm) is Swarm:  # a run without a link
            if command.robots is not None:
                self.swarm.step_robots(command.robots, dt, rng)
            else:
                assert command.field is not None
                self.swarm.step(command.field, dt, rng)
            self.tracking_error = 0.0
        else:
            field = self.link.common_field()
            move_field = getattr(self.swarm, "move_field", None)
            if field is not None and move_field is not None:  # one pass for a shared field
                self.tracking_error = move_field(field, dt, rng)
            else:
                held = self.link.velocities(self.swarm.positions, self.grid)
                applied = self.swarm.move(held, dt, rng)
                # tracking error: (1/N) sum_k |applied_k - commanded_k|
                self.tracking_error = float(np.mean(np.hypot(*(applied - held))))

    def advance(
        self, command: Command, a: sp.csr_matrix | None, dt: float, rng: np.random.Generator
    ) -> None:
        """The command through the link; the robots over the step under what each
        holds (their own velocities when the command has them, else the field's
        interpolant; ideal integrators by Euler-Maruyama with reflection); the limit
        ``p_inf`` under the law's field of its own noise-free KDE and of ``p_inf``
        itself (held over the step, like the command), or the robots' histogram
        without a limit; then the localisation error of the new positions.
        """
        self.move_robots(command, dt, rng)
        assert self.swarm is not None
        self.command_age = self.link.age
        self._steps += 1
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


class Unicycles(Agents):
    """``N`` unicycles (:mod:`harness.unicycles`) measured by their KDE, with the
    limit ``p_inf`` of ideal integrators beside them (:class:`Agents`).

    Args:
        grid, model, init, control, n, bandwidth, mirror, method, localisation_noise,
            seed, link_period, link_latency, link_loss, dt: As :class:`Agents`.
        v_max: Nominal forward-speed limit (length / s), ``> 0``.
        omega_max: Nominal turn-rate limit (rad / s), ``> 0``.
        lookahead: Nominal look-ahead ``l`` of the feedback linearisation (length),
            ``> 0``.
        spread: Relative spread of the per-robot limits and look-ahead, ``0 <= s <
            1``: robot ``k``'s value is the nominal times ``1 + s U_k``, ``U_k``
            uniform on ``[-1, 1]``, drawn once per run.

    Headings start uniform on ``[-pi, pi)``. The headings and the per-robot values come
    from the plant's own stream ``[seed, 4]`` (in that order: headings, ``v_max``,
    ``omega_max``, ``lookahead``), so the robots' positions and noise are those of the
    ideal integrators' run of the same seed.
    """

    BYTES_PER_ROBOT = 400
    """:attr:`Agents.BYTES_PER_ROBOT` plus the heading, three limits, the held and
    applied velocities, and the logged pose (69 bytes, and its serialised copy)."""

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
        link_period: float | None = None,
        link_latency: float = 0.0,
        link_loss: float = 0.0,
        dt: float | None = None,
        v_max: float = 0.1,
        omega_max: float = 3.0,
        lookahead: float = 0.01,
        spread: float = 0.0,
    ) -> None:
        super().__init__(
            grid, model, init, control, n, bandwidth, mirror, method, localisation_noise,
            seed, link_period, link_latency, link_loss, dt,
        )  # fmt: skip
        self.v_max = number("v_max", v_max, 0.0, strict=True)
        self.omega_max = number("omega_max", omega_max, 0.0, strict=True)
        self.lookahead = number("lookahead", lookahead, 0.0, strict=True)
        self.spread = _spread(spread)

    @property
    def headings(self) -> np.ndarray | None:  # type: ignore[override]
        """Robot headings as unit vectors ``(cos theta, sin theta)``, ``(2, N)``; None
        before :meth:`start`.
        """
        return None if self.swarm is None else cast(UnicycleSwarm, self.swarm).headings

    def _robots(self, positions: np.ndarray) -> Swarm:
        """Unicycles at ``positions``, headings and limits from the stream ``[seed, 4]``."""
        rng = np.random.default_rng([self.seed, 4])
        n, s = positions.shape[1], self.spread
        headings = np.asarray(rng.uniform(-np.pi, np.pi, n))
        return UnicycleSwarm(
            self.grid, positions, self.model.sigma, headings,
            spread_values(self.v_max, s, n, rng),
            spread_values(self.omega_max, s, n, rng),
            spread_values(self.lookahead, s, n, rng),
        )  # fmt: skip


class DoubleIntegrators(Agents):
    """``N`` acceleration-limited robots (:mod:`harness.double_integrators`) measured
    by their KDE, with the limit ``p_inf`` of ideal integrators beside them
    (:class:`Agents`).

    Args:
        grid, model, init, control, n, bandwidth, mirror, method, localisation_noise,
            seed, link_period, link_latency, link_loss, dt: As :class:`Agents`.
        a_max: Nominal acceleration limit (length / s^2), ``> 0``.
        gain: Nominal velocity-loop gain ``g`` (1 / s), ``> 0``.
        spread: Relative spread of the per-robot limit and gain, as for
            :class:`Unicycles` (drawn from the stream ``[seed, 4]``: ``a_max``, then
            ``gain``).

    The robots start at rest.
    """

    BYTES_PER_ROBOT = 300
    """:attr:`Agents.BYTES_PER_ROBOT` plus the velocity, two limits, the held and
    applied velocities."""

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
        link_period: float | None = None,
        link_latency: float = 0.0,
        link_loss: float = 0.0,
        dt: float | None = None,
        a_max: float = 0.5,
        gain: float = 5.0,
        spread: float = 0.0,
    ) -> None:
        super().__init__(
            grid, model, init, control, n, bandwidth, mirror, method, localisation_noise,
            seed, link_period, link_latency, link_loss, dt,
        )  # fmt: skip
        self.a_max = number("a_max", a_max, 0.0, strict=True)
        self.gain = number("gain", gain, 0.0, strict=True)
        self.spread = _spread(spread)

    def _robots(self, positions: np.ndarray) -> Swarm:
        """Double integrators at rest at ``positions``, limits from ``[seed, 4]``."""
        rng = np.random.default_rng([self.seed, 4])
        n, s = positions.shape[1], self.spread
        return DoubleIntegratorSwarm(
            self.grid, positions, self.model.sigma,
            spread_values(self.a_max, s, n, rng),
            spread_values(self.gain, s, n, rng),
        )  # fmt: skip


class MeanField:
    """The mean-field density, measured with KDE-like noise (no robots).

    Args:
        grid, model, init, control: Run-time arguments (``control`` is not used: the
            density moves under the applied velocity).
        robots: Swarm size ``N >= 1`` whose KDE noise is imitated.
        bandwidth: KDE bandwidth ``h > 0`` (length) whose noise is imitated.
        localisation_noise: Must be 0: without robots there are no positions to
            mislocate.
        link_period, link_latency, link_loss, dt: Must be the ideal link (the
            defaults): without robots there is no one to send commands to.
    """

    positions = None
    observed = None
    headings = None
    tracking_error = None
    command_age = None
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
