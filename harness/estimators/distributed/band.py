"""Band-limited messages: robots exchange the band's cosine coefficients, not grid fields.

The filters estimate the band-limited density ``Pi p``
(:class:`harness.estimators.filters.common.BandLimit`: the Neumann cosine modes of
wavenumber ``|kappa| <= kappa_c``, ``kappa_c = band_limit / h``), and above ``kappa_c`` the
KDE carries neither signal nor noise. So a robot need not send its whole tracked field
(``M`` cell values) to its neighbours: the ``K`` band coefficients carry everything the
filters use. With ``C_y``, ``C_x`` the orthonormal DCT-II matrices (rows up to the band's
highest mode on each axis) and ``mask`` the band's disc, the coefficients of a field ``F``
``(n_y, n_x)`` are

    c = mask o (C_y F C_x^T),       and    Pi F = C_y^T c C_x                    (BAND)

(``Pi`` the orthogonal projector; the coefficient vector keeps only the ``K`` entries
inside ``mask``). Robot ``i``'s kernel is separable, ``phi_i = ky_i kx_i^T``
(:func:`harness.estimators.distributed.robot_kde.kernel_factors`), so its coefficients are the
outer product of two short transforms, ``c_i[b, a] = (C_y ky_i)_b (C_x kx_i)_a``: about
``n (b_max + a_max)`` operations per robot instead of ``M``.

Consensus is linear and acts on the robots' index (``z <- W z``), and ``c = B z`` is
linear and acts on the cells, so the two commute: consensus on coefficients is
consensus on the grid followed by ``Pi``, exactly (tested to 1e-12). At the paper's
``h = 0.04`` and ``band_limit = 2.5`` the band holds ``K = 329`` modes of the 30 x 30
grid's 900: a message of ``8 K = 2632`` bytes instead of 7200; ``band_limit = 2`` keeps
214 modes (1712 bytes).
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from harness.estimators.distributed.messages import KernelFactors
from harness.estimators.distributed.mixing import Mixer
from harness.estimators.filters.common import BandLimit
from harness.grid import Grid


class BandMessages:
    """The band's coefficients of the robots' kernels, and the fields they stand for
    (eq. ``BAND`` in the module docstring): the messages of ``estimator.messages: band``
    (:class:`harness.estimators.distributed.messages.Messages`).

    The kernels' change (:meth:`increment`) is the difference of their coefficients
    from one step to the next; the last step's coefficients are kept for it.

    Args:
        grid: The grid.
        cutoff: ``kappa_c`` (1 / length), finite: ``band_limit / h``.
    """

    def __init__(self, grid: Grid, cutoff: float) -> None:
        if not np.isfinite(cutoff) or cutoff <= 0:
            raise ValueError(f"the band's cutoff must be a finite number > 0, got {cutoff}")
        self.grid = grid
        self.band = BandLimit(grid, float(cutoff))
        self.c_y, self.c_x = self.band.bases
        mask = self.band.mask[: self.c_y.shape[0], : self.c_x.shape[0]]
        self.rows, self.cols = np.nonzero(mask)
        self._previous: np.ndarray | None = None  # the last increment's coefficients

    @property
    def size(self) -> int:
        """``K``, the number of band coefficients (floats per message)."""
        return int(self.rows.size)

    @cached_property
    def message_bytes(self) -> int:
        """Bytes of one message: ``K`` float64 values."""
        return 8 * self.size

    def coefficients(self, fields: np.ndarray) -> np.ndarray:
        """``(N, K)`` band coefficients of ``(N, M)`` fields (rows are robots)."""
        g = self.grid
        f = np.asarray(fields, dtype=float).reshape(-1, g.ny, g.nx)
        coef = self.c_y @ f @ self.c_x.T
        return coef[:, self.rows, self.cols]

    def kernels(self, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        """``(N, K)`` band coefficients of the robots' kernels ``outer(ky_i, kx_i)`` from
        their 1-D factors (``(N, nx)``, ``(N, ny)``), by two short transforms per robot.
        """
        a = ky @ self.c_y.T  # (N, b_max + 1): C_y ky_i
        b = kx @ self.c_x.T  # (N, a_max + 1): C_x kx_i
        return a[:, self.rows] * b[:, self.cols]

    def fields(self, coef: np.ndarray) -> np.ndarray:
        """``(N, M)`` fields ``Pi F_i = C_y^T c_i C_x`` of ``(N, K)`` coefficients."""
        coef = np.asarray(coef, dtype=float)
        n = coef.shape[0]
        full = np.zeros((n, self.c_y.shape[0], self.c_x.shape[0]))
        full[:, self.rows, self.cols] = coef
        return (self.c_y.T @ full @ self.c_x).reshape(n, self.grid.size)

    def project(self, fields: np.ndarray) -> np.ndarray:
        """``Pi F_i`` of ``(N, M)`` fields (the coefficients and back)."""
        return self.fields(self.coefficients(fields))

    def increment(self, factors: KernelFactors, old: KernelFactors | None) -> np.ndarray:
        """The coefficients' change ``C_y ky_i (C_x kx_i)^T`` minus the last step's,
        ``(N, K)`` (the coefficients themselves when ``old`` is None).
        """
        kx, _, ky, _ = factors
        coef = self.kernels(kx, ky)
        delta = coef if old is None or self._previous is None else coef - self._previous
        self._previous = coef
        return delta

    def add_increment(
        self, z: np.ndarray, factors: KernelFactors, old: KernelFactors | None
    ) -> None:
        """``z += increment(factors, old)`` in place (:meth:`increment`)."""
        z += self.increment(factors, old)

    def mixed(self, fields: np.ndarray, mix: Mixer, rounds: int) -> np.ndarray:
        """``rounds`` rounds of ``mix`` on the band's coefficients ``c`` of ``(N, M)``
        fields ``F``; each robot keeps its own part outside the band: ``F - Pi F`` plus
        the fields of ``W^rounds c`` (eq. ``BAND``).
        """
        coef = self.coefficients(fields)
        outside = fields - self.fields(coef)
        for _ in range(rounds):
            coef = mix(coef)
        return outside + self.fields(coef)
