"""What both filter forms share: settings, measurement covariances, the
sampled-data transition, and the integration operator of the gradient filter.

Sampled-data form (derivation). The paper writes the filters in continuous time
(eqs. ``density filter`` and ``density Riccati``) for ``dp/dt = A(t) p`` observed
through ``y = p + w``. In the harness, measurements (KDEs) arrive every ``dt`` and
the velocity, hence ``A``, is held over each interval. The plant's own discrete
model is the truth stepper of :mod:`harness.fokker_planck`:

    p_{n+1} = F_n p_n,      F_n = (I - dt A(v_n))^{-1}       (backward Euler),

so the filter that is exact for the discretised plant is the discrete Kalman
filter with that ``F_n``; ``F_n`` agrees with ``exp(dt A)`` to ``O(dt^2)`` per step,
which makes it a consistent discretisation of the continuous filter (the
continuous gain ``P R_c^{-1}`` corresponds to ``R_c = R dt``). With process noise
``Q`` and ``H = I``:

    predict:  x^- = F x^+,               P^- = F P^+ F^T + Q
    update:   S = P^- + R,  K = P^- S^{-1},
              x^+ = x^- + K (y - x^-),   P^+ = (I - K) P^- (I - K)^T + K R K^T.

Unlike an explicit Euler step of the Riccati equation, which turns ``P`` indefinite
when ``P >> R dt`` (start-up with a large ``P0``), the discrete update keeps
``0 <= P^+ <= min(P^-, R)`` for every ``P^-``: it is stable for any initial
covariance. ``F`` has non-negative entries and unit column sums, so the prediction
also keeps the mass of ``x``.

Measurement covariances (notes section 3). The KDE's pointwise variance is
``k p`` for the density and ``k_g p`` for each gradient component, so

    R   = r_scale k   diag(max(p_KDE, r_floor))
    R_g = r_scale k_g diag(max(p_KDE, r_floor))   (both components).

``R_g`` uses the variance the KDE gradient actually has, proportional to ``p``; the
paper's ``k_g diag(grad p_KDE)`` is not positive definite. The floor keeps
``R^{-1}`` bounded where the KDE is about 0 (outside the initial square at
``t = 0``), as the paper's Theorems ``thm:stability of density filter`` and
``thm:stability of gradient filter`` assume. ``r_scale`` (default 1) accounts for
the strong correlation of successive KDE frames, which makes independent-frame
filters overconfident.

Process noise. ``Q = q dt k I`` (density) and ``q dt k_g I`` (gradient), ``q`` in
1 / s. With ``Q = 0`` the covariance tends to 0 and with it the gain, and
``P^{-1}`` is unbounded, contrary to the theorems' assumption ``c_1 I <= P^{-1}
<= c_2 I``. A positive ``q`` keeps ``P`` bounded below. The default ``q = 0.1 / s``
models what a mean-field model misses: the swarm's finite-N density deviates
from the mean field by fluctuations of the KDE's own size (variance ``~ k p``)
that persist while the robots cross a kernel width, ``h / |v|`` or ``h^2 /
sigma``, about 10 s at paper scale; a variance ``k`` renewed every ``1/q`` = 10 s
is that error.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import scipy.fft as sfft
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from harness.domains.base import FreeSpace
from harness.estimators.diffusion import gradient_matrix
from harness.estimators.kde import noise_constants
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import number
from harness.velocity import VelocityField


@dataclass(frozen=True)
class FilterSettings:
    """Filter parameters (config block ``filter``).

    Attributes:
        process_noise: ``q >= 0`` (1 / s): ``Q = q dt k I`` per step for the density
            filter and ``q dt k_g I`` for the gradient filter, i.e. the fraction of a
            single KDE frame's variance (at unit density) that the model's error
            adds per second. Default 0.1 / s, see the module docstring.
        r_scale: Multiplier ``> 0`` on the KDE noise constants in ``R`` and ``R_g``.
        r_floor: Density floor ``> 0`` in ``R`` (1 / length^2).
        initial_variance: ``P0 = initial_variance * k * I`` for the density and
            ``initial_variance * k_g * I`` for the gradient (dimensionless factor
            ``> 0``, in units of the measurement variance at unit density).
        band_limit: ``kappa_c h > 0`` (dimensionless): the filters' states are the
            Neumann cosine modes of wavenumber ``|kappa| <= band_limit / h`` (see
            :class:`BandLimit`); ``inf`` keeps every grid mode (the grid filter of
            the paper). Default 2.5: the KDE's noise spectrum there is ``exp(-6.25)
            = 0.2 %`` of its peak.
    """

    process_noise: float = 0.1
    r_scale: float = 1.0
    r_floor: float = 0.05
    initial_variance: float = 10.0
    band_limit: float = 2.5

    @classmethod
    def checked(
        cls,
        process_noise: Any = 0.1,
        r_scale: Any = 1.0,
        r_floor: Any = 0.05,
        initial_variance: Any = 10.0,
        band_limit: Any = 2.5,
    ) -> FilterSettings:
        """The settings from config values (the ``filter`` block), each checked by
        :func:`harness.parameters.number`: a refused value raises
        :class:`~harness.parameters.ParameterError` naming its parameter, which the
        builder reports as one line naming the config key. The estimators validate the
        ``filter`` block here. ``band_limit`` is a finite number here; ``inf`` (every
        grid mode) is for settings made in code.
        """
        return cls(
            process_noise=number("process_noise", process_noise, 0.0),
            r_scale=number("r_scale", r_scale, 0.0, strict=True),
            r_floor=number("r_floor", r_floor, 0.0, strict=True),
            initial_variance=number("initial_variance", initial_variance, 0.0, strict=True),
            band_limit=number("band_limit", band_limit, 0.0, strict=True),
        )

    def __post_init__(self) -> None:
        if not (self.band_limit > 0):
            raise ValueError(f"filter.band_limit must be > 0, got {self.band_limit}")
        if not (np.isfinite(self.process_noise) and self.process_noise >= 0):
            raise ValueError(f"filter.process_noise must be >= 0, got {self.process_noise}")
        for name in ("r_scale", "r_floor", "initial_variance"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"filter.{name} must be > 0, got {value}")


@dataclass(frozen=True)
class MeasurementModel:
    """KDE measurement covariances for ``N`` robots and bandwidth ``h``."""

    n_robots: int
    bandwidth: float
    settings: FilterSettings

    @property
    def constants(self) -> tuple[float, float]:
        """``(k, k_g)`` of :func:`harness.estimators.kde.noise_constants`."""
        return noise_constants(self.n_robots, self.bandwidth)

    def density_variance(self, p_kde: np.ndarray) -> np.ndarray:
        """Diagonal of ``R``, flattened (1 / length^4)."""
        k, _ = self.constants
        s = self.settings
        return s.r_scale * k * np.maximum(p_kde, s.r_floor).ravel()

    def gradient_variance(self, p_kde: np.ndarray) -> np.ndarray:
        """Diagonal of ``R_g`` for the stacked ``(gx, gy)``, flattened (1 / length^6)."""
        _, k_g = self.constants
        s = self.settings
        one = s.r_scale * k_g * np.maximum(p_kde, s.r_floor).ravel()
        return np.concatenate([one, one])


def transition_dense(a: sp.spmatrix, dt: float) -> np.ndarray:
    """Dense ``F = (I - dt A)^{-1}`` (reference filters, small grids)."""
    m = a.shape[0]
    lu = spla.splu((sp.identity(m, format="csc") - dt * a).tocsc())
    return lu.solve(np.eye(m))


@dataclass(frozen=True)
class Integrator:
    """The integration operator ``I`` of eq. ``gradient equation`` on the grid.

    ``I(q)`` is the density whose grid gradient best matches ``q`` and whose mass is
    1: ``I(q) = G^+ q + 1 / |Omega|``, with ``G`` the grid gradient
    (:attr:`harness.grid.Grid.gradient_matrix`) and ``G^+`` its Moore-Penrose
    pseudo-inverse. ``G`` annihilates exactly the constants, so ``G^+ q`` has zero
    mean, and for every density of unit mass ``I(G p) = p``: the gradient, the
    integrator and the Fokker-Planck matrix fit together so that ``q = G p``
    evolves exactly as ``q_{n+1} = G F_n I(q_n)`` (the discrete eq. ``gradient
    equation``, affine because of the mass constraint):

        q_{n+1} = F_g q_n + u_n,   F_g = G F_n G^+,   u_n = G F_n 1 / |Omega|.

    The paper fixes the constant by the wall condition instead; for a density of
    known mass the two agree. Dense, for the reference filter on small grids.
    """

    grid: Grid
    pinv: np.ndarray

    @classmethod
    def build(cls, grid: Grid) -> Integrator:
        """Compute ``G^+`` densely (an SVD of the ``2M x M`` gradient matrix)."""
        g = grid.gradient_matrix.toarray()
        return cls(grid=grid, pinv=sla.pinv(g))

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """``I(q)`` for a stacked gradient ``(2M,)`` or ``(2, ny, nx)``."""
        p = self.pinv @ np.asarray(q).ravel() + 1.0 / self.grid.area
        return p.reshape(self.grid.shape)


@dataclass(frozen=True)
class BandLimit:
    """Orthogonal projector ``Pi`` onto the Neumann cosine modes the KDE resolves.

    Why (derivation). A Gaussian KDE of bandwidth ``h`` has expectation ``K_h * p``
    and noise of covariance ``k p(x) exp(-|x - x'|^2 / 4 h^2)``: the cosine mode of
    wavenumber ``kappa`` (``|kappa|^2 = (pi a / L_x)^2 + (pi b / L_y)^2``) is
    measured with gain ``exp(-(kappa h)^2 / 2)`` and noise spectrum
    ``exp(-(kappa h)^2)``. Above ``kappa_c = band_limit / h`` the KDE carries
    neither signal nor noise, so those modes are not observable: a Kalman filter
    that keeps them as states (the grid filter, with white ``P0``, ``Q`` and per-cell
    gains) propagates them by its model alone. Its model is the closed loop under
    the held feedback, ``d_t p = div(alpha p grad(p / p_*)) + ...`` with the
    gradient taken from the estimate at the start of the step: an explicit
    diffusion of coefficient up to ``alpha r`` (``r = max p / p_*``), whose mode
    ``kappa`` grows by ``|1 - dt alpha r kappa^2|`` per step. On a grid that mode
    exists up to ``kappa ~ 2 sqrt(2) / dx``: with ``dt = 0.01``, ``alpha =
    0.003``, ``r ~ 10`` it grows once ``kappa > 82`` (``n >~ 40``), and the
    measurement update, with its small gain (``~ 0.03``), cannot hold it: that is
    the divergence of the grid filters at ``n = 128``. The filters here therefore
    estimate the band-limited density ``Pi p`` (the part the KDE resolves): the
    state space is ``range(Pi)``, the model ``x_{n+1} = Pi F_n x_n``, the
    measurement ``Pi y``. Within the band the loop gain per step is at most
    ``dt alpha r kappa_c^2`` (stable for ``r < 2 / (dt alpha kappa_c^2) ~ 17`` at the
    paper's settings), independent of the grid, so the estimates and their errors
    converge as the grid is refined. ``Pi`` keeps the constant mode: it conserves
    mass. It is diagonal in the orthonormal DCT-II basis, the eigenbasis of the
    grid Laplacian ``G^T G`` (:meth:`harness.grid.Grid.gradient`), so it commutes
    with it, and ``G Pi G^+`` is the matching orthogonal projector for gradients.

    Args:
        grid: The grid.
        cutoff: ``kappa_c`` (1 / length); ``inf`` keeps every mode.
    """

    grid: Grid
    cutoff: float

    @cached_property
    def mask(self) -> np.ndarray:
        """Kept modes, shape ``(ny, nx)`` (DCT-II index ``(b, a)``)."""
        g = self.grid
        kx = np.pi * np.arange(g.nx) / (g.x1 - g.x0)
        ky = np.pi * np.arange(g.ny) / (g.y1 - g.y0)
        return ky[:, None] ** 2 + kx[None, :] ** 2 <= self.cutoff**2

    @cached_property
    def is_identity(self) -> bool:
        """Whether every grid mode is kept."""
        return bool(self.mask.all())

    @cached_property
    def bases(self) -> tuple[np.ndarray, np.ndarray]:
        """``(C_y, C_x)``: the rows of the orthonormal DCT-II matrices up to the highest
        kept mode along each axis (``(b_max + 1, n_y)`` and ``(a_max + 1, n_x)``), so that
        the coefficients of a field ``F`` ``(n_y, n_x)`` on the kept rows and columns
        are ``C_y F C_x^T``. The band is a disc of radius ``kappa_c``, about ``kappa_c
        L / pi`` modes along each axis whatever the grid (20 at the paper's ``h``).
        """
        g = self.grid
        rows = np.nonzero(self.mask.any(axis=1))[0]
        cols = np.nonzero(self.mask.any(axis=0))[0]
        top_y = int(rows.max()) + 1 if rows.size else 1
        top_x = int(cols.max()) + 1 if cols.size else 1
        c_y = sfft.dct(np.eye(g.ny), type=2, norm="ortho", axis=0)[:top_y]
        c_x = sfft.dct(np.eye(g.nx), type=2, norm="ortho", axis=0)[:top_x]
        return c_y, c_x

    def __call__(self, f: np.ndarray) -> np.ndarray:
        """``Pi f`` for a flattened field ``(M,)`` or several columns ``(M, c)``.

        By the truncated transform matrices (:attr:`bases`): ``Pi F = C_y^T (mask o
        (C_y F C_x^T)) C_x``, about ``4 n^2 kappa_c / pi`` operations per column instead
        of a full transform's ``n^2 log n``, and two to eight times faster from ``n = 30``
        to 256 (measured); :meth:`reference` is the full fast transform.
        """
        g = self.grid
        if self.is_identity:
            return np.array(f, dtype=float)
        c_y, c_x = self.bases
        f = np.asarray(f, dtype=float)
        if f.ndim == 1:  # one field: the same products without the stacking
            coef = c_y @ f.reshape(g.ny, g.nx) @ c_x.T
            coef *= self._band_mask
            return (c_y.T @ coef @ c_x).ravel()
        fields = np.moveaxis(f.reshape(g.ny, g.nx, -1), 2, 0)
        coef = c_y @ fields @ c_x.T
        coef *= self._band_mask
        return np.moveaxis(c_y.T @ coef @ c_x, 0, 2).reshape(f.shape)

    @cached_property
    def _band_mask(self) -> np.ndarray:
        """:attr:`mask` on the rows and columns of :attr:`bases`."""
        c_y, c_x = self.bases
        return self.mask[: c_y.shape[0], : c_x.shape[0]]

    def correlations(self) -> np.ndarray:
        """Correlations of a band-limited white field between cells a 5-point
        transition couples: ``rho[k, o, i]`` for the density (``k = 0``) and the two
        gradient components (``k = 1, 2``: the fields ``G_x Pi w``, ``G_y Pi w``) between
        cell ``i`` and cell ``i + BAND_OFFSETS[o]`` (0 where that cell is off the grid),
        shape ``(3, 6, M + 1)``: column ``M``, zero, is what an absent neighbour reads
        in :func:`harness.compiled.filters.band_transition_variance` (:func:`band_correlations`).
        """
        return band_correlations(self)

    def reference(self, f: np.ndarray) -> np.ndarray:
        """``Pi f`` by the full fast transforms (the statement of :meth:`__call__`)."""
        g = self.grid
        if self.is_identity:
            return np.array(f, dtype=float)
        cols = f.reshape(g.ny, g.nx, -1)
        coef = sfft.dctn(cols, type=2, norm="ortho", axes=(0, 1))
        coef *= self.mask[:, :, None]
        return sfft.idctn(coef, type=2, norm="ortho", axes=(0, 1)).reshape(f.shape)

    def matrix(self) -> np.ndarray:
        """Dense ``Pi`` (``M x M``), for the reference filters."""
        return self.reference(np.eye(self.grid.size))


BAND_OFFSETS = ((0, 1), (1, 0), (0, 2), (2, 0), (1, 1), (1, -1))
"""Cell offsets ``(dy, dx)`` of the pairs two entries of one 5-point row couple (with
their negatives): neighbours of a cell are at most two cells apart."""


def _band_factors(band: BandLimit) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per field of :meth:`BandLimit.correlations`, the separable factors ``(u, w)`` of
    its mode fields ``f_ab(y, x) = u_b(y) w_a(x)`` on the band's rows: the cosines for the
    density, one of them differentiated by the grid's 1-D central difference for the
    gradient components.
    """
    g = band.grid
    c_y, c_x = band.bases
    d_x = _central_difference(g.nx, g.dx)
    d_y = _central_difference(g.ny, g.dy)
    return [(c_y, c_x), (c_y, c_x @ d_x.T), (c_y @ d_y.T, c_x)]


def _central_difference(n: int, h: float) -> np.ndarray:
    """The 1-D grid gradient of :meth:`harness.grid.Grid.gradient` as a dense matrix."""
    d = np.zeros((n, n))
    for i in range(n):
        lo, hi = max(i - 1, 0), min(i + 1, n - 1)
        d[i, hi] += 0.5 / h
        d[i, lo] -= 0.5 / h
    return d


def _shifted(u: np.ndarray, o: int) -> np.ndarray:
    """``u[:, i] u[:, i + o]`` for each column ``i`` (0 where ``i + o`` is off the grid)."""
    out = np.zeros_like(u)
    n = u.shape[1]
    if o >= 0:
        out[:, : n - o] = u[:, : n - o] * u[:, o:]
    else:
        out[:, -o:] = u[:, -o:] * u[:, : n + o]
    return out


def band_correlations(band: BandLimit) -> np.ndarray:
    """``rho[k, o, i] = C_k(i, j) / sqrt(C_k(i, i) C_k(j, j))``, ``j = i +
    BAND_OFFSETS[o]``, with ``C_0 = Pi`` and ``C_1, C_2 = G_x Pi G_x^T, G_y Pi G_y^T``
    the covariances of the band-limited white field and of its gradient components.

    Separable sums over the band's modes: ``C(i, j) = sum_ab mask_ab u_b(y_i) u_b(y_j)
    w_a(x_i) w_a(x_j) = [U^T mask W](y_i, x_i)`` with ``U`` and ``W`` the products of the
    factors at the two rows and the two columns (:func:`_band_factors`), so each offset
    costs two small matrix products. 0 where ``j`` is off the grid or a variance
    vanishes (below ``1e-12`` of the largest); shape ``(3, 6, M + 1)`` with a zero
    column ``M``. A test compares with the entries of the dense ``Pi``
    (:meth:`BandLimit.matrix`) and of ``G_c Pi G_c^T``.
    """
    g = band.grid
    mask = band.mask[: band.bases[0].shape[0], : band.bases[1].shape[0]].astype(float)
    out = np.zeros((3, len(BAND_OFFSETS), g.size + 1))  # column M: absent neighbours
    for k, (u, w) in enumerate(_band_factors(band)):
        var = (u * u).T @ mask @ (w * w)
        for o, (oy, ox) in enumerate(BAND_OFFSETS):
            cov = _shifted(u, oy).T @ mask @ _shifted(w, ox)
            partner = np.zeros_like(var)  # var at (y + oy, x + ox)
            ys = slice(0, g.ny - oy)
            xs = slice(max(-ox, 0), g.nx - max(ox, 0))
            partner[ys, xs] = var[oy : oy + (g.ny - oy), xs.start + ox : xs.stop + ox]
            denom = np.sqrt(var * partner)
            # a variance that is zero but for round-off (a component only the constant
            # mode reaches) gets no correlation
            keep = denom > 1e-12 * max(float(var.max()), np.finfo(float).tiny)
            rho = np.divide(cov, denom, out=np.zeros_like(cov), where=keep)
            out[k, o, : g.size] = np.clip(rho, -1.0, 1.0).ravel()
    return out


class FreeBand:
    """The band limit on free space: the orthogonal projector onto the eigenvectors of
    the drift-free Fokker-Planck operator of unit diffusivity on free space (the masked
    5-point Laplacian with no flux through closed faces) whose eigenvalue is at most
    ``lambda_c = 4 sin^2(kappa_c dx / 2) / dx^2`` (``dx`` the larger cell side; every
    mode when ``kappa_c dx >= pi``).

    On the rectangle these eigenvectors are the Neumann cosine modes, with the grid's
    eigenvalue ``4 sin^2(kappa_x dx / 2) / dx^2 + 4 sin^2(kappa_y dy / 2) / dy^2`` for the
    wavenumber ``kappa``; ``lambda_c`` is the eigenvalue of the mode ``kappa_c`` along an
    axis. ``sin^2(sqrt(u))`` is concave in ``u``, so at a given ``|kappa|`` the axis modes
    have the least eigenvalue: the band keeps the modes :class:`BandLimit` keeps along
    the axes and fewer between them, a subset of its band (293 of its 329 modes at ``n =
    30``, ``kappa_c = 62.5``, 312 at ``n = 40``; a test checks the subset).
    On free space the cosine modes are not eigenvectors, and these are the modes a
    diffusion smooths alike. Each component's constant (eigenvalue 0) is kept, so ``Pi``
    conserves the mass of every component; blocked cells are 0 in every mode, so ``Pi``
    leaves no mass there. The modes are computed once: a dense symmetric eigensolver up to
    ``DENSE_MAX_CELLS`` free cells, else ARPACK in shift-invert mode (a sparse LU),
    asking for more modes until one above the cut is found.

    Args:
        free: Free space.
        cutoff: ``kappa_c`` (1 / length); ``inf`` keeps every mode.
    """

    DENSE_MAX_CELLS = 4000

    def __init__(self, free: FreeSpace, cutoff: float) -> None:
        self.free, self.grid, self.cutoff = free, free.grid, float(cutoff)
        self.is_identity = not np.isfinite(self.cutoff)
        self.cells = np.flatnonzero(free.cells.ravel())
        if self.is_identity:
            self.modes = np.empty((self.cells.size, 0))
            return
        a = FokkerPlanck(self.grid, 1.0, free=free).matrix(VelocityField.zeros(self.grid))
        lap = -sp.csr_matrix(a)[self.cells][:, self.cells]
        dx = max(self.grid.dx, self.grid.dy)
        top = (2.0 / dx * np.sin(min(0.5 * self.cutoff * dx, 0.5 * np.pi))) ** 2
        if self.cells.size <= self.DENSE_MAX_CELLS:
            lam, vec = sla.eigh(lap.toarray(), subset_by_value=(-np.inf, top))
        else:
            lam, vec = _lowest_modes(lap.tocsc(), top, free)
        self.eigenvalues = lam
        self.modes = np.ascontiguousarray(vec)

    def __call__(self, f: np.ndarray) -> np.ndarray:
        """``Pi f`` for a flattened field ``(M,)`` or several columns ``(M, c)``."""
        f = np.asarray(f, dtype=float)
        if self.is_identity:
            return np.array(f, dtype=float)
        out = np.zeros_like(f)
        v = self.modes
        out[self.cells] = v @ (v.T @ f[self.cells])
        return out

    def matrix(self) -> np.ndarray:
        """Dense ``Pi`` (``M x M``)."""
        return self(np.eye(self.grid.size))

    def correlations(self) -> np.ndarray:
        """As :meth:`BandLimit.correlations`, from the modes: the band-limited white
        field ``Pi w`` (covariance ``V V^T``) and its gradient components
        (:meth:`harness.domains.base.FreeSpace.gradient`; covariance ``(G_c V)(G_c V)^T``),
        ``(3, 6, M + 1)``, 0 where a variance vanishes.
        """
        g = self.grid
        m = g.size
        full = np.zeros((m, self.modes.shape[1]))
        full[self.cells] = self.modes
        grad = gradient_matrix(self.free) @ full
        return correlations_from_factors([full, grad[:m], grad[m:]], g)


def _lowest_modes(lap: sp.csc_matrix, top: float, free: FreeSpace) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs of the symmetric ``lap`` with eigenvalue ``<= top`` by ARPACK in
    shift-invert mode about a point just below 0 (Weyl's count of the modes, grown until
    one above ``top`` is found).
    """
    n = lap.shape[0]
    guess = int(free.free_area * top / (4 * np.pi) * 1.3) + 2 * free.n_components + 20
    k = min(guess, n - 2)
    while True:
        lam, vec = spla.eigsh(lap, k=k, sigma=-1e-6 * top, which="LM")
        order = np.argsort(lam)
        lam, vec = lam[order], vec[:, order]
        if lam[-1] > top or k >= n - 2:
            keep = lam <= top
            return lam[keep], vec[:, keep]
        k = min(2 * k, n - 2)


def correlations_from_factors(factors: list[np.ndarray], grid: Grid) -> np.ndarray:
    """``rho[k, o, i] = C_k(i, j) / sqrt(C_k(i, i) C_k(j, j))`` with ``C_k = U_k U_k^T``
    (``factors[k]`` ``(M, K)``), ``j = i + BAND_OFFSETS[o]``: the layout of
    :func:`band_correlations`, for covariances given by factors (0 off the grid or where
    a variance is below ``1e-12`` of the largest), ``(len(factors), 6, M + 1)``.
    """
    ny, nx = grid.shape
    m = grid.size
    out = np.zeros((len(factors), len(BAND_OFFSETS), m + 1))
    jj, ii = np.divmod(np.arange(m), nx)
    for k, u in enumerate(factors):
        var = np.einsum("ik,ik->i", u, u)
        small = 1e-12 * max(float(var.max(initial=0.0)), np.finfo(float).tiny)
        for o, (oy, ox) in enumerate(BAND_OFFSETS):
            ok = (jj + oy < ny) & (ii + ox >= 0) & (ii + ox < nx)
            i = np.flatnonzero(ok)
            j = i + oy * nx + ox
            cov = np.einsum("ik,ik->i", u[i], u[j])
            denom = np.sqrt(var[i] * var[j])
            keep = denom > small
            rho = np.zeros(i.size)
            rho[keep] = cov[keep] / denom[keep]
            out[k, o, i] = np.clip(rho, -1.0, 1.0)
    return out
