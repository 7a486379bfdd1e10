"""How much a run log may hold, so a forged one cannot make its reader allocate without
bound (:class:`Limits`, used by :func:`analysis.load.load_run`).

A log's own ``config`` record says how many robots and steps the run had: no topic has
more messages than steps (and the target's first), no positions or poses message more
points than robots. The record is as forgeable as the rest of the file, so the log's
size bounds it too, always: no more robot points in all than
:data:`POINTS_PER_FILE_BYTE` per byte of the file, whatever the record claims, and no
more bytes decompressed from its chunks than :data:`DECODED_PER_FILE_BYTE` per byte of
the file (beyond :data:`DECODED_FLOOR`), whatever a chunk's header declares. Messages
and chunks beyond a bound are counted and never decoded.
"""

from __future__ import annotations

import math

import yaml

from analysis.safe_yaml import ConfigRecordError, safe_config

ROBOT_TOPICS = ("/swarm/positions", "/swarm/poses")
"""The topics that carry one point per robot."""

MAX_BYTES_PER_ROBOT = 128
"""Most bytes one robot takes in a positions or poses message (a pose with every value
explicit takes 69), for the size check before a message is parsed."""

POINTS_PER_FILE_BYTE = 4
"""Most robot points read in all per byte of a log, whatever its config record says (a
log's own positions take several bytes each, compressed)."""


DECODED_PER_FILE_BYTE = 64
"""Most bytes decompressed from a log's chunks per byte of the file, in all, beyond
:data:`DECODED_FLOOR` (a run's own log decompresses to a few times its size: positions
and fields are floats that compress little)."""

DECODED_FLOOR = 64 << 20
"""Bytes any log may decompress whatever its size (a chunk of a small log holds up to
the writer's 1 MiB and one message)."""


class Limits:
    """How much a log may hold, from its ``config`` record (the number of robots and of
    steps) and from its size (the smaller bound wins); what was beyond them is counted,
    never decoded.

    Args:
        size: The log's size in bytes.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.robots: int | None = None
        self.messages: int | None = None  # per topic: one per step at most, and p_target
        self.seen: dict[str, int] = {}
        self.points = 0
        self.decoded = 0
        self.beyond: dict[str, int] = {}

    def configure(self, text: str) -> None:
        """Take the number of robots (``agents.n``, ``plant.n``) and of steps
        (``sim.t_final / sim.dt``) from the ``config`` record's YAML ``text``; a record
        that does not say leaves the bound by the file's size.
        """
        try:
            cfg = safe_config(text)
        except (ConfigRecordError, yaml.YAMLError):
            return
        if not isinstance(cfg, dict):
            return

        def number(block: str, key: str) -> float | None:
            node = cfg.get(block)
            return _positive(node.get(key) if isinstance(node, dict) else None)

        robots = [n for n in (number("agents", "n"), number("plant", "n")) if n is not None]
        self.robots = int(max(robots)) if robots else None
        t_final, dt = number("sim", "t_final"), number("sim", "dt")
        if t_final is not None and dt is not None and t_final / dt < 1e12:
            self.messages = math.ceil(t_final / dt * (1 + 1e-9)) + 2

    def admit(self, topic: str) -> bool:
        """Whether one more message on ``topic`` is within the log's steps; one beyond
        is counted and not decoded.
        """
        self.seen[topic] = self.seen.get(topic, 0) + 1
        if self.messages is not None and self.seen[topic] > self.messages:
            self._beyond(f"{topic} messages beyond its {self.messages} steps")
            return False
        return True

    def unpack(self, declared: int, content: int | None) -> bool:
        """Whether a chunk may be decompressed: what it declares (``declared``, its
        header's uncompressed size, and ``content``, the size its compressed frame
        declares when it does) fits in :data:`DECODED_PER_FILE_BYTE` bytes per byte of
        the file beyond :data:`DECODED_FLOOR`, less what earlier chunks took; one beyond
        is counted and not decompressed.
        """
        size = max(declared, content or 0)
        if self.decoded + size > DECODED_FLOOR + DECODED_PER_FILE_BYTE * self.size:
            self._beyond(f"chunks beyond {DECODED_PER_FILE_BYTE} decompressed bytes per byte")
            return False
        self.decoded += size
        return True

    @property
    def left(self) -> int:
        """Robot points the file's size still allows (:data:`POINTS_PER_FILE_BYTE` per
        byte in all, less those kept).
        """
        return max(POINTS_PER_FILE_BYTE * self.size - self.points, 0)

    def room(self, topic: str, size: int) -> bool:
        """Whether a robots message of ``size`` bytes may be parsed: at most
        :data:`MAX_BYTES_PER_ROBOT` per point it may hold, the fewer of the config's
        robots and the points the file's size still allows (:attr:`left`).
        """
        if self.robots is not None and self.robots <= self.left:
            if size > MAX_BYTES_PER_ROBOT * self.robots + 4096:
                self._beyond(f"{topic} messages too large for {self.robots} robots")
                return False
        elif size > MAX_BYTES_PER_ROBOT * self.left + 4096:
            self._beyond(f"{topic} messages beyond {POINTS_PER_FILE_BYTE} points per byte")
            return False
        return True

    def take(self, topic: str, points: int) -> bool:
        """Whether a robots message of ``points`` points is kept: at most one point per
        robot of the config, and no more than :data:`POINTS_PER_FILE_BYTE` points per
        byte of the file in all (:attr:`left`).
        """
        if self.robots is not None and points > self.robots:
            self._beyond(f"{topic} messages of more than {self.robots} robots")
            return False
        if points > self.left:
            self._beyond(f"{topic} messages beyond {POINTS_PER_FILE_BYTE} points per byte")
            return False
        self.points += points
        return True

    def _beyond(self, what: str) -> None:
        self.beyond[what] = self.beyond.get(what, 0) + 1

    def summary(self) -> str | None:
        """What was beyond the limits, in words; None when nothing was."""
        if not self.beyond:
            return None
        parts = ", ".join(f"{n} {what}" for what, n in sorted(self.beyond.items()))
        return f"more than the log's config and size allow, not read: {parts}"


def _positive(value: object) -> float | None:
    """``value`` as a float when it is a finite number above 0 (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        x = float(value)
    except OverflowError:
        return None
    return x if math.isfinite(x) and x > 0 else None
