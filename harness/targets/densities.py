"""Targets ``p_*`` and initial densities ``p_0``: Gaussian mixtures with a floor,
uniform, and uniform on a sub-rectangle.

Every density can be (a) put on a grid as cell values normalised so that the
grid integral is exactly 1, and (b) sampled, for placing robots. Densities are
in 1 / length^2.

The three densities here also give two quantities in closed form, the optional methods
of :class:`~harness.targets.densities.Density` (callers go through
:func:`harness.estimators.smoothing.smoothed_density` and
:func:`harness.estimators.smoothing.cell_masses`, which fall back to approximations for
a density without them):

* ``smoothed(grid, h, mirror)``: ``K_h * p`` at the cell centres, with ``K_h`` the KDE's
  kernel and its wall images (:mod:`harness.observers.swarm_metrics` describes the kernel).
  Writing ``k(c, x) = sum_{c'} g_h(c' - x)`` over the three reflected evaluation points
  ``c' in {c, 2 lo - c, 2 hi - c}`` (``g_h`` is even; only ``c`` without ``mirror``),
  each axis needs ``int_lo^hi f(x) g_h(c' - x) dx``:

  - uniform on ``[a, b]``: ``Phi((b - c') / h) - Phi((a - c') / h)``;
  - Gaussian ``N(mu, s^2)`` restricted to ``[lo, hi]`` (the product of two Gaussians
    is a Gaussian): ``N(c'; mu, s^2 + h^2) [Phi((hi - m) / r) - Phi((lo - m) / r)]``
    with ``m = (mu h^2 + c' s^2) / (s^2 + h^2)`` and ``r = s h / sqrt(s^2 + h^2)``;

  with ``Phi`` the standard normal distribution function. Each density here is a sum of
  products of such factors per axis (mixture bumps are isotropic, the floor and boxes
  are uniform), so ``K_h * p`` is exact to round-off (~1e-15 relative).
* ``cell_masses(grid)``: the exact mass ``int_cell p`` of every cell (sum 1), from
  error-function differences per axis for the mixture bumps and overlap lengths for
  uniform parts; ``p`` is the continuous density the robots are sampled from, not its
  grid normalisation.

Default target (the paper shows its ``p_*`` only as a missing picture): the
three-bump mixture :data:`DEFAULT_TARGET`, chosen multi-modal and asymmetric so
that the swarm must split, with a 20 % uniform floor so ``p_*`` is bounded below
(``min p_* >= 0.2`` on the unit square) as the paper's theorems require.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from math import erf, sqrt
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.special import ndtr

from harness.domains.base import FreeSpace
from harness.grid import Grid
from harness.parameters import number, require


@runtime_checkable
class Density(Protocol):
    """A target ``p_*`` or initial density ``p_0`` (1 / length^2).

    ``on_grid`` refuses a density that does not fit the grid's domain with a
    ``ValueError`` (the builder names the config key with its message).

    Optional, for a density with closed forms (:class:`ExactSmoothing`,
    :class:`ExactCellMasses`): ``smoothed(grid, h, mirror)``, ``K_h * p`` at the cell
    centres, and ``cell_masses(grid)``, the mass of every cell. Without them the swarm
    metrics and the debiased laws use approximations from the cell values
    (:func:`harness.estimators.smoothing.smoothed_density_cells`,
    :func:`harness.estimators.smoothing.cell_masses_midpoint`). A subclass that changes the density
    redefines them.
    """

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Cell values, shape ``(ny, nx)``, with grid integral 1."""
        ...

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """``n`` positions drawn from the density on the grid's domain, shape ``(2, n)``
        (row 0: x, row 1: y).
        """
        ...


@runtime_checkable
class ExactSmoothing(Protocol):
    """A density that gives ``K_h * p`` exactly (optional part of :class:`Density`)."""

    def smoothed(self, grid: Grid, h: float, mirror: bool) -> np.ndarray:
        """``K_h * p`` at the cell centres, shape ``(ny, nx)`` (1 / length^2), with
        ``K_h`` the KDE's Gaussian kernel of bandwidth ``h > 0`` (length), with its wall
        images when ``mirror`` (:mod:`harness.observers.swarm_metrics`).
        """
        ...


@runtime_checkable
class ExactCellMasses(Protocol):
    """A density that gives its cell masses exactly (optional part of :class:`Density`)."""

    def cell_masses(self, grid: Grid) -> np.ndarray:
        """``int_cell p`` of every cell of ``grid``, shape ``(ny, nx)`` (dimensionless,
        sum 1), of the continuous density the robots are sampled from.
        """
        ...


@dataclass(frozen=True)
class Uniform:
    """The uniform density ``1 / |Omega|``."""

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Cell values ``1 / |Omega|``."""
        return np.full(grid.shape, 1.0 / grid.area)

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """Uniform positions on the domain, shape ``(2, n)``."""
        return Box(grid.x0, grid.x1, grid.y0, grid.y1).sample(n, grid, rng)

    def smoothed(self, grid: Grid, h: float, mirror: bool) -> np.ndarray:
        """``K_h * p`` at the cell centres, exactly (see the module docstring)."""
        return _box_smoothed(grid.x0, grid.x1, grid.y0, grid.y1, grid, h, mirror)

    def cell_masses(self, grid: Grid) -> np.ndarray:
        """Exact cell masses (the cells' area fractions)."""
        return _box_masses(grid.x0, grid.x1, grid.y0, grid.y1, grid)


@dataclass(frozen=True)
class Box:
    """Uniform density on the sub-rectangle ``[x0, x1] x [y0, y1]`` (zero outside).

    On the grid each cell gets the fraction of its area inside the box divided by
    the box area, so the grid integral is exactly 1 also when the box edges cut
    cells (the paper's ``[0.15, 0.85]^2`` on a 30 x 30 grid cuts cells in half).
    """

    x0: float = 0.15
    x1: float = 0.85
    y0: float = 0.15
    y1: float = 0.85

    def __post_init__(self) -> None:
        for name in ("x0", "x1", "y0", "y1"):
            object.__setattr__(self, name, number(name, getattr(self, name)))
        require(self.x1 > self.x0, "x1", self.x1, f"a number > x0 = {self.x0}")
        require(self.y1 > self.y0, "y1", self.y1, f"a number > y0 = {self.y0}")

    def _check(self, grid: Grid) -> None:
        if not (
            grid.x0 <= self.x0 < self.x1 <= grid.x1 and grid.y0 <= self.y0 < self.y1 <= grid.y1
        ):
            raise ValueError(
                f"box [{self.x0}, {self.x1}] x [{self.y0}, {self.y1}] is empty or not inside "
                f"the domain [{grid.x0}, {grid.x1}] x [{grid.y0}, {grid.y1}]"
            )

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Covered cell fraction over the box area."""
        self._check(grid)
        fx = _overlap(grid.x - grid.dx / 2, grid.x + grid.dx / 2, self.x0, self.x1) / grid.dx
        fy = _overlap(grid.y - grid.dy / 2, grid.y + grid.dy / 2, self.y0, self.y1) / grid.dy
        return np.outer(fy, fx) / ((self.x1 - self.x0) * (self.y1 - self.y0))

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """Uniform positions in the box, shape ``(2, n)``."""
        self._check(grid)
        x = rng.uniform(self.x0, self.x1, size=n)
        y = rng.uniform(self.y0, self.y1, size=n)
        return np.vstack([x, y])

    def smoothed(self, grid: Grid, h: float, mirror: bool) -> np.ndarray:
        """``K_h * p`` at the cell centres, exactly (see the module docstring)."""
        return _box_smoothed(self.x0, self.x1, self.y0, self.y1, grid, h, mirror)

    def cell_masses(self, grid: Grid) -> np.ndarray:
        """Exact cell masses: each cell's area inside the box over the box area."""
        return _box_masses(self.x0, self.x1, self.y0, self.y1, grid)


@dataclass(frozen=True)
class GaussianMixture:
    """Isotropic Gaussian mixture restricted to the domain, plus a uniform floor.

        p(x) = (1 - floor) * m(x) / int_Omega m  +  floor / |Omega|,
        m(x) = sum_k w_k N(x; mu_k, s_k^2 I).

    Smooth, bounded below by ``floor / |Omega|`` and of unit mass. On the grid the
    mixture part is normalised by its grid integral, so the grid integral of the
    cell values is exactly 1.

    Args:
        means: Bump centres ``mu_k`` (length), each ``(x, y)``.
        stds: Bump widths ``s_k > 0`` (length).
        weights: Relative weights ``w_k > 0`` (normalised internally).
        floor: Fraction of the mass spread uniformly, in ``(0, 1]``.
    """

    means: Sequence[Sequence[float]]
    stds: Sequence[float]
    weights: Sequence[float]
    floor: float = 0.2
    _w: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        k = len(self.means) if isinstance(self.means, Sequence) else 0
        require(k >= 1, "means", self.means, "a list of at least one (x, y) pair")
        require(
            isinstance(self.stds, Sequence) and len(self.stds) == k,
            "stds",
            self.stds,
            f"a list of {k} widths, one per mean",
        )
        require(
            isinstance(self.weights, Sequence) and len(self.weights) == k,
            "weights",
            self.weights,
            f"a list of {k} weights, one per mean",
        )
        for m in self.means:
            require(
                isinstance(m, Sequence) and len(m) == 2,
                "means",
                self.means,
                "a list of (x, y) pairs",
            )
        means = tuple((number("means", m[0]), number("means", m[1])) for m in self.means)
        stds = tuple(number("stds", s_, 0.0, strict=True) for s_ in self.stds)
        weights = tuple(number("weights", w, 0.0, strict=True) for w in self.weights)
        floor = number("floor", self.floor, 0.0, strict=True)
        require(floor <= 1, "floor", self.floor, "a number in (0, 1]")
        object.__setattr__(self, "means", means)
        object.__setattr__(self, "stds", stds)
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "floor", floor)
        w = np.asarray(weights, dtype=float)
        object.__setattr__(self, "_w", w / w.sum())

    def mixture(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Unnormalised mixture ``m(x, y)`` (1 / length^2)."""
        out = np.zeros(np.broadcast(x, y).shape)
        for w, (mx, my), s in zip(self._w, self.means, self.stds, strict=True):
            out += w * np.exp(-((x - mx) ** 2 + (y - my) ** 2) / (2 * s * s)) / (2 * np.pi * s * s)
        return out

    def mixture_mass(self, grid: Grid) -> float:
        """Exact ``int_Omega m`` over the rectangle (products of error functions)."""
        total = 0.0
        for w, (mx, my), s in zip(self._w, self.means, self.stds, strict=True):
            cx = 0.5 * (erf((grid.x1 - mx) / (s * sqrt(2))) - erf((grid.x0 - mx) / (s * sqrt(2))))
            cy = 0.5 * (erf((grid.y1 - my) / (s * sqrt(2))) - erf((grid.y0 - my) / (s * sqrt(2))))
            total += w * cx * cy
        return total

    def evaluate(self, x: np.ndarray, y: np.ndarray, grid: Grid) -> np.ndarray:
        """The continuous density ``p(x, y)`` on the grid's domain."""
        m = self.mixture(x, y) / self.mixture_mass(grid)
        return (1 - self.floor) * m + self.floor / grid.area

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Mixture at the cell centres normalised on the grid, plus the floor.

        Raises:
            ValueError: for a bump centred outside the domain (its weight would be lost
                in the normalisation, without a word).
        """
        for k, (mx, my) in enumerate(self.means):
            if not (grid.x0 <= mx <= grid.x1 and grid.y0 <= my <= grid.y1):
                raise ValueError(
                    f"means: every bump centred inside the domain [{grid.x0:g}, {grid.x1:g}]"
                    f" x [{grid.y0:g}, {grid.y1:g}] (bump {k} at ({mx:g}, {my:g}) is not; "
                    "its weight would be lost in the normalisation)"
                )
        x, y = grid.mesh
        m = grid.normalise(self.mixture(x, y))
        return (1 - self.floor) * m + self.floor / grid.area

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """Exact samples of the continuous density by rejection from the uniform
        proposal (acceptance ``p / p_max``; ``p_max`` bounded by the sum of peaks).
        """
        peak = (
            sum(w / (2 * np.pi * s * s) for w, s in zip(self._w, self.stds, strict=True))
            * (1 - self.floor)
            / self.mixture_mass(grid)
            + self.floor / grid.area
        )
        out = np.empty((2, 0))
        while out.shape[1] < n:
            m = max(2 * (n - out.shape[1]), 1024)
            x = rng.uniform(grid.x0, grid.x1, size=m)
            y = rng.uniform(grid.y0, grid.y1, size=m)
            keep = rng.uniform(0.0, peak, size=m) < self.evaluate(x, y, grid)
            out = np.hstack([out, np.vstack([x[keep], y[keep]])])
        return out[:, :n]

    def smoothed(self, grid: Grid, h: float, mirror: bool) -> np.ndarray:
        """``K_h * p`` at the cell centres, exactly: the floor as a uniform density, each
        bump as a product of the Gaussian factors (see the module docstring).
        """
        g = grid
        mass = self.mixture_mass(g)
        out = self.floor * _box_smoothed(g.x0, g.x1, g.y0, g.y1, g, h, mirror)
        for w, (mx, my), s in zip(self._w, self.means, self.stds, strict=True):
            fx = _gauss_axis(g.x, mx, s, h, g.x0, g.x1, mirror)
            fy = _gauss_axis(g.y, my, s, h, g.y0, g.y1, mirror)
            out += (1.0 - self.floor) * w / mass * np.outer(fy, fx)
        return out

    def cell_masses(self, grid: Grid) -> np.ndarray:
        """Exact cell masses of the continuous density (:meth:`evaluate`): the floor's
        area fractions plus each bump's products of error-function differences.
        """
        g = grid
        ex, ey = _edges(g)
        mass = self.mixture_mass(g)
        out = self.floor * _box_masses(g.x0, g.x1, g.y0, g.y1, g)
        for w, (mx, my), s in zip(self._w, self.means, self.stds, strict=True):
            fx = np.diff(ndtr((ex - mx) / s))
            fy = np.diff(ndtr((ey - my) / s))
            out += (1.0 - self.floor) * w / mass * np.outer(fy, fx)
        return out


DEFAULT_TARGET = GaussianMixture(
    means=((0.30, 0.30), (0.72, 0.38), (0.45, 0.74)),
    stds=(0.09, 0.07, 0.11),
    weights=(0.35, 0.25, 0.40),
    floor=0.2,
)
"""The project's default target ``p_*`` (see the module docstring)."""


def _overlap(a0: np.ndarray, a1: np.ndarray, b0: float, b1: float) -> np.ndarray:
    """Length of the overlap of intervals ``[a0, a1]`` and ``[b0, b1]``."""
    return np.clip(np.minimum(a1, b1) - np.maximum(a0, b0), 0.0, None)


def _images(c: np.ndarray, lo: float, hi: float, mirror: bool) -> list[np.ndarray]:
    """Reflected evaluation points ``c, 2 lo - c, 2 hi - c`` (only ``c`` without mirror)."""
    return [c, 2.0 * lo - c, 2.0 * hi - c] if mirror else [c]


def _uniform_axis(
    c: np.ndarray, a: float, b: float, h: float, lo: float, hi: float, mirror: bool
) -> np.ndarray:
    """``int_a^b k(c, x) dx`` for the 1-D mirrored kernel ``k`` (dimensionless)."""
    out = np.zeros_like(c)
    for ci in _images(c, lo, hi, mirror):
        out += ndtr((b - ci) / h) - ndtr((a - ci) / h)
    return out


def _gauss_axis(
    c: np.ndarray, mu: float, s: float, h: float, lo: float, hi: float, mirror: bool
) -> np.ndarray:
    """``int_lo^hi N(x; mu, s^2) k(c, x) dx`` for the 1-D mirrored kernel (1 / length)."""
    var = s * s + h * h
    r = s * h / sqrt(var)
    out = np.zeros_like(c)
    for ci in _images(c, lo, hi, mirror):
        peak = np.exp(-((ci - mu) ** 2) / (2.0 * var)) / sqrt(2.0 * np.pi * var)
        m = (mu * h * h + ci * s * s) / var
        out += peak * (ndtr((hi - m) / r) - ndtr((lo - m) / r))
    return out


def _box_smoothed(
    a0: float, a1: float, b0: float, b1: float, grid: Grid, h: float, mirror: bool
) -> np.ndarray:
    """``K_h *`` the uniform density on ``[a0, a1] x [b0, b1]`` at the cell centres."""
    fx = _uniform_axis(grid.x, a0, a1, h, grid.x0, grid.x1, mirror)
    fy = _uniform_axis(grid.y, b0, b1, h, grid.y0, grid.y1, mirror)
    return np.outer(fy, fx) / ((a1 - a0) * (b1 - b0))


def _edges(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """The cell edges along x and y."""
    return np.linspace(grid.x0, grid.x1, grid.nx + 1), np.linspace(grid.y0, grid.y1, grid.ny + 1)


def _box_masses(a0: float, a1: float, b0: float, b1: float, grid: Grid) -> np.ndarray:
    """Cell masses of the uniform density on ``[a0, a1] x [b0, b1]``."""
    ex, ey = _edges(grid)
    fx = np.clip(np.minimum(ex[1:], a1) - np.maximum(ex[:-1], a0), 0.0, None)
    fy = np.clip(np.minimum(ey[1:], b1) - np.maximum(ey[:-1], b0), 0.0, None)
    return np.outer(fy, fx) / ((a1 - a0) * (b1 - b0))


@dataclass(frozen=True)
class Target:
    """A target ``p_*`` on a grid with the quantities the control laws use.

    Attributes:
        p: ``p_*`` cell values (1 / length^2), grid integral 1, strictly positive.
        grad: ``grad p_*`` by the grid's discrete gradient (1 / length^3); using the
            same operator as for the estimates makes ``v = 0`` exactly at
            ``p_hat = p_*``, ``q_hat = grad p_*`` (the exact estimator's values).
        log_p: ``log p_*``, used for the face drift ``sigma grad log p_*``.
        density: The continuous density the target was put on the grid from (None for a
            target given by cell values only, such as a smoothed one).
        free: Free space (:class:`harness.domains.base.FreeSpace`) when the domain has
            obstacles: ``p`` is 0 on blocked cells and integrates to 1 over the free
            ones, ``grad`` is :meth:`~harness.domains.base.FreeSpace.gradient` (the
            obstacles' faces reflect as walls do), ``log_p`` is 0 on blocked cells (no
            face of theirs is open, so no law reads it). None: the plain rectangle.
    """

    grid: Grid
    p: np.ndarray
    grad: np.ndarray
    log_p: np.ndarray
    density: Density | None = None
    free: FreeSpace | None = None

    @classmethod
    def from_values(cls, grid: Grid, p: np.ndarray, free: FreeSpace | None = None) -> Target:
        """A target given by its cell values ``p`` (strictly positive; on free space, on
        its free cells, and restricted to them with unit mass).
        """
        if free is None:
            if not (np.isfinite(p).all() and p.min() > 0):
                raise ValueError(
                    f"a target must be finite and strictly positive on the grid (min {p.min():.3g})"
                )
            return cls(grid=grid, p=p, grad=grid.gradient(p), log_p=np.log(p))
        on_free = p[free.cells]
        if not (np.isfinite(on_free).all() and on_free.min() > 0):
            raise ValueError(
                "a target must be finite and strictly positive on free space "
                f"(min {on_free.min():.3g})"
            )
        q = free.restrict(p)
        log_p = np.log(np.where(free.cells, q, 1.0))
        return cls(grid=grid, p=q, grad=free.gradient(q), log_p=log_p, free=free)

    @classmethod
    def from_density(cls, grid: Grid, density: Density, free: FreeSpace | None = None) -> Target:
        """Put ``density`` on ``grid`` (restricted to ``free`` when given); it must be
        strictly positive there.
        """
        on_grid = cls.from_values(grid, density.on_grid(grid), free)
        return cls(grid, on_grid.p, on_grid.grad, on_grid.log_p, density, free)
