"""Unicycles: robots with a heading that track a commanded velocity
(``plant=unicycles``, :class:`harness.plants.unicycles.Unicycles`).

Robot ``k`` has an axle position ``X_k`` (length, the point the KDE measures and the
metrics count) and a heading ``theta_k`` (rad). Its kinematics, with forward speed
``u`` and turn rate ``omega``,

    dX = u e(theta) dt + sqrt(2 sigma) dB,    d theta = omega dt,
    e(theta) = (cos theta, sin theta),        |u| <= v_max,  |omega| <= omega_max,

keep the positions' diffusion ``sigma`` (eq. ``Langevin equation``), so the estimators
apply unchanged.

Controller: feedback linearisation about the point ``P = X + l e(theta)`` a look-ahead
``l > 0`` ahead of the axle. With ``e_perp = (-sin theta, cos theta)``, the law

    u = e . v,    omega = (e_perp . v) / l

gives ``dP/dt = v`` exactly (without the limits): the point ahead is a single
integrator, and the axle lags it by ``l``. Write ``psi`` for the angle from the heading
to ``v``; under a held ``v`` the law turns the heading by ``d psi / dt = -(|v| / l)
sin psi``, whose solution over a hold of ``dt`` is

    tan(psi_1 / 2) = tan(psi_0 / 2) exp(-|v| dt / l).

The robot's own controller runs much faster than the command is refreshed, so each
hold is solved exactly where the law stays within the limits. Along the solution
``|psi|`` falls monotonically from ``|psi_0|`` to ``|psi_1|``, so the largest forward
speed ``|v| |cos psi|`` and turn rate ``|v| |sin psi| / l`` over the hold are taken at
an end, or (``|sin psi| = 1``) where ``|psi|`` passes ``pi / 2``; when both are within
``v_max`` and ``omega_max`` the hold is exact:

    theta_1 = theta_0 + psi_0 - psi_1,
    X_1 = X_0 + v dt + l (e(theta_0) - e(theta_1))

(the point ahead moves by ``v dt``; the axle's deviation from ``v dt`` telescopes over
the holds, so a unicycle that stays within its limits is never further than ``2 l``
from an ideal integrator fed the same velocities; at ``psi_0 = pi`` exactly the law
rests, ``sin psi = 0``, and the robot backs up along ``v`` without turning). Otherwise
the hold is one arc of constant speeds: the turn rate ``omega = (psi_0 - psi_1) /
dt`` (the one that reaches the law's heading) clipped to ``[-omega_max, omega_max]``
and the forward speed ``u = e(theta_0) . v`` clipped to ``[-v_max, v_max]``,

    X_1 = X_0 + u dt sinc(omega dt / 2) e(theta_0 + omega dt / 2),
    theta_1 = theta_0 + omega dt,

an approximation of the saturated law's hold that keeps the limits. Either way the
noise ``sqrt(2 sigma dt) xi`` follows (the run's stream, drawn as for the single
integrators, so a run of the same seed has the same increments), then the walls
reflect the axle position (:func:`harness.plants.agents.reflect`; the heading is kept),
and so do the obstacles on a domain with them (:mod:`harness.compiled.obstacles`; the
heading is kept there too, also when the robot stays where it was).

What the mean-field model no longer captures: the density of axle positions is not
transported by ``v`` but by ``u e(theta)``, a velocity that depends on each robot's
heading, a hidden state the Fokker-Planck equation (eq. ``FP equation``) and the
filters' transport model do not carry; the limits cut the velocity where the law asks
for more; and robots pointing away from ``v`` move more slowly for a time of order
``l / |v|`` after each change of direction.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from harness.compiled.robots import interpolate_robots, unicycle_step
from harness.grid import Grid
from harness.parameters import number
from harness.plants.agents import Agents, Swarm, check_spread, draw_normals, reflect, spread_values
from harness.plants.link import Link
from harness.plants.obstacles import RobotMap
from harness.records import Command
from harness.velocity import VelocityField


class Unicycles(Agents):
    """``plant=unicycles``: ``N`` unicycles (module docstring) measured by their KDE, behind
    the command link (:class:`~harness.plants.agents.Agents`).

    Args:
        robots: The parameters every robot plant takes, as
            :class:`~harness.plants.agents.Agents`.
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
        v_max: float = 0.1,
        omega_max: float = 3.0,
        lookahead: float = 0.01,
        spread: float = 0.0,
        **robots: Any,
    ) -> None:
        super().__init__(**robots)
        self.v_max = number("v_max", v_max, 0.0, strict=True)
        self.omega_max = number("omega_max", omega_max, 0.0, strict=True)
        self.lookahead = number("lookahead", lookahead, 0.0, strict=True)
        self.spread = check_spread(spread)

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
            self.obstacles,
        )  # fmt: skip


class UnicycleSwarm(Swarm):
    """``N`` unicycles in the grid's rectangle (module docstring).

    Args:
        grid: The grid (domain).
        positions: Initial axle positions ``(2, N)`` (length), inside the domain.
        sigma: Noise intensity ``sigma >= 0`` (length^2 / s).
        headings: Initial headings ``(N,)`` (rad); kept as the unit vectors
            ``e(theta)``, :attr:`headings` ``(2, N)``.
        v_max: Forward-speed limit per robot ``(N,)`` (length / s), ``> 0``.
        omega_max: Turn-rate limit per robot ``(N,)`` (rad / s), ``> 0``.
        lookahead: Look-ahead distance ``l`` per robot ``(N,)`` (length), ``> 0``.
        obstacles: The robots' map of obstacles, None on the plain rectangle
            (:class:`~harness.plants.agents.Swarm`).
    """

    def __init__(
        self,
        grid: Grid,
        positions: np.ndarray,
        sigma: float,
        headings: np.ndarray,
        v_max: np.ndarray,
        omega_max: np.ndarray,
        lookahead: np.ndarray,
        obstacles: RobotMap | None = None,
    ) -> None:
        super().__init__(grid, positions, sigma, obstacles)
        n = self.n
        theta = np.array(headings, dtype=float).reshape(n)
        self.headings = np.array([np.cos(theta), np.sin(theta)])
        """The headings as unit vectors ``e(theta) = (cos theta, sin theta)``, ``(2, N)``."""
        self.v_max = np.array(v_max, dtype=float).reshape(n)
        self.omega_max = np.array(omega_max, dtype=float).reshape(n)
        self.lookahead = np.array(lookahead, dtype=float).reshape(n)
        self.applied = np.zeros_like(self.positions)
        self._commanded = np.empty_like(self.positions)  # a field's velocity at each robot

    def move(self, v: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """One hold of ``dt`` (s) under the commanded velocities ``v`` ``(2, N)``
        (length / s); returns the applied velocities ``(2, N)`` (the arc's
        displacement over ``dt``, noise excluded). Compiled
        (:func:`harness.compiled.robots.unicycle_step`); :func:`unicycle_step_reference`
        is its numpy statement.
        """
        g = self.grid
        draw_normals(rng, self._noise)
        unicycle_step(
            self.positions, self.headings, np.ascontiguousarray(v, dtype=float), self._noise,
            self.v_max, self.omega_max, self.lookahead, self.applied, float(dt),
            g.x0, g.x1, g.y0, g.y1, float(np.sqrt(2.0 * self.sigma * dt)),
            self._clear, self.obstacles is not None,
        )  # fmt: skip
        return self.applied

    def follow(self, command: Command, link: Link, dt: float, rng: np.random.Generator) -> float:
        """One step under what each robot holds from ``link``: in one compiled pass when
        every robot holds the same field (:meth:`move_field`), else by the velocity each
        holds (:meth:`~harness.plants.agents.Swarm.follow_held`); returns the tracking
        error (length / s).
        """
        field = link.common_field()
        if field is not None:
            return self.move_field(field, dt, rng)
        return self.follow_held(link, dt, rng)

    def move_field(self, field: VelocityField, dt: float, rng: np.random.Generator) -> float:
        """:meth:`move` with every robot commanded the bilinear interpolant of ``field``'s
        cell centres at its position (:func:`harness.velocity.interpolate`), in two
        compiled passes (:func:`harness.compiled.robots.interpolate_robots`, then
        :func:`harness.compiled.robots.unicycle_step`); returns the tracking error, the
        mean over robots of ``|applied - commanded|`` (length / s).
        """
        g = self.grid
        interpolate_robots(
            self.positions, np.ascontiguousarray(field.centres, dtype=float), self._commanded,
            g.x0, g.x1, g.y0, g.y1, g.nx, g.ny,
        )  # fmt: skip
        draw_normals(rng, self._noise)
        total = unicycle_step(
            self.positions, self.headings, self._commanded, self._noise, self.v_max,
            self.omega_max, self.lookahead, self.applied, float(dt),
            g.x0, g.x1, g.y0, g.y1, float(np.sqrt(2.0 * self.sigma * dt)),
            self._clear, self.obstacles is not None,
        )  # fmt: skip
        return float(total) / self.n


def unicycle_step_reference(
    swarm: UnicycleSwarm, v: np.ndarray, dt: float, rng: np.random.Generator
) -> np.ndarray:
    """Numpy statement of :meth:`UnicycleSwarm.move` (same draws, same result)."""
    g = swarm.grid
    draw_normals(rng, swarm._noise)
    theta = np.arctan2(swarm.headings[1], swarm.headings[0])
    e = np.array([np.cos(theta), np.sin(theta)])
    along = e[0] * v[0] + e[1] * v[1]
    across = e[0] * v[1] - e[1] * v[0]
    # the heading error psi under the held v: tan(psi_1 / 2) = tan(psi_0 / 2) exp(-|v| dt / l)
    psi0 = np.arctan2(across, along)
    decay = np.exp(-np.hypot(v[0], v[1]) * dt / swarm.lookahead)
    with np.errstate(invalid="ignore"):
        psi1 = 2.0 * np.arctan(np.tan(0.5 * psi0) * decay)
    psi1 = np.where(decay == 0.0, 0.0, psi1)  # aligned within the hold
    psi1 = np.where((along < 0) & (across == 0), psi0, psi1)  # psi_0 = pi: the law's rest
    a0, a1 = np.abs(psi0), np.abs(psi1)
    top_cos = np.maximum(np.abs(np.cos(psi0)), np.abs(np.cos(psi1)))
    passes = (a1 <= 0.5 * np.pi) & (0.5 * np.pi <= a0)
    top_sin = np.where(passes, 1.0, np.maximum(np.abs(np.sin(psi0)), np.abs(np.sin(psi1))))
    speed = np.hypot(v[0], v[1])
    exact = (speed * top_cos <= swarm.v_max) & (
        speed * top_sin <= swarm.omega_max * swarm.lookahead
    )
    # exact hold: theta_1 = theta_0 + psi_0 - psi_1, X_1 = X_0 + v dt + l (e(theta_0) - e(theta_1))
    end = theta + psi0 - psi1
    held = v * dt + swarm.lookahead * (e - np.array([np.cos(end), np.sin(end)]))
    # at a limit: one arc of the clipped (u, omega)
    omega = np.clip((psi0 - psi1) / dt, -swarm.omega_max, swarm.omega_max)
    u = np.clip(along, -swarm.v_max, swarm.v_max)
    half = 0.5 * omega * dt
    small = np.abs(half) <= 1e-6
    sinc = np.where(small, 1.0 - half * half / 6.0, np.sin(half) / np.where(small, 1.0, half))
    # X_1 = X_0 + u dt sinc(omega dt / 2) e(theta_0 + omega dt / 2)
    arc = u * dt * sinc * np.array([np.cos(theta + half), np.sin(theta + half)])
    disp = np.where(exact, held, arc)
    heading = np.where(exact, end, theta + omega * dt)
    swarm.applied[:] = disp / dt
    old = swarm._before()
    swarm.positions += disp + swarm._noise * np.sqrt(2.0 * swarm.sigma * dt)
    reflect(swarm.positions[0], g.x0, g.x1)
    reflect(swarm.positions[1], g.y0, g.y1)
    swarm._avoid(old)
    swarm.headings[:] = [np.cos(heading), np.sin(heading)]
    return swarm.applied
