"""``estimator=injected``: the plant's mean-field density plus a seeded error of known L2
size, for the ISS gain curves of the laws (``docs/laws.md``).

The error's shape (``estimator.shape``) is a class, chosen once when the estimator is
built: ``smooth`` (:class:`RotatingModes`) or ``hole`` (:class:`Hole`); both give
``(eps, eps_g)`` by ``error(t, p)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import integer, number, pair, require
from harness.records import Estimate, StepInput


class RotatingModes:
    """The ``smooth`` error shape: a rotating combination of low cosine modes,

        eps(t)   = delta e(t),                e(t) = cos(omega t) e1 + sin(omega t) e2,
        eps_g(t) = delta G e(t) / ||G e(t)||,

    with ``e1, e2`` L2-orthonormal, zero-mean (mass is kept) combinations of the
    Neumann cosine modes up to ``modes`` per axis, with random coefficients from
    ``rng``. So ``||eps|| = ||eps_g|| = delta`` at every step; the error rotates
    between two shapes with angular frequency ``omega`` (rad / s).

    Args:
        grid: The grid.
        delta: Error size ``>= 0`` (1 / length for ``eps``; 1 / length^2 for ``eps_g``,
            the same number).
        omega: Angular frequency (rad / s).
        modes: Highest cosine mode per axis (``>= 1``).
        rng: The coefficients' random stream.
    """

    def __init__(
        self, grid: Grid, delta: float, omega: float, modes: int, rng: np.random.Generator
    ) -> None:
        self.grid, self.delta, self.omega = grid, delta, omega
        x, y = grid.mesh
        lx, ly = grid.x1 - grid.x0, grid.y1 - grid.y0
        shapes = []
        for _ in range(2):
            f = np.zeros(grid.shape)
            for a in range(modes + 1):
                for b in range(modes + 1):
                    if a == b == 0:
                        continue
                    f += (
                        rng.normal()
                        / (1 + a * a + b * b)
                        * np.cos(a * np.pi * (x - grid.x0) / lx)
                        * np.cos(b * np.pi * (y - grid.y0) / ly)
                    )
            shapes.append(f - grid.integrate(f) / grid.area)
        e1 = shapes[0] / grid.l2(shapes[0])
        e2 = shapes[1] - grid.inner(shapes[1], e1) * e1
        self.e1, self.e2 = e1, e2 / grid.l2(e2)

    def error(self, t: float, p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(eps, eps_g)`` at time ``t`` (s); the density ``p`` is not needed."""
        g = self.grid
        e = np.cos(self.omega * t) * self.e1 + np.sin(self.omega * t) * self.e2
        ge = g.gradient(e)
        return self.delta * e, self.delta * ge / g.l2(ge)


class Hole:
    """The ``hole`` error shape: small in L2, but the estimate of a region the robots
    must reach drops towards zero. With the Gaussian well ``w(x) = exp(-|x - c|^2 / (2
    r^2))`` at ``c = hole_centre`` of width ``r = hole_radius`` and the plant's density
    ``p``,

        b = p w - (1 / |Omega|) int p w,          eps = -delta b / ||b||,
        eps_g = G eps,

    so ``||eps|| = delta`` exactly, mass is kept, and ``p_hat = p + eps = p (1 - d w)
    + d <p w>`` with depth ``d = delta / ||b||``: at ``d = 1`` the estimate at ``c``
    falls to the small offset ``d <p w>`` (the mean of ``p w`` over the domain), and
    for ``d > 1`` it turns negative there. Everywhere within ``r / 2`` of ``c``,
    ``p_hat <= p (1 - d exp(-1/8)) + d <p w>`` (:meth:`level` gives the bound).
    The gradient error is the gradient of the hole itself (an estimate with a hole has
    its slopes), so ``||eps_g||`` is not ``delta`` (it is logged as ``eps_g_l2``).

    Args:
        grid: The grid.
        delta: Error size ``>= 0`` (1 / length).
        centre: ``c`` (length), inside the domain.
        radius: ``r > 0`` (length).
    """

    def __init__(
        self, grid: Grid, delta: float, centre: tuple[float, float], radius: float
    ) -> None:
        self.grid, self.delta = grid, delta
        x, y = grid.mesh
        self.well = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * radius**2))
        self.centre, self.radius = centre, radius

    def error(self, t: float, p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(eps, eps_g)`` for the plant's density ``p`` (at any time ``t``)."""
        assert p is not None, "the hole is cut from the plant's density"
        g = self.grid
        pw = np.maximum(p, 0.0) * self.well
        b = pw - g.integrate(pw) / g.area
        norm = g.l2(b)
        eps = -self.delta * b / norm if norm > 0 else np.zeros_like(b)
        return eps, g.gradient(eps)

    def level(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The guarantee for density ``p``: the cells within ``radius / 2`` of the
        centre (a boolean mask) and the bound ``p (1 - d exp(-1/8)) + d <p w>`` that
        ``p_hat`` stays at or below there.
        """
        g = self.grid
        x, y = g.mesh
        cx, cy = self.centre
        inside = (x - cx) ** 2 + (y - cy) ** 2 <= (self.radius / 2) ** 2
        pw = np.maximum(p, 0.0) * self.well
        mean = g.integrate(pw) / g.area
        norm = g.l2(pw - mean)
        depth = self.delta / norm if norm > 0 else 0.0
        return inside, p * (1 - depth * np.exp(-1 / 8)) + depth * mean


class InjectedEstimator:
    """Truth plus a seeded error of prescribed L2 size (for ISS gain curves).

    Two shapes (``estimator.shape``), each a class: ``smooth`` (:class:`RotatingModes`,
    a rotating combination of low cosine modes, ``||eps|| = ||eps_g|| = delta``) and
    ``hole`` (:class:`Hole`, small in L2, but the estimate of a region the robots must
    reach drops towards zero). Every parameter is checked whichever the shape.

    ``estimator=injected``.

    Args:
        grid, model: Run-time arguments.
        delta: Error size ``>= 0`` (1 / length for ``eps``; 1 / length^2 for ``eps_g``,
            the same number, for ``smooth``).
        seed: Seed of the error shapes (the run's ``seed``; the shapes use the stream
            ``[seed, 1]``, apart from the plant's).
        omega: Angular frequency (rad / s), ``smooth``.
        modes: Highest cosine mode per axis in the shapes (``>= 1``), ``smooth``.
        shape: ``smooth`` | ``hole``.
        hole_centre: ``c`` (length), inside the domain, ``hole``.
        hole_radius: ``r > 0`` (length), ``hole``.
    """

    uses_kde = False

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        delta: float,
        seed: int,
        omega: float = 0.1,
        modes: int = 4,
        shape: str = "smooth",
        hole_centre: Sequence[float] = (0.45, 0.74),
        hole_radius: float = 0.08,
    ) -> None:
        delta = number("delta", delta, 0.0)
        omega = number("omega", omega)
        modes = integer("modes", modes, 1)
        cx, cy = (number("hole_centre", c) for c in pair("hole_centre", hole_centre))
        require(
            bool(grid.contains(np.array([cx]), np.array([cy])).all()),
            "hole_centre", list(hole_centre), "a point inside the domain",
        )  # fmt: skip
        radius = number("hole_radius", hole_radius, 0.0, strict=True)
        rng = np.random.default_rng([integer("seed", seed, 0), 1])
        shapes: dict[str, Callable[[], RotatingModes | Hole]] = {
            "smooth": lambda: RotatingModes(grid, delta, omega, modes, rng),
            "hole": lambda: Hole(grid, delta, (cx, cy), radius),
        }  # estimator.shape: each value's class, from the checked parameters
        known = isinstance(shape, str) and shape in shapes
        require(known, "shape", shape, f"one of {', '.join(shapes)}")
        self.grid, self.delta = grid, delta
        self.shape = shapes[shape]()

    def error(self, t: float, p: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(eps, eps_g)`` at time ``t`` (``p``: the plant's density, for ``hole``)."""
        return self.shape.error(t, p)

    def initialize(self, inp: StepInput) -> Estimate:
        """Mean-field density plus the error at ``inp.t``."""
        eps, eps_g = self.error(inp.t, inp.p_true)
        return Estimate(inp.p_true + eps, self.grid.gradient(inp.p_true) + eps_g)

    step = initialize
