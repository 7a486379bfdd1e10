"""The MCAP log of a run: the contract analysis scripts and users rely on.

File ``run.mcap`` (zstd chunks). ``log_time`` and ``publish_time`` are the
simulated time in integer nanoseconds (``round(t * 1e9)``), so reruns give identical
files apart from the provenance record.

Topics (a topic that does not apply to the plant or estimator is absent):

* ``/fields/p_target`` (at t = 0; for a moving target also ``p_*(t)`` at the field
  rate), ``/fields/p_true``, ``/fields/p_kde``, ``/fields/p_hat``: ``foxglove.Grid``
  with one float32 field ``p`` (1 / length^2);
* ``/fields/<name>`` for each density field an estimator publishes
  (``Estimate.fields``, field ``p``, 1 / length^2): with ``estimator=distributed``
  ``/fields/p_hat`` is the robots' mean estimate and the estimator publishes two more
  (:data:`harness.estimators.distributed.metrics.FIELD_NAMES`);
* ``/fields/grad_kde``, ``/fields/grad_hat``: fields ``gx``, ``gy`` (1 / length^3);
* ``/fields/velocity``: fields ``vx``, ``vy`` (length / s), the cell-centre values;
* ``/swarm/positions``: ``foxglove.PointCloud`` with float32 ``x, y, z`` (z = 0);
* ``/swarm/poses`` (robots with a heading, ``plant=unicycles``):
  ``foxglove.PosesInFrame``, each robot's position ``(x, y, 0)`` (length) and heading
  ``theta`` (rad) as the rotation ``theta`` about z, at the positions' rate;
* ``/metrics``: JSON (schema encoding ``jsonschema``, :data:`METRICS_SCHEMA`), one
  message per step, the keys of :data:`METRIC_KEYS` in that order (``null`` where not
  applicable; the schema types every key as ``"number"``, see there); on a domain with
  obstacles followed by :func:`harness.observers.swarm.domain_keys`
  (``component_fraction_gap``, ``component_fraction_<c>``, ``start_fraction``,
  ``start_target_mass``);
* on a domain with obstacles only (``target.free``), once at t = 0:
  ``/domain/mask``, a ``foxglove.Grid`` on the control grid with one uint8 field
  ``free`` (1 on a free cell, 0 on a blocked one), and ``/domain/obstacles``, a
  ``foxglove.SceneUpdate`` with one entity ``obstacles`` in frame ``world``: grey flat
  cubes (``z`` from 0 to :data:`OBSTACLE_HEIGHT`) covering the blocked squares of the
  robots' raster, merged into rectangles (:func:`obstacle_rectangles`);

Grids follow ``foxglove.Grid``: ``column_count = nx`` cells along x, rows along y
starting at the pose origin ``(x0, y0, 0)``, ``cell_size = (dx, dy)``, little-endian
float32 values interleaved per cell, frame ``world``. Field messages every
``field_every`` steps (and at the last step), positions every ``positions_every``.

Metadata records: ``domain`` (on a domain with obstacles only, :func:`domain_record`:
``n_components``, ``component_mass``, the target's mass in each connected component of
free space as a JSON list, ``free_cells``, ``free_area``, ``raster``), ``config`` (key
``yaml``: the resolved config), ``choices`` (Hydra's
choices: the option of each config group, ``plant: agents``, ``control: paper``, as the
command line or :func:`harness.api.compose` chose them), ``provenance``
(git commit and dirty flag, ``git_diff_sha256`` of the uncommitted code, package
versions, Python version, ``code_sha256`` of all of these
(:func:`harness.runs.identity.provenance`), seed, host, start time; the only wall-clock
values in the file), ``theory`` (``poincare_lambda``, the
``p_*``-weighted Poincare constant on the grid in 1 / length^2, and ``rate_exact`` =
``(alpha + sigma) lambda`` in 1 / s, the decay rate with exact estimates) and
``status`` (key ``state``: ``completed`` | ``aborted`` | ``diverged``, key
``reason``, key ``wall_s``: the run's wall time in s), written just before the
file is finished. :meth:`McapLogger.finalize` always runs (the run calls every
observer's in a ``finally`` block), so the summary and index are written also after an
exception.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from foxglove_schemas_protobuf.Grid_pb2 import Grid as GridMsg
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema

from harness.domains.base import FreeSpace
from harness.estimators.distributed.metrics import NETWORK_KEYS
from harness.grid import Grid
from harness.observers.base import Cadence, RunContext, Status
from harness.observers.metrics import FIELD_KEYS
from harness.observers.motion import DISAGREEMENT_KEY, MOTION_KEYS, ROBOT_KEYS
from harness.observers.swarm import SWARM_KEYS, domain_keys
from harness.parameters import integer
from harness.protocols import Identity
from harness.records import StepRecord
from harness.targets.densities import Target
from harness.targets.moving import TargetPath

if TYPE_CHECKING:
    from harness.observers.live import LiveServer


LOG_FILE = "run.mcap"
"""The log's file name in the run directory."""


METRIC_KEYS = (
    FIELD_KEYS + SWARM_KEYS + MOTION_KEYS + ROBOT_KEYS + (DISAGREEMENT_KEY,) + NETWORK_KEYS
)
"""The keys of every ``/metrics`` message, in log order, as the modules that compute them
declare them: the field metrics (:data:`harness.observers.metrics.FIELD_KEYS`), the
swarm metrics (:data:`harness.observers.swarm.SWARM_KEYS`), the motion metrics and what
the plant reports (:mod:`harness.observers.motion`), and the numbers the decentralised
estimator publishes (:data:`harness.estimators.distributed.metrics.NETWORK_KEYS`). A key
no observer gave is ``null``."""


ALWAYS_NUMBERS = ("t", "phi_l2", "phat_target_l2", "eps_l2", "eps_g_l2", "lyapunov", "mass")
"""Keys that are never null (the divergence guard's default)."""


MISSING_VALUE = "null where not applicable"
"""How the schema describes a key that may be missing (JSON ``null``)."""


def metrics_schema(keys: tuple[str, ...]) -> dict[str, Any]:
    """The ``/metrics`` JSON schema of messages holding ``keys`` (:data:`METRICS_SCHEMA`)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "densityloop.Metrics",
        "description": (
            "Per-step metrics of a densityloop run; units in the README. Every key is "
            "written; a key whose description says so is null where not applicable."
        ),
        "type": "object",
        "properties": {
            key: {"type": "number"}
            if key in ALWAYS_NUMBERS
            else {"type": "number", "description": MISSING_VALUE}
            for key in keys
        },
        "required": list(keys),
    }


METRICS_SCHEMA = metrics_schema(METRIC_KEYS)
"""The ``/metrics`` JSON schema (on a domain with obstacles, :func:`metrics_schema` of
:data:`METRIC_KEYS` followed by :func:`harness.observers.swarm.domain_keys`). Each
property has the single type ``"number"``:
Foxglove-protocol viewers (Foxglove Studio 1.x, Lichtblick) read a property's ``type``
as one string and drop the whole channel for a type array such as
``["number", "null"]``. A missing value is still JSON ``null`` (the keys other than
:data:`ALWAYS_NUMBERS`, marked by their ``description``); the viewers parse the message
without validating it, so a Plot panel leaves the step out and Raw Messages shows
``null``. A strict JSON Schema validator flags those nulls: the contract is "a number, or
null for a key that may be missing"."""


FIELD_TOPICS = {
    "/fields/p_true": ("p",),
    "/fields/p_kde": ("p",),
    "/fields/p_hat": ("p",),
    "/fields/grad_kde": ("gx", "gy"),
    "/fields/grad_hat": ("gx", "gy"),
    "/fields/velocity": ("vx", "vy"),
    "/fields/p_target": ("p",),
}
"""The value names of each field topic the log writes itself; a field an estimator
publishes (``/fields/<name>``, ``Estimate.fields``) is a density (``p``)."""


def time_ns(t: float) -> int:
    """Simulated time ``t`` (s) as integer nanoseconds."""
    return round(t * 1e9)


def grid_message(grid: Grid, t: float, names: tuple[str, ...], values: np.ndarray) -> GridMsg:
    """A ``foxglove.Grid`` holding ``values`` (shape ``(len(names), ny, nx)``) as float32."""
    msg = GridMsg()
    ns = time_ns(t)
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)
    msg.frame_id = "world"
    msg.pose.position.x, msg.pose.position.y = grid.x0, grid.y0
    msg.pose.orientation.w = 1.0
    msg.column_count = grid.nx
    msg.cell_size.x, msg.cell_size.y = grid.dx, grid.dy
    k = len(names)
    msg.cell_stride = 4 * k
    msg.row_stride = 4 * k * grid.nx
    for i, name in enumerate(names):
        msg.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
    data = np.ascontiguousarray(np.moveaxis(values.reshape(k, grid.ny, grid.nx), 0, -1), "<f4")
    msg.data = data.tobytes()
    return msg


def points_message(t: float, positions: np.ndarray) -> PointCloud:
    """A ``foxglove.PointCloud`` of the robots (float32 x, y, z = 0)."""
    msg = PointCloud()
    ns = time_ns(t)
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(ns, 1_000_000_000)
    msg.frame_id = "world"
    msg.pose.orientation.w = 1.0
    msg.point_stride = 12
    for i, name in enumerate("xyz"):
        msg.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
    pts = np.zeros((positions.shape[1], 3), dtype="<f4")
    pts[:, 0], pts[:, 1] = positions[0], positions[1]
    msg.data = pts.tobytes()
    return msg


POSE_RECORD = np.dtype(
    {
        "names": ["tag", "size", "p_tag", "p_size", "x_tag", "x", "y_tag", "y", "z_tag",
                  "z", "q_tag", "q_size", "qx_tag", "qx", "qy_tag", "qy", "qz_tag", "qz",
                  "qw_tag", "qw"],
        "formats": ["u1", "u1", "u1", "u1", "u1", "<f8", "u1", "<f8", "u1", "<f8",
                    "u1", "u1", "u1", "<f8", "u1", "<f8", "u1", "<f8", "u1", "<f8"],
        "offsets": [0, 1, 2, 3, 4, 5, 13, 14, 22, 23, 31, 32, 33, 34, 42, 43, 51, 52, 60, 61],
        "itemsize": 69,
    }
)  # fmt: skip
"""One entry of ``PosesInFrame.poses`` in protobuf's wire format: field 3 (length 67)
holding a ``Pose`` whose ``position`` (field 1, length 27: ``x``, ``y``, ``z`` as fixed64
fields 1 to 3) and ``orientation`` (field 2, length 36: ``x``, ``y``, ``z``, ``w`` as
fixed64 fields 1 to 4) carry every value explicitly."""


def poses_message(t: float, positions: np.ndarray, headings: np.ndarray) -> bytes:
    """A serialised ``foxglove.PosesInFrame`` of the robots: position ``(x, y, 0)``
    and the heading ``e(theta) = (cos theta, sin theta)`` (``headings``, ``(2, N)``) as
    the rotation ``theta = atan2(sin theta, cos theta)`` (in ``[-pi, pi]``) about z,
    quaternion ``(0, 0, sin(theta / 2), cos(theta / 2))``.

    The poses are written as packed records (:data:`POSE_RECORD`) after the serialised
    header (time, frame): protobuf parses concatenated messages as one, appending the
    repeated field, so the bytes parse to the message the protobuf API would build
    (building ``N`` Python pose objects would cost seconds at a million robots).
    """
    head = PosesInFrame()
    head.timestamp.seconds, head.timestamp.nanos = divmod(time_ns(t), 1_000_000_000)
    head.frame_id = "world"
    rec = np.zeros(positions.shape[1], dtype=POSE_RECORD)
    rec["tag"], rec["size"] = 0x1A, 67
    rec["p_tag"], rec["p_size"], rec["q_tag"], rec["q_size"] = 0x0A, 27, 0x12, 36
    rec["x_tag"], rec["y_tag"], rec["z_tag"] = 0x09, 0x11, 0x19
    rec["qx_tag"], rec["qy_tag"], rec["qz_tag"], rec["qw_tag"] = 0x09, 0x11, 0x19, 0x21
    rec["x"], rec["y"] = positions[0], positions[1]
    half = 0.5 * np.arctan2(headings[1], headings[0])
    rec["qz"], rec["qw"] = np.sin(half), np.cos(half)
    return head.SerializeToString() + rec.tobytes()


OBSTACLE_HEIGHT = 0.002
"""Height of the obstacles' cubes in ``/domain/obstacles`` (length): above the grids,
which lie at z = 0, so the viewer draws the obstacles over the (zero) cells they block."""


OBSTACLE_COLOR = (0.45, 0.45, 0.45, 1.0)
"""RGBA of the obstacles in ``/domain/obstacles`` (opaque grey)."""


MAX_RECTANGLES = 4096
"""Most rectangles :func:`obstacle_rectangles` draws; a raster that needs more is
coarsened by 2 per side (a coarse square blocked when any of its squares is) until it
fits, so the drawing covers every obstacle."""


def _runs(row: np.ndarray) -> list[tuple[int, int]]:
    """The runs ``[start, end)`` of True in a boolean row."""
    edges = np.diff(np.concatenate([[0], row.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def obstacle_rectangles(free: FreeSpace) -> np.ndarray:
    """The blocked squares of the robots' raster (``free.raster``) as rectangles
    ``(K, 4)``: ``x0, y0, x1, y1`` (length), each a maximal vertical stack of equal
    runs of blocked squares along x. At most :data:`MAX_RECTANGLES`: a raster that needs
    more is coarsened (see there).
    """
    g = free.grid
    blocked = free.raster.astype(bool)
    while True:
        rows, cols = blocked.shape
        sx, sy = (g.x1 - g.x0) / cols, (g.y1 - g.y0) / rows
        out: list[tuple[float, float, float, float]] = []
        open_: dict[tuple[int, int], int] = {}  # run -> first row of its stack
        for j in range(rows + 1):
            runs = set(_runs(blocked[j])) if j < rows else set()
            for run in [r for r in open_ if r not in runs]:
                j0 = open_.pop(run)
                out.append((g.x0 + run[0] * sx, g.y0 + j0 * sy, g.x0 + run[1] * sx, g.y0 + j * sy))
            for run in runs:
                open_.setdefault(run, j)
            if len(out) > MAX_RECTANGLES:
                break
        if len(out) <= MAX_RECTANGLES:
            return np.array(out, dtype=float).reshape(-1, 4)
        pad = ((0, rows % 2), (0, cols % 2))
        b = np.pad(blocked, pad)
        blocked = np.asarray(b.reshape(b.shape[0] // 2, 2, -1, 2).any(axis=(1, 3)), dtype=bool)


def obstacles_message(free: FreeSpace) -> SceneUpdate:
    """``/domain/obstacles``: one entity ``obstacles`` (frame ``world``, t = 0, no
    lifetime limit) whose cubes are :func:`obstacle_rectangles`, ``OBSTACLE_HEIGHT``
    high, their base at z = 0, grey.
    """
    msg = SceneUpdate()
    entity = msg.entities.add()
    entity.frame_id = "world"
    entity.id = "obstacles"
    entity.frame_locked = True
    for x0, y0, x1, y1 in obstacle_rectangles(free):
        cube = entity.cubes.add()
        cube.pose.position.x, cube.pose.position.y = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
        cube.pose.position.z = 0.5 * OBSTACLE_HEIGHT
        cube.pose.orientation.w = 1.0
        cube.size.x, cube.size.y, cube.size.z = x1 - x0, y1 - y0, OBSTACLE_HEIGHT
        cube.color.r, cube.color.g, cube.color.b, cube.color.a = OBSTACLE_COLOR
    return msg


def mask_message(free: FreeSpace) -> GridMsg:
    """``/domain/mask``: a ``foxglove.Grid`` on the control grid, one uint8 field
    ``free`` (1 free, 0 blocked), t = 0.
    """
    g = free.grid
    msg = GridMsg()
    msg.frame_id = "world"
    msg.pose.position.x, msg.pose.position.y = g.x0, g.y0
    msg.pose.orientation.w = 1.0
    msg.column_count = g.nx
    msg.cell_size.x, msg.cell_size.y = g.dx, g.dy
    msg.cell_stride, msg.row_stride = 1, g.nx
    msg.fields.add(name="free", offset=0, type=PackedElementField.UINT8)
    msg.data = np.ascontiguousarray(free.cells, dtype=np.uint8).tobytes()
    return msg


def component_masses(p: np.ndarray, free: FreeSpace) -> np.ndarray:
    """The target's mass in each connected component of free space (sums to 1)."""
    masses = np.bincount(free.labels[free.cells], p[free.cells], free.n_components)
    return masses / masses.sum()


def domain_record(target: Target) -> dict[str, str]:
    """The ``domain`` metadata record of a target on free space (see the module
    docstring): string values, the masses as a JSON list of ``repr`` floats.
    """
    free = target.free
    assert free is not None
    masses = component_masses(target.p, free)
    return {
        "n_components": str(free.n_components),
        "component_mass": json.dumps([float(m) for m in masses]),
        "free_cells": str(int(free.cells.sum())),
        "free_area": repr(free.free_area),
        "raster": str(free.raster.shape[0]),
    }


def _json_number(x: Any) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


class McapLogger:
    """Writes a run's ``run.mcap`` (see the module docstring): the observer ``log``.

    Args:
        grid, target: Run-time arguments (the target is logged once, at t = 0).
        steps: The run's last step (run-time argument; it always logs fields).
        identity: The config and provenance records (run-time argument).
        field_every: Steps between field messages (``>= 1``).
        positions_every: Steps between position messages (``>= 1``).

    :meth:`initialize` opens ``run.mcap`` in the run directory (and hands every message
    to the run's live servers, ``RunContext.publishers``: same topics, schemas and
    bytes; the file is written exactly as without them) and writes the target; the
    first :meth:`handle` writes the ``theory`` record the observers before it filled.
    """

    def __init__(
        self,
        grid: Grid,
        target: Target,
        steps: int,
        identity: Identity,
        field_every: int,
        positions_every: int,
    ) -> None:
        self.grid, self.target, self.identity = grid, target, identity
        self.metric_keys = METRIC_KEYS + domain_keys(target.free)
        self._path = TargetPath(target)  # p_*(t) of a moving target, logged with the fields
        self.field_every = integer("field_every", field_every, 1)
        self.positions_every = integer("positions_every", positions_every, 1)
        self.total_steps = steps
        self.field_cadence = Cadence(self.field_every, steps)
        self.positions_cadence = Cadence(self.positions_every, steps)
        self.path = Path(LOG_FILE)
        self.live: LiveServer | None = None
        self.run: RunContext | None = None
        self._opened = False
        self._finished = False
        self.seconds = 0.0  # wall time spent logging steps (s)

    writes_log = True  # the run's log (harness.observers.base.writes_log)

    @property
    def needs(self) -> dict[str | None, tuple[str, ...]]:
        """The log contract's always-numbers, which every ``/metrics`` message carries
        (:data:`ALWAYS_NUMBERS`): an observer before the logger must give them at every
        step (:func:`harness.observers.base.needs`; the observer ``metrics`` does).
        """
        return {None: ALWAYS_NUMBERS}

    BYTES_PER_STEP = 400
    """Bytes of one ``/metrics`` message with its record header (JSON of 24 numbers)."""

    def disk_bytes(self, robots: int) -> tuple[int, str]:
        """Upper estimate of the log's size (bytes) before compression, and the
        parameter that sets most of it: per step a metrics message; every
        ``field_every`` steps nine float32 grid fields (``p_true``, ``p_kde``,
        ``p_hat``, two gradients and the velocity, two components each for those);
        every ``positions_every`` steps ``robots`` float32 points (12 bytes).
        """
        steps = self.total_steps
        fields = (steps // self.field_every + 2) * (9 * 4 * self.grid.size + 9 * 200)
        points = (steps // self.positions_every + 2) * (12 * robots + 200) if robots else 0
        need = steps * self.BYTES_PER_STEP + fields + points
        return need, "positions_every" if points > need / 2 else "field_every"

    def initialize(self, run: RunContext) -> None:
        """Open ``run.out_dir / run.mcap`` and write the target."""
        self.run = run
        live = run.publishers[0] if run.publishers else None
        self.open(run.out_dir / LOG_FILE, live, exclusive=run.exclusive)
        self.write_target(self.target.p)
        if self.target.free is not None:
            self.write_domain(self.target.free)

    def open(self, path: Path, live: LiveServer | None = None, exclusive: bool = True) -> None:
        """Create the file, register the schemas and write the ``config`` and
        ``provenance`` records; also publish every message to ``live`` when given.

        Raises:
            FileExistsError: when ``exclusive`` and the file exists (the open itself
                refuses, so two writers can never share one log).
        """
        self.path, self.live = Path(path), live
        self._schema_defs: dict[int, tuple[str, str, bytes]] = {}
        self._file = open(self.path, "xb" if exclusive else "wb")
        self._opened = True
        # data-section CRC too: metadata records outside chunks are then protected as well
        self._writer = McapWriter(
            self._file, compression=CompressionType.ZSTD, enable_data_crcs=True
        )
        self._writer.start(profile="", library="densityloop")
        self._channels: dict[str, int] = {}
        # register_schema(self, ...) calls self.register_schema, which keeps each schema
        as_writer = cast(McapWriter, self)
        self._grid_schema = register_schema(as_writer, GridMsg)
        self._points_schema = register_schema(as_writer, PointCloud)
        self._poses_schema: int | None = None  # registered with the first poses
        self._metrics_schema = self.register_schema(
            name="densityloop.Metrics",
            encoding="jsonschema",
            data=json.dumps(metrics_schema(self.metric_keys)).encode(),
        )
        for name, record in self.identity.records().items():
            self._writer.add_metadata(name, record)
        if self.target.free is not None:
            self._writer.add_metadata("domain", domain_record(self.target))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Register a schema in the file (and keep it for the live view); its id."""
        schema_id = self._writer.register_schema(name=name, encoding=encoding, data=data)
        self._schema_defs[schema_id] = (name, encoding, data)
        return schema_id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """An extra metadata record (string values)."""
        self._writer.add_metadata(name, data)

    def _channel(self, topic: str, schema_id: int, encoding: str) -> int:
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=schema_id
            )
            if self.live is not None:
                self.live.channel(topic, *self._schema_defs[schema_id], encoding)
        return self._channels[topic]

    def _write(self, topic: str, t: float, data: bytes, schema_id: int, encoding: str) -> None:
        ns = time_ns(t)
        self._writer.add_message(
            channel_id=self._channel(topic, schema_id, encoding),
            log_time=ns,
            publish_time=ns,
            data=data,
        )
        if self.live is not None:
            self.live.publish(topic, ns, data)

    def write_grid(self, topic: str, t: float, values: np.ndarray) -> None:
        """A field message on ``topic`` (fields named as in :data:`FIELD_TOPICS`)."""
        msg = grid_message(self.grid, t, FIELD_TOPICS.get(topic, ("p",)), values)
        self._write(topic, t, msg.SerializeToString(), self._grid_schema, "protobuf")

    def write_target(self, p_target: np.ndarray) -> None:
        """``/fields/p_target`` at t = 0."""
        self.write_grid("/fields/p_target", 0.0, p_target)

    def write_domain(self, free: FreeSpace) -> None:
        """``/domain/mask`` and ``/domain/obstacles`` at t = 0 (a domain with obstacles)."""
        self._write("/domain/mask", 0.0, mask_message(free).SerializeToString(),
                    self._grid_schema, "protobuf")  # fmt: skip
        scene = register_schema(cast(McapWriter, self), SceneUpdate)
        data = obstacles_message(free).SerializeToString()
        self._write("/domain/obstacles", 0.0, data, scene, "protobuf")

    def handle(self, rec: StepRecord, metric_values: dict[str, float | None]) -> None:
        """Log one step: metrics always, fields and positions at their rates (and,
        with the start record, the ``theory`` record).
        """
        t0 = time.perf_counter()
        try:
            if rec.step == 0 and self.run is not None:
                self.add_metadata("theory", dict(self.run.theory))
            self._handle(rec, metric_values)
        finally:
            self.seconds += time.perf_counter() - t0

    def _handle(self, rec: StepRecord, metric_values: dict[str, float | None]) -> None:
        payload = {k: _json_number(metric_values.get(k)) for k in self.metric_keys}
        self._write("/metrics", rec.t, json.dumps(payload).encode(), self._metrics_schema, "json")
        if self.field_cadence.due(rec.step):
            t = rec.t
            self.write_grid("/fields/p_true", t, rec.p_true)
            if rec.measurement is not None:
                self.write_grid("/fields/p_kde", t, rec.measurement.p)
                self.write_grid("/fields/grad_kde", t, rec.measurement.grad)
            self.write_grid("/fields/p_hat", t, rec.estimate.p_hat)
            if self._path.moves and rec.step > 0:
                self.write_grid("/fields/p_target", t, self._path.at(t).p)
            self.write_grid("/fields/grad_hat", t, rec.estimate.q_hat)
            if rec.command.field is not None:
                self.write_grid("/fields/velocity", t, rec.command.field.centres)
            for name, values in rec.estimate.fields.items():
                self.write_grid(f"/fields/{name}", t, values)
        if rec.positions is not None and self.positions_cadence.due(rec.step):
            msg = points_message(rec.t, rec.positions)
            self._write(
                "/swarm/positions", rec.t, msg.SerializeToString(), self._points_schema, "protobuf"
            )
            if rec.headings is not None:
                if self._poses_schema is None:
                    self._poses_schema = register_schema(cast(McapWriter, self), PosesInFrame)
                data = poses_message(rec.t, rec.positions, rec.headings)
                self._write("/swarm/poses", rec.t, data, self._poses_schema, "protobuf")

    def finalize(self, status: Status) -> None:
        """Close the log with the run's status (:meth:`close`)."""
        self.close(status.state, status.reason, status.wall_s)

    def close(self, state: str, reason: str = "", wall_s: float | None = None) -> None:
        """Write the ``status`` record (``state``, ``reason`` and, when given, the run's
        wall time ``wall_s`` in s), the summary and index, and close the file.
        """
        if self._finished or not self._opened:
            return
        self._finished = True
        status = {"state": state, "reason": reason}
        if wall_s is not None:
            status["wall_s"] = f"{wall_s:.3f}"
        try:
            self._writer.add_metadata("status", status)
            self._writer.finish()
        finally:
            self._file.close()
