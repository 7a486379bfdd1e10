"""Robots that head for a goal point each period: the motion shared by the laws that
decide, once per period, where each robot should be (:mod:`harness.control.guidance`,
:mod:`harness.control.assignment`).

A law of this kind is called once per step at ``t = n dt`` but decides only at the
start of each period ``[k T, (k + 1) T)`` (``T`` the law's ``period``, s), which it
recognises by the integer period index ``k = floor(t / T + 1e-9)`` (the ``1e-9`` keeps
an ``n dt`` that round-off leaves just below ``k T`` in period ``k``). In between, robot
``i`` with goal ``g_i`` moves with

    u_i = (g_i - x_i) / max((k + 1) T - t, h),

recomputed at every step from its position ``x_i`` as the law sees it, then capped at
``v_max`` by the command (:meth:`harness.records.Command.capped`); ``h`` is the step,
the spacing of the last two calls (0 at the first call). Held over a step of ``h``, this
covers the fraction ``h / ((k + 1) T - t)`` of the remaining way, so a robot without
noise and without a binding cap reaches ``g_i`` at the period's last step, ``t = (k + 1)
T``, to round-off, when ``T`` is a multiple of ``h`` (otherwise the ``max`` makes it
arrive at the first step past the period's end, without overshooting). With the noise
``sqrt(2 sigma) dB`` the recomputation steers the noise back out: the error ``e = x - g``
follows ``e <- e (1 - h / tau) + sqrt(2 sigma h) xi`` with ``tau`` the time left, a
discrete Brownian bridge, so a robot ends the period at ``g_i`` plus one step's noise
(standard deviation ``sqrt(2 sigma h)`` per axis) and strays from its straight path by
the bridge's ``sqrt(2 sigma s (T - s) / T)`` at time ``s`` into the period (at most
``sqrt(2 sigma T) / 2``, at mid-period). A robot without a goal (``NaN``) holds still:
velocity 0, and only the plant's noise moves it.

The laws' default period, ``T`` = 1 s: it is 100 of the paper's steps (``dt`` = 0.01 s),
so a solve made once per period costs a hundredth of itself per step; the noise spreads
a robot by ``sqrt(2 sigma T)`` = 0.01 per period at the paper's ``sigma``, under a third
of a 30 x 30 cell, so the cell a robot is counted in at a period's start is, within
that, the one it was sent to; and a move to a point of a neighbouring cell, at most
``sqrt(5)`` cells' widths (0.075) in ``T``, asks for speeds of the paper's law (its robots'
mean speed is 0.08 at the start from the paper's box and 0.02 after 1 s). A shorter
period speeds the chains' mixing in proportion and the robots with it.
"""

from __future__ import annotations

import math

import numpy as np

from harness.grid import Grid
from harness.records import Command
from harness.velocity import VelocityField, cap_vectors

PERIOD_ROUNDING = 1e-9
"""Slack of the period index ``floor(t / T + PERIOD_ROUNDING)`` (a fraction of ``T``)."""


def cell_of(grid: Grid, positions: np.ndarray) -> np.ndarray:
    """The flat cell index (C order, ``row * nx + col``) of each position ``(2, N)``
    (length), binned as :meth:`harness.velocity.VelocityField.from_robots` bins them (a
    position on an inner edge belongs to the cell above it or to its right; one on the
    far wall to the last cell).
    """
    col = np.clip(((positions[0] - grid.x0) / grid.dx).astype(np.intp), 0, grid.nx - 1)
    row = np.clip(((positions[1] - grid.y0) / grid.dy).astype(np.intp), 0, grid.ny - 1)
    return row * grid.nx + col


def points_in_cells(grid: Grid, cells: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One point drawn uniformly in each of the flat cells ``cells``, shape ``(2,
    len(cells))`` (length), from one ``(2, len(cells))`` array of uniform draws of
    ``rng`` (row 0 for x, row 1 for y).
    """
    row, col = np.divmod(np.asarray(cells, dtype=np.intp), grid.nx)
    u = rng.random((2, row.size))
    return np.stack([grid.x0 + (col + u[0]) * grid.dx, grid.y0 + (row + u[1]) * grid.dy])


class PeriodClock:
    """Which period a call at ``t`` falls in, and the time left in it.

    Args:
        period: ``T > 0`` (s).

    Attributes:
        index: The current period ``k`` (-1 before the first call).
        step: The step ``h`` (s) between the last two calls (0 after the first).
        restarted: Whether the last call began a run: the first call, or one at an
            earlier time than the call before (the law reused for a new run).
    """

    def __init__(self, period: float) -> None:
        self.period = period
        self.index = -1
        self.step = 0.0
        self.restarted = False
        self._last_t = math.nan

    def tick(self, t: float) -> bool:
        """Register a call at ``t`` (s); True when it starts a period."""
        self.restarted = not math.isfinite(self._last_t) or t < self._last_t
        if self.restarted:
            self.index, self.step = -1, 0.0
        elif t > self._last_t:
            self.step = t - self._last_t
        self._last_t = t
        k = math.floor(t / self.period + PERIOD_ROUNDING)
        starts = k != self.index
        self.index = k
        return starts

    def time_left(self, t: float) -> float:
        """``max((k + 1) T - t, h)`` (s) for the current period ``k`` and step ``h``
        (module docstring), and at least ``1e-12 T``.
        """
        left = (self.index + 1) * self.period - t
        return max(left, self.step, 1e-12 * self.period)


def steer(
    grid: Grid, positions: np.ndarray, goals: np.ndarray, time_left: float, v_max: float | None
) -> Command:
    """The command that takes each robot to its goal by the end of the period.

    Args:
        grid: The grid (for the field: the swarm's mean velocity per cell).
        positions: ``(2, N)`` (length), as the law sees them.
        goals: ``(2, N)`` (length); a robot whose goal is ``NaN`` holds (velocity 0).
        time_left: Time left in the period (s, > 0; :meth:`PeriodClock.time_left`).
        v_max: Speed cap (length / s), or None.

    Returns:
        ``Command(VelocityField.from_robots(grid, positions, u), u)`` with ``u`` the
        capped ``(goals - positions) / time_left`` (length / s; 0 for a holding robot):
        the field is the mean of the velocities the robots are given.
    """
    holding = np.isnan(goals[0])
    u = np.where(holding, 0.0, goals - positions) / time_left
    if v_max is not None:
        u = cap_vectors(u, v_max)
    return Command(VelocityField.from_robots(grid, positions, u), u)
