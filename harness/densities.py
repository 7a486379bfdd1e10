"""Targets ``p_*`` and initial densities ``p_0``: Gaussian mixtures with a floor,
uniform, and uniform on a sub-rectangle.

Every density can be (a) put on a grid as cell values normalised so that the
grid integral is exactly 1, and (b) sampled, for placing robots. Densities are
in 1 / length^2.

Default target (the paper shows its ``p_*`` only as a missing picture): the
three-bump mixture :data:`DEFAULT_TARGET`, chosen multi-modal and asymmetric so
that the swarm must split, with a 20 % uniform floor so ``p_*`` is bounded below
(``min p_* >= 0.2`` on the unit square) as the paper's theorems require.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from math import erf, sqrt

import numpy as np

from harness.components import Density, number, require
from harness.grid import Grid

__all__ = ["DEFAULT_TARGET", "Box", "Density", "GaussianMixture", "Target", "Uniform"]


@dataclass(frozen=True)
class Uniform:
    """The uniform density ``1 / |Omega|``."""

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Cell values ``1 / |Omega|``."""
        return np.full(grid.shape, 1.0 / grid.area)

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """Uniform positions on the domain, shape ``(2, n)``."""
        return Box(grid.x0, grid.x1, grid.y0, grid.y1).sample(n, grid, rng)


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
        """Mixture at the cell centres normalised on the grid, plus the floor."""
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
    """

    grid: Grid
    p: np.ndarray
    grad: np.ndarray
    log_p: np.ndarray
    density: Density | None = None

    @classmethod
    def from_values(cls, grid: Grid, p: np.ndarray) -> Target:
        """A target given by its cell values ``p`` (strictly positive)."""
        if not (np.isfinite(p).all() and p.min() > 0):
            raise ValueError(
                f"a target must be finite and strictly positive on the grid (min {p.min():.3g})"
            )
        return cls(grid=grid, p=p, grad=grid.gradient(p), log_p=np.log(p))

    @classmethod
    def from_density(cls, grid: Grid, density: Density) -> Target:
        """Put ``density`` on ``grid``; it must be strictly positive there."""
        on_grid = cls.from_values(grid, density.on_grid(grid))
        return cls(grid, on_grid.p, on_grid.grad, on_grid.log_p, density)
