"""Double integrators: acceleration-limited robots that track a commanded velocity
(``plant=double_integrators``, :class:`harness.plants.double_integrators.DoubleIntegrators`).

Robot ``k`` has a position ``X_k`` (length) and a velocity ``W_k`` (length / s,
starting at rest); it is pushed by an acceleration ``a`` with ``|a| <= a_max`` and
keeps the positions' diffusion ``sigma`` (eq. ``Langevin equation``):

    dX = W dt + sqrt(2 sigma) dB,    dW = a dt.

Controller: proportional on the velocity error (a PD law on the position with the
commanded velocity as its reference),

    a = sat(g (v - W)),    sat(z) = z min(1, a_max / |z|),

with gain ``g > 0`` (1 / s; time constant ``1 / g``). Under a held ``v`` the error
``E = v - W`` keeps its direction and the loop is solved exactly over a hold of
``dt``: while ``g |E| > a_max`` the acceleration is ``a_max E / |E|`` and ``|E|``
falls at the rate ``a_max``, which lasts ``t_s = (|E_0| - a_max / g) / a_max``; after
that (or from the start when ``g |E_0| <= a_max``) the error decays as ``E(t) = E(t_s)
exp(-g (t - t_s))``, so

    W(t) = v - E(t_s) exp(-g (t - t_s)),
    X(t) = X(t_s) + v (t - t_s) - E(t_s) (1 - exp(-g (t - t_s))) / g.

The acceleration never exceeds ``a_max``, at every instant. Then the noise
``sqrt(2 sigma dt) xi`` (the run's stream, drawn as for the single integrators) and the
walls reflect the position (:func:`harness.plants.agents.reflect`; the velocity is kept),
and so do the obstacles on a domain with them (:mod:`harness.compiled.obstacles`; the
velocity is kept there too, also when the robot stays where it was).
With a large gain and limit the robot's velocity reaches ``v`` within a step and its
position follows the single integrator's.

What the mean-field model no longer captures: the density is transported by the
robots' own velocities ``W``, a state that lags the commanded field by about ``1 / g``
(longer where the limit binds), which the Fokker-Planck equation (eq. ``FP equation``)
and the filters' transport model do not carry.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.compiled.robots import double_integrator_step
from harness.grid import Grid
from harness.parameters import number
from harness.plants.agents import Agents, Swarm, check_spread, draw_normals, reflect, spread_values
from harness.plants.link import Link
from harness.plants.obstacles import RobotMap
from harness.records import Command


class DoubleIntegrators(Agents):
    """``plant=double_integrators``: ``N`` acceleration-limited robots (module docstring)
    measured by their KDE, behind the command link (:class:`~harness.plants.agents.Agents`).

    Args:
        robots: The parameters every robot plant takes, as
            :class:`~harness.plants.agents.Agents`.
        a_max: Nominal acceleration limit (length / s^2), ``> 0``.
        gain: Nominal velocity-loop gain ``g`` (1 / s), ``> 0``.
        spread: Relative spread of the per-robot limit and gain, as for
            :class:`~harness.plants.unicycles.Unicycles` (drawn from the stream
            ``[seed, 4]``: ``a_max``, then ``gain``).

    The robots start at rest.
    """

    BYTES_PER_ROBOT = 300
    """:attr:`Agents.BYTES_PER_ROBOT` plus the velocity, two limits, the held and
    applied velocities."""

    def __init__(
        self, a_max: float = 0.5, gain: float = 5.0, spread: float = 0.0, **robots: Any
    ) -> None:
        super().__init__(**robots)
        self.a_max = number("a_max", a_max, 0.0, strict=True)
        self.gain = number("gain", gain, 0.0, strict=True)
        self.spread = check_spread(spread)

    def _robots(self, positions: np.ndarray) -> Swarm:
        """Double integrators at rest at ``positions``, limits from ``[seed, 4]``."""
        rng = np.random.default_rng([self.seed, 4])
        n, s = positions.shape[1], self.spread
        return DoubleIntegratorSwarm(
            self.grid, positions, self.model.sigma,
            spread_values(self.a_max, s, n, rng),
            spread_values(self.gain, s, n, rng),
            self.obstacles,
        )  # fmt: skip


class DoubleIntegratorSwarm(Swarm):
    """``N`` double integrators in the grid's rectangle (module docstring).

    Args:
        grid: The grid (domain).
        positions: Initial positions ``(2, N)`` (length), inside the domain.
        sigma: Noise intensity ``sigma >= 0`` (length^2 / s).
        a_max: Acceleration limit per robot ``(N,)`` (length / s^2), ``> 0``.
        gain: Velocity-loop gain per robot ``(N,)`` (1 / s), ``> 0``.
        obstacles: The robots' map of obstacles, None on the plain rectangle
            (:class:`~harness.plants.agents.Swarm`).
    """

    def __init__(
        self,
        grid: Grid,
        positions: np.ndarray,
        sigma: float,
        a_max: np.ndarray,
        gain: np.ndarray,
        obstacles: RobotMap | None = None,
    ) -> None:
        super().__init__(grid, positions, sigma, obstacles)
        n = self.n
        self.velocities = np.zeros_like(self.positions)
        self.a_max = np.array(a_max, dtype=float).reshape(n)
        self.gain = np.array(gain, dtype=float).reshape(n)
        self.applied = np.zeros_like(self.positions)

    def follow(self, command: Command, link: Link, dt: float, rng: np.random.Generator) -> float:
        """One step under the velocity each robot holds from ``link``
        (:meth:`~harness.plants.agents.Swarm.follow_held`); the tracking error (length / s).
        """
        return self.follow_held(link, dt, rng)

    def move(self, v: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """One hold of ``dt`` (s) under the commanded velocities ``v`` ``(2, N)``
        (length / s); returns the applied velocities ``(2, N)`` (the displacement over
        ``dt``, noise excluded). Compiled
        (:func:`harness.compiled.robots.double_integrator_step`);
        :func:`double_integrator_step_reference` is its numpy statement.
        """
        g = self.grid
        draw_normals(rng, self._noise)
        double_integrator_step(
            self.positions, self.velocities, np.ascontiguousarray(v, dtype=float), self._noise,
            self.a_max, self.gain, self.applied, float(dt),
            g.x0, g.x1, g.y0, g.y1, float(np.sqrt(2.0 * self.sigma * dt)),
            self._clear, self.obstacles is not None,
        )  # fmt: skip
        return self.applied


def double_integrator_step_reference(
    swarm: DoubleIntegratorSwarm, v: np.ndarray, dt: float, rng: np.random.Generator
) -> np.ndarray:
    """Numpy statement of :meth:`DoubleIntegratorSwarm.move` (same draws, same
    result up to round-off).
    """
    g = swarm.grid
    draw_normals(rng, swarm._noise)
    w = swarm.velocities
    gain, a_max = swarm.gain, swarm.a_max
    err = v - w
    gap = np.hypot(err[0], err[1])
    limited = gain * gap > a_max
    # saturated phase: |E| falls at the rate a_max for t_s = (|E_0| - a_max / g) / a_max
    tau = np.where(limited, np.minimum((gap - a_max / gain) / a_max, dt), 0.0)
    acc = np.where(limited, a_max / np.where(limited, gap, 1.0), 0.0) * err
    disp = w * tau + 0.5 * acc * tau**2
    w = w + acc * tau
    rest = dt - tau
    # linear phase: W(t) = v - E exp(-g t), X(t) = X + v t - E (1 - exp(-g t)) / g
    lag = -np.expm1(-gain * rest) / gain
    disp = disp + v * rest + (w - v) * lag
    w = v + (w - v) * np.exp(-gain * rest)
    swarm.velocities[:] = w
    swarm.applied[:] = disp / dt
    old = swarm._before()
    swarm.positions += disp + swarm._noise * np.sqrt(2.0 * swarm.sigma * dt)
    reflect(swarm.positions[0], g.x0, g.x1)
    reflect(swarm.positions[1], g.y0, g.y1)
    swarm._avoid(old)
    return swarm.applied
