"""Read a densityloop ``run.mcap`` into numpy arrays (no import of the run loop).

``load_run(path)`` returns a :class:`RunLog`: the metrics as one array per key,
each field topic as a :class:`FieldSeries` (times and values), the robot positions,
and the metadata records (``config``, ``provenance``, ``status``). Topic names and
units are those of the log contract in ``harness/mcap_log.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.Grid_pb2 import Grid as GridMsg
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from mcap.reader import make_reader


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
    """A decoded run (see the module docstring)."""

    path: Path
    metadata: dict[str, dict[str, str]]
    metrics: dict[str, np.ndarray]
    fields: dict[str, FieldSeries]
    positions_t: np.ndarray
    positions: list[np.ndarray] = field(repr=False)

    @property
    def state(self) -> str:
        """``completed`` | ``aborted`` | ``diverged`` (``truncated`` without a status)."""
        return self.metadata.get("status", {}).get("state", "truncated")


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


def load_run(path: str | Path) -> RunLog:
    """Decode ``path`` (a ``run.mcap`` or a directory holding one).

    Raises:
        LogError: if the file is missing or is not an MCAP file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "run.mcap"
    if not path.is_file():
        raise LogError(f"no run log at {path}")
    metrics: dict[str, list] = {}
    grids: dict[str, dict] = {}
    pos_t: list[float] = []
    positions: list[np.ndarray] = []
    metadata: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for record in reader.iter_metadata():
                metadata[record.name] = dict(record.metadata)
        with open(path, "rb") as f:
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                t = message.log_time / 1e9
                name = schema.name if schema is not None else ""
                if channel.topic == "/metrics" and channel.message_encoding == "json":
                    for key, value in json.loads(message.data).items():
                        metrics.setdefault(key, []).append(np.nan if value is None else value)
                elif channel.topic.startswith("/fields/") and name == "foxglove.Grid":
                    values, names, origin, cell = _decode_grid(GridMsg.FromString(message.data))
                    g = grids.setdefault(
                        channel.topic, {"t": [], "v": [], "names": names, "o": origin, "c": cell}
                    )
                    g["t"].append(t)
                    g["v"].append(values)
                elif channel.topic == "/swarm/positions" and name == "foxglove.PointCloud":
                    cloud = PointCloud.FromString(message.data)
                    pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
                    pos_t.append(t)
                    positions.append(pts[:, :2].astype(float))
    except LogError:
        raise
    except Exception as err:  # the mcap reader raises many types on damaged files
        raise LogError(
            f"{path} is not a readable densityloop log: {type(err).__name__}: {err}"
        ) from err
    fields = {
        topic: FieldSeries(np.array(g["t"]), np.stack(g["v"]), g["names"], g["o"], g["c"])
        for topic, g in grids.items()
    }
    return RunLog(
        path=path,
        metadata=metadata,
        metrics={k: np.asarray(v, dtype=float) for k, v in metrics.items()},
        fields=fields,
        positions_t=np.array(pos_t),
        positions=positions,
    )
