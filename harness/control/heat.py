"""``control=heat`` and ``control=langevin``: the heat-equation law and the open-loop
Langevin drift, field laws (:mod:`harness.control.field`) with their sources and
equations in :func:`heat_law`, :class:`HeatControl` and :class:`LangevinControl`.
"""

from __future__ import annotations

import numpy as np

from harness.control.field import FieldLaw, check_gains, no_flux_into_obstacles
from harness.control.paper import feedback_target, paper_law
from harness.parameters import flag, number, speed_cap
from harness.targets.densities import Target
from harness.velocity import VelocityField


def heat_law(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    target: Target,
    alpha: float,
    sigma: float,
    density_floor: float = 0.1,
    noise_compensation: bool = True,
    feedback_target: Target | None = None,
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
        feedback_target: Replaces ``p_*`` in the feedback term (the debiased law).

    Free space (``target.free``): faces take the mean of their two centres where open
    and 0 where closed, and centres are 0 on blocked cells
    (:func:`harness.control.field.no_flux_into_obstacles`), so no flux crosses an
    obstacle's face, as the Fokker-Planck operator has it. ``grad p_*`` reflects at
    closed faces (:meth:`harness.domains.base.FreeSpace.gradient`), as do the
    estimators' gradients; the law's fixed point is the rectangle's, on free space.
    """
    check_gains(alpha, sigma)
    if not density_floor > 0:
        raise ValueError(f"heat law density_floor must be > 0, got {density_floor}")
    denom = np.maximum(p_hat, density_floor)
    f = target if feedback_target is None else feedback_target
    centres = -alpha * (q_hat - f.grad) / denom
    if noise_compensation:
        centres = centres + sigma * q_hat / denom
    return no_flux_into_obstacles(VelocityField.from_centres(centres), target.free)


class HeatControl(FieldLaw):
    """The prior heat-equation law (``control=heat``), :func:`heat_law` with fixed gains.

    Source: Eren and Açıkmeşe, "Velocity field generation for density control of
    swarms using heat equation and smoothing kernels", IFAC-PapersOnLine 50(1), 2017:
    ``v = -D (grad p_hat - grad p_*) / p_hat`` (``D`` is ``alpha`` here), with the floor
    ``max(p_hat, c)`` and the noise compensation ``sigma q_hat / max(p_hat, c)``. Inputs:
    the density and gradient estimates, ``grad p_*``. The density estimate sits in the
    denominator: locally robust at best (the seed paper), and the floor ``c`` bounds the
    gain ``1 / c`` that an estimate near zero multiplies the error with. Fixed point:
    with exact estimates and ``p >= c`` the loop is ``d_t p = alpha Laplacian(p -
    p_*)`` (the compensation cancels the noise), whose steady state is ``p_*``; without
    the compensation, ``(alpha p_* + sigma c') / (alpha + sigma)`` (:func:`heat_law`).

    Args:
        target: The target on the grid (run-time argument).
        alpha: Feedback gain ``>= 0`` (length^2 / s times density, as in :func:`heat_law`).
        sigma: Noise intensity ``>= 0`` (length^2 / s).
        density_floor: ``c > 0`` (1 / length^2).
        noise_compensation: Include the ``sigma q_hat / p_hat`` term.
        debias, bandwidth, mirror: As :class:`PaperControl` (``grad p~_*`` replaces
            ``grad p_*`` in the feedback term).
        v_max: Speed cap (length / s), or None.
    """

    free_space = True  # no flux through closed faces (tests/test_field_laws_domains.py)

    divides_by_density = True

    def __init__(
        self,
        target: Target,
        alpha: float,
        sigma: float,
        density_floor: float = 0.1,
        noise_compensation: bool = True,
        debias: bool = False,
        bandwidth: float | None = None,
        mirror: bool = True,
        v_max: float | None = None,
    ) -> None:
        self.v_max = speed_cap(v_max)
        self.target = target
        self.alpha = number("alpha", alpha, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self.density_floor = number("density_floor", density_floor, 0.0, strict=True)
        self.noise_compensation = flag("noise_compensation", noise_compensation)
        self._debias = (debias, bandwidth, mirror)
        self.feedback_target = feedback_target(target, debias, bandwidth, mirror)

    def retarget(self, target: Target) -> None:
        """``target`` and its feedback target (smoothed again when debiased)."""
        self.target = target
        self.feedback_target = feedback_target(target, *self._debias)

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The heat-equation law of :func:`heat_law`."""
        return heat_law(
            p_hat,
            q_hat,
            self.target,
            self.alpha,
            self.sigma,
            density_floor=self.density_floor,
            noise_compensation=self.noise_compensation,
            feedback_target=self.feedback_target,
        )

    def at_cells(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cell-centre values of :meth:`field` at flat cell indices ``cells``,
        from estimates given at those cells (see :meth:`PaperControl.at_cells`).
        """
        f = self.feedback_target
        denom = np.maximum(p, self.density_floor)
        # v = -alpha (q_hat - grad p~_*) / max(p_hat, c) [+ sigma q_hat / max(p_hat, c)]
        vx = -self.alpha * (qx - f.grad[0].ravel()[cells]) / denom
        vy = -self.alpha * (qy - f.grad[1].ravel()[cells]) / denom
        if self.noise_compensation:
            vx, vy = vx + self.sigma * qx / denom, vy + self.sigma * qy / denom
        return vx, vy

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``alpha max(p0 / max(p0, c))``: with exact estimates the feedback flux is
        ``-alpha p / max(p, c) grad(p - p_*)``.
        """
        return self.alpha * float(np.max(p0 / np.maximum(p0, self.density_floor)))


class LangevinControl(FieldLaw):
    """Open-loop Langevin drift (``control=langevin``): the baseline without feedback.

        v = sigma grad log p_* = sigma grad p_* / p_*,

    the paper's law (eq. ``modified density feedback law 1``) at ``alpha = 0``, given its
    own name so that studies group it. Inputs: the target's score ``grad log p_*`` only
    (no estimate, no position); no density in a denominator other than the target's.

    Fixed point and stability. The closed loop is the Fokker-Planck equation ``d_t p =
    div(sigma p_* grad(p / p_*))`` (the paper's ``d_t p = div((alpha p + sigma p_*)
    grad(p / p_*))`` at ``alpha = 0``): ``p_*`` is its stationary density (the drift is
    exactly the compensation ``sigma grad log p_*``), and ``V = 1/2 int (p - p_*)^2 /
    p_*`` decays at the rate ``sigma lambda`` of the ``p_*``-weighted Poincare constant
    ``lambda`` (the paper's rate ``(alpha + sigma) lambda`` at ``alpha = 0``). It needs
    no estimate, so estimation errors do not reach it: its ISS gain is zero, and its
    convergence is as slow as the noise (``1 / (sigma lambda)``; about 2100 s for the
    paper's target and ``sigma = 5e-5``). Discretised as :func:`paper_law` at ``alpha =
    0`` (the face drift makes ``p_*`` the exact discrete steady state).

    Args:
        target: The target on the grid (run-time argument).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s).
        v_max: Speed cap (length / s), or None.
    """

    free_space = True  # no flux through closed faces (tests/test_field_laws_domains.py)

    uses = "target score"

    def __init__(self, target: Target, sigma: float, v_max: float | None = None) -> None:
        self.alpha = 0.0
        self.sigma = number("sigma", sigma, 0.0)
        self.v_max = speed_cap(v_max)
        self.retarget(target)

    def retarget(self, target: Target) -> None:
        """``target`` and its drift ``sigma grad log p_*``."""
        self.target = target
        zero = np.zeros(target.grid.shape)
        self._field = paper_law(zero, np.zeros((2, *zero.shape)), target, 0.0, self.sigma)

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """``sigma grad log p_*`` (the estimates are not used)."""
        return self._field

    def at_cells(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``sigma grad p_* / p_*`` at flat ``cells`` (the estimates are not used)."""
        t = self.target
        tp = t.p.ravel()[cells]
        return self.sigma * t.grad[0].ravel()[cells] / tp, self.sigma * t.grad[1].ravel()[
            cells
        ] / tp

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """0: no feedback."""
        return 0.0
