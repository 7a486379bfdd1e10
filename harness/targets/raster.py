"""Densities that are constant on the pixels of an image: ``target=ring``, ``target=picture``.

An image of ``rows x cols`` pixels is stretched over the grid's rectangle
``[x0, x1] x [y0, y1]``: pixel ``(r, c)`` covers

    x0 + c a <= x <= x0 + (c + 1) a,     y1 - (r + 1) b <= y <= y1 - r b,

with ``a = (x1 - x0) / cols`` and ``b = (y1 - y0) / rows`` (length), so row 0 is the top
of the domain (``y = y1``), as an image is shown, and column 0 its left side. From
non-negative pixel weights ``w_rc`` and a floor ``f in (0, 1]`` the density is

    p(x) = (1 - f) w_rc / (a b sum w)  +  f / |Omega|     for x in pixel (r, c)

(1 / length^2): the share ``1 - f`` of the mass spread over the pixels in proportion to
their weights, uniform inside each pixel, and the share ``f`` uniform on the rectangle,
so ``p >= f / |Omega| > 0`` everywhere as the paper's theorems require.

Everything the harness asks of a density is exact for such a ``p``
(:class:`Raster`): the cell masses are separable sums of overlap lengths, the samples a
pixel drawn by weight and a uniform point inside it. ``K_h * p`` has no method of its
own; :func:`harness.estimators.smoothing.smoothed_density` falls back to the noise-free
KDE of the cell values (:func:`~harness.estimators.smoothing.smoothed_density_cells`),
whose error is the midpoint rule's on the grid's cells.

:class:`Ring` rasterises a uniform annulus, :class:`Picture` a grey PNG.
"""

from __future__ import annotations

from collections.abc import Sequence
from math import pi, sqrt
from pathlib import Path
from typing import Any

import numpy as np

from harness.domains.mask import image_file, read_grey
from harness.grid import Grid
from harness.parameters import flag, integer, number, pair, require

SHIPPED = Path(__file__).resolve().parent / "data"
"""The pictures the package ships (``shipped: NAME`` reads ``SHIPPED / NAME.png``),
drawn by ``scripts/make_targets.py``."""

SUPERSAMPLING = 4
"""Points per pixel side at which :class:`Ring` tests the annulus (``4 x 4`` a pixel)."""


def _overlaps(cells: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Overlap lengths of the intervals between consecutive ``cells`` edges (rows) with
    those between consecutive ``pixels`` edges (columns), shape ``(len(cells) - 1,
    len(pixels) - 1)`` (length). Both edge lists ascending.
    """
    lo = np.maximum(cells[:-1, None], pixels[None, :-1])
    hi = np.minimum(cells[1:, None], pixels[None, 1:])
    return np.clip(hi - lo, 0.0, None)


class Raster:
    """A density constant on each pixel of an image stretched over the grid's rectangle,
    plus a uniform floor (the module docstring gives the formula and the orientation).

    Args:
        weights: Pixel weights ``w``, shape ``(rows, cols)``, finite, ``>= 0``, not all
            zero (row 0 at the top); only their ratios matter.
        floor: Share ``f`` of the mass spread uniformly, in ``(0, 1]``.

    Raises:
        ParameterError: naming ``weights`` for an array that is not 2-D, has a negative
            or non-finite entry or is all zero; ``floor`` outside ``(0, 1]``.
    """

    def __init__(self, weights: Any, floor: float = 0.1) -> None:
        self.floor = number("floor", floor, 0.0, strict=True)
        require(self.floor <= 1.0, "floor", floor, "a number in (0, 1]")
        try:
            w = np.array(weights, dtype=float)
        except (TypeError, ValueError):
            w = np.empty(0)
        require(w.ndim == 2 and w.size > 0, "weights", weights, "a 2-D array of pixel weights")
        given = f"<{w.shape[0]} x {w.shape[1]} pixels>"
        require(bool(np.isfinite(w).all()), "weights", given, "finite pixel weights")
        require(bool((w >= 0).all()), "weights", given, "pixel weights >= 0")
        total = float(w.sum())
        require(total > 0, "weights", given, "pixel weights not all zero (no mass to spread)")
        w.setflags(write=False)
        self.weights = w
        """The pixel weights as given (read-only), shape ``(rows, cols)``."""
        shares = w / total
        shares.setflags(write=False)
        self.shares = shares
        """Each pixel's share ``w_rc / sum w`` of the mass ``1 - floor`` (sum 1)."""
        self._cdf = np.cumsum(shares.ravel())
        self._masses: dict[Grid, np.ndarray] = {}

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)`` of the image."""
        rows, cols = self.weights.shape
        return rows, cols

    def __repr__(self) -> str:
        rows, cols = self.shape
        return f"{type(self).__name__}({rows} x {cols} pixels, floor={self.floor:g})"

    def pixel_edges(self, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
        """The pixels' edges on ``grid``'s rectangle, both ascending (length): along x
        (``cols + 1``, column ``c`` between entries ``c`` and ``c + 1``) and along y
        (``rows + 1``, image row ``r`` between entries ``rows - 1 - r`` and ``rows - r``).
        """
        rows, cols = self.shape
        return np.linspace(grid.x0, grid.x1, cols + 1), np.linspace(grid.y0, grid.y1, rows + 1)

    def evaluate(self, x: np.ndarray, y: np.ndarray, grid: Grid) -> np.ndarray:
        """The continuous density ``p(x, y)`` (1 / length^2) at points of ``grid``'s
        rectangle; a point on a pixel edge takes the pixel above or to the right of it.
        """
        rows, cols = self.shape
        u = (np.asarray(x, dtype=float) - grid.x0) / (grid.x1 - grid.x0)
        v = (grid.y1 - np.asarray(y, dtype=float)) / (grid.y1 - grid.y0)
        col = np.clip(np.floor(u * cols).astype(int), 0, cols - 1)
        row = np.clip(np.floor(v * rows).astype(int), 0, rows - 1)
        pixel = rows * cols / grid.area  # 1 / pixel area
        return (1.0 - self.floor) * self.shares[row, col] * pixel + self.floor / grid.area

    def cell_masses(self, grid: Grid) -> np.ndarray:
        """Exact cell masses ``int_cell p``, shape ``(ny, nx)`` (dimensionless, sum 1).

        A pixel's mass is uniform on it, so the share of pixel ``(r, c)`` in cell
        ``(j, i)`` is the product of the fractions of its width and height inside the
        cell: with ``A_x[i, c]`` the overlap of cell column ``i`` with pixel column ``c``
        over the pixel width and ``A_y[j, r]`` that of cell row ``j`` with image row
        ``r`` over the pixel height,

            m = (1 - f) A_y S A_x^T  +  f dx dy / |Omega|,

        ``S`` the pixels' shares. Each column of ``A_x`` and ``A_y`` sums to 1 (to
        round-off), so the masses sum to 1.
        """
        cached = self._masses.get(grid)
        if cached is None:
            ex, ey = self.pixel_edges(grid)
            cx = np.linspace(grid.x0, grid.x1, grid.nx + 1)
            cy = np.linspace(grid.y0, grid.y1, grid.ny + 1)
            ax = _overlaps(cx, ex) / (ex[1] - ex[0])
            ay = _overlaps(cy, ey)[:, ::-1] / (ey[1] - ey[0])  # image row 0 is the top
            cached = (1.0 - self.floor) * (ay @ self.shares @ ax.T) + self.floor * (
                grid.cell_area / grid.area
            )
            cached.setflags(write=False)
            self._masses[grid] = cached
        return cached.copy()

    def on_grid(self, grid: Grid) -> np.ndarray:
        """Cell values: the exact cell masses over the cell area (1 / length^2), so the
        grid integral is 1 to round-off.
        """
        return self.cell_masses(grid) / grid.cell_area

    def sample(self, n: int, grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """``n`` exact samples of ``p``, shape ``(2, n)`` (length): each robot from the
        floor with probability ``f`` (uniform on the rectangle), else a pixel drawn with
        probability its share (inverse distribution function of the shares) and a
        uniform point inside it.
        """
        rows, cols = self.shape
        floor = rng.random(n) < self.floor
        k = int(n - floor.sum())
        u = rng.random(k) * self._cdf[-1]
        # side="right": a pixel of share 0 spans an empty interval and is never drawn
        last = int(np.flatnonzero(self.shares.ravel() > 0)[-1])
        pixel = np.minimum(np.searchsorted(self._cdf, u, side="right"), last)
        row, col = np.divmod(pixel, cols)
        a = (grid.x1 - grid.x0) / cols
        b = (grid.y1 - grid.y0) / rows
        out = np.empty((2, n))
        out[0, ~floor] = grid.x0 + (col + rng.random(k)) * a
        out[1, ~floor] = grid.y1 - (row + rng.random(k)) * b
        m = n - k
        out[0, floor] = rng.uniform(grid.x0, grid.x1, size=m)
        out[1, floor] = rng.uniform(grid.y0, grid.y1, size=m)
        return out


class Ring(Raster):
    """The uniform annulus ``inner <= |x - centre| <= outer`` rasterised, plus a floor.

    Coordinates are in units of the domain's side: the annulus is declared on the unit
    square ``[0, 1]^2`` of the image, which is stretched over the grid's rectangle like
    any raster's, so on the default unit square they are lengths (on ``[0, L]^2`` a
    ring of radii ``L inner``, ``L outer`` about ``L centre``). The image has
    ``resolution x resolution`` pixels; each pixel's weight is the annulus's area
    fraction in it, estimated by testing the ``4 x 4`` centres of its sub-squares
    (:data:`SUPERSAMPLING`): a sub-square counts whole when its centre lies in the
    annulus. Only sub-squares that a circle crosses can be misjudged, each by at most
    its area ``s^2`` (``s = 1 / (4 resolution)``); their centres lie within ``s /
    sqrt(2)`` of a circle, so they lie inside the band ``|rho - r| <= s sqrt(2)``, so
    the raster's annulus area differs from ``pi (outer^2 - inner^2)`` by at most that
    band's area summed over both circles (:meth:`area_error_bound`): ``4 sqrt(2) pi
    (inner + outer) s`` = 5.2e-3 of the unit square at the defaults, 2.8 % of the
    annulus. The errors of the crossed sub-squares nearly cancel: measured at the
    defaults the raster's area is 1.2e-5 below ``pi (outer^2 - inner^2)`` = 0.18850
    (6.5e-5 of it).
    Every pixel the annulus misses entirely has weight 0, so the density there is the
    floor's: thin support with sharp edges, by design.

    Args:
        centre: Centre ``(x, y)`` in ``[0, 1]^2`` (domain sides).
        inner: Inner radius, ``>= 0`` (domain sides).
        outer: Outer radius, ``> inner``; the disc of radius ``outer`` must lie inside
            the unit square.
        floor: Share of the mass spread uniformly, in ``(0, 1]``.
        resolution: Pixels per side of the image, ``>= 16``.

    Raises:
        ParameterError: naming the key: ``centre`` not a pair in ``[0, 1]^2``, ``inner <
            0``, ``outer <= inner``, an annulus leaving the domain (``outer``),
            ``resolution < 16``, ``floor`` outside ``(0, 1]``.
    """

    def __init__(
        self,
        centre: Sequence[float] = (0.5, 0.5),
        inner: float = 0.25,
        outer: float = 0.35,
        floor: float = 0.1,
        resolution: int = 512,
    ) -> None:
        cx, cy = pair("centre", centre)
        cx, cy = number("centre", cx), number("centre", cy)
        require(0 <= cx <= 1 and 0 <= cy <= 1, "centre", centre, "a point of [0, 1]^2")
        self.centre = (cx, cy)
        self.inner = number("inner", inner, 0.0)
        self.outer = number("outer", outer, self.inner, strict=True)
        room = min(cx, 1.0 - cx, cy, 1.0 - cy)
        require(
            self.outer <= room,
            "outer",
            outer,
            f"a radius <= {room:g}, so that the ring about ({cx:g}, {cy:g}) stays inside the "
            "domain (radii and centre in domain sides)",
        )
        self.resolution = integer("resolution", resolution, 16)
        super().__init__(self._annulus_fractions(), floor)

    def _annulus_fractions(self) -> np.ndarray:
        """Each pixel's area fraction inside the annulus by ``4 x 4`` supersampling,
        shape ``(resolution, resolution)``, row 0 at the top (dimensionless).
        """
        n, k = self.resolution, SUPERSAMPLING
        t = (np.arange(n * k) + 0.5) / (n * k)  # sub-square centres, 0 .. 1
        dx2 = (t - self.centre[0]) ** 2
        dy2 = (1.0 - t - self.centre[1]) ** 2  # sub-row 0 at the top
        r2 = dy2[:, None] + dx2[None, :]
        inside = (r2 >= self.inner**2) & (r2 <= self.outer**2)
        return inside.reshape(n, k, n, k).sum(axis=(1, 3)) / (k * k)

    def __repr__(self) -> str:
        return (
            f"Ring(centre={self.centre}, inner={self.inner:g}, outer={self.outer:g}, "
            f"floor={self.floor:g}, resolution={self.resolution})"
        )

    @property
    def area(self) -> float:
        """The raster's annulus area, ``sum w / resolution^2`` (domain sides squared);
        ``pi (outer^2 - inner^2)`` up to :meth:`area_error_bound`.
        """
        return float(self.weights.sum()) / self.resolution**2

    def area_error_bound(self) -> float:
        """A bound on ``|area - pi (outer^2 - inner^2)|`` (domain sides squared): the
        area of the bands ``|rho - r| <= s sqrt(2)`` about both circles, ``s`` the
        sub-square's side (see the class docstring).
        """
        s = 1.0 / (SUPERSAMPLING * self.resolution)
        band = s * sqrt(2.0)
        total = 0.0
        for r in (self.inner, self.outer):
            if r > 0:
                total += pi * ((r + band) ** 2 - max(r - band, 0.0) ** 2)
        return total


class Picture(Raster):
    """The density of a grey picture: mass where the picture is dark (``invert``) or
    light, plus a floor. The pixel weight is ``1 - g`` (``invert``) or ``g``, with ``g``
    the pixel's grey level from 0 (black) to 1 (white), read by
    :func:`harness.domains.mask.read_grey` (luminance, 16-bit grey scaled, transparency
    over white); the image is stretched over the grid's rectangle, row 0 at the top, as
    every :class:`Raster`'s.

    Args:
        path: A PNG file of the user's (``~`` expanded; relative to the working
            directory), or None to use ``shipped``.
        shipped: The name of a picture the package ships (``harness/targets/data``;
            ``letters``, "DL" in dark letters on white), used when ``path`` is None.
        floor: Share of the mass spread uniformly, in ``(0, 1]``.
        invert: Mass where the picture is dark (true) or where it is light (false).

    Raises:
        ParameterError: naming ``path`` or ``shipped`` for a file that is missing, not a
            regular file, too large, not a PNG image, or without mass (all white with
            ``invert``, all black without); ``floor`` outside ``(0, 1]``; ``invert`` not
            a boolean.
    """

    def __init__(
        self,
        path: str | None = None,
        shipped: str | None = "letters",
        floor: float = 0.1,
        invert: bool = True,
    ) -> None:
        self.invert = flag("invert", invert)
        number("floor", floor, 0.0, strict=True)
        require(float(floor) <= 1.0, "floor", floor, "a number in (0, 1]")
        key, file = image_file(path, shipped, SHIPPED)
        self.source = str(file)
        grey = read_grey(key, file)
        weights = 1.0 - grey if self.invert else grey
        require(
            float(weights.sum()) > 0,
            key,
            str(file),
            f"a picture with some {'dark' if self.invert else 'light'} pixel (it has no mass: "
            f"all {'white' if self.invert else 'black'})",
        )
        super().__init__(weights, floor)

    def __repr__(self) -> str:
        rows, cols = self.shape
        return f"Picture({Path(self.source).name!r}, {rows} x {cols} pixels, floor={self.floor:g})"
