"""Read a densityloop ``run.mcap`` into numpy arrays (no import of the run loop).

``load_run(path)`` returns a :class:`RunLog`: the metrics as one array per key,
each field topic as a :class:`FieldSeries` (times and values), the robot positions
(and, for robots with a heading, their poses ``(N, 3)``: x, y in length, heading in
rad), the domain of a run with obstacles (:class:`DomainShapes`: its free cells from
``/domain/mask`` and its obstacles' rectangles from ``/domain/obstacles``; None for a
run on the square or a log written before these topics), and the metadata records
(``config``, ``choices``, ``provenance``, ``status``; ``domain`` with obstacles);
:attr:`RunLog.choices` is the option the run took in each config group. Topic names and
units are those of the log contract in ``harness/observers/log.py``.

The same run as xarray objects (built from the numpy arrays, so the values are the
same numbers): :meth:`RunLog.field_xarray` (one field topic, dims ``t``, ``y``, ``x``
and ``component`` for two-component fields), :meth:`RunLog.metrics_xarray` (dim ``t``),
:meth:`RunLog.to_xarray` (everything in one Dataset) and :meth:`RunLog.to_netcdf`;
:func:`open_netcdf` reads such a file back. xarray is imported only when used::

    log = load_run("outputs/reproduce")
    p_hat = log.field_xarray("/fields/p_hat")          # (t, y, x), 1/length^2
    p_hat.sel(t=10.0, method="nearest").plot()
    log.metrics_xarray().phat_target_l2.plot()
    log.to_netcdf("run.nc")
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zstandard
from foxglove_schemas_protobuf.Grid_pb2 import Grid as GridMsg
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.records import Channel, Chunk, Footer, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import InvalidMagic, StreamReader, breakup_chunk

from analysis.domain import DomainShapes, decode_mask, decode_obstacles
from analysis.limits import ROBOT_TOPICS, Limits
from analysis.output import atomic_path

if TYPE_CHECKING:
    import xarray as xr

# units of the field topics (log contract, harness/observers/log.py) and of the metrics
# (docs/units.md)
FIELD_UNITS = {
    "/fields/p_target": "1/length^2",
    "/fields/p_true": "1/length^2",
    "/fields/p_kde": "1/length^2",
    "/fields/p_hat": "1/length^2",
    "/fields/grad_kde": "1/length^3",
    "/fields/grad_hat": "1/length^3",
    "/fields/velocity": "length/s",
}
FIELD_DESCRIPTIONS = {
    "/fields/p_target": "target density p_*",
    "/fields/p_true": "true density p (the Fokker-Planck solution)",
    "/fields/p_kde": "kernel density estimate of the swarm",
    "/fields/p_hat": "density filter estimate p_hat",
    "/fields/grad_kde": "gradient of the kernel density estimate",
    "/fields/grad_hat": "gradient filter estimate q_hat",
    "/fields/velocity": "velocity field at the cell centres",
}
METRIC_UNITS = {
    "t": "s",
    "phi_l2": "1/length",
    "phat_target_l2": "1/length",
    "eps_l2": "1/length",
    "eps_g_l2": "1/length^2",
    "kde_l2": "1/length",
    "lyapunov": "1/length^2",
    "mass": "1",
    "trace_P": "1/length^2",
    "trace_Q": "1/length^2",
    "trace_P_grad": "1/length^4",
    "trace_Q_grad": "1/length^4",
    "start_fraction": "1",
    "start_target_mass": "1",
}


class LogError(RuntimeError):
    """A log that cannot be read as a densityloop run."""


@dataclass
class FieldSeries:
    """A field topic: ``t`` (s) of shape ``(K,)``, ``values`` of shape ``(K, c, ny, nx)``,
    the field ``names`` (``c`` of them), the grid ``origin`` and ``cell_size``.
    """

    t: np.ndarray
    values: np.ndarray
    names: tuple[str, ...]
    origin: tuple[float, float]
    cell_size: tuple[float, float]

    def extent(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` for ``imshow``."""
        ny, nx = self.values.shape[-2:]
        x0, y0 = self.origin
        return (x0, x0 + nx * self.cell_size[0], y0, y0 + ny * self.cell_size[1])

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(x, y)``."""
        ny, nx = self.values.shape[-2:]
        x0, y0 = self.origin
        return (
            x0 + (np.arange(nx) + 0.5) * self.cell_size[0],
            y0 + (np.arange(ny) + 0.5) * self.cell_size[1],
        )

    def at(self, t: float) -> tuple[float, np.ndarray]:
        """The message nearest to time ``t``: ``(time, values (c, ny, nx))``."""
        i = int(np.argmin(np.abs(self.t - t)))
        return float(self.t[i]), self.values[i]


@dataclass
class RunLog:
    """A decoded run (see the module docstring); ``recovery`` says what was lost to
    damage, ``foreign`` which metric values were not finite numbers (read as NaN).
    """

    path: Path
    metadata: dict[str, dict[str, str]]
    metrics: dict[str, np.ndarray]
    fields: dict[str, FieldSeries]
    positions_t: np.ndarray
    positions: list[np.ndarray] = field(repr=False)
    recovery: str | None = None
    foreign: str | None = None
    poses_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    poses: list[np.ndarray] = field(default_factory=list, repr=False)
    domain: DomainShapes | None = None

    @property
    def choices(self) -> dict[str, str]:
        """Hydra's choices: the option taken in each config group (``{"control":
        "paper", "plant": "agents", "experiment": "smoke", ...}``; group names as Hydra
        spells them, ``null`` for a group set to nothing), from the ``choices`` record.
        Empty for a log written before the record existed (see :attr:`has_choices`).
        """
        return {str(k): str(v) for k, v in self.metadata.get("choices", {}).items()}

    @property
    def has_choices(self) -> bool:
        """Whether the log holds a ``choices`` record (a log written before the record
        existed has none; one whose config was made without Hydra has an empty one).
        """
        return "choices" in self.metadata

    @property
    def state(self) -> str:
        """``completed`` | ``aborted`` | ``diverged`` (``truncated`` without a status)."""
        return self.metadata.get("status", {}).get("state", "truncated")

    def field_xarray(self, topic: str) -> xr.DataArray:
        """Field ``topic`` as a DataArray (see :func:`field_dataarray`).

        Raises:
            KeyError: if the run has no messages on ``topic``.
        """
        return field_dataarray(self.fields[topic], topic)

    def metrics_xarray(self) -> xr.Dataset:
        """The metrics as a Dataset (see :func:`metrics_dataset`)."""
        return metrics_dataset(self.metrics)

    def to_xarray(self) -> xr.Dataset:
        """The whole run (metrics, every field topic, metadata) as one Dataset.

        The metrics keep dim ``t``; field topic ``/fields/NAME`` becomes variable
        ``NAME`` with its own time dim ``t_NAME`` (topics are logged at different
        times: ``p_target`` once) and, for two-component fields, dim
        ``component_NAME``; all fields share ``y`` and ``x`` (a metric named like one of
        these, as a foreign log may have, is renamed ``metric_KEY``). The metadata records
        become string attributes ``RECORD.KEY`` (``config.yaml``,
        ``provenance.git_commit``, ``status.state``, ...).
        """
        import xarray as xr

        taken = {"x", "y"}
        for topic in self.fields:
            name = topic.removeprefix("/fields/")
            taken |= {name, f"t_{name}", f"component_{name}"}
        metrics = {}
        for key, values in self.metrics.items():
            new = key
            while new in taken or (new != key and new in self.metrics):
                new = f"metric_{new}"  # a foreign metric named like a field or coordinate
            metrics[new] = values
        parts: list[xr.Dataset | xr.DataArray] = [metrics_dataset(metrics)]
        for topic in self.fields:
            name = topic.removeprefix("/fields/")
            da = self.field_xarray(topic).rename({"t": f"t_{name}"})
            if "component" in da.dims:
                da = da.rename({"component": f"component_{name}"})
            parts.append(da.rename(name))
        ds = xr.merge(parts, join="outer", compat="no_conflicts", combine_attrs="override")
        ds.attrs = {
            f"{record}.{key}": value
            for record, values in sorted(self.metadata.items())
            for key, value in sorted(values.items())
        }
        ds.attrs["source"] = str(self.path)
        if self.recovery is not None:
            ds.attrs["recovery"] = self.recovery
        return ds

    def to_netcdf(self, path: str | Path) -> Path:
        """Write :meth:`to_xarray` to a NetCDF file (netCDF3 through scipy: no extra
        dependency). Field values are stored as float32, the precision of the log, so
        reading the file back gives exactly the values of :func:`load_run`.

        Returns:
            The path written.
        """
        path = Path(path)
        ds = self.to_xarray()
        encoding = {topic.removeprefix("/fields/"): {"dtype": "float32"} for topic in self.fields}
        with atomic_path(path) as tmp:  # an interrupted write leaves the old file
            ds.to_netcdf(tmp, engine="scipy", format="NETCDF3_64BIT", encoding=encoding)
        return path


def _decode_grid(
    msg,
) -> tuple[np.ndarray, tuple[str, ...], tuple[float, float], tuple[float, float]]:
    names = tuple(f.name for f in msg.fields)
    k = len(names)
    raw = np.frombuffer(msg.data, dtype="<f4")
    cols = msg.column_count
    rows = raw.size // (k * cols) if k and cols else 0
    values = raw.reshape(rows, cols, k).transpose(2, 0, 1).astype(float)
    return (
        values,
        names,
        (msg.pose.position.x, msg.pose.position.y),
        (msg.cell_size.x, msg.cell_size.y),
    )


def field_dataarray(series: FieldSeries, topic: str = "") -> xr.DataArray:
    """A field topic as an ``xarray.DataArray``.

    Dims ``(t, y, x)`` for one-component fields (densities) and
    ``(t, component, y, x)`` for two-component ones (``gx, gy``; ``vx, vy``), values as
    in ``series.values``. Coordinates: ``t`` (s), ``y`` and ``x`` the cell centres
    (length, :meth:`FieldSeries.centres`), ``component`` the field names. Attributes:
    ``units``, ``topic``, ``long_name``, ``field_names``, ``cell_size`` and
    ``origin`` (length).
    """
    import xarray as xr

    x, y = series.centres()
    coords: dict[str, tuple[str, object, dict[str, str]]] = {
        "t": ("t", series.t, {"units": "s", "long_name": "simulated time"}),
        "y": ("y", y, {"units": "length", "long_name": "cell centre y"}),
        "x": ("x", x, {"units": "length", "long_name": "cell centre x"}),
    }
    if len(series.names) == 1:
        dims: tuple[str, ...] = ("t", "y", "x")
        values = series.values[:, 0]
    else:
        dims = ("t", "component", "y", "x")
        values = series.values
        coords["component"] = ("component", list(series.names), {})
    attrs: dict[str, object] = {
        "units": FIELD_UNITS.get(topic, ""),
        "topic": topic,
        "long_name": FIELD_DESCRIPTIONS.get(topic, topic),
        "field_names": " ".join(series.names),
        "cell_size": np.array(series.cell_size, dtype=float),
        "origin": np.array(series.origin, dtype=float),
    }
    name = topic.removeprefix("/fields/") or None
    return xr.DataArray(values, coords=coords, dims=dims, name=name, attrs=attrs)


def metrics_dataset(metrics: dict[str, np.ndarray]) -> xr.Dataset:
    """The ``/metrics`` arrays as an ``xarray.Dataset`` on dim ``t`` (s).

    One variable per key other than ``t``, ``NaN`` where the log has ``null``, with
    its ``units`` attribute (``docs/units.md``).
    """
    import xarray as xr

    t = metrics.get("t", np.array([]))
    data_vars = {
        key: ("t", values, {"units": METRIC_UNITS.get(key, "")})
        for key, values in metrics.items()
        if key != "t"
    }
    return xr.Dataset(
        data_vars, coords={"t": ("t", t, {"units": "s", "long_name": "simulated time"})}
    )


def open_netcdf(path: str | Path) -> xr.Dataset:
    """Read a file written by :meth:`RunLog.to_netcdf` (loaded into memory)."""
    import xarray as xr

    with xr.open_dataset(path, engine="scipy") as ds:
        return ds.load()


class LogWarning(UserWarning):
    """A log that was only partly readable (truncated or damaged)."""


def load_run(path: str | Path, topics: set[str] | None = None, poses: bool = True) -> RunLog:
    """Decode ``path`` (a ``run.mcap`` or a directory holding one).

    The file is read record by record, so a log cut short (a run killed with
    SIGKILL) or damaged part-way yields every complete chunk before the damage:
    the result then has ``recovery`` set, ``state`` ``truncated`` when the status
    record is missing, and a :class:`LogWarning` is issued. Messages on unknown
    topics or with other schemas are ignored; a message that fails to decode, or a
    metrics message without a finite time, is skipped and counted. A metric value that
    is not a finite number (``true``, a string, ``1e400``, ``NaN``; ``null`` is the
    contract's "not applicable") is read as NaN, counted in ``foreign`` and warned
    about. What the log holds is bounded before it is decoded (:class:`Limits`): no
    more messages per topic than the config record's steps, no more points per positions
    or poses message than its robots, and never more points in all, nor more bytes
    decompressed from its chunks, than in proportion to the file's size (whatever the
    config record or a chunk's header claims); what lies beyond is skipped unread,
    counted in ``recovery`` and warned about.

    Args:
        path: The log or its directory.
        topics: Decode only these topics (all when None); metadata is always read.
        poses: Decode ``/swarm/poses`` (False: skip them unread, for a reader that
            uses no poses).

    Raises:
        LogError: if the file is missing, empty, not an MCAP file, or holds nothing
            readable.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "run.mcap"
    if not path.is_file():
        raise LogError(f"no run log at {path}")
    if path.stat().st_size == 0:
        raise LogError(f"{path} is empty")
    limits = Limits(path.stat().st_size)
    metric_rows: list[dict[str, float]] = []
    grids: dict[str, dict] = {}
    pos_t: list[float] = []
    positions: list[np.ndarray] = []
    pose_list: list[tuple[float, np.ndarray]] = []
    metadata: dict[str, dict[str, str]] = {}
    domain: dict[str, object] = {}
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    complete, problem, n_messages, n_bad = False, None, 0, 0
    replaced: dict[str, int] = {}
    with open(path, "rb") as f:
        try:
            reader = StreamReader(
                f, validate_crcs=True, record_size_limit=1 << 30, emit_chunks=True
            )
            for record in _records(reader, limits):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata):
                    metadata[record.name] = dict(record.metadata)
                    if record.name == "config":
                        limits.configure(str(record.metadata.get("yaml", "")))
                elif isinstance(record, Footer):
                    complete = True
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        n_bad += 1
                        continue
                    if topics is not None and channel.topic not in topics:
                        continue
                    if not poses and channel.topic == "/swarm/poses":
                        continue
                    if not limits.admit(channel.topic):
                        continue
                    if channel.topic in ROBOT_TOPICS and not limits.room(
                        channel.topic, len(record.data)
                    ):
                        continue
                    schema = schemas.get(channel.schema_id)
                    try:
                        n_messages += _take(
                            record,
                            channel,
                            schema,
                            metric_rows,
                            grids,
                            pos_t,
                            positions,
                            replaced,
                            pose_list,
                            limits,
                            domain,
                        )
                    except Exception:  # a damaged message: skip it, count it
                        n_bad += 1
        except InvalidMagic as err:
            raise LogError(f"{path} is not an MCAP file ({err})") from None
        except Exception as err:  # truncation or damage: keep what was read
            problem = f"{type(err).__name__}: {err}"
    if n_messages == 0 and not metadata:
        raise LogError(f"{path} holds no readable densityloop data ({problem or 'no messages'})")
    recovery = None
    beyond = limits.summary()
    if problem is not None or not complete or n_bad or beyond:
        last_t = metric_rows[-1]["t"] if metric_rows else float("nan")
        damage = "file ends early" if not complete else "file damaged"
        if complete and problem is None and not n_bad:
            damage = ""  # whole, but holding more than its config and size allow
        recovery = "; ".join(
            part
            for part in (
                f"recovered {n_messages} messages up to t = {last_t:.3f} s"
                f"{f', skipped {n_bad} damaged' if n_bad else ''}",
                f"{damage}{f' ({problem})' if problem else ''}",
                beyond or "",
            )
            if part
        )
        warnings.warn(f"{path}: {recovery}", LogWarning, stacklevel=2)
    foreign = None
    if replaced:
        foreign = "metric values that are not finite numbers, read as NaN: " + ", ".join(
            f"{key} ({n})" for key, n in sorted(replaced.items())
        )
        warnings.warn(f"{path}: {foreign}", LogWarning, stacklevel=2)
    fields = {
        topic: FieldSeries(np.array(g["t"]), np.stack(g["v"]), g["names"], g["o"], g["c"])
        for topic, g in grids.items()
        if g["v"]
    }
    return RunLog(
        path=path,
        metadata=metadata,
        metrics=_metric_arrays(metric_rows),
        fields=fields,
        positions_t=np.array(pos_t),
        positions=positions,
        recovery=recovery,
        foreign=foreign,
        poses_t=np.array([t for t, _ in pose_list]),
        poses=[p for _, p in pose_list],
        domain=DomainShapes(**domain) if domain else None,  # type: ignore[arg-type]
    )


class ChunkError(ValueError):
    """A chunk whose compressed data does not decompress to the size its header declares."""


def _records(reader: StreamReader, limits: Limits) -> Iterator[McapRecord]:
    """The records of ``reader`` (which emits chunks whole) in order, each chunk's records
    in place of the chunk: decompressed (uncompressed CRC checked) only when
    ``limits`` allow what it declares (:meth:`Limits.unpack`), else left out unread.
    """
    for record in reader.records:
        if not isinstance(record, Chunk):
            yield record
            continue
        content = None
        if record.compression == "zstd":
            told = zstandard.frame_content_size(record.data)  # ZstdError: damaged
            content = told if told >= 0 else None  # -1: the frame does not say
        if limits.unpack(record.uncompressed_size, content):
            if record.compression == "lz4":
                record = _inflated_lz4(record)
            yield from breakup_chunk(record, validate_crc=True)


def _inflated_lz4(chunk: Chunk) -> Chunk:
    """``chunk`` with its LZ4 frame decompressed, never past one byte beyond the size its
    header declares (the LZ4 frame need not state its own size, so that is the only
    bound; ``mcap`` itself would decompress the whole frame first).

    Raises:
        ChunkError: when the frame holds more or fewer bytes than declared, or is cut.
    """
    import lz4.frame  # only for logs written with LZ4 (the harness writes zstd)

    declared = int(chunk.uncompressed_size)
    inflater = lz4.frame.LZ4FrameDecompressor()
    data = inflater.decompress(chunk.data, max_length=declared + 1)
    if len(data) != declared or not inflater.eof:
        raise ChunkError(f"an LZ4 chunk does not decompress to the {declared} bytes it declares")
    return dataclasses.replace(chunk, compression="", data=data)


def _metric_arrays(rows: list[dict[str, float]]) -> dict[str, np.ndarray]:
    """One array per metric key over all rows, aligned: NaN where a row lacks the key
    (a foreign or older log), so index ``i`` of every array is the same message.
    """
    keys: dict[str, None] = {}
    for row in rows:
        keys.update(dict.fromkeys(row))
    return {k: np.array([row.get(k, np.nan) for row in rows], dtype=float) for k in keys}


def _finite(value: object) -> float | None:
    """``value`` as a float when it is a finite real number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        x = float(value)
    except OverflowError:  # an integer beyond float range
        return None
    return x if math.isfinite(x) else None


def _take(
    record, channel, schema, metric_rows, grids, pos_t, positions, replaced, poses, limits, domain
) -> bool:
    """Decode one message of a known topic into the accumulators; False when the
    topic or schema is not one of the log contract's, or a robots message holds more
    points than ``limits`` (:class:`Limits`) allow (then nothing is allocated for them).
    Metric values that are not finite numbers (other than ``null``) become NaN, counted
    by key in ``replaced``.
    """
    t = record.log_time / 1e9
    name = schema.name if schema is not None else ""
    if channel.topic == "/metrics" and channel.message_encoding == "json":
        values = json.loads(record.data)
        if not isinstance(values, dict) or _finite(values.get("t")) is None:
            raise ValueError("metrics message is not a JSON object with a finite time")
        row = {}
        for key, value in values.items():
            x = _finite(value)
            if x is None and value is not None:
                replaced[str(key)] = replaced.get(str(key), 0) + 1
            row[str(key)] = np.nan if x is None else x
        metric_rows.append(row)
    elif channel.topic.startswith("/fields/") and name == "foxglove.Grid":
        values, names, origin, cell = _decode_grid(GridMsg.FromString(record.data))
        if values.size == 0 or not names:
            raise ValueError("empty grid")
        g = grids.setdefault(
            channel.topic, {"t": [], "v": [], "names": names, "o": origin, "c": cell}
        )
        if values.shape[1:] != (g["v"][0].shape[1:] if g["v"] else values.shape[1:]):
            raise ValueError("grid size changed within a topic")
        g["t"].append(t)
        g["v"].append(values)
    elif channel.topic == "/swarm/positions" and name == "foxglove.PointCloud":
        cloud = PointCloud.FromString(record.data)
        if not limits.take(channel.topic, len(cloud.data) // 12):
            return False
        pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
        pos_t.append(t)
        positions.append(pts[:, :2].astype(float))
    elif channel.topic == "/swarm/poses" and name == "foxglove.PosesInFrame":
        msg = PosesInFrame.FromString(record.data)
        if not limits.take(channel.topic, len(msg.poses)):
            return False
        xy = np.array([(p.position.x, p.position.y) for p in msg.poses]).reshape(-1, 2)
        qz = np.array([p.orientation.z for p in msg.poses])
        qw = np.array([p.orientation.w for p in msg.poses])
        poses.append((t, np.column_stack([xy, 2.0 * np.arctan2(qz, qw)])))
    elif channel.topic == "/domain/mask" and name == "foxglove.Grid":
        domain.update(decode_mask(GridMsg.FromString(record.data)))
    elif channel.topic == "/domain/obstacles" and name == "foxglove.SceneUpdate":
        domain["rectangles"] = decode_obstacles(SceneUpdate.FromString(record.data))
    else:
        return False
    return True
