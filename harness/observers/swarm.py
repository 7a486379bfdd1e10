"""Where the robots are, independently of every estimator: the observer ``swarm``
(:class:`SwarmTruth`), which adds to the ``/metrics`` topic of the log.

All L2 norms are :meth:`harness.grid.Grid.l2`, ``(dx dy sum f^2)^(1/2)``.

The swarm metrics say where the robots are, independently of every estimator,
and split the error at the agent level into estimation, finite-N and control parts:

    swarm_l2        = ||K_h mu_N - K_h p_*||      where the robots are, against the target
    est_swarm_l2    = ||p_hat - K_h mu_N||        the estimator, against what it estimates
    limit_swarm_l2  = ||K_h mu_N - K_h p_inf||    finite-N noise: the swarm against its limit
    limit_target_l2 = ||K_h p_inf - K_h p_*||     the control error of the limit loop

(``swarm_l2 <= limit_swarm_l2 + limit_target_l2``), with ``mu_N`` the robots'
empirical measure and ``K_h`` the KDE's kernel with its wall images; and ``swarm_w2``,
an optimal-transport distance between the robots and ``p_*`` (length).

On a domain with obstacles (``target.free``, :class:`harness.domains.base.FreeSpace`)
``p_*`` is the target on free space (0 on blocked cells, unit mass on free ones): the
KDE and the smoother are built on free space (``free=target.free``), ``K_h p_*`` is the
noise-free KDE of the target's cell values there (no closed form on free space), the
floors draw robots from ``p_*`` on free space
(:class:`harness.observers.swarm_metrics.FreeSampler`), ``swarm_w2``'s target measure is
``p_*`` on free space with the Euclidean ground cost
(:func:`harness.observers.swarm_metrics.free_target_measure`), and the observer adds
:func:`domain_keys`: ``component_fraction_gap`` and ``component_fraction_<c>``, the
robots' fraction in each connected component of free space
(:class:`harness.observers.swarm_metrics.Components`), and, given the run's initial
density, ``start_fraction`` and ``start_target_mass``: the robots' fraction in the
support of the initial density against the target's mass there
(:class:`harness.observers.swarm_metrics.StartRegion`). The finite-N
floor of ``swarm_l2`` and ``swarm_w2`` (N robots drawn independently from ``p_*``) is
computed once per content (:meth:`SwarmTruth.floors`, reused across runs by
:mod:`harness.observers.floor_cache`) and logged in the ``theory`` record.
It is the spread of *independent* robots, not a lower bound: feedback can spread a
swarm more evenly than independent samples, so a controlled swarm may sit below it.

A moving target (``target=moving``, :mod:`harness.targets.moving`): every metric compares with
the target at the step's time, ``p_*(t)`` (:class:`harness.targets.moving.TargetPath`), so
``phi_l2`` is the tracking error. The finite-N floors are those of ``p_*(0)``
(:class:`SwarmTruth`).

Which keys the log carries, and in which order, is the log's contract
(:data:`harness.observers.log.METRIC_KEYS`).
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import numpy as np

from harness.domains.base import FreeSpace
from harness.estimators.kde import KDE
from harness.estimators.smoothing import Smoother, smoothed_target
from harness.grid import Grid
from harness.observers import floor_cache, swarm_metrics
from harness.observers.base import Cadence, RunContext, Status
from harness.observers.floor_cache import FloorCache
from harness.observers.swarm_metrics import (
    Components,
    FreeSampler,
    StartRegion,
    TargetMeasure,
    free_target_measure,
    swarm_w2,
    w2_method,
)
from harness.parameters import integer, require
from harness.plants.limit import Limit
from harness.protocols import Plant
from harness.records import StepRecord
from harness.targets.densities import Density, Target
from harness.targets.moving import TargetPath

SWARM_KEYS = (
    "swarm_l2",
    "swarm_w2",
    "est_swarm_l2",
    "limit_swarm_l2",
    "limit_target_l2",
    "phat_smoothed_target_l2",
)
"""The swarm metrics (:meth:`SwarmTruth.measure`), in log order."""
"""The swarm metrics (null between their steps and without robots)."""

ON_POSITIONS = ("swarm_l2", "est_swarm_l2", "limit_swarm_l2", "limit_target_l2")
"""The swarm metrics computed every ``every`` steps (``swarm_w2`` every ``w2_every`` of
those), from the robots' positions (:class:`SwarmTruth`)."""

GAP_KEY = "component_fraction_gap"
"""``max_c |robots' fraction in component c - p_*'s mass there|`` (dimensionless), on a
domain with obstacles (:class:`harness.observers.swarm_metrics.Components`)."""

START_KEYS = ("start_fraction", "start_target_mass")
"""The robots' fraction in the support of the initial density and ``p_*``'s mass there
(dimensionless), on a domain with obstacles
(:class:`harness.observers.swarm_metrics.StartRegion`)."""


def domain_keys(free: FreeSpace | None) -> tuple[str, ...]:
    """The metrics a domain with obstacles adds to every ``/metrics`` message, after
    the others: :data:`GAP_KEY` and ``component_fraction_<c>`` for each connected
    component ``c = 0, 1, ...`` of free space (the robots' fraction there,
    dimensionless), then :data:`START_KEYS`; none on the plain square (``free`` None).
    """
    if free is None:
        return ()
    components = tuple(f"component_fraction_{c}" for c in range(free.n_components))
    return (GAP_KEY, *components, *START_KEYS)


def on_free(free: FreeSpace | None) -> dict[str, Any]:
    """The keyword that builds a KDE or a smoother on free space: ``{"free": free}`` on a
    domain with obstacles, nothing on the plain square (whose KDE is built exactly as
    without domains).
    """
    return {} if free is None else {"free": free}


class SwarmTruth:
    """The swarm metrics (see the module docstring), from robot positions.

    Moving target: every metric compares with ``p_*(t)`` at the step's time
    (``K_h p_*(t)`` exactly, the target measure of ``swarm_w2`` at ``t``). The finite-N
    floors are those of ``p_*(0)``: the rotating mixture (:mod:`harness.targets.moving`) keeps
    its shape along the path up to the walls, which cut the bumps slightly differently
    at every angle; for the default target on the paper's grid the mean floor of
    ``swarm_l2`` changes by less than the Monte-Carlo spread of its estimate along a
    turn (``tests/test_moving_target.py`` measures it).

    ``K_h p_*`` for ``swarm_l2`` is exact where the target's density has a closed form
    (:func:`harness.estimators.smoothing.smoothed_target`); ``K_h p_inf`` and, for a like-for-like
    ``limit_target_l2``, ``K_h p_*`` there are the noise-free KDE of cell values
    (:class:`harness.estimators.smoothing.Smoother`). ``K_h mu_N`` is the KDE of the positions with
    the run's KDE settings, so ``swarm_l2`` of N robots drawn from ``p_*`` has the
    finite-N floor of :meth:`floors`.

    As the observer ``swarm`` it adds these metrics to every step's values and, at the
    start, the finite-N floors to the ``theory`` record (:meth:`floor_record`): drawn
    from the stream ``[seed, 2]``, apart from the run's own, or read back bit-identical
    from the floor cache when the same content was computed before
    (:mod:`harness.observers.floor_cache`).

    Args:
        grid: The grid (run-time argument).
        target: The target (run-time argument; its continuous density is sampled for
            the floors).
        steps: The run's last step (run-time argument; always evaluated).
        bandwidth, mirror, method: The KDE's settings (``kde.*``).
        every: Steps between evaluations of ``swarm_l2`` and the decomposition.
        w2_every: Steps between evaluations of ``swarm_w2`` (the transport is costlier).
        floor_draws: Monte-Carlo draws of the finite-N floors (``>= 2``).
        seed: The run's seed.
        floor_cache: Directory of the floor cache (``~`` expanded); None or ``""``:
            the floors are computed every run.
        limit: The loop's ``N -> infinity`` limit (run-time argument,
            :class:`harness.plants.limit.Limit`): without one (a law without a
            mean-field form) the two terms against the limit, ``limit_swarm_l2`` and
            ``limit_target_l2``, are None.
        plant: The run's plant (run-time argument): one without robots (the mean
            field) gives only ``phat_smoothed_target_l2``, so the builder refuses a guard
            that requires a metric of the robots' positions of it.
        init: The run's initial density (run-time argument): on a domain with
            obstacles its support on the grid is the start region of
            :data:`START_KEYS`; without it those two keys are None.
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)

    def __init__(
        self,
        grid: Grid,
        target: Target,
        steps: int,
        bandwidth: float,
        mirror: bool,
        method: str,
        every: int,
        w2_every: int,
        floor_draws: int = 30,
        seed: int = 0,
        floor_cache: str | None = None,
        limit: Limit | None = None,
        plant: Plant | None = None,
        init: Density | None = None,
    ) -> None:
        self.path = TargetPath(target)
        self.has_robots = plant is None or plant.has_robots
        self.grid, self.target = grid, self.path.floor_target()
        self.has_limit = limit is not None
        self.every = integer("every", every, 1)
        self.w2_every = integer("w2_every", w2_every, 1)
        self.cadence = Cadence(self.every, steps)
        self.w2_cadence = Cadence(self.w2_every, steps)
        self.floor_draws = integer("floor_draws", floor_draws, 2)
        self.seed = integer("seed", seed, 0)
        require(
            floor_cache is None or isinstance(floor_cache, str),
            "floor_cache",
            floor_cache,
            "a directory, or null or '' for no floor cache",
        )
        self.cache = FloorCache(floor_cache) if floor_cache else None
        self.run: RunContext | None = None
        self.free = target.free
        self.kde = KDE(grid, bandwidth, mirror=mirror, method=method, **on_free(self.free))
        self.smoother = Smoother(grid, bandwidth, mirror, **on_free(self.free))
        self.bandwidth, self.mirror = bandwidth, mirror
        self.smoothed_target_cells = self.smoother(target.p)[0]
        if self.free is None:
            self.smoothed_target = smoothed_target(target, bandwidth, mirror).p
        else:  # no closed form on free space: the noise-free KDE of the cell values
            self.smoothed_target = self.smoothed_target_cells
        self.components = None if self.free is None else Components(target.p, self.free)
        self.start = (
            None
            if self.free is None or init is None
            else StartRegion(init.on_grid(grid), target.p, self.free)
        )
        self._measures: dict[int, TargetMeasure] = {}
        self._at: tuple[float, np.ndarray, np.ndarray | None] | None = None
        # POT and the scipy.stats it loads (about a second) are loaded where the run is
        # built: a sweep builds its jobs in the launcher's worker and forks each job from
        # it, so the worker loads them once instead of every job
        import ot  # noqa: F401

    @property
    def gives(self) -> tuple[str, ...]:
        """The swarm metrics this observer adds (:func:`harness.observers.base.gives`):
        all of :data:`SWARM_KEYS` with robots, less the two against the limit without
        one, then on a domain with obstacles :func:`domain_keys` (less
        :data:`START_KEYS` without the initial density); only
        ``phat_smoothed_target_l2`` without robots.
        """
        if not self.has_robots:
            return ("phat_smoothed_target_l2",)
        against_limit = ("limit_swarm_l2", "limit_target_l2")
        keys = tuple(k for k in SWARM_KEYS if self.has_limit or k not in against_limit)
        given = domain_keys(self.free)
        if self.start is None:
            given = tuple(k for k in given if k not in START_KEYS)
        return keys + given

    @property
    def at_cadence(self) -> dict[str, str]:
        """The swarm metrics given only at a cadence, each with the parameter that sets
        it (:func:`harness.observers.base.at_cadence`): with ``every`` above 1 all but
        ``phat_smoothed_target_l2``; else, with ``w2_every`` above 1, ``swarm_w2``.
        """
        if self.every > 1:
            return dict.fromkeys((*ON_POSITIONS, "swarm_w2", *domain_keys(self.free)), "every")
        return {"swarm_w2": "w2_every"} if self.w2_every > 1 else {}

    def smoothed_at(self, t: float, cells: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """``K_h p_*(t)`` exactly and, when ``cells``, the noise-free KDE of its cell
        values (1 / length^2); the start's for a static target.
        """
        if not self.path.moves:
            return self.smoothed_target, self.smoothed_target_cells
        if self._at is None or self._at[0] != t or (cells and self._at[2] is None):
            target = self.path.at(t)
            exact = smoothed_target(target, self.bandwidth, self.mirror).p
            self._at = (t, exact, self.smoother(target.p)[0] if cells else None)
        return self._at[1], self._at[2]

    def __call__(self, rec: StepRecord) -> dict[str, float | None]:
        """The swarm metrics of ``rec`` (all None without robots or off their steps), and
        ``phat_smoothed_target_l2`` = ``||p_hat - K_h p_*||`` at every step.
        """
        out: dict[str, float | None] = dict.fromkeys(SWARM_KEYS + domain_keys(self.free))
        on_step = rec.positions is not None and self.cadence.due(rec.step)
        smoothed, smoothed_cells = self.smoothed_at(rec.t, on_step and self.has_limit)
        out["phat_smoothed_target_l2"] = self.grid.l2(rec.estimate.p_hat - smoothed)
        if rec.positions is None or not on_step:
            return out
        g = self.grid
        smooth_swarm, _ = self.kde(rec.positions)
        out["swarm_l2"] = g.l2(smooth_swarm - smoothed)
        out["est_swarm_l2"] = g.l2(rec.estimate.p_hat - smooth_swarm)
        if self.has_limit:
            assert smoothed_cells is not None
            smooth_limit = self.smoother(rec.p_true)[0]
            out["limit_swarm_l2"] = g.l2(smooth_swarm - smooth_limit)
            out["limit_target_l2"] = g.l2(smooth_limit - smoothed_cells)
        if self.components is not None:
            fractions = self.components.fractions(rec.positions)
            out[GAP_KEY] = self.components.gap(fractions)
            for c, value in enumerate(fractions):
                out[f"component_fraction_{c}"] = float(value)
        if self.start is not None:
            out["start_fraction"] = self.start.fraction(rec.positions)
            moving = self.path.moves
            mass = self.start.mass_of(self.path.at(rec.t).p) if moving else self.start.target_mass
            out["start_target_mass"] = mass
        if self.w2_cadence.due(rec.step):
            n = rec.positions.shape[1]
            measure = self.measure(n) if not self.path.moves else self.measure_at(n, rec.t)
            out["swarm_w2"] = swarm_w2(rec.positions, measure)
        return out

    def measure_at(self, n_robots: int, t: float) -> TargetMeasure:
        """The target measure of ``swarm_w2`` of ``p_*(t)`` (:meth:`measure` at ``t``;
        computed at each evaluation).
        """
        refine = MEASURE_REFINE[w2_method(n_robots)]
        return _target_measure(self.path.at(t), measure_grid(self.grid), refine)

    def initialize(self, run: RunContext) -> None:
        """Keep the run's context: the floors go into its theory record at the start."""
        self.run = run

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """The step's swarm metrics; at the start, the floors for its robots."""
        if rec.step == 0 and rec.positions is not None and self.run is not None:
            floors = self.floor_record(rec.positions.shape[1], self.run.window)
            self.run.theory.update(floors)
        values.update(self(rec))

    def finalize(self, status: Status) -> None:
        """Nothing to close."""

    def measure(self, n_robots: int) -> TargetMeasure:
        """``p_*`` as a discrete measure for ``n_robots``: exact cell masses on the grid
        for the exact transport, on a grid 4 times finer per axis for the sliced one
        (whose value otherwise depends on how the projected atoms fall); on grids finer
        than :data:`MEASURE_CELLS` per side, on that many cells instead
        (:func:`measure_grid`).
        """
        refine = MEASURE_REFINE[w2_method(n_robots)]
        if refine not in self._measures:
            on = measure_grid(self.grid)
            self._measures[refine] = (
                _target_measure(self.target, on, refine)
                if self.free is None
                else free_target_measure(self.target.p, self.free, on, refine)
            )
        return self._measures[refine]

    def floor_seed(self) -> list[int]:
        """The entropy of the floors' generator, ``default_rng([seed, 2])``."""
        return [self.seed, 2]

    def measure_inputs(self, n_robots: int) -> dict[str, object]:
        """The target measure of ``swarm_w2`` for ``n_robots`` and the transport's
        settings, as plain values for the floors' key (:mod:`harness.observers.floor_cache`):
        method, refinement, grid, the SHA-256 of its atoms and masses, the EMD threshold
        and the sliced distance's directions.
        """
        method = w2_method(n_robots)
        measure = self.measure(n_robots)
        return {
            "method": method,
            "refine": MEASURE_REFINE[method],
            "grid": floor_cache.grid_inputs(measure_grid(self.grid)),
            "points_sha256": floor_cache.array_digest(measure.points),
            "weights_sha256": floor_cache.array_digest(measure.weights),
            "emd_max_robots": swarm_metrics.EMD_MAX_ROBOTS,
            "n_projections": swarm_metrics.N_PROJECTIONS,
        }

    def floor_inputs(self, n_robots: int) -> dict[str, object] | None:
        """Everything the floors for ``n_robots`` depend on
        (:func:`harness.observers.floor_cache.floor_inputs`); None for a target without a faithful
        content description, or without a continuous density (no floors); on free
        space the floors sample the target's cell values, so the density is not needed.
        """
        if self.target.density is None and self.free is None:
            return None
        return floor_cache.floor_inputs(
            target=self.target,
            grid=self.grid,
            kde=self.kde,
            smoothed_target=self.smoothed_target,
            measure=self.measure_inputs(n_robots),
            n_robots=n_robots,
            draws=self.floor_draws,
            seed=self.floor_seed(),
        )

    def floor_record(
        self,
        n_robots: int,
        window: Callable[[], AbstractContextManager[object]] = nullcontext,
    ) -> dict[str, str]:
        """The ``theory`` record's floors for ``n_robots`` robots (:meth:`floors`, drawn
        from ``default_rng([seed, 2])``), read from the floor cache when it holds them
        for the same content, else computed and stored there; with
        ``swarm_floor_source`` (``computed`` | ``cache``) and, when the target has a
        content key, ``swarm_floor_key`` (the SHA-256 of the inputs,
        :func:`harness.observers.floor_cache.floor_key`). Empty when the target has no continuous
        density to sample. ``window`` is entered around each draw (the run's stop
        window, :attr:`harness.observers.base.RunContext.window`).
        """
        if self.target.density is None and self.free is None:
            return {}
        inputs = self.floor_inputs(n_robots)

        def compute() -> dict[str, str]:
            rng = np.random.default_rng(self.floor_seed())
            return self.floors(n_robots, rng, self.floor_draws, window)

        found, source = floor_cache.cached(self.cache, inputs, compute)
        out = {**found, "swarm_floor_source": source}
        if inputs is not None:
            out["swarm_floor_key"] = floor_cache.floor_key(inputs)
        return out

    def floors(
        self,
        n_robots: int,
        rng: np.random.Generator,
        draws: int,
        window: Callable[[], AbstractContextManager[object]] = nullcontext,
    ) -> dict[str, str]:
        """The finite-N floors of ``swarm_l2`` and ``swarm_w2`` for ``n_robots`` robots,
        as string values for the ``theory`` record: mean, 2.5 and 97.5 percentiles and
        the number of Monte-Carlo draws (:func:`harness.observers.swarm_metrics.floors`), and the
        transport method; ``window`` entered around each draw. Empty when the target has
        no continuous density to sample.
        """
        density = self.target.density
        if self.free is not None:
            sampler: Density | FreeSampler = FreeSampler(self.target.p, self.free)
        elif density is None:
            return {}
        else:
            sampler = density
        bands = swarm_metrics.floors(
            sampler,
            self.grid,
            self.kde,
            self.smoothed_target,
            self.measure(n_robots),
            n_robots,
            rng,
            draws=draws,
            window=window,
        )
        out = {"swarm_w2_method": w2_method(n_robots)}
        for name, band in bands.items():
            for key, value in band.as_dict().items():
                out[f"{name}_floor_{key}"] = repr(value)
        return out


MEASURE_REFINE = {"emd": 1, "sliced": 4}
"""Refinement per axis of the target measure's grid for each transport method of
``swarm_w2`` (:meth:`SwarmTruth.measure`)."""


MEASURE_CELLS = 64
"""Cells per side of the target measure of ``swarm_w2`` at most: the exact transport
holds ``8 N M`` bytes for ``M`` atoms (0.5 GB and minutes per evaluation for 1024
robots against a 256 x 256 grid's cells), and the distance should not depend on the
simulation grid. On grids up to 64 per side the measure is the grid's cells."""


def measure_grid(grid: Grid) -> Grid:
    """The grid of the target measure: ``grid``, or ``MEASURE_CELLS`` cells per side of
    the same domain when ``grid`` is finer.
    """
    if grid.nx <= MEASURE_CELLS and grid.ny <= MEASURE_CELLS:
        return grid
    nx, ny = min(grid.nx, MEASURE_CELLS), min(grid.ny, MEASURE_CELLS)
    return Grid(nx, ny, grid.x0, grid.x1, grid.y0, grid.y1)


def _target_measure(target: Target, grid: Grid, refine: int) -> TargetMeasure:
    """``p_*`` as cell masses at cell centres: the masses of the target's density on the
    grid refined ``refine`` times (:meth:`TargetMeasure.from_density`; exact for a
    density with a closed form); for a target given by cell values only, its cell values
    times cell area, summed into the cells of ``grid`` that hold their centres (``grid``
    may be coarser than the target's, :func:`measure_grid`).
    """
    if target.density is not None:
        return TargetMeasure.from_density(target.density, grid, refine)
    fine = target.grid
    fx, fy = fine.mesh
    col = np.minimum(((fx - grid.x0) / grid.dx).astype(np.intp), grid.nx - 1)
    row = np.minimum(((fy - grid.y0) / grid.dy).astype(np.intp), grid.ny - 1)
    masses = np.zeros(grid.shape)
    np.add.at(masses, (row.ravel(), col.ravel()), (target.p * fine.cell_area).ravel())
    x, y = grid.mesh
    weights = masses.ravel()
    return TargetMeasure(np.column_stack([x.ravel(), y.ravel()]), weights / weights.sum())
