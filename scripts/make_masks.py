"""Draw the masks ``domain=mask`` ships (``harness/domains/data/*.png``).

    python scripts/make_masks.py

``warehouse``: a 256 x 256 floor (white, free) with four rows of shelves (black) and
aisles between them, an outer margin free for the robots to go round; drawn here, so
the repository owns it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

OUT = Path(__file__).resolve().parents[1] / "harness" / "domains" / "data"


def warehouse(size: int = 256, shelves: int = 4) -> np.ndarray:
    """The warehouse floor: uint8 image, 255 free, 0 shelves. ``shelves`` rows, each
    ``size / 16`` wide, ``size / 8`` apart, centred, from ``size / 6`` to ``5 size / 6``
    in height, cut by a cross aisle ``size / 20`` wide at mid-height.
    """
    floor = np.full((size, size), 255, dtype=np.uint8)
    width, aisle = size // 16, size // 8
    left = (size - shelves * width - (shelves - 1) * aisle) // 2
    top, bottom = size // 6, size - size // 6
    for k in range(shelves):
        x = left + k * (width + aisle)
        floor[top:bottom, x : x + width] = 0
    cross = size // 20
    floor[size // 2 - cross // 2 : size // 2 + cross // 2 + 1, :] = 255
    return floor


def main() -> None:
    """Write every mask into ``harness/domains/data``."""
    OUT.mkdir(parents=True, exist_ok=True)
    Image.fromarray(warehouse(), mode="L").save(OUT / "warehouse.png", optimize=True)
    print(OUT / "warehouse.png")


if __name__ == "__main__":
    main()
