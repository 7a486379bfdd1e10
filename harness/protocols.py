"""The component protocols of the closed loop, and the one place their optional members
are read.

    plant --Measurement--> estimator --Estimate--> control --Command--> plant

Each option of each config group (``plant``, ``estimator``, ``control``) is a class
implementing one of these protocols plus a YAML file with ``_target_`` and the class's
own parameters (the densities of ``target`` and ``init`` implement
:class:`harness.targets.densities.Density`, the observers
:class:`harness.observers.base.Observer`); :func:`harness.runs.build.build` instantiates
them and hands each the run-time objects of its group as keyword arguments:

* ``plant``: ``grid`` (:class:`~harness.grid.Grid`), ``model``
  (:class:`~harness.fokker_planck.FokkerPlanck`), ``init`` (a
  :class:`~harness.targets.densities.Density`);
* ``estimator``: ``grid``, ``model``;
* ``control``: ``target`` (:class:`~harness.targets.densities.Target`).

A constructor checks its own parameters (:mod:`harness.parameters`). Compatibility across
components is each component's own: a plant, estimator or control may define
``check(plant=..., estimator=..., control=...)`` (keyword arguments; accept ``**parts``
for the ones not needed), which the builder calls once all three are built and which
raises :class:`~harness.parameters.Incompatible` for a combination it cannot run.

A protocol lists what every component has. What only some have (a plant's ``observed``
positions, a law's ``needs_robots``, a component's ``check``) is optional: it is read
only through the functions of this module, which say what its absence means.

See ``docs/extending.md`` for a complete example of each.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp

from harness.grid import Grid
from harness.parameters import Incompatible
from harness.records import Command, ControlInput, Estimate, Measurement, StepInput


def require_field(control: Any, where: str) -> None:
    """Raise :class:`Incompatible` naming ``control`` unless the law gives a velocity
    field (``gives_field``); ``where`` says who needs it and why
    (``"on plant=meanfield (the density moves by it)"``).
    """
    if not control.gives_field:
        raise Incompatible(
            "control", type(control).__name__, f"a law with a velocity field {where}"
        )


def needs_robots(control: Any) -> bool:
    """Whether ``control`` has no mean-field form (its optional ``needs_robots``)."""
    return bool(getattr(control, "needs_robots", False))


def refuse_robot_law(control: Any, where: str) -> None:
    """Raise :class:`Incompatible` naming ``control`` when it needs robots
    (:func:`needs_robots`); ``where`` says who cannot give them.
    """
    if needs_robots(control):
        raise Incompatible(
            "control", type(control).__name__, f"a law with a mean-field form {where}"
        )


@runtime_checkable
class Plant(Protocol):
    """What moves under the held velocity, and what it lets the estimator measure.

    Attributes:
        density: The mean-field density ``(ny, nx)`` (1 / length^2) the plant carries: its
            state (``meanfield``) or the loop's deterministic ``N -> infinity`` limit
            (``agents``).
        positions: Robot positions ``(2, N)`` (length), or None without robots.
        has_robots: Whether the plant has robots (``positions`` after ``start``), which
            move by a command's own velocities when it has them.
    """

    density: np.ndarray
    positions: np.ndarray | None
    has_robots: bool

    def start(self, rng: np.random.Generator) -> None:
        """Place the initial state (robots are drawn from ``init`` with ``rng``)."""
        ...

    def advance(
        self, command: Command, a: sp.csr_matrix | None, dt: float, rng: np.random.Generator
    ) -> None:
        """Move over one step of ``dt`` (s) under the held command; ``a`` is ``A(v)``,
        the Fokker-Planck matrix of the command's field ``v`` (None without a field).
        """
        ...

    def measure(self, rng: np.random.Generator) -> Measurement:
        """The measurement at the current time."""
        ...


@runtime_checkable
class Estimator(Protocol):
    """Measurements in, ``(p_hat, q_hat)`` out.

    Attributes:
        uses_kde: Whether it reads the plant's measurement (the loop measures only then).
    """

    uses_kde: bool

    def initialize(self, inp: StepInput) -> Estimate:
        """First estimate, at ``t = 0``."""
        ...

    def step(self, inp: StepInput) -> Estimate:
        """Estimate at a later step."""
        ...


@runtime_checkable
class Control(Protocol):
    """A control law: what it uses in (the estimate, the robots' positions, the time),
    a command out (a velocity field on the grid, one velocity per robot, or both).

    Attributes:
        gives_field: Whether every command has a field. The mean-field plant, the
            agents plant's ``N -> infinity`` limit and the filters' transport model need
            one, and refuse a law without (their ``check``).
        own_estimates: Whether the law moves each robot by the law of the robot's own
            estimate when the estimate carries them (``Estimate.robots``); an estimator
            whose robots estimate on their own refuses a law without.
        needs_robots: Whether the law has no mean-field form: it moves robots and cannot
            act on a density (``ControlInput.density``). The mean-field plant refuses
            it, and the agents plant then has no ``N -> infinity`` limit to carry
            (:class:`harness.plants.agents.Agents`). Optional; false when absent
            (:func:`needs_robots`).
        v_max: The speed cap (length / s) every command is capped at
            (:meth:`harness.records.Command.capped`), or None.
        follows_moving_target: Whether the law follows a moving target, ``p_*(t)`` in
            ``ControlInput.target`` (:mod:`harness.targets.moving`). Optional; false when
            absent, and ``target=moving`` then refuses the law.
    """

    gives_field: bool
    own_estimates: bool

    def __call__(self, inp: ControlInput) -> Command:
        """The command at ``inp.t`` (velocities in length / s)."""
        ...

    def feedback_diffusivity(self, p0: np.ndarray) -> float | None:
        """Largest diffusivity (length^2 / s) the held feedback acts with, for a start
        ``p0``; None when the law has no such bound (the step bound is then not checked,
        and the run says so).
        """
        ...


class MemoryEstimate(NamedTuple):
    """An up-front estimate of the memory a component will hold while running.

    Attributes:
        nbytes: Bytes (an upper estimate: arrays, temporaries and factorisations).
        parameter: The component parameter that sets the size (``"n"`` for robots,
            ``"engine"`` for a filter engine), or ``""`` when only the grid does.
    """

    nbytes: int
    parameter: str = ""


GRID_ARRAYS = 64
"""Grid-sized float64 arrays a component is assumed to hold when it does not say
(:func:`default_memory`): generous for every component in this project."""


def default_memory(grid: Grid) -> MemoryEstimate:
    """The estimate for a component without ``memory_estimate``: :data:`GRID_ARRAYS`
    float64 fields of ``grid`` (and their gradients) plus one sparse LU factorisation
    on the grid (:func:`sparse_lu_bytes`).
    """
    return MemoryEstimate(GRID_ARRAYS * 8 * 3 * grid.size + sparse_lu_bytes(grid.size))


def sparse_lu_bytes(m: int) -> int:
    """Bytes of a sparse LU factorisation (SuperLU, COLAMD) of a 5-point operator on
    ``m`` cells: measured fill ``nnz(L + U) <= 1.2 m^1.5`` for 32^2 to 256^2 cells, at
    12 bytes per entry (value and index) plus the matrix itself.
    """
    return int(12 * (1.2 * m**1.5 + 10 * m))


def memory_estimate(cls: type, grid: Grid, params: dict[str, Any]) -> MemoryEstimate:
    """The estimate of a component class before it is built, from its YAML parameters.

    A class may define ``memory_estimate(grid, **params) -> MemoryEstimate`` (a
    classmethod that ignores the parameters it does not need); otherwise
    :func:`default_memory`.
    """
    method = getattr(cls, "memory_estimate", None)
    if method is None:
        return default_memory(grid)
    return method(grid, **params)
