"""Draw the pictures ``target=picture`` ships (``harness/targets/data/*.png``).

    python scripts/make_targets.py

``letters``: a 256 x 256 8-bit grey image, white background, the letters "DL" in
black, drawn by matplotlib's Agg backend with its bundled DejaVu Sans Bold, so the
repository makes the picture itself and the same matplotlib draws the same pixels.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.font_manager import FontProperties
from PIL import Image

OUT = Path(__file__).resolve().parents[1] / "harness" / "targets" / "data"

SIZE = 256
"""Pixels per side."""


def letters(text: str = "DL", size: int = SIZE) -> np.ndarray:
    """``text`` in black on white: uint8 image ``(size, size)``, 255 white. The letters
    are about 0.44 of the side tall and 0.8 of it wide, in DejaVu Sans Bold
    (matplotlib's bundled font, read from its data directory, not found among the
    system's fonts), their ink centred in the image.
    """
    font = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans-Bold.ttf"
    dpi = 100
    fig = plt.figure(figsize=(size / dpi, size / dpi), dpi=dpi, facecolor="white")
    fig.text(
        0.5,
        0.5,
        text,
        fontproperties=FontProperties(fname=str(font), size=0.6 * size * 72 / dpi),
        color="black",
        ha="center",
        va="center",
    )
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())  # type: ignore[attr-defined]
    plt.close(fig)
    grey = rgba[..., :3].astype(float) @ np.array([0.299, 0.587, 0.114])
    drawn = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    # centre the ink: the text box's centre includes the font's descent, the letters not
    rows = np.flatnonzero((drawn < 255).any(axis=1))
    cols = np.flatnonzero((drawn < 255).any(axis=0))
    ink = drawn[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    out = np.full((size, size), 255, dtype=np.uint8)
    top, left = (size - ink.shape[0]) // 2, (size - ink.shape[1]) // 2
    out[top : top + ink.shape[0], left : left + ink.shape[1]] = ink
    return out


def main() -> None:
    """Write every picture into ``harness/targets/data``."""
    OUT.mkdir(parents=True, exist_ok=True)
    Image.fromarray(letters(), mode="L").save(OUT / "letters.png", optimize=True)
    print(OUT / "letters.png")


if __name__ == "__main__":
    main()
