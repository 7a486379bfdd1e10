"""``domain=square``: the grid's square with no obstacle (the paper's domain)."""

from __future__ import annotations

import numpy as np

from harness.domains.base import Domain


class Square(Domain):
    """No obstacle: free space is the whole square ``[0, L]^2``, walls reflect.

    Args:
        resolution: Squares per side of the robots' raster (unused: nothing to look up).
    """

    name = "square"

    @property
    def trivial(self) -> bool:
        """Whether the domain has no obstacle (always so for the plain square)."""
        return True

    def blocked(self, x: np.ndarray, y: np.ndarray, length: float) -> np.ndarray:
        """Nothing is blocked."""
        return np.zeros(np.shape(x), dtype=bool)
