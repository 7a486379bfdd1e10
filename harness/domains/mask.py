"""``domain=mask``: free space read from a PNG image (white free, dark blocked).

:func:`read_grey` reads a PNG file's grey levels with every check a file from a user
needs; ``target=picture`` (:class:`harness.targets.raster.Picture`) reads its image with
it too.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from harness.domains.base import Domain
from harness.files import UnreadableFile, read_bytes
from harness.parameters import ParameterError, number, require
from harness.png import MAX_SIDE, png_problem

SHIPPED = Path(__file__).resolve().parent / "data"
"""The masks the package ships (``shipped: NAME`` reads ``SHIPPED / NAME.png``)."""

MAX_BYTES = 16 << 20
"""Largest image file read (bytes): a mask, or a picture of ``target=picture``."""

MAX_PIXELS = MAX_SIDE * MAX_SIDE
"""Largest image (pixels): each side at most :data:`harness.png.MAX_SIDE`, checked
before its pixels are decoded (:func:`harness.png.png_problem`)."""


class Mask(Domain):
    """Free space from an image stretched over the square: a pixel is free when its
    grey level (0 to 1, the image converted to luminance) is at least ``threshold``.
    The image's top row is the top of the square (``y = L``); a point is looked up in
    the pixel that contains it.

    Args:
        path: A PNG file of the user's (``~`` expanded; relative to the working
            directory), or None to use ``shipped``.
        shipped: The name of a mask the package ships (``harness/domains/data``), used
            when ``path`` is None.
        threshold: Grey level in ``(0, 1]`` from which a pixel is free.
        resolution: Squares per side of the robots' raster (``>= 16``).

    Raises:
        ParameterError: naming ``path`` or ``shipped`` for a file that is missing, not a
            regular file, too large or not an image; ``threshold`` outside ``(0, 1]``.
    """

    name = "mask"

    def __init__(
        self,
        path: str | None = None,
        shipped: str | None = "warehouse",
        threshold: float = 0.5,
        resolution: int = 1024,
    ) -> None:
        super().__init__(resolution)
        self.threshold = number("threshold", threshold, 0.0, strict=True)
        require(self.threshold <= 1.0, "threshold", threshold, "a grey level in (0, 1]")
        key, file = image_file(path, shipped, SHIPPED)
        self.source = str(file)
        self.free = read_grey(key, file) >= self.threshold

    def blocked(self, x: np.ndarray, y: np.ndarray, length: float) -> np.ndarray:
        """In a pixel darker than the threshold."""
        rows, cols = self.free.shape
        col = np.clip((np.asarray(x) / length * cols).astype(int), 0, cols - 1)
        row = np.clip(((1.0 - np.asarray(y) / length) * rows).astype(int), 0, rows - 1)
        return ~self.free[row, col]


def image_file(path: str | None, shipped: str | None, folder: Path) -> tuple[str, Path]:
    """The image a ``path`` / ``shipped`` pair of parameters names, with the key to name
    when it is refused: the user's ``path`` (``~`` expanded; relative to the working
    directory) when given, else ``folder / (shipped + ".png")``.

    Raises:
        ParameterError: naming ``shipped`` for a name none of the PNG files in
            ``folder`` has.
    """
    if path:
        return "path", Path(str(path)).expanduser()
    names = sorted(p.stem for p in folder.glob("*.png"))
    require(shipped in names, "shipped", shipped, f"one of {names}, or a path")
    return "shipped", folder / f"{shipped}.png"


def read_grey(key: str, file: Path) -> np.ndarray:
    """The grey level of every pixel of the PNG image ``file``, 0 (black) to 1 (white),
    shape ``(rows, cols)`` with row 0 at the top (:func:`grey_levels`).

    Read without trusting the file: a regular file of at most :data:`MAX_BYTES` bytes
    (:func:`harness.files.read_bytes`), a whole PNG a viewer can show
    (:func:`harness.png.png_problem`, which also bounds each side by
    :data:`harness.png.MAX_SIDE` before anything is decoded), at least 2 pixels a side,
    then decoded by Pillow.

    Raises:
        ParameterError: naming ``key`` for a file that is missing, not a regular file,
            too large, not a PNG image, damaged, or smaller than 2 pixels a side.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        data = read_bytes(file, MAX_BYTES)
    except UnreadableFile as err:
        raise ParameterError(key, str(file), f"a readable PNG file ({err})") from None
    problem = png_problem(data)
    if problem:
        raise ParameterError(key, str(file), f"a PNG image a viewer can show ({problem})")
    try:
        with Image.open(io.BytesIO(data)) as image:
            width, height = image.size
            if min(width, height) < 2:
                raise ParameterError(
                    key,
                    str(file),
                    f"an image 2 to {MAX_SIDE} pixels a side ({width} x {height})",
                )
            return grey_levels(image)
    except ParameterError:
        raise
    except Image.DecompressionBombError:
        raise ParameterError(
            key, str(file), f"an image of 2 to {MAX_PIXELS} pixels (it declares far more)"
        ) from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as err:
        raise ParameterError(key, str(file), f"a PNG image ({type(err).__name__})") from None


SIXTEEN_BIT_MODES = ("I;16", "I;16B", "I;16L", "I")
"""Pillow's modes of a 16-bit grey PNG (levels 0 to 65535)."""


def grey_levels(image: Any) -> np.ndarray:
    """The grey level of each pixel of a Pillow ``image``, 0 (black) to 1 (white): a
    16-bit grey image scaled by 65535, any other converted to 8-bit luminance (ITU-R
    601) over 255; a transparent pixel is composited over white (an obstacle drawn on a
    transparent background leaves the background free).
    """
    from PIL import Image

    if image.mode in SIXTEEN_BIT_MODES:
        levels = np.asarray(image)
        grey = levels.astype(float) / 65535.0
        clear = image.info.get("transparency")  # tRNS: the one level that is transparent
        if isinstance(clear, int) and not isinstance(clear, bool):
            grey[levels == clear] = 1.0
        return grey
    if image.mode in ("LA", "RGBA", "PA", "La", "RGBa") or "transparency" in image.info:
        rgba = image.convert("RGBA")
        image = Image.alpha_composite(Image.new("RGBA", rgba.size, (255, 255, 255, 255)), rgba)
    return np.asarray(image.convert("L"), dtype=float) / 255.0
