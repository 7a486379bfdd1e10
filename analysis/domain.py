"""The domain of a run with obstacles, as its log holds it: the free cells of the control
grid (``/domain/mask``, a ``foxglove.Grid``) and the obstacles (``/domain/obstacles``, a
``foxglove.SceneUpdate`` of cubes), written by :mod:`harness.observers.log` only on a
domain with obstacles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from foxglove_schemas_protobuf.Grid_pb2 import Grid as GridMsg
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate


@dataclass
class DomainShapes:
    """The domain of a run with obstacles, from its log.

    Attributes:
        free: ``(ny, nx)`` booleans, the free cells of the control grid
            (``/domain/mask``), or None when the log has no mask.
        origin: The grid's origin ``(x0, y0)`` (length).
        cell_size: ``(dx, dy)`` (length).
        rectangles: ``(K, 4)`` obstacles ``x0, y0, x1, y1`` (length), the cubes of
            ``/domain/obstacles`` seen from above.
    """

    free: np.ndarray | None = None
    origin: tuple[float, float] = (0.0, 0.0)
    cell_size: tuple[float, float] = (0.0, 0.0)
    rectangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def extent(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of the mask, for ``imshow``."""
        if self.free is None:
            raise ValueError("the log has no /domain/mask")
        ny, nx = self.free.shape
        x0, y0 = self.origin
        return (x0, x0 + nx * self.cell_size[0], y0, y0 + ny * self.cell_size[1])


def decode_mask(msg: GridMsg) -> dict[str, object]:
    """``/domain/mask``: its one uint8 field as booleans ``(ny, nx)``, with the grid's
    origin and cell size.

    Raises:
        ValueError: when the message is not one uint8 field on a whole number of rows.
    """
    uint8 = PackedElementField.UINT8
    if len(msg.fields) != 1 or msg.fields[0].type != uint8 or msg.cell_stride != 1:
        raise ValueError("a domain mask holds one uint8 field")
    cols = msg.column_count
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if cols < 1 or raw.size == 0 or raw.size % cols or msg.row_stride != cols:
        raise ValueError("a domain mask of whole rows")
    return {
        "free": raw.reshape(-1, cols) != 0,
        "origin": (msg.pose.position.x, msg.pose.position.y),
        "cell_size": (msg.cell_size.x, msg.cell_size.y),
    }


def decode_obstacles(msg: SceneUpdate) -> np.ndarray:
    """``/domain/obstacles``: the cubes of every entity as rectangles ``(K, 4)``
    (``x0, y0, x1, y1``, length), seen from above (an unrotated cube's footprint).
    """
    boxes = [
        (
            c.pose.position.x - c.size.x / 2,
            c.pose.position.y - c.size.y / 2,
            c.pose.position.x + c.size.x / 2,
            c.pose.position.y + c.size.y / 2,
        )
        for entity in msg.entities
        for c in entity.cubes
    ]
    out = np.array(boxes, dtype=float).reshape(-1, 4)
    if not np.isfinite(out).all():
        raise ValueError("obstacles with coordinates that are not finite numbers")
    return out
