"""The feedforward of a moving target: the velocity ``w`` that carries ``p_*`` along.

A target that moves, ``p_*(t)``, changes at the rate ``d_t p_*`` (of zero mass,
:mod:`harness.targets.moving`). The feedforward is a velocity ``w`` that transports ``p_*`` at
exactly that rate with no flux through the walls:

    div(p_* w) = -d_t p_*   in Omega,        (p_* w) . n = 0   on the walls.

One such ``w`` (the one whose flux is a gradient): ``p_* w = grad phi`` with the Neumann
problem

    Laplacian phi = -d_t p_*,     grad phi . n = 0,     int phi = 0,

solvable because ``int d_t p_* = 0`` (the compatibility condition of the Neumann
problem), with the constant fixed by the zero mean.

Discretisation: the same divergence as the Fokker-Planck step. On the grid the plant
moves mass by the Scharfetter-Gummel face fluxes of :mod:`harness.fokker_planck` (eq.
``FP equation``) and ``d_t p = -div_h F`` with ``div_h`` the finite-volume divergence of
the face fluxes (zero on the walls). So:

1. ``phi`` solves the 5-point Neumann Laplacian ``div_h grad_h phi = -d_t p_*``
   (``grad_h`` the face differences), diagonal in the orthonormal DCT-II basis
   (:class:`NeumannPoisson`: one forward and one inverse transform), and the wanted face
   flux is ``J = grad_h phi`` (zero on the walls), so ``div_h J = -d_t p_*`` to
   round-off;
2. on each face the total velocity ``u`` is the one whose Scharfetter-Gummel flux of
   ``p_*`` equals ``J`` (:func:`sg_velocity`: the flux is strictly increasing in ``u``),
   and ``w = u - sigma (log p*_R - log p*_L) / h``: the paper's face drift, whose flux
   of ``p_*`` is zero, plus ``w`` gives the flux ``J``. With the paper's law at ``p_hat
   = p_*``, ``q_hat = G p_*`` (feedback zero) the plant's rate at ``p = p_*`` is then
   ``A(v + w) p_* = -div_h J = d_t p_*`` to round-off (``tests/test_moving_target.py``).
   In the limit of small cell Peclet numbers ``w -> J / p_*`` on the faces; for the
   robots' noise of the paper's experiment (``|Pe| = |u| h / sigma`` of order 1 to 10)
   the exponential fitting differs from it at first order, which is why ``w`` is found
   from the flux itself;
3. the cell centres, which robots interpolate, carry ``grad phi / p_*`` with ``grad
   phi`` the mean of the two neighbouring face fluxes (zero on the walls).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from harness.compiled.feedforward import sg_velocity_faces
from harness.grid import Grid
from harness.targets.densities import Target
from harness.velocity import VelocityField


class NeumannPoisson:
    """Solver of the 5-point Neumann Poisson problem ``div_h grad_h phi = f`` on a grid.

    ``div_h grad_h`` is the finite-volume Laplacian with zero flux through the walls,
    ``(phi_{i+1} - 2 phi_i + phi_{i-1}) / dx^2`` per axis with ``phi_{-1} = phi_0`` and
    ``phi_n = phi_{n-1}``. The orthonormal DCT-II diagonalises it: the mode
    ``cos(pi a (i + 1/2) / nx) cos(pi b (j + 1/2) / ny)`` has the eigenvalue

        -(4 / dx^2) sin^2(pi a / (2 nx)) - (4 / dy^2) sin^2(pi b / (2 ny)),

    zero only on the constants. :meth:`solve` divides by it off the constants and
    returns the solution of zero mean (the right-hand side's mean, zero for a
    compatible one, is dropped). Cost two fast transforms, ``O(M log M)``.
    """

    def __init__(self, grid: Grid) -> None:
        self.grid = grid
        a, b = np.arange(grid.nx), np.arange(grid.ny)
        lam_x = (4 / grid.dx**2) * np.sin(np.pi * a / (2 * grid.nx)) ** 2
        lam_y = (4 / grid.dy**2) * np.sin(np.pi * b / (2 * grid.ny)) ** 2
        lam = -(lam_y[:, None] + lam_x[None, :])
        inverse = np.zeros_like(lam)
        inverse[lam != 0] = 1.0 / lam[lam != 0]
        self._inverse = inverse

    def solve(self, f: np.ndarray) -> np.ndarray:
        """``phi`` of zero mean with ``div_h grad_h phi = f - mean(f)``, ``(ny, nx)``."""
        coef = sfft.dctn(f, type=2, norm="ortho")
        coef *= self._inverse
        return sfft.idctn(coef, type=2, norm="ortho")

    def laplacian(self, phi: np.ndarray) -> np.ndarray:
        """``div_h grad_h phi`` (the operator :meth:`solve` inverts), by face fluxes."""
        jx, jy = face_gradient(self.grid, phi)
        return divergence(self.grid, jx, jy)


def face_gradient(grid: Grid, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``grad_h phi`` on the interior faces: ``(phi_R - phi_L) / h``, shapes
    ``(ny, nx - 1)`` and ``(ny - 1, nx)``.
    """
    return np.diff(phi, axis=1) / grid.dx, np.diff(phi, axis=0) / grid.dy


def divergence(grid: Grid, flux_x: np.ndarray, flux_y: np.ndarray) -> np.ndarray:
    """The finite-volume divergence ``div_h F`` of interior face fluxes (zero on the
    walls), as :func:`harness.fokker_planck.rate` sums them, ``(ny, nx)``.
    """
    out = np.zeros(grid.shape)
    out[:, :-1] += flux_x / grid.dx
    out[:, 1:] -= flux_x / grid.dx
    out[:-1, :] += flux_y / grid.dy
    out[1:, :] -= flux_y / grid.dy
    return out


def bernoulli_and_slope(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``B(z) = z / (e^z - 1)`` and ``B'(z)``, stable for every real ``z``.

    ``B'(z) = B(z) / z + B(z) / (e^{-z} - 1)`` away from 0 (both terms finite for large
    ``|z|``), the series ``B = 1 - z/2 + z^2/12 - z^4/720``, ``B' = -1/2 + z/6 - z^3/180``
    for ``|z| < 1e-3``.
    """
    z = np.asarray(z, dtype=float)
    small = np.abs(z) < 1e-3
    safe = np.where(small, 1.0, z)
    with np.errstate(over="ignore"):
        b = safe / np.expm1(safe)
        slope = b / safe + b / np.expm1(-safe)
    b = np.where(small, 1 - z / 2 + z**2 / 12 - z**4 / 720, b)
    slope = np.where(small, -0.5 + z / 6 - z**3 / 180, slope)
    return b, slope


def sg_flux(u: np.ndarray, p_left: np.ndarray, p_right: np.ndarray, sigma: float, h: float):
    """The Scharfetter-Gummel face flux ``F = (sigma / h) [B(-Pe) p_L - B(Pe) p_R]``,
    ``Pe = u h / sigma`` (:func:`harness.fokker_planck.face_coefficients`; upwind for
    ``sigma = 0``), in 1 / (length s).
    """
    if sigma == 0:
        return np.maximum(u, 0.0) * p_left - np.maximum(-u, 0.0) * p_right
    z = u * h / sigma
    b, _ = bernoulli_and_slope(z)
    # B(-z) = B(z) + z
    return (sigma / h) * ((b + z) * p_left - b * p_right)


def sg_velocity(
    flux: np.ndarray,
    p_left: np.ndarray,
    p_right: np.ndarray,
    sigma: float,
    h: float | np.ndarray,
    max_iter: int = 100,
) -> np.ndarray:
    """The face velocity ``u`` whose Scharfetter-Gummel flux of ``(p_L, p_R)`` is
    ``flux`` (length / s), the inverse of :func:`sg_flux` in ``u``: compiled, face by
    face (:func:`harness.compiled.feedforward.sg_velocity_faces`), by the iteration of
    :func:`sg_velocity_reference` (which holds the equation), each face stopping on its
    own (the two agree to round-off, not bit for bit).

    Raises:
        ArithmeticError: when some face has not converged in ``max_iter`` steps.
    """
    flux, p_left, p_right = (np.asarray(a, dtype=float).ravel() for a in (flux, p_left, p_right))
    if sigma == 0:
        return sg_velocity_reference(flux, p_left, p_right, sigma, h)
    spacing = np.broadcast_to(np.asarray(h, dtype=float), flux.shape).ravel()
    u, ok = sg_velocity_faces(flux, p_left, p_right, float(sigma), spacing, max_iter)
    if not ok:
        raise ArithmeticError("the Scharfetter-Gummel velocity did not converge")
    return u


def sg_velocity_reference(
    flux: np.ndarray,
    p_left: np.ndarray,
    p_right: np.ndarray,
    sigma: float,
    h: float | np.ndarray,
    max_iter: int = 100,
) -> np.ndarray:
    """Numpy statement of :func:`sg_velocity`: the face velocity ``u`` whose
    Scharfetter-Gummel flux of ``(p_L, p_R)`` is ``flux`` (length / s), the inverse of
    :func:`sg_flux` in ``u``, all faces iterated together until every one has converged.

    With ``z = u h / sigma`` the flux is ``(sigma / h) g(z)``, ``g(z) = (B(z) + z) p_L -
    B(z) p_R``, and ``g'(z) = (1 + B'(z)) p_L - B'(z) p_R`` lies between ``p_L`` and
    ``p_R`` (``-1 < B' < 0``): ``g`` is strictly increasing, zero at ``z_0 = log(p_R /
    p_L)``, and the root of ``g(z) = y`` lies between ``z_0 + y / max(p)`` and ``z_0 + y
    / min(p)``. Newton's iteration from ``z_0 + 2 y / (p_L + p_R)``, kept inside the
    bracket (bisection when a step leaves it), converges quadratically; it stops after
    one more step once a step moves no value by more than ``1e-12 (1 + |z|)`` (the
    error left is then round-off). For ``sigma = 0`` the upwind flux inverts in
    closed form (``u = F / p_L`` for ``F > 0``, ``F / p_R`` otherwise).

    Raises:
        ArithmeticError: when the iteration has not converged in ``max_iter`` steps.
    """
    flux, p_left, p_right = (np.asarray(a, dtype=float) for a in (flux, p_left, p_right))
    if sigma == 0:
        return np.where(flux > 0, flux / p_left, flux / p_right)
    y = flux * h / sigma
    z0 = np.log(p_right / p_left)
    lo_p, hi_p = np.minimum(p_left, p_right), np.maximum(p_left, p_right)
    lo = np.where(y >= 0, z0 + y / hi_p, z0 + y / lo_p)
    hi = np.where(y >= 0, z0 + y / lo_p, z0 + y / hi_p)
    z = z0 + 2 * y / (p_left + p_right)
    converged = False
    for _ in range(max_iter):
        b, slope = bernoulli_and_slope(z)
        g = (b + z) * p_left - b * p_right - y
        # keep the bracket: g is increasing
        lo = np.where(g < 0, z, lo)
        hi = np.where(g > 0, z, hi)
        step = g / ((1 + slope) * p_left - slope * p_right)
        new = z - step
        new = np.where((new < lo) | (new > hi), 0.5 * (lo + hi), new)
        new = np.where(g == 0, z, new)
        done = np.abs(new - z) <= 1e-12 * (1 + np.abs(z))
        z = new
        if converged:  # one more step after convergence: the error left is round-off
            return z * sigma / h
        converged = bool(done.all())
    raise ArithmeticError("the Scharfetter-Gummel velocity did not converge")


def feedforward(
    target: Target, rate: np.ndarray, sigma: float, poisson: NeumannPoisson | None = None
) -> VelocityField:
    """The feedforward ``w`` of a target moving at ``d_t p_* = rate`` (length / s).

    Implements ``div(p_* w) = -d_t p_*`` with ``(p_* w) . n = 0`` as described in the
    module docstring:

        div_h grad_h phi = -d_t p_*                       (Neumann, zero mean)
        F_SG(u; p*_L, p*_R) = (phi_R - phi_L) / h         on every interior face
        w = u - sigma (log p*_R - log p*_L) / h           on the faces
        w = (grad phi) / p_*                              at the centres

    so that the paper's face drift plus ``w`` moves ``p_*`` by exactly ``d_t p_*`` in
    the plant's own discretisation.

    Args:
        target: ``p_*(t)`` on the grid.
        rate: ``d_t p_*(t)`` on the grid (1 / (length^2 s)), of zero grid integral.
        sigma: The robots' noise intensity (length^2 / s), the Fokker-Planck step's.
        poisson: A solver for the grid (one is made when None).
    """
    g = target.grid
    solver = NeumannPoisson(g) if poisson is None else poisson
    # Laplacian phi = -d_t p_*
    phi = solver.solve(-rate)
    u_x, u_y, flux = carrying_velocity(g, *face_gradient(g, phi), target.p, sigma)
    # w = u - sigma grad log p_* on the faces
    face_x = u_x - sigma * np.diff(target.log_p, axis=1) / g.dx
    face_y = u_y - sigma * np.diff(target.log_p, axis=0) / g.dy
    # centres: grad phi / p_*
    return VelocityField(flux / target.p, face_x, face_y)


def carrying_velocity(
    grid: Grid, jx: np.ndarray, jy: np.ndarray, p: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The face velocities that carry the face fluxes ``J = (jx, jy)`` (1 / (length s))
    on the density ``p``, and ``J`` at the cell centres.

    On every interior face ``u`` solves ``F_SG(u; p_L, p_R) = J`` with the noise
    ``sigma`` (:func:`sg_velocity`, both directions in one solve), so the plant's
    Scharfetter-Gummel divergence of ``p`` under ``u`` is ``div_h J``. At a centre ``J``
    is the mean of its two faces along each axis (a wall face counts as 0).

    Returns:
        ``u_x`` ``(ny, nx - 1)`` and ``u_y`` ``(ny - 1, nx)`` (length / s), and the
        centre flux ``(2, ny, nx)`` (1 / (length s)).
    """
    nx_faces = jx.size
    h = np.concatenate([np.full(nx_faces, grid.dx), np.full(jy.size, grid.dy)])
    u = sg_velocity(
        np.concatenate([jx.ravel(), jy.ravel()]),
        np.concatenate([p[:, :-1].ravel(), p[:-1, :].ravel()]),
        np.concatenate([p[:, 1:].ravel(), p[1:, :].ravel()]),
        sigma,
        h,
    )
    centres = np.zeros((2, *grid.shape))
    centres[0, :, :-1] += 0.5 * jx
    centres[0, :, 1:] += 0.5 * jx
    centres[1, :-1, :] += 0.5 * jy
    centres[1, 1:, :] += 0.5 * jy
    return u[:nx_faces].reshape(jx.shape), u[nx_faces:].reshape(jy.shape), centres
