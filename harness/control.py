"""Density feedback laws (config group ``control``): estimates in, velocity field out.

:class:`PaperControl` (``control=paper``) and :class:`HeatControl` (``control=heat``)
implement :class:`harness.components.Control`; the functions :func:`paper_law` and
:func:`heat_law` hold the equations. Both laws take the density estimate ``p_hat``
(``(ny, nx)``, 1 / length^2), the gradient estimate ``q_hat`` (``(2, ny, nx)``,
1 / length^3), the target (``p_*``, ``grad p_*`` and ``log p_*`` on the grid, see
:class:`harness.densities.Target`), the gain ``alpha >= 0`` (length^4 / time, so that
``alpha grad(p / p_*)`` is a velocity) and the noise intensity ``sigma >= 0``
(length^2 / time), and return a :class:`~harness.velocity.VelocityField` (length / time).
"""

from __future__ import annotations

import numpy as np

from harness.components import flag, number
from harness.densities import Target
from harness.grid import Grid
from harness.velocity import VelocityField, centres_to_face_x, centres_to_face_y


def _check_gains(alpha: float, sigma: float) -> None:
    if not (np.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"control.alpha must be finite and >= 0, got {alpha}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"dynamics.sigma must be finite and >= 0, got {sigma}")


def paper_law(
    p_hat: np.ndarray, q_hat: np.ndarray, target: Target, alpha: float, sigma: float
) -> VelocityField:
    """The paper's law with estimates (eq. ``modified density feedback law using
    estimates``):

        v = -alpha (p_* q_hat - p_hat grad p_*) / p_*^2 + sigma grad p_* / p_*.

    With exact estimates it equals eq. ``modified density feedback law 1``,
    ``v = -alpha grad(p / p_*) + sigma grad p_* / p_*``, and the closed loop is
    ``d_t p = div((alpha p + sigma p_*) grad(p / p_*))``. ``p_hat`` never appears in
    a denominator.

    Discretisation. Cell centres take the formula above. On the faces, the
    feedback term is the mean of its two neighbouring centre values, and the
    drift ``sigma grad p_* / p_* = sigma grad log p_*`` is the face difference
    ``sigma (log p*_R - log p*_L) / h``. With the Scharfetter-Gummel fluxes of
    :mod:`harness.fokker_planck` this makes ``p_*`` an exact discrete steady state
    for ``alpha = 0``, and for every ``alpha`` when ``p_hat = p_*`` and ``q_hat``
    is the grid gradient of ``p_*``.
    """
    _check_gains(alpha, sigma)
    g = target.grid
    feedback = -alpha * (target.p * q_hat - p_hat * target.grad) / target.p**2
    drift = sigma * target.grad / target.p
    centres = feedback + drift
    face_x = centres_to_face_x(feedback[0]) + sigma * np.diff(target.log_p, axis=1) / g.dx
    face_y = centres_to_face_y(feedback[1]) + sigma * np.diff(target.log_p, axis=0) / g.dy
    return VelocityField(centres, face_x, face_y)


def heat_law(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    target: Target,
    alpha: float,
    sigma: float,
    density_floor: float = 0.1,
    noise_compensation: bool = True,
) -> VelocityField:
    """The prior heat-equation law, estimate in the denominator (the paper's
    remark after eq. ``modified density feedback law 1`` contrasts it):

        v = -alpha (q_hat - grad p_*) / max(p_hat, c)  +  sigma q_hat / max(p_hat, c).

    With exact estimates and ``p >= c`` the closed loop is the heat equation
    ``d_t p = alpha Laplacian(p - p_*)``: the second term's transport
    ``-div(sigma grad p)`` cancels the robots' diffusion ``sigma Laplacian(p)``.
    Without it (``noise_compensation=False``, the law as usually written for
    noise-free robots) the loop settles at ``(alpha p_* + sigma c') / (alpha +
    sigma)`` rather than at ``p_*``.

    Args:
        density_floor: ``c > 0`` (1 / length^2), the floor that keeps the
            denominator away from zero where ``p_hat`` is small or negative. The
            default 0.1 is a tenth of the uniform density on the unit square.
        noise_compensation: Include the ``+sigma q_hat / p_hat`` term.
    """
    _check_gains(alpha, sigma)
    if not density_floor > 0:
        raise ValueError(f"heat law density_floor must be > 0, got {density_floor}")
    denom = np.maximum(p_hat, density_floor)
    centres = -alpha * (q_hat - target.grad) / denom
    if noise_compensation:
        centres = centres + sigma * q_hat / denom
    return VelocityField.from_centres(centres)


def sampled_data_dt_bound(grid: Grid, diffusivity: float) -> float:
    """Largest ``dt`` for which the held feedback does not overshoot at grid scale.

    The control is computed once per step and held for ``dt`` (sampled data). With
    exact estimates the feedback term of the paper's law acts as the nonlinear
    diffusion ``div(alpha p grad(p / p_*))``, of local diffusivity ``D = alpha p /
    p_*`` (:meth:`PaperControl.feedback_diffusivity` gives its largest value ``D``).
    Held over ``dt``, a grid-scale mode of the discrete Laplacian (eigenvalue up to
    ``lambda_max = 4/dx^2 + 4/dy^2``) is multiplied by ``1 - dt D lambda_max``, which
    leaves ``[-1, 1]`` when

        dt > 2 / (D lambda_max).

    The bound concerns the physical sampled-data loop, not the Fokker-Planck
    stepper (which is implicit and stable for every ``dt``): the robots receive
    the same held velocity. Estimates smoothed by a KDE of bandwidth ``h`` carry
    little grid-scale content, so in practice the loop tolerates more.

    Args:
        grid: The grid.
        diffusivity: ``D``, the largest feedback diffusivity (length^2 / s).

    Returns:
        The bound in time units (``inf`` when ``D = 0``).
    """
    lam_max = 4.0 / grid.dx**2 + 4.0 / grid.dy**2
    if diffusivity <= 0:
        return float("inf")
    return 2.0 / (diffusivity * lam_max)


class PaperControl:
    """The paper's law (``control=paper``), :func:`paper_law` with fixed gains.

    Args:
        target: The target on the grid (run-time argument).
        alpha: Feedback gain ``>= 0`` (length^4 / s).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s), for the drift term.
    """

    def __init__(self, target: Target, alpha: float, sigma: float) -> None:
        self.target = target
        self.alpha = number("alpha", alpha, 0.0)
        self.sigma = number("sigma", sigma, 0.0)

    def __call__(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The velocity by eq. ``modified density feedback law using estimates``."""
        return paper_law(p_hat, q_hat, self.target, self.alpha, self.sigma)

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``alpha max(p0 / p_*)``: the feedback term is the nonlinear diffusion
        ``div(alpha p grad(p / p_*))`` of local diffusivity ``alpha p / p_*``.
        """
        return self.alpha * float(np.max(p0 / self.target.p))


class HeatControl:
    """The prior heat-equation law (``control=heat``), :func:`heat_law` with fixed gains.

    Args:
        target: The target on the grid (run-time argument).
        alpha: Feedback gain ``>= 0`` (length^2 / s times density, as in :func:`heat_law`).
        sigma: Noise intensity ``>= 0`` (length^2 / s).
        density_floor: ``c > 0`` (1 / length^2).
        noise_compensation: Include the ``sigma q_hat / p_hat`` term.
    """

    def __init__(
        self,
        target: Target,
        alpha: float,
        sigma: float,
        density_floor: float = 0.1,
        noise_compensation: bool = True,
    ) -> None:
        self.target = target
        self.alpha = number("alpha", alpha, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self.density_floor = number("density_floor", density_floor, 0.0, strict=True)
        self.noise_compensation = flag("noise_compensation", noise_compensation)

    def __call__(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The heat-equation law of :func:`heat_law`."""
        return heat_law(
            p_hat,
            q_hat,
            self.target,
            self.alpha,
            self.sigma,
            density_floor=self.density_floor,
            noise_compensation=self.noise_compensation,
        )

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``alpha max(p0 / max(p0, c))``: with exact estimates the feedback flux is
        ``-alpha p / max(p, c) grad(p - p_*)``.
        """
        return self.alpha * float(np.max(p0 / np.maximum(p0, self.density_floor)))
