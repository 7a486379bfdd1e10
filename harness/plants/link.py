"""The command link between the law and the robots (config block ``link``, read by
every plant with robots).

The law computes a command ``u_n`` at every step ``t_n = n dt``. The link

* broadcasts it every ``period`` seconds (``P = period / dt`` steps: at the steps
  ``n`` with ``n mod P = 0``), and nothing in between;
* delivers a broadcast ``latency`` seconds later (``L = latency / dt`` steps: the
  broadcast of step ``n`` arrives at step ``n + L``);
* loses it, at each robot independently, with probability ``loss`` (draws from the
  link's own stream ``[seed, 5]``, so the robots' noise is that of the lossless run).

A robot keeps the last command it received and applies it over every step until the
next one reaches it: over ``[t_m, t_{m+1}]`` robot ``k`` moves by the command of the
broadcast it last received at or before step ``m`` (a field is evaluated at the robot's
position at ``t_m``, as for the ideal link). A robot that has received nothing yet holds
zero velocity, aged from ``t = 0``.

The ideal link (``period = dt``, ``latency = 0``, ``loss = 0``, the defaults) is the
identity: every robot applies ``u_n`` over ``[t_n, t_{n+1}]``, no draw is made, and
the plant moves the robots by the code path of a run without a link (the same bits).

Per step the link reports the commands' age: the mean over robots of ``t_m`` minus the
time the held command was computed (s). Without loss it is ``(L + (P - 1) / 2) dt`` on
average over a period once the first broadcast has arrived.

Period and latency must be whole numbers of steps: a value that is not (within a
relative ``1e-9``) is refused rather than rounded.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from harness.compiled.robots import interpolate_robots
from harness.grid import Grid
from harness.parameters import ParameterError, number, require
from harness.records import Command
from harness.velocity import VelocityField


def command_link(
    period: float | None, latency: float, loss: float, dt: float | None, seed: int
) -> Link:
    """The plant's command link (:class:`harness.plants.link.Link`; ``period`` None: every
    step), its refusals named by the plant's keys (``link_period``, ...). Without ``dt``
    only the ideal link is possible.
    """
    if dt is None:
        ideal = period is None and latency == 0 and loss == 0
        require(ideal, "dt", dt, "the step sim.dt, for a link that is not ideal")
    step = 1.0 if dt is None else dt
    try:
        return Link(step if period is None else period, latency, loss, step, seed)
    except ParameterError as err:
        name = "dt" if err.name == "dt" else f"link_{err.name}"
        raise ParameterError(name, err.value, err.allowed) from None


def whole_steps(name: str, value: float, dt: float, low: int) -> int:
    """``value / dt`` as an integer ``>= low``; refuse a value that is not a whole
    number of steps (relative ``1e-9``) or not finite.
    """
    seconds = number(name, value, 0.0)
    steps = seconds / dt
    k = round(steps)
    require(
        abs(steps - k) <= 1e-9 * max(1.0, abs(steps)) and k >= low,
        name, value,
        f"a whole number of steps of sim.dt = {dt:g} s, at least {low * dt:g} s",
    )  # fmt: skip
    return int(k)


def copied(command: Command) -> Command:
    """A copy of ``command``'s arrays."""
    v = command.field
    field = None if v is None else VelocityField(v.centres.copy(), v.face_x.copy(), v.face_y.copy())
    return Command(field, None if command.robots is None else command.robots.copy())


@dataclass(frozen=True)
class Broadcast:
    """A command on its way: computed at step ``sent``, arriving at step ``arrives``."""

    sent: int
    arrives: int
    command: Command


class Link:
    """Broadcast, latency and loss between the law and the robots (module docstring).

    Args:
        period: Time between broadcasts (s), a whole number ``>= 1`` of steps.
        latency: Delay from broadcast to arrival (s), a whole number ``>= 0`` of steps.
        loss: Probability that a robot misses a broadcast, ``0 <= loss < 1``.
        dt: The step (s).
        seed: The run's seed (the loss draws' stream ``[seed, 5]``).
    """

    def __init__(
        self, period: float, latency: float, loss: float, dt: float, seed: int = 0
    ) -> None:
        self.dt = number("dt", dt, 0.0, strict=True)
        self.period_steps = whole_steps("period", period, self.dt, 1)
        self.latency_steps = whole_steps("latency", latency, self.dt, 0)
        self.loss = number("loss", loss, 0.0)
        require(self.loss < 1, "loss", loss, "a probability below 1")
        self.seed = int(seed)
        self.ideal = self.period_steps == 1 and self.latency_steps == 0 and self.loss == 0
        self.start(0)

    def start(self, n: int) -> None:
        """Reset for ``n`` robots: nothing sent, nothing held, the stream restarted."""
        self.n = n
        self._rng = np.random.default_rng([self.seed, 5])
        self._queue: deque[Broadcast] = deque()
        self.held = np.full(n, -1, dtype=np.int64)  # step of the held broadcast, -1: none
        self._commands: dict[int, Command] = {}
        self._count: dict[int, int] = {-1: n}
        self.step = 0
        self.sent = 0  # broadcasts sent
        self.delivered = 0  # deliveries attempted (robots x arrived broadcasts), lost ones included
        self.missed = 0  # of those, lost

    def transmit(self, command: Command, step: int) -> None:
        """The law's command of step ``step``: broadcast it when the step is a
        broadcast step, then deliver what arrives at this step.
        """
        self.step = step
        if step % self.period_steps == 0:
            if not self.ideal:  # held for steps: a copy the law cannot overwrite
                command = copied(command)
            self._queue.append(Broadcast(step, step + self.latency_steps, command))
            self.sent += 1
        while self._queue and self._queue[0].arrives <= step:
            self._deliver(self._queue.popleft())

    def _deliver(self, b: Broadcast) -> None:
        if self.loss > 0:
            got = self._rng.random(self.n) >= self.loss
            self.missed += int(self.n - np.count_nonzero(got))
            self.held[got] = b.sent
            counts = np.bincount(self.held + 1)  # held >= -1; index 0 counts "none"
            self._count = {int(k) - 1: int(counts[k]) for k in np.flatnonzero(counts)}
        else:
            self.held[:] = b.sent
            self._count = {b.sent: self.n}
        self.delivered += self.n
        self._commands[b.sent] = b.command
        self._commands = {k: c for k, c in self._commands.items() if k in self._count}

    def common_field(self) -> VelocityField | None:
        """The field every robot holds, when they all hold one command that is a field
        without velocities of its own; else None.
        """
        if len(self._count) != 1 or -1 in self._count:
            return None
        command = self._commands[next(iter(self._count))]
        return command.field if command.robots is None else None

    def velocities(self, positions: np.ndarray, grid: Grid) -> np.ndarray:
        """Each robot's commanded velocity ``(2, N)`` (length / s) at its position
        ``(2, N)`` (length) under the command it holds (zero for none).
        """
        g = grid
        if len(self._count) == 1 and -1 not in self._count:  # one command for all
            command = self._commands[next(iter(self._count))]
            if command.robots is not None:
                return command.robots
            assert command.field is not None
            values = np.empty((2, self.n))
            centres = np.ascontiguousarray(command.field.centres, dtype=float)
            interpolate_robots(
                np.ascontiguousarray(positions, dtype=float), centres, values,
                g.x0, g.x1, g.y0, g.y1, g.nx, g.ny,
            )  # fmt: skip
            return values
        out = np.zeros((2, self.n))
        for k in self._count:
            if k < 0:
                continue
            command = self._commands[k]
            sel = slice(None) if len(self._count) == 1 else np.flatnonzero(self.held == k)
            if command.robots is not None:
                out[:, sel] = command.robots[:, sel]
                continue
            assert command.field is not None
            at = np.ascontiguousarray(positions[:, sel], dtype=float)
            values = np.empty_like(at)
            centres = np.ascontiguousarray(command.field.centres, dtype=float)
            interpolate_robots(at, centres, values, g.x0, g.x1, g.y0, g.y1, g.nx, g.ny)
            out[:, sel] = values
        return out

    @property
    def age(self) -> float:
        """Mean over robots of the held command's age at the current step (s)."""
        total = sum((self.step - max(k, 0)) * c for k, c in self._count.items())
        return total * self.dt / self.n if self.n else 0.0
