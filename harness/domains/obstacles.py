"""``domain=obstacles``: discs and polygons listed in the YAML, in length units."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.path import Path as Polygon
from shapely import Point, box, is_valid_reason
from shapely import Polygon as ShapelyPolygon

from harness.domains.base import Domain, FreeSpace
from harness.grid import Grid
from harness.parameters import ParameterError, number, require


class Obstacles(Domain):
    """The square less a union of discs and polygons.

    A point is blocked when it lies in a closed disc ``|z - c| <= r`` or inside a
    polygon (matplotlib's point-in-polygon test on its vertices, which need not repeat
    the first at the end). A polygon must be simple with a positive area (checked with
    shapely's ``is_valid``: no self-intersection, no repeated or collinear-only
    vertices), and every obstacle must cover part of the square.

    Args:
        discs: Each ``{center: [x, y], radius: r}`` (length; ``r > 0``).
        polygons: Each a list of at least 3 vertices ``[x, y]`` (length).
        resolution: Squares per side of the robots' raster.
    """

    name = "obstacles"

    def __init__(
        self,
        discs: Sequence[Any] = (),
        polygons: Sequence[Any] = (),
        resolution: int = 1024,
    ) -> None:
        super().__init__(resolution)
        self.discs = [_disc(i, d) for i, d in enumerate(discs or ())]
        self.polygons = [_polygon(i, p) for i, p in enumerate(polygons or ())]
        self._paths = [Polygon(np.array(p)) for p in self.polygons]

    def resolve(self, grid: Grid) -> FreeSpace:
        """:meth:`Domain.resolve`, after each obstacle is checked to cover part of the
        grid's rectangle with an area (an obstacle wholly outside it, or touching it only
        on its edge, is a mistake, never ignored).
        """
        side = box(grid.x0, grid.y0, grid.x1, grid.y1)
        for i, ((cx, cy), r) in enumerate(self.discs):
            if not Point(cx, cy).buffer(r).intersection(side).area > 0:
                raise ParameterError(f"discs[{i}]", {"center": [cx, cy], "radius": r}, INSIDE)
        for i, vertices in enumerate(self.polygons):
            if not ShapelyPolygon(vertices).intersection(side).area > 0:
                raise ParameterError(f"polygons[{i}]", [list(v) for v in vertices], INSIDE)
        return super().resolve(grid)

    def blocked(self, x: np.ndarray, y: np.ndarray, length: float) -> np.ndarray:
        """Inside a disc or a polygon."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        out = np.zeros(x.shape, dtype=bool)
        for (cx, cy), r in self.discs:
            out |= (x - cx) ** 2 + (y - cy) ** 2 <= r * r
        if self._paths:
            points = np.column_stack([x.ravel(), y.ravel()])
            for path in self._paths:
                out |= path.contains_points(points).reshape(x.shape)
        return out


def _disc(i: int, disc: Any) -> tuple[tuple[float, float], float]:
    """A disc ``((x, y), r)`` from its config, or a :class:`ParameterError` naming it."""
    name = f"discs[{i}]"
    ok = hasattr(disc, "get") and disc.get("center") is not None and "radius" in disc
    require(bool(ok), name, disc, "{center: [x, y], radius: r} in length units")
    unknown = sorted(str(k) for k in disc if k not in ("center", "radius"))
    require(not unknown, name, disc, f"only center and radius (not {', '.join(unknown)})")
    center = list(disc["center"])
    require(len(center) == 2, f"{name}.center", center, "two numbers [x, y] (length)")
    x = number(f"{name}.center", center[0])
    y = number(f"{name}.center", center[1])
    r = number(f"{name}.radius", disc["radius"], 0.0, strict=True)
    return (x, y), r


def _polygon(i: int, polygon: Any) -> list[tuple[float, float]]:
    """A polygon's vertices from its config, or a :class:`ParameterError` naming it."""
    name = f"polygons[{i}]"
    try:
        vertices = [tuple(v) for v in polygon]
    except TypeError:
        raise ParameterError(name, polygon, "a list of vertices [x, y] (length)") from None
    require(len(vertices) >= 3, name, polygon, "at least 3 vertices [x, y] (length)")
    out = []
    for k, v in enumerate(vertices):
        require(len(v) == 2, f"{name}[{k}]", list(v), "a vertex [x, y] (length)")
        out.append((number(f"{name}[{k}]", v[0]), number(f"{name}[{k}]", v[1])))
    shape = ShapelyPolygon(out)
    if not shape.is_valid or not shape.area > 0:
        why = is_valid_reason(shape) if not shape.is_valid else "no area"
        raise ParameterError(
            name, [list(v) for v in out], f"a simple polygon with an area ({why}; shapely)"
        )
    return out


INSIDE = "an obstacle that covers part of the grid's rectangle (this one lies outside it)"
