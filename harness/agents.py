"""Robots: Euler-Maruyama for the Langevin equation with reflecting walls.

Each robot follows (eq. ``Langevin equation``)

    dX = v(X, t) dt + sqrt(2 sigma) dB,

integrated with the Euler-Maruyama step

    X_{n+1} = R( X_n + v(X_n, t_n) dt + sqrt(2 sigma dt) xi_n ),   xi_n ~ N(0, I_2),

where ``v(X_n)`` is the bilinear interpolant of the cell-centre velocities (the
value of the nearest centre row/column beyond the outermost centres) and ``R``
reflects a coordinate that left the interval ``[lo, hi]`` back across the wall,
``x -> 2 lo - x`` or ``x -> 2 hi - x`` (exact for the reflected Brownian motion's
law when one step crosses at most one wall; a final clip guards against steps
longer than the domain). Positions are stored as an array of shape ``(2, N)``
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
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from harness.compiled.agents import euler_maruyama_step
from harness.grid import Grid
from harness.velocity import VelocityField

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


def interpolate(grid: Grid, centres: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a cell-centred vector field at positions.

    Args:
        grid: The grid.
        centres: Field of shape ``(c, ny, nx)``.
        positions: Points of shape ``(2, N)`` inside the domain.

    Returns:
        Values of shape ``(c, N)``. Beyond the outermost cell centres (within half
        a cell of a wall) the field is extended by its nearest centre values.
    """
    c = centres.shape[0]
    u = np.clip((positions[0] - grid.x0) / grid.dx - 0.5, 0.0, grid.nx - 1)
    w = np.clip((positions[1] - grid.y0) / grid.dy - 0.5, 0.0, grid.ny - 1)
    i0 = np.minimum(u.astype(np.intp), grid.nx - 2)
    j0 = np.minimum(w.astype(np.intp), grid.ny - 2)
    fx = u - i0
    fy = w - j0
    base = j0 * grid.nx + i0
    flat = centres.reshape(c, -1)
    v00 = flat[:, base]
    v10 = flat[:, base + 1]
    v01 = flat[:, base + grid.nx]
    v11 = flat[:, base + grid.nx + 1]
    return (v00 + fx * (v10 - v00)) * (1 - fy) + (v01 + fx * (v11 - v01)) * fy


def reflect(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Reflect coordinates across the walls ``lo`` and ``hi`` in place, then clip."""
    np.copyto(x, 2.0 * lo - x, where=x < lo)
    np.copyto(x, 2.0 * hi - x, where=x > hi)
    np.clip(x, lo, hi, out=x)
    return x


@dataclass
class Swarm:
    """``N`` robots in the grid's rectangle.

    Args:
        grid: Grid giving the domain and the velocity field's layout.
        positions: Initial positions, shape ``(2, N)``, inside the domain.
        sigma: Noise intensity ``sigma >= 0`` (length^2 / time).
    """

    grid: Grid
    positions: np.ndarray
    sigma: float
    _noise: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.positions = np.array(self.positions, dtype=float)
        if self.positions.ndim != 2 or self.positions.shape[0] != 2 or self.positions.shape[1] < 1:
            raise ValueError(
                f"positions must have shape (2, N) with N >= 1, got {self.positions.shape}"
            )
        if not self.grid.contains(self.positions[0], self.positions[1]).all():
            raise ValueError("initial positions must lie inside the domain")
        if not (np.isfinite(self.sigma) and self.sigma >= 0):
            raise ValueError(f"sigma must be finite and >= 0, got {self.sigma}")
        self._noise = np.empty_like(self.positions)

    @property
    def n(self) -> int:
        """Number of robots ``N``."""
        return self.positions.shape[1]

    def step(self, v: VelocityField, dt: float, rng: np.random.Generator) -> np.ndarray:
        """Advance every robot by one Euler-Maruyama step of length ``dt`` under
        ``v`` (eq. ``Langevin equation``) and return the new positions.

        The Gaussian increments come from ``rng`` (:func:`draw_normals`); the
        scaling by ``sqrt(2 sigma dt)``, interpolation, update and reflection run in
        one compiled parallel pass (:func:`harness.compiled.agents.euler_maruyama_step`),
        which :meth:`step_reference` states in plain numpy.
        """
        g = self.grid
        draw_normals(rng, self._noise)
        centres = np.ascontiguousarray(v.centres, dtype=float)
        euler_maruyama_step(
            self.positions,
            centres,
            self._noise,
            float(dt),
            g.x0,
            g.x1,
            g.y0,
            g.y1,
            g.nx,
            g.ny,
            float(np.sqrt(2.0 * self.sigma * dt)),
        )
        return self.positions

    def step_robots(
        self, velocities: np.ndarray, dt: float, rng: np.random.Generator
    ) -> np.ndarray:
        """Euler-Maruyama with each robot's own velocity ``(2, N)`` (length / s), for a
        law that moves each robot itself: ``X_i <- R(X_i + v_i dt + sqrt(2 sigma dt) xi_i)``, the
        draws as in :meth:`step` (``R`` the reflection at the walls).
        """
        g = self.grid
        v = np.asarray(velocities, dtype=float)
        if v.shape != self.positions.shape:
            raise ValueError(f"velocities must have shape {self.positions.shape}, got {v.shape}")
        draw_normals(rng, self._noise)
        self.positions += v * dt + self._noise * np.sqrt(2.0 * self.sigma * dt)
        reflect(self.positions[0], g.x0, g.x1)
        reflect(self.positions[1], g.y0, g.y1)
        return self.positions

    def move(self, v: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """One step under the commanded velocities ``v`` ``(2, N)`` (length / s)
        (:meth:`step_robots`); returns the applied velocities, ``v`` itself: an ideal
        integrator applies what it is commanded.
        """
        self.step_robots(v, dt, rng)
        return np.asarray(v, dtype=float)

    def step_reference(self, v: VelocityField, dt: float, rng: np.random.Generator) -> np.ndarray:
        """Plain-numpy statement of :meth:`step` (same random draws, same result)."""
        g = self.grid
        draw_normals(rng, self._noise)
        self._noise *= np.sqrt(2.0 * self.sigma * dt)
        drift = interpolate(g, v.centres, self.positions)
        self.positions += drift * dt + self._noise
        reflect(self.positions[0], g.x0, g.x1)
        reflect(self.positions[1], g.y0, g.y1)
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
