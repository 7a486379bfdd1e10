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


@runtime_checkable
class Plant(Protocol):
    """What moves under the held command, and what it lets the estimator measure.

    Attributes:
        density: The density ``(ny, nx)`` (1 / length^2) the plant carries: the
            mean-field state (``meanfield``), or the robots' histogram (robots per cell
            over ``N`` times the cell area); the loop measures errors against the
            ``N -> infinity`` limit instead when the run has one
            (:class:`harness.plants.limit.Limit`).
        positions: Robot positions ``(2, N)`` (length), or None without robots.
        has_robots: Whether the plant has robots (``positions`` after ``start``), which
            move by a command's own velocities when it has them.

    Optional members, read through this module: ``observed`` (:func:`observed`),
    ``headings`` (:func:`headings`), ``tracking_error`` and ``command_age``
    (:func:`reported`), ``n`` (:func:`robot_count`), ``link`` (:func:`command_link`),
    ``kde`` (:func:`kernel`), ``resolution`` (:func:`resolution`), ``check``
    (:func:`check_parts`).
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

    Optional members: ``resolution`` (:func:`resolution`), ``check``
    (:func:`check_parts`), ``publishes`` (:func:`publishes`), ``carries``
    (:func:`carries`).
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
            ``N -> infinity`` limit and the filters' transport model need one, and refuse
            a law without (their ``check``).
        own_estimates: Whether the law moves each robot by the law of the robot's own
            estimate when the estimate carries them (``Estimate.robots``); an estimator
            whose robots estimate on their own refuses a law without.

    Optional members, read through this module: ``needs_robots``
    (:func:`needs_robots`), ``follows_moving_target`` (:func:`follows_moving_target`),
    ``alpha``, ``uses`` and ``divides_by_density`` (:func:`law_record`), ``resolution``
    (:func:`resolution`), ``check`` (:func:`check_parts`); the project's laws also take a
    speed cap ``v_max`` (length / s) and return :meth:`harness.records.Command.capped`.
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


@runtime_checkable
class Identity(Protocol):
    """What identifies a run in its log (:class:`harness.runs.identity.RunIdentity`)."""

    def records(self) -> dict[str, dict[str, str]]:
        """The metadata records the log opens with, by name, in order (string values)."""
        ...


# --- optional members ------------------------------------------------------------------


def observed(plant: Plant) -> np.ndarray | None:
    """The robots' positions as the estimator and the law see them: the plant's
    ``observed`` (with its localisation error) when it has one, else its positions.
    """
    return getattr(plant, "observed", plant.positions)


def headings(plant: Plant) -> np.ndarray | None:
    """The robots' headings as unit vectors ``(cos theta, sin theta)``, ``(2, N)``: the
    plant's ``headings``, None for robots without one (or no robots).
    """
    return getattr(plant, "headings", None)


REPORTED = ("tracking_error", "command_age")
"""What a plant with robots may report of the step just taken: ``tracking_error``, the
mean over robots of ``|velocity applied - velocity commanded|`` (length / s), and
``command_age``, the mean age of the held commands (s)."""


def reported(plant: Plant) -> dict[str, float | None]:
    """The plant's :data:`REPORTED` numbers (None for one it does not report)."""
    values = {key: getattr(plant, key, None) for key in REPORTED}
    return {key: None if v is None else float(v) for key, v in values.items()}


def robot_count(plant: Plant) -> int:
    """The number of robots ``N`` of a plant with robots (its ``n``), 0 without robots."""
    return int(getattr(plant, "n", 0) or 0) if plant.has_robots else 0


def command_link(plant: Plant) -> Any:
    """The plant's command link (:class:`harness.plants.link.Link`, its ``link``), or
    None for a plant without one.
    """
    return getattr(plant, "link", None)


def kernel(plant: Plant) -> tuple[float, bool] | None:
    """The bandwidth ``h`` (length) and wall images of the KDE that measures the plant
    (its ``kde``, a :class:`harness.estimators.kde.KDE`), or None when none does.
    """
    kde = getattr(plant, "kde", None)
    return None if kde is None else (float(kde.bandwidth), bool(kde.mirror))


def publishes(estimator: Estimator) -> tuple[str, ...]:
    """The metric names ``estimator`` puts in every estimate's ``Estimate.metrics`` (its
    optional ``publishes``: the decentralised loop's network metrics); none when it
    does not say, so a guard may require them only of an estimator that publishes them.
    """
    return tuple(str(name) for name in getattr(estimator, "publishes", None) or ())


CARRIED = ("traces", "reference")
"""What an estimate may hold besides ``(p_hat, q_hat)`` (:func:`carries`): the filters'
covariance traces (``Estimate.trace_P`` ...), and per robot the centralised reference's
estimate (``RobotEstimates``' reference, from which a command's ``reference`` comes)."""


def carries(estimator: Estimator) -> frozenset[str]:
    """Which of :data:`CARRIED` every estimate of ``estimator`` holds (its optional
    ``carries``); none when it does not say, so a guard may require the metrics made
    from them (``trace_P`` ..., ``command_disagreement``) only of an estimator that says.
    """
    return frozenset(str(c) for c in getattr(estimator, "carries", None) or ())


def carries_traces(estimator: Estimator) -> bool:
    """Whether every estimate of ``estimator`` holds the filters' covariance traces."""
    return CARRIED[0] in carries(estimator)


def carries_reference(estimator: Estimator) -> bool:
    """Whether every estimate of ``estimator`` holds, per robot, the centralised
    reference's estimate (so each command has its ``reference``).
    """
    return CARRIED[1] in carries(estimator)


def on_free_space(part: object) -> bool:
    """Whether ``part`` honours a domain with obstacles (its optional ``free_space``):
    it reads free space from the model or the target it is built with
    (:class:`harness.domains.base.FreeSpace`) and never puts robots, mass or velocity
    through an obstacle. A part that does not say runs only on the plain square, and
    the builder refuses it on another domain.
    """
    return bool(getattr(part, "free_space", False))


def resolution(part: object) -> Any:
    """A component's optional ``resolution``: for a plant the smallest length its
    measurement resolves (None: the grid's); for an estimator a function of the
    measurement's resolution; for a law the smallest length its feedback resolves.
    """
    return getattr(part, "resolution", None)


SHARED_QUANTITIES = {
    "robots": ("agents.n", "", "the swarm's size"),
    "dt": ("sim.dt", " s", "the loop's step"),
}
"""The quantities a component may hold a copy of (:func:`copies`), each with the shared
key that sets it for the whole run, its unit and what it is."""


def copies(part: object) -> dict[str, tuple[str, float]]:
    """What ``part`` holds of the run's :data:`SHARED_QUANTITIES` (its optional ``copies``):
    ``{parameter: (quantity, value)}``, such as ``{"robots": ("robots", 1024)}`` for a
    filter whose noise constants are those of ``N`` robots, or ``{"dt": ("dt", 0.01)}``
    for a link that counts its period in steps. The builder refuses a copy that differs
    from the run's own value (an override of ``estimator.robots`` alone): the component
    would compute with one number while the log says another.
    """
    return dict(getattr(part, "copies", None) or {})


def period(control: Control) -> float | None:
    """The time (s) between the decisions of a law that decides once per period (its
    optional ``period``: ``psg``, ``psg_feedback``, ``ot``), None for a law that decides
    every step; it must be a whole number of the loop's steps.
    """
    value = getattr(control, "period", None)
    return None if value is None else float(value)


def needs_robots(control: Control) -> bool:
    """Whether ``control`` has no mean-field form (its optional ``needs_robots``): it
    moves robots and cannot act on a density, so the mean-field plant refuses it and a
    run with robots has no ``N -> infinity`` limit.
    """
    return bool(getattr(control, "needs_robots", False))


def follows_moving_target(control: Control) -> bool:
    """Whether ``control`` follows a moving target ``p_*(t)`` (its optional
    ``follows_moving_target``); ``target=moving`` refuses a law that does not.
    """
    return bool(getattr(control, "follows_moving_target", False))


def law_record(control: Control) -> dict[str, Any]:
    """What a law says of itself for the log's ``theory`` record: its gain ``alpha``
    (a float, length^4 / s), ``uses`` (a phrase such as ``"estimate, gradient
    estimate"``) and ``divides_by_density`` (a bool), each when the law has it.
    """
    out = {}
    for name, kind in (("alpha", float), ("uses", str), ("divides_by_density", bool)):
        value = getattr(control, name, None)
        if isinstance(value, kind):
            out[name] = value
    return out


def check_parts(plant: Plant, estimator: Estimator, control: Control) -> None:
    """Each component's own optional ``check(plant=..., estimator=..., control=...)`` of
    the others, in that order; raises :class:`~harness.parameters.Incompatible`.
    """
    for part in (plant, estimator, control):
        check = getattr(part, "check", None)
        if check is not None:
            check(plant=plant, estimator=estimator, control=control)


def require_field(control: Control, where: str) -> None:
    """Raise :class:`~harness.parameters.Incompatible` naming ``control`` unless the law
    gives a velocity field (``gives_field``); ``where`` says who needs it and why
    (``"on plant=meanfield (the density moves by it)"``).
    """
    if not control.gives_field:
        raise Incompatible(
            "control", type(control).__name__, f"a law with a velocity field {where}"
        )


def refuse_robot_law(control: Control, where: str) -> None:
    """Raise :class:`~harness.parameters.Incompatible` naming ``control`` when it needs
    robots (:func:`needs_robots`); ``where`` says who cannot give them.
    """
    if needs_robots(control):
        raise Incompatible(
            "control", type(control).__name__, f"a law with a mean-field form {where}"
        )


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
