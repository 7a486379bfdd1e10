"""``plant=agents``: ``N`` ideal integrators, Euler-Maruyama for the Langevin equation
with reflecting walls, measured by their KDE; and what every robot plant shares.

Each robot follows (eq. ``Langevin equation``)

    dX = v(X, t) dt + sqrt(2 sigma) dB,

integrated with the Euler-Maruyama step

    X_{n+1} = R( X_n + v(X_n, t_n) dt + sqrt(2 sigma dt) xi_n ),   xi_n ~ N(0, I_2),

where ``v(X_n)`` is the bilinear interpolant of the cell-centre velocities (the
value of the nearest centre row/column beyond the outermost centres) and ``R``
reflects a coordinate that left the interval ``[lo, hi]`` back across the wall,
``x -> 2 lo - x`` or ``x -> 2 hi - x`` (exact for the reflected Brownian motion's
law when one step crosses at most one wall; a final clip guards against steps
longer than the domain). On a domain with obstacles (the run's ``model.free``) the
robots start from ``p_0`` restricted to free space and every move then reflects at the
obstacles of the robots' map (:mod:`harness.plants.obstacles`, the rule in
:mod:`harness.compiled.obstacles`). Positions are stored as an array of shape ``(2, N)``
(row 0: x, row 1: y), in length units. All randomness comes from the
``numpy.random.Generator`` passed in.

Parallelism. The compiled step runs the robots in parallel (numba ``prange``); each
robot's arithmetic does not depend on the thread count. The Gaussian increments are
drawn by numpy outside it: for fewer than ``PARALLEL_DRAW_MIN`` values in one call
of ``rng.standard_normal`` (the stream of the serial harness); above, in fixed
chunks of ``DRAW_CHUNK`` values, chunk ``c`` from a generator on the ``c``-th child
of ``rng``'s ``SeedSequence`` (independent streams, numpy's own construction, as
``rng.spawn`` makes them) with numpy's ``SFC64`` bit generator, filled by a thread
pool. Which numbers land where is fixed by ``N`` and ``rng``, never by the number
of threads. Why ``SFC64`` for the chunks: numpy's normals from it are faster than
from the default ``PCG64`` (2e6 values on two threads: 8.3 to 10.3 ms against 12.5
to 12.8 ms, measured), and at ``N = 1e6`` the draws are most of an agent step; it is
one of numpy's own generators, with the same statistical standing (it passes the
usual test batteries). Swarms below ``PARALLEL_DRAW_MIN / 2`` robots, every study
preset among them, draw from ``rng`` itself, as before.

The plant (:class:`Agents`). The robots move under the command as it reaches them
through the command link (:mod:`harness.plants.link`), are seen with an optional
localisation error, and are measured by their KDE (:class:`harness.estimators.kde.KDE`).
Its constructor is the one every robot plant shares: unicycles
(:mod:`harness.plants.unicycles`) and double integrators
(:mod:`harness.plants.double_integrators`) add their own parameters and robots
(:meth:`Agents._robots`, a subclass of :class:`Swarm` with its own ``move``). The loop's
``N -> infinity`` limit beside the robots is :mod:`harness.plants.limit`.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from harness.compiled.agents import euler_maruyama_step, euler_maruyama_step_free
from harness.estimators.kde import KDE
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import flag, integer, number, require
from harness.plants.link import Link, command_link
from harness.plants.obstacles import NO_MAP, RobotMap
from harness.protocols import (
    MemoryEstimate,
    default_memory,
)
from harness.records import Command, Measurement
from harness.targets.densities import Density
from harness.velocity import VelocityField, interpolate

DRAW_CHUNK = 1 << 17
"""Gaussian values drawn per child generator on the parallel path."""


PARALLEL_DRAW_MIN = 1 << 18
"""Fewest values (``2 N``) drawn on the parallel path; below, one serial draw."""


_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=os.cpu_count() or 1)
    return _POOL


def draw_normals(rng: np.random.Generator, out: np.ndarray) -> np.ndarray:
    """Fill ``out`` with independent standard normal values from ``rng``.

    Fewer than ``PARALLEL_DRAW_MIN`` values: ``rng.standard_normal(out=out)``.
    Otherwise chunk ``c`` (values ``c DRAW_CHUNK`` onwards of the flattened ``out``)
    comes from an ``SFC64`` generator on the ``c``-th of ``chunks`` children spawned
    from ``rng``'s ``SeedSequence`` (the children ``rng.spawn`` would use); numpy
    releases the GIL while filling, so the chunks fill in parallel, and the values do
    not depend on the number of threads.

    Raises:
        ValueError: on the parallel path, ``rng`` has no ``SeedSequence`` to spawn from.
    """
    flat = out.reshape(-1)
    if flat.size < PARALLEL_DRAW_MIN:
        rng.standard_normal(out=flat)
        return out
    chunks = (flat.size + DRAW_CHUNK - 1) // DRAW_CHUNK
    seed_seq = rng.bit_generator.seed_seq
    if not isinstance(seed_seq, np.random.SeedSequence):
        raise ValueError("draw_normals needs a generator made from a SeedSequence (seeded)")
    children = [np.random.Generator(np.random.SFC64(s)) for s in seed_seq.spawn(chunks)]

    def fill(c: int) -> None:
        children[c].standard_normal(out=flat[c * DRAW_CHUNK : (c + 1) * DRAW_CHUNK])

    list(_pool().map(fill, range(chunks)))
    return out


def reflect(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Reflect coordinates across the walls ``lo`` and ``hi`` in place, then clip."""
    np.copyto(x, 2.0 * lo - x, where=x < lo)
    np.copyto(x, 2.0 * hi - x, where=x > hi)
    np.clip(x, lo, hi, out=x)
    return x


@dataclass
class Swarm:
    """``N`` robots in the grid's rectangle, less the obstacles of ``obstacles``.

    Args:
        grid: Grid giving the domain and the velocity field's layout.
        positions: Initial positions, shape ``(2, N)``, inside the domain (and in free
            squares of ``obstacles``).
        sigma: Noise intensity ``sigma >= 0`` (length^2 / time).
        obstacles: The robots' map of obstacles (:class:`harness.plants.obstacles.RobotMap`),
            None on the plain rectangle. Every move reflects at the walls, then at the
            obstacles (:mod:`harness.compiled.obstacles`).
    """

    grid: Grid
    positions: np.ndarray
    sigma: float
    obstacles: RobotMap | None = None
    _noise: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.positions = np.array(self.positions, dtype=float, order="C")  # draws fill it flat
        if self.positions.ndim != 2 or self.positions.shape[0] != 2 or self.positions.shape[1] < 1:
            raise ValueError(
                f"positions must have shape (2, N) with N >= 1, got {self.positions.shape}"
            )
        if not self.grid.contains(self.positions[0], self.positions[1]).all():
            raise ValueError("initial positions must lie inside the domain")
        if self.obstacles is not None and self.obstacles.blocked(*self.positions).any():
            raise ValueError("initial positions must lie in free space (not in an obstacle)")
        if not (np.isfinite(self.sigma) and self.sigma >= 0):
            raise ValueError(f"sigma must be finite and >= 0, got {self.sigma}")
        self._noise = np.empty_like(self.positions)
        self._clear = NO_MAP if self.obstacles is None else self.obstacles.clear

    @property
    def n(self) -> int:
        """Number of robots ``N``."""
        return self.positions.shape[1]

    def step(self, v: VelocityField, dt: float, rng: np.random.Generator) -> np.ndarray:
        """Advance every robot by one Euler-Maruyama step of length ``dt`` under
        ``v`` (eq. ``Langevin equation``) and return the new positions.

        The Gaussian increments come from ``rng`` (:func:`draw_normals`); the
        scaling by ``sqrt(2 sigma dt)``, interpolation, update and reflection run in
        one compiled parallel pass (:func:`harness.compiled.agents.euler_maruyama_step`; on a
        domain with obstacles :func:`harness.compiled.agents.euler_maruyama_step_free`),
        which :meth:`step_reference` states in plain numpy.
        """
        g = self.grid
        draw_normals(rng, self._noise)
        centres = np.ascontiguousarray(v.centres, dtype=float)
        args = (self.positions, centres, self._noise, float(dt), g.x0, g.x1, g.y0, g.y1)
        scale = float(np.sqrt(2.0 * self.sigma * dt))
        if self.obstacles is None:
            euler_maruyama_step(*args, g.nx, g.ny, scale)
        else:
            euler_maruyama_step_free(*args, g.nx, g.ny, scale, self.obstacles.clear)
        return self.positions

    def _avoid(self, old: np.ndarray | None) -> None:
        """The obstacles' rule on the moves from ``old`` to the positions (in place;
        nothing on the plain rectangle, where ``old`` is None).
        """
        if self.obstacles is not None:
            assert old is not None
            self.obstacles.avoid(old, self.positions)

    def _before(self) -> np.ndarray | None:
        """A copy of the positions before a move made in numpy, for :meth:`_avoid`; None
        on the plain rectangle.
        """
        return None if self.obstacles is None else self.positions.copy()

    def step_robots(
        self, velocities: np.ndarray, dt: float, rng: np.random.Generator
    ) -> np.ndarray:
        """Euler-Maruyama with each robot's own velocity ``(2, N)`` (length / s), for a
        law that moves each robot itself: ``X_i <- R(X_i + v_i dt + sqrt(2 sigma dt) xi_i)``, the
        draws as in :meth:`step` (``R`` the reflection at the walls, then at the obstacles).
        """
        g = self.grid
        v = np.asarray(velocities, dtype=float)
        if v.shape != self.positions.shape:
            raise ValueError(f"velocities must have shape {self.positions.shape}, got {v.shape}")
        draw_normals(rng, self._noise)
        old = self._before()
        self.positions += v * dt + self._noise * np.sqrt(2.0 * self.sigma * dt)
        reflect(self.positions[0], g.x0, g.x1)
        reflect(self.positions[1], g.y0, g.y1)
        self._avoid(old)
        return self.positions

    def move(self, v: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """One step under the commanded velocities ``v`` ``(2, N)`` (length / s)
        (:meth:`step_robots`); returns the applied velocities, ``v`` itself: an ideal
        integrator applies what it is commanded.
        """
        self.step_robots(v, dt, rng)
        return np.asarray(v, dtype=float)

    def follow(self, command: Command, link: Link, dt: float, rng: np.random.Generator) -> float:
        """One step under what each robot holds from ``link`` (which has transmitted
        ``command``); returns the tracking error, the mean over robots of ``|applied -
        commanded|`` (length / s). Through the ideal link ideal integrators move by the
        command itself (its own velocities, else the field's interpolant, :meth:`step`)
        and apply exactly what they are commanded (error 0); otherwise by what each holds
        (:meth:`follow_held`).
        """
        if not link.ideal:
            return self.follow_held(link, dt, rng)
        if command.robots is not None:
            self.step_robots(command.robots, dt, rng)
        else:
            assert command.field is not None
            self.step(command.field, dt, rng)
        return 0.0

    def follow_held(self, link: Link, dt: float, rng: np.random.Generator) -> float:
        """One step under the velocity each robot holds from ``link`` at its position
        (:meth:`move`); returns the tracking error (:meth:`follow`).
        """
        held = link.velocities(self.positions, self.grid)
        applied = self.move(held, dt, rng)
        # tracking error: (1/N) sum_k |applied_k - commanded_k|
        return float(np.mean(np.hypot(*(applied - held))))

    def step_reference(self, v: VelocityField, dt: float, rng: np.random.Generator) -> np.ndarray:
        """Plain-numpy statement of :meth:`step` (same random draws, same result)."""
        g = self.grid
        draw_normals(rng, self._noise)
        self._noise *= np.sqrt(2.0 * self.sigma * dt)
        drift = interpolate(g, v.centres, self.positions)
        old = self._before()
        self.positions += drift * dt + self._noise
        reflect(self.positions[0], g.x0, g.x1)
        reflect(self.positions[1], g.y0, g.y1)
        self._avoid(old)
        return self.positions

    def histogram(self) -> np.ndarray:
        """Empirical density on the grid: robots per cell / (N cell area),
        shape ``(ny, nx)``, grid integral 1 (1 / length^2). A robot on the upper wall
        counts in the last cell (as :func:`numpy.histogram2d` counts it, the reference).
        """
        g = self.grid
        col = np.minimum(((self.positions[0] - g.x0) / g.dx).astype(np.intp), g.nx - 1)
        row = np.minimum(((self.positions[1] - g.y0) / g.dy).astype(np.intp), g.ny - 1)
        counts = np.bincount(row * g.nx + col, minlength=g.size)
        return counts.reshape(g.shape) / (self.n * g.cell_area)


def spread_values(nominal: float, spread: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Per-robot values ``nominal (1 + spread U)``, ``U`` uniform on ``[-1, 1]`` (drawn
    from ``rng``); ``nominal > 0`` and ``0 <= spread < 1`` (checked by the plant's
    constructor), so every value is positive.
    """
    return np.asarray(nominal * (1.0 + spread * rng.uniform(-1.0, 1.0, n)))


def check_spread(spread: float) -> float:
    """The relative spread ``0 <= s < 1`` of per-robot values (:func:`spread_values`),
    refused otherwise (:class:`~harness.parameters.ParameterError` naming ``spread``).
    """
    s = number("spread", spread, 0.0)
    require(s < 1, "spread", spread, "below 1 (a relative half-width; values stay positive)")
    return s


class Agents:
    """``plant=agents``: ``N`` ideal integrators (eq. ``Langevin equation``, :class:`Swarm`)
    measured by their KDE, behind the command link; the constructor every robot plant
    shares (:class:`harness.plants.unicycles.Unicycles` and
    :class:`harness.plants.double_integrators.DoubleIntegrators` add their own parameters
    and robots, :meth:`_robots`).

    Args:
        grid, model, init: Run-time arguments (grid, Fokker-Planck model, ``p_0``).
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
            ones. 0 draws nothing. On a domain with obstacles the observation is kept
            out of them as a move from the true position would be
            (:meth:`harness.plants.obstacles.RobotMap.avoid`).
        seed: The run's seed, for the localisation error's stream and the link's.
        link_period, link_latency, link_loss: The command link
            (:class:`harness.plants.link.Link`): time between broadcasts (s; None: every
            step), delay to arrival (s) and the probability that a robot misses a
            broadcast. The defaults are the ideal link, under which the robots move by
            the code path of a run without one.
        dt: The step (s), which the link's period and latency count in.

    Per step the plant reports ``tracking_error``, the mean over robots of
    ``|velocity applied - velocity commanded|`` (length / s; the commanded velocity is
    the held command at the robot, the applied one its displacement over the step
    without the noise; 0 for these ideal integrators, which apply what they hold), and
    ``command_age``, the mean age of the held commands (s, :class:`harness.plants.link.Link`);
    both None before the first step.

    Its ``density`` is the robots' histogram (robots per cell over ``N`` times the cell
    area, 1 / length^2); the run measures its errors against the loop's ``N -> infinity``
    limit instead when the law has a mean-field form (:mod:`harness.plants.limit`).
    """

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        init: Density,
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
        self.grid, self.model, self.init = grid, model, init
        self.localisation_noise = number("localisation_noise", localisation_noise, 0.0)
        quarter = min(grid.x1 - grid.x0, grid.y1 - grid.y0) / 4
        require(
            self.localisation_noise <= quarter,
            "localisation_noise", localisation_noise, f"at most a quarter of the side, {quarter:g}",
        )  # fmt: skip
        self.seed = integer("seed", seed, 0)
        self._sight = np.random.default_rng([self.seed, 3])
        self.n = integer("n", n, 1)
        h = number("bandwidth", bandwidth, 0.0, strict=True)
        side = min(grid.x1 - grid.x0, grid.y1 - grid.y0)
        require(h <= side, "bandwidth", bandwidth, f"at most the domain side {side:g}")
        require(method in KDE.METHODS, "method", method, f"one of {', '.join(KDE.METHODS)}")
        self.kde = KDE(grid, h, mirror=flag("mirror", mirror), method=method, free=model.free)
        self.obstacles = RobotMap.of(getattr(model, "free", None))
        self.swarm: Swarm | None = None
        self.resolution: float | None = h  # the KDE resolves no scale below h
        self.link = command_link(link_period, link_latency, link_loss, dt, self.seed)
        # the swarm's size and the loop's step, as the run's shared keys must give them
        self.copies: dict[str, tuple[str, float]] = {"n": ("robots", self.n)}
        if dt is not None:
            self.copies["dt"] = ("dt", self.link.dt)
        self.tracking_error: float | None = None
        self.command_age: float | None = None
        self._steps = 0

    has_robots = True

    free_space = True
    """The robots honour a domain with obstacles (:mod:`harness.plants.obstacles`)."""

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
    def density(self) -> np.ndarray:
        """The robots' histogram ``(ny, nx)`` (1 / length^2, :meth:`Swarm.histogram`);
        ``p_0`` on the grid before :meth:`start`.
        """
        if self.swarm is None:
            return self.init.on_grid(self.grid)
        return self.swarm.histogram()

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
            if self.obstacles is not None:
                self.obstacles.avoid(self.swarm.positions, seen)
            self._observed = seen

    headings: np.ndarray | None = None
    """Robot headings as unit vectors ``(cos theta, sin theta)``, ``(2, N)``, for robots
    that have one, else None."""

    def _robots(self, positions: np.ndarray) -> Swarm:
        """The robots at ``positions`` ``(2, N)``: ideal integrators here."""
        return Swarm(self.grid, positions, self.model.sigma, self.obstacles)

    def start(self, rng: np.random.Generator) -> None:
        """Draw ``N`` robots from ``p_0`` (on a domain with obstacles, from ``p_0``
        restricted to free space: :meth:`harness.plants.obstacles.RobotMap.sample`).
        """
        if self.obstacles is None:
            positions = self.init.sample(self.n, self.grid, rng)
        else:
            positions = self.obstacles.sample(self.init, self.n, rng)
        self.swarm = self._robots(positions)
        self.link.start(self.n)
        self.tracking_error = self.command_age = None
        self._steps = 0
        self._sight = np.random.default_rng([self.seed, 3])  # the stream restarts
        self._observe()

    def advance(
        self, command: Command, a: sp.csr_matrix | None, dt: float, rng: np.random.Generator
    ) -> None:
        """The command through the link; the robots over the step under what each holds
        (:meth:`Swarm.follow`: ideal integrators by Euler-Maruyama with reflection, under
        their own velocities when the command has them, else the field's interpolant);
        then the localisation error of the new positions.
        """
        assert self.swarm is not None, "call start first"
        self.link.transmit(command, self._steps)
        self.tracking_error = self.swarm.follow(command, self.link, dt, rng)
        self.command_age = self.link.age
        self._steps += 1
        self._observe()

    def measure(self, rng: np.random.Generator) -> Measurement:
        """The KDE of the robots as observed (:attr:`observed`) and its analytic gradient."""
        assert self.swarm is not None, "call start first"
        seen = self.observed
        assert seen is not None
        return Measurement(*self.kde(seen))
