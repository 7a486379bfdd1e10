"""How much the robots move: the per-step cost of a law (observer ``motion``).

For the command ``u_n`` computed at ``t_n`` (held over the next step) and the robots'
true positions ``X_k`` at ``t_n``, with ``v_k`` the velocity robot ``k`` is commanded
(its own velocity when the command has one, else the bilinear interpolant of the
field's cell centres at ``X_k``, as the robots move, :func:`harness.velocity.interpolate`):

    effort     = (1/N) sum_k |v_k|^2     (length^2 / s^2)
    mean_speed = (1/N) sum_k |v_k|       (length / s)
    peak_speed = max_k |v_k|             (length / s)

The commanded velocity, not the realised one: the robots' noise ``sqrt(2 sigma) dB`` is
not part of it. A law that steers each robot to a waypoint (:mod:`harness.control.waypoints`)
sends a robot back over the noise's displacement within the time left in its period, so
its motion counts that correction: about ``1.25 (pi / 2) sqrt(2 sigma / T)`` in mean
speed for a robot that holds (0.020 length / s at ``T`` = 1 s and ``sigma`` = 5e-5), and
an effort that grows like ``log(T / dt)`` from the last steps of each period. Without
robots (``plant=meanfield``) the means are over the mean-field
density ``p`` instead, ``int p |v|^2`` and ``int p |v|`` on the cell centres, and the
peak is over the cells where ``p > 0``.

With robots the observer also reports what the plant says of the step just taken
(:class:`harness.plants.agents.Agents`): ``tracking_error``, the mean over robots of
``|velocity applied - velocity commanded|`` (length / s; 0 for ideal integrators), and
``command_age``, the mean age of the commands the robots hold (s, the link,
:class:`harness.plants.link.Link`); ``null`` before the first step and without robots.

In the decentralised loop (``estimator=distributed``) it reports the law's disagreement,
``command_disagreement`` = ``(1/N) sum_k |v_k - v_ref,k|`` (length / s): robot ``k``'s
own command against the command the law gives at ``X_k`` from the centralised
reference's estimate (with the robots' own central differences of ``p_hat_central``),
:func:`command_disagreement`;
``null`` in every other loop.

:mod:`analysis.sweep` integrates ``effort`` over time (length^2 / s) and averages
``mean_speed`` over the tail (motion at steady state).
"""

from __future__ import annotations

import numpy as np

from harness.compiled.agents import speed_sums
from harness.grid import Grid
from harness.observers.base import RunContext, Status
from harness.protocols import REPORTED, Estimator, Plant, carries_reference, reported
from harness.records import StepRecord
from harness.velocity import interpolate

MOTION_KEYS = ("effort", "mean_speed", "peak_speed")
"""The motion metrics, in log order."""


ROBOT_KEYS = REPORTED
"""What the plant reports of the step just taken (:data:`harness.protocols.REPORTED`),
in log order."""


DISAGREEMENT_KEY = "command_disagreement"
"""The decentralised loop's command disagreement (module docstring)."""


def command_disagreement(rec: StepRecord) -> float | None:
    """Mean over robots of ``|v_i - v_ref(X_i)|`` (length / s): each robot's own command
    against the command the law gives at its position from the centralised reference's
    estimate (:attr:`harness.records.Command.reference`); None without one.
    """
    command = rec.command
    if command.robots is None or command.reference is None:
        return None
    d = command.robots - command.reference
    return float(np.mean(np.hypot(d[0], d[1])))


def speed_sums_reference(
    grid: Grid, centres: np.ndarray, positions: np.ndarray
) -> tuple[float, float, float]:
    """Numpy statement of :func:`harness.compiled.agents.speed_sums`."""
    speed = np.hypot(*interpolate(grid, centres, positions))
    return float(np.sum(speed**2)), float(speed.max()), float(speed.sum())


def motion(grid: Grid, rec: StepRecord) -> dict[str, float | None]:
    """The motion metrics of ``rec`` (module docstring)."""
    command, x = rec.command, rec.positions
    if x is not None:
        n = x.shape[1]
        if command.robots is not None:
            speed = np.hypot(command.robots[0], command.robots[1])
            sq, peak, total = float(np.dot(speed, speed)), float(speed.max()), float(speed.sum())
        else:
            assert command.field is not None
            g = grid
            centres = np.ascontiguousarray(command.field.centres, dtype=float)
            sq, peak, total = speed_sums(
                np.ascontiguousarray(x, dtype=float), centres,
                g.x0, g.x1, g.y0, g.y1, g.nx, g.ny,
            )  # fmt: skip
        return {"effort": sq / n, "mean_speed": total / n, "peak_speed": peak}
    if command.field is None:
        return dict.fromkeys(MOTION_KEYS)
    p = np.maximum(rec.p_true, 0.0)
    speed = np.hypot(*command.field.centres)
    mass = grid.integrate(p)
    return {
        "effort": grid.integrate(p * speed**2) / mass,
        "mean_speed": grid.integrate(p * speed) / mass,
        "peak_speed": float(speed[p > 0].max()) if (p > 0).any() else 0.0,
    }


class Motion:
    """The motion metrics of every step (:func:`motion`; observer ``motion``).

    Args:
        grid: The grid (run-time argument).
        plant: The plant (run-time argument), whose ``tracking_error`` and
            ``command_age`` are reported when it has them.
        estimator: The run's estimator (run-time argument). What this observer gives at
            every step (``gives``): the motion metrics, and ``command_disagreement``
            when the estimator's estimates carry the centralised reference
            (:func:`harness.protocols.carries`). The plant's numbers come only from its
            first move on (None at the start), so they are never promised at every step.
    """

    computes = True  # adds to the step's values, writes nothing (harness.api.simulate)

    def __init__(self, grid: Grid, plant: Plant, estimator: Estimator | None = None) -> None:
        self.grid = grid
        self.plant = plant
        reference = estimator is not None and carries_reference(estimator)
        self.gives: tuple[str, ...] = (*MOTION_KEYS, *((DISAGREEMENT_KEY,) if reference else ()))

    def initialize(self, run: RunContext) -> None:
        """Nothing to prepare."""

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """The step's motion metrics."""
        values.update(motion(self.grid, rec))
        values[DISAGREEMENT_KEY] = command_disagreement(rec)
        values.update(reported(self.plant))

    def finalize(self, status: Status) -> None:
        """Nothing to close."""
