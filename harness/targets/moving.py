"""Moving targets ``p_*(t)``: the default three-bump mixture rotating about a point.

``target=moving`` (:class:`RotatingMixture`) is the mixture of
:class:`harness.targets.densities.GaussianMixture` (the default target's bumps, widths, weights
and floor, ``conf/target/three_bumps.yaml``) whose bump centres turn rigidly about the
point ``c = target.centre`` (length; the domain centre ``(0.5, 0.5)`` by default) at the
angular velocity ``omega = target.speed / r_max`` (rad / s, counter-clockwise), with
``r_max = max_k |mu_k - c|`` the radius of the centre farthest from ``c``:

    mu_k(t) = c + R(omega t) (mu_k - c),      R(a) = [[cos a, -sin a], [sin a, cos a]],

so every centre moves on its own circle about ``c``, the farthest at exactly
``target.speed`` (length / s), the others slower; the path is closed with period
``2 pi / omega``. Widths, weights and the floor do not change. The default centres lie
0.25 to 0.28 from the domain centre, so along the whole turn each bump stays as far from
the walls as the static target's nearest one (at least 0.22, 2.4 widths); the walls cut
the bumps slightly differently at every angle (the mixture is restricted to the square
and renormalised), so the shape is the static one up to that. ``target.speed = 0`` is
the static target itself (:meth:`RotatingMixture.at` returns the unrotated mixture, and
the loop treats the target as static: the run is the static run bit for bit).

The time derivative ``d_t p_*`` is analytic (:meth:`RotatingMixture.rate`), of the
target exactly as the loop puts it on the grid (:meth:`GaussianMixture.on_grid`: the
mixture at the cell centres normalised by its grid integral, plus the floor), so its
grid integral is zero to round-off.

:class:`TargetPath` gives a run's target at a time, ``p_*(t)`` on the grid (a
:class:`~harness.targets.densities.Target` whose ``density`` is the mixture at ``t``) and
``d_t p_*``, for the loop (:class:`harness.loop.ClosedLoop` fills
:attr:`harness.records.ControlInput.target` and ``target_rate``), the laws and the
metrics (:mod:`harness.observers.metrics`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from math import cos, hypot, sin
from typing import Protocol, runtime_checkable

import numpy as np

from harness.grid import Grid
from harness.parameters import ParameterError, number, require
from harness.targets.densities import GaussianMixture, Target


@runtime_checkable
class MovingDensity(Protocol):
    """A target density that moves: the density at a time and its time derivative."""

    @property
    def moves(self) -> bool:
        """Whether the density changes in time (False: the static density)."""
        ...

    def at(self, t: float) -> GaussianMixture:
        """The density at time ``t`` (s)."""
        ...

    def rate(self, grid: Grid, t: float) -> np.ndarray:
        """``d_t p_*`` of the density's cell values on ``grid`` at ``t``, ``(ny, nx)``
        (1 / (length^2 s)).
        """
        ...


def check_path(density: object, grid: Grid) -> None:
    """A density's optional check of its path on ``grid`` (its ``check(grid)``: a moving
    target refuses, with :class:`~harness.parameters.ParameterError`, a path that leaves
    the domain, :meth:`RotatingMixture.check`); nothing for a density without one.
    """
    check = getattr(density, "check", None)
    if check is not None:
        check(grid)


def moves(target: Target) -> bool:
    """Whether ``target`` is the start of a moving target (its density moves)."""
    density = target.density
    return isinstance(density, MovingDensity) and density.moves


@dataclass(frozen=True)
class RotatingMixture:
    """The Gaussian mixture with a floor whose centres rotate about ``centre``
    (``target=moving``; the module docstring gives the path).

    At ``t = 0`` it is :class:`~harness.targets.densities.GaussianMixture` of the same
    parameters, and it is a :class:`~harness.targets.densities.Density` through that mixture
    (cell values, samples, ``K_h * p``, cell masses: what the run starts from, and what
    the finite-N floors are drawn from, see :class:`harness.observers.swarm.SwarmTruth`).

    Args:
        means, stds, weights, floor: As :class:`~harness.targets.densities.GaussianMixture`
            (the centres ``mu_k`` at ``t = 0``, length).
        speed: Speed of the centre farthest from ``centre`` (length / s), ``>= 0``.
        centre: The rotation centre ``c`` (length), ``(x, y)``.
    """

    means: Sequence[Sequence[float]]
    stds: Sequence[float]
    weights: Sequence[float]
    floor: float = 0.2
    speed: float = 0.0
    centre: Sequence[float] = (0.5, 0.5)
    _base: GaussianMixture = field(init=False, repr=False, compare=False)
    _omega: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        base = GaussianMixture(self.means, self.stds, self.weights, self.floor)
        speed = number("speed", self.speed, 0.0)
        require(
            isinstance(self.centre, Sequence) and len(self.centre) == 2,
            "centre",
            self.centre,
            "an (x, y) pair",
        )
        c = (number("centre", self.centre[0]), number("centre", self.centre[1]))
        r_max = max(hypot(mx - c[0], my - c[1]) for mx, my in base.means)
        require(
            speed == 0 or r_max > 0,
            "speed",
            self.speed,
            "0 when every bump centre sits at the rotation centre (nothing to rotate)",
        )
        for name, value in (
            ("means", base.means),
            ("stds", base.stds),
            ("weights", base.weights),
            ("floor", base.floor),
            ("speed", speed),
            ("centre", c),
        ):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_base", base)
        object.__setattr__(self, "_omega", speed / r_max if speed > 0 else 0.0)

    @property
    def moves(self) -> bool:
        """Whether the centres move (``speed > 0``)."""
        return self._omega > 0

    @property
    def omega(self) -> float:
        """Angular velocity ``omega = speed / r_max`` (rad / s)."""
        return self._omega

    def check(self, grid: Grid) -> None:
        """Refuse a path that takes a bump centre out of the grid's domain.

        Raises:
            ParameterError: naming ``centre`` when some centre's circle about it leaves
                the domain (only for a target that moves).
        """
        if not self.moves:
            return
        cx, cy = self.centre
        for mx, my in self.means:
            r = hypot(mx - cx, my - cy)
            inside = grid.x0 < cx - r and cx + r < grid.x1 and grid.y0 < cy - r and cy + r < grid.y1
            if not inside:
                raise ParameterError(
                    "centre",
                    list(self.centre),
                    f"a rotation centre whose circle through every bump centre stays inside "
                    f"the domain [{grid.x0}, {grid.x1}] x [{grid.y0}, {grid.y1}] (the centre "
                    f"({mx}, {my}) turns on a circle of radius {r:.3g})",
                )

    def centres(self, t: float) -> tuple[tuple[float, float], ...]:
        """The bump centres ``mu_k(t) = c + R(omega t) (mu_k - c)`` (length)."""
        a = self._omega * t
        ca, sa = cos(a), sin(a)
        cx, cy = self.centre
        return tuple(
            (cx + ca * (mx - cx) - sa * (my - cy), cy + sa * (mx - cx) + ca * (my - cy))
            for mx, my in self.means
        )

    def at(self, t: float) -> GaussianMixture:
        """The mixture at time ``t`` (s): the static mixture itself at ``omega t = 0``."""
        if self._omega * t == 0:
            return self._base
        return GaussianMixture(self.centres(t), self.stds, self.weights, self.floor)

    def rate(self, grid: Grid, t: float) -> np.ndarray:
        """``d_t p_*`` of the cell values at ``t``, analytically (1 / (length^2 s)).

        The cell values are ``p = (1 - f) m / S + f / |Omega|`` with the mixture ``m =
        sum_k w_k N(x; mu_k, s_k^2 I)`` at the centres and its grid integral ``S = dx dy
        sum m`` (:meth:`GaussianMixture.on_grid`). A centre moving at ``mu_k'(t) = omega
        J (mu_k - c)`` (``J (a, b) = (-b, a)``) changes its bump by

            d_t N(x; mu_k, s_k^2 I) = N(x; mu_k, s_k^2 I) (x - mu_k) . mu_k' / s_k^2,

        so ``m' = sum_k w_k N_k (x - mu_k) . mu_k' / s_k^2`` and

            d_t p = (1 - f) (m' / S - m S' / S^2),      S' = dx dy sum m',

        whose grid integral is zero (mass is conserved on the grid exactly).
        """
        shape = grid.shape
        if not self.moves:
            return np.zeros(shape)
        x, y = grid.mesh
        mix = self.at(t)
        cx, cy = self.centre
        m = np.zeros(shape)
        dm = np.zeros(shape)
        for w, (mx, my), s in zip(mix._w, mix.means, mix.stds, strict=True):
            bump = w * np.exp(-((x - mx) ** 2 + (y - my) ** 2) / (2 * s * s)) / (2 * np.pi * s * s)
            vx, vy = -self._omega * (my - cy), self._omega * (mx - cx)
            m += bump
            # d_t N_k = N_k (x - mu_k) . mu_k' / s_k^2
            dm += bump * ((x - mx) * vx + (y - my) * vy) / (s * s)
        total, dtotal = grid.integrate(m), grid.integrate(dm)
        # d_t p = (1 - f) (m' / S - m S' / S^2)
        return (1 - self.floor) * (dm / total - m * dtotal / total**2)

    # --- the Density protocol, through the mixture at t = 0 ---------------------------

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Cell values of ``p_*(0)`` (:meth:`GaussianMixture.on_grid`)."""
        return self._base.on_grid(grid)

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """Samples of ``p_*(0)``, shape ``(2, n)``."""
        return self._base.sample(n, grid, rng)

    def smoothed(self, grid: Grid, h: float, mirror: bool) -> np.ndarray:
        """``K_h * p_*(0)`` at the cell centres, exactly."""
        return self._base.smoothed(grid, h, mirror)

    def cell_masses(self, grid: Grid) -> np.ndarray:
        """Exact cell masses of ``p_*(0)``."""
        return self._base.cell_masses(grid)


class TargetPath:
    """A run's target at every time: ``p_*(t)`` on the grid and ``d_t p_*``.

    For a static target (:func:`moves` false) :meth:`at` is the target itself and
    :meth:`rate` None. The last time asked is kept (the loop, the laws and the metrics
    ask each step's time more than once).

    Args:
        target: The run's target at ``t = 0`` (its ``density`` says whether it moves).
    """

    def __init__(self, target: Target) -> None:
        self.start = target
        density = target.density
        self.density: MovingDensity | None = (
            density if isinstance(density, MovingDensity) and density.moves else None
        )
        self._t: float | None = None
        self._target = target
        self._rate: np.ndarray | None = None

    @property
    def moves(self) -> bool:
        """Whether the target moves."""
        return self.density is not None

    def _update(self, t: float) -> None:
        if self._t == t or self.density is None:
            return
        grid = self.start.grid
        self._target = Target.from_density(grid, self.density.at(t))
        self._rate = self.density.rate(grid, t)
        self._t = t

    def at(self, t: float) -> Target:
        """``p_*(t)`` on the grid (its ``density`` the mixture at ``t``)."""
        self._update(t)
        return self._target

    def rate(self, t: float) -> np.ndarray | None:
        """``d_t p_*`` on the grid at ``t`` (1 / (length^2 s)), None when static."""
        self._update(t)
        return self._rate

    def floor_target(self) -> Target:
        """The target the finite-N floors are drawn from: ``p_*(0)`` with its static
        density (see :class:`harness.observers.swarm.SwarmTruth`).
        """
        if self.density is None:
            return self.start
        return Target(
            self.start.grid,
            self.start.p,
            self.start.grad,
            self.start.log_p,
            self.density.at(0.0),
            self.start.free,
        )
