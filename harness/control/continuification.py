"""``control=continuification``: the continuification law of di Bernardo's group, a field
law (:mod:`harness.control.field`) that asks the density error to decay exponentially,

    d_t (p - p_*) = -K (p - p_*),

and finds the velocity that does so on the grid from one Neumann Poisson solve
(:func:`continuification_law`; the component is :class:`ContinuificationControl`).

Sources: G. C. Maffettone, A. Boldini, M. Porfiri, M. di Bernardo, "Continuification
control of large-scale multiagent systems in a ring", IEEE Transactions on Control
Systems Technology, 2023 (agents on a circle); G. C. Maffettone, D. Salzano, M. di
Bernardo, "Robust macroscopic density control of heterogeneous multi-agent systems",
arXiv 2602.09695 (2-D, bounded unknown drifts). What was retrieved of them: their
abstracts and summaries (the macroscopic model ``d_t p + div(p U) = D Laplacian p`` with
zero-flux walls, a feedback designed on the density with global exponential convergence
of the error in L2, the velocity recovered from the designed flux, and, in
2602.09695, bounding models with the drift bound ``+-K_d`` added that make the
feedback reject every bounded unknown drift). Their equations, with their numbers, were
not retrieved: the form implemented here is the one derived in the project's notes
(``/work/shared/notes/laws.md``, row "continuification") and it was **not checked
against the sources' equations**; the robustifying terms of 2602.09695 are not
implemented.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from harness.control.field import FieldLaw
from harness.control.paper import feedback_target
from harness.parameters import number, require, speed_cap
from harness.targets.densities import Target
from harness.targets.feedforward import NeumannPoisson, carrying_velocity, face_gradient
from harness.velocity import VelocityField


def continuification_law(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    target: Target,
    gain: float,
    sigma: float,
    density_floor: float,
    rate: np.ndarray | None = None,
    feedback_target: Target | None = None,
    poisson: NeumannPoisson | None = None,
) -> VelocityField:
    """The continuification velocity: the field whose transport of ``p_hat`` makes the
    density error decay at the rate ``K`` (1 / s).

    Design (derived here; the sources' own equations were not retrieved, see the module
    docstring). The robots' density obeys ``d_t p = -div(p u) + sigma Laplacian p`` with
    zero normal flux (eq. ``FP equation`` of the paper). Asking the error ``e = p - p_*``
    to obey ``d_t e = -K e`` at ``p = p_hat`` gives the flux equation

        div(p_hat u) = K (p_hat - p_*) + sigma Laplacian p_hat - d_t p_*,
        (p_hat u) . n = 0 on the walls,

    solvable because the right-hand side has zero integral when ``int p_hat = int p_*``
    (the solve drops its mean otherwise). Choice where the design leaves the flux free
    (any divergence-free flux may be added): the gradient one, ``p_hat u = grad phi +
    sigma grad p_hat`` with the Neumann problem

        Laplacian phi = K (p_hat - p_*) - d_t p_*,   grad phi . n = 0,   int phi = 0,

    and the division ``u = (grad phi + sigma q_hat) / max(p_hat, c)``, ``c`` the density
    floor (1 / length^2).

    Discretisation: the plant's own divergence. ``phi`` solves the 5-point Neumann
    Laplacian (:class:`harness.targets.feedforward.NeumannPoisson`, a DCT), the wanted face
    flux is ``J = grad_h phi``, and on each face ``u`` is the velocity whose
    Scharfetter-Gummel flux of ``(max(p_hat_L, c), max(p_hat_R, c))`` with the noise
    ``sigma`` is ``J`` (:func:`harness.targets.feedforward.sg_velocity`). The noise
    compensation ``sigma grad p_hat`` is then inside the flux: where ``p_hat >= c`` the
    Fokker-Planck operator gives ``A(u) p_hat = -div_h J = -K (p_hat - p_*) + d_t p_*``
    to round-off (``tests/test_new_laws.py``). The centres, which robots
    interpolate, carry ``(grad phi + sigma q_hat) / max(p_hat, c)`` with ``grad phi``
    the mean of the two neighbouring face fluxes (zero on the walls).

    Fixed point. At ``p_hat = p_*`` (``>= c``) with a static target, ``phi = 0`` and
    every face flux is 0: ``u = sigma (log p*_R - log p*_L) / h`` on the faces and
    ``sigma q_hat / p_*`` at the centres, the noise-compensating drift of ``control=langevin``
    (with ``sigma = 0``, ``u = 0``).

    Args:
        p_hat: Density estimate ``(ny, nx)`` (1 / length^2).
        q_hat: Gradient estimate ``(2, ny, nx)`` (1 / length^3), at the centres only.
        target: ``p_*`` on the grid.
        gain: ``K >= 0`` (1 / s).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s).
        density_floor: ``c > 0`` (1 / length^2).
        rate: ``d_t p_*`` (1 / (length^2 s)) of a moving target, or None (static).
        feedback_target: Replaces ``p_*`` in ``K (p_hat - p_*)`` (the debiased law).
        poisson: A solver for the grid (one is made when None).

    Returns:
        The velocity field (length / s).
    """
    g = target.grid
    p_hat, q_hat = np.asarray(p_hat, dtype=float), np.asarray(q_hat, dtype=float)
    if p_hat.shape != g.shape or q_hat.shape != (2, *g.shape):
        raise ValueError(
            f"estimates of shapes {p_hat.shape} and {q_hat.shape} do not fit the grid "
            f"{g.shape} (p_hat (ny, nx), q_hat (2, ny, nx))"
        )
    if not (np.isfinite(gain) and gain >= 0):
        raise ValueError(f"control.gain must be finite and >= 0, got {gain}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"dynamics.sigma must be finite and >= 0, got {sigma}")
    if not density_floor > 0:
        raise ValueError(f"control.density_floor must be > 0, got {density_floor}")
    solver = NeumannPoisson(g) if poisson is None else poisson
    f = target if feedback_target is None else feedback_target
    # Laplacian phi = K (p_hat - p_*) - d_t p_*
    source = gain * (p_hat - f.p)
    if rate is not None:
        source = source - rate
    phi = solver.solve(source)
    p = np.maximum(p_hat, density_floor)
    # u with F_SG(u; p_L, p_R) = grad_h phi on every face; grad phi at the centres
    u_x, u_y, flux = carrying_velocity(g, *face_gradient(g, phi), p, sigma)
    return VelocityField((flux + sigma * q_hat) / p, u_x, u_y)


class ContinuificationControl(FieldLaw):
    """The continuification law (``control=continuification``),
    :func:`continuification_law` with fixed gains.

    Sources: Maffettone, Boldini, Porfiri, di Bernardo (IEEE TCST 2023) and Maffettone,
    Salzano, di Bernardo (arXiv 2602.09695): design the macroscopic feedback on the
    density, then recover the robots' velocity from the flux it asks for. Their equations
    were not retrieved (module docstring); the form is the one derived in the project's
    notes, ``div(p_hat u) = K (p_hat - p_*) + sigma Laplacian p_hat - d_t p_*`` with
    ``p_hat u`` a gradient, not checked against theirs. The robustifying terms of
    2602.09695 (rejection of bounded unknown drifts) are not implemented.

    Inputs: the density and gradient estimates, ``p_*`` and, for a moving target, ``d_t
    p_*``. A density estimate sits in the denominator (``u = flux / max(p_hat, c)``).
    The law is not local: ``phi`` depends on the error everywhere, so no robot can
    evaluate it from its own estimate (``own_estimates`` is false and
    ``estimator=distributed`` refuses it).

    Stability. With exact estimates and ``p >= c`` the closed loop is ``d_t e = -K e``
    pointwise: exponential convergence at the rate ``K`` in every norm, whatever ``p_*``
    (no Poincare constant enters, unlike the paper's law), and ``p_*`` is the fixed point
    with the noise (the ``sigma`` term compensates it exactly, in the plant's own
    discretisation). On the grid the command is held for a step ``dt`` and the error
    falls by about ``1 - K dt`` per step, so ``K dt <= 1`` is required (no overshoot;
    checked here with ``dt``, the run's ``sim.dt``). Where ``p < c`` the flux out of a
    nearly empty cell is smaller than asked (the division is floored), and the decay is
    slower there. With estimates the loop drives ``p_hat`` to ``p_*``: a KDE-based
    estimate estimates ``K_h * p``, so without ``debias`` the robots sharpen toward
    ``K_h^{-1}`` of the target (as for the paper's law); with ``debias`` the feedback
    compares ``p_hat`` with ``K_h * p_*``. The gain ``1 / c`` that an estimate near zero
    multiplies the flux with makes the law locally robust at best, as the heat law; no
    ISS result is known to the project. Obstacles: not supported (the Poisson solve is
    the rectangle's), so a domain with obstacles refuses it in one line.

    Moving target (``target=moving``): the ``-d_t p_*`` term of the source (the
    feedforward is part of the law itself, not an option). With ``debias`` the rate is
    ``d_t p_*``, not ``d_t (K_h * p_*)``: they differ by the kernel's smoothing of the
    rate (of order ``h^2 Laplacian d_t p_*``).

    Args:
        target: The target on the grid (run-time argument).
        gain: ``K >= 0`` (1 / s), the error's decay rate.
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s).
        density_floor: ``c > 0`` (1 / length^2) in the division by ``p_hat``.
        dt: The loop's step (s), ``sim.dt``: ``K dt <= 1``.
        debias, bandwidth, mirror: As :class:`harness.control.paper.PaperControl`.
        v_max: Speed cap (length / s), or None.
    """

    divides_by_density: ClassVar[bool] = True
    uses: ClassVar[str] = "estimate, gradient estimate, target rate"

    def __init__(
        self,
        target: Target,
        gain: float,
        sigma: float,
        density_floor: float = 0.05,
        dt: float = 0.01,
        debias: bool = False,
        bandwidth: float | None = None,
        mirror: bool = True,
        v_max: float | None = None,
    ) -> None:
        self.gain = number("gain", gain, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self.density_floor = number("density_floor", density_floor, 0.0, strict=True)
        self.dt = number("dt", dt, 0.0, strict=True)
        require(self.gain * self.dt <= 1.0, "gain", gain, f"K with K sim.dt <= 1 (<= {1 / dt:g})")
        self.copies = {"dt": ("dt", self.dt)}
        self.v_max = speed_cap(v_max)
        self._debias = (debias, bandwidth, mirror)
        self.target = target
        self.feedback_target = feedback_target(target, debias, bandwidth, mirror)
        self._poisson = NeumannPoisson(target.grid)
        self._rate: np.ndarray | None = None

    def retarget(self, target: Target) -> None:
        """``target`` and its feedback target (smoothed again when debiased)."""
        self.target = target
        self.feedback_target = feedback_target(target, *self._debias)

    def feedforward_field(self, target: Target, rate: np.ndarray) -> VelocityField | None:
        """None: the rate ``d_t p_*`` enters the law's own Poisson problem, not a field
        added to it. :meth:`harness.control.field.FieldLaw.__call__` calls this on the
        law at ``p_*(t)`` (a copy, :meth:`at_target`) before :meth:`field`, so the copy
        keeps ``rate`` for its :meth:`field`.
        """
        self._rate = rate
        return None

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The velocity of :func:`continuification_law`."""
        return continuification_law(
            p_hat,
            q_hat,
            self.target,
            self.gain,
            self.sigma,
            self.density_floor,
            rate=self._rate,
            feedback_target=self.feedback_target,
            poisson=self._poisson,
        )

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """0: the feedback is no diffusion (it asks ``d_t e = -K e``, a rate without a
        length scale), so the diffusive sampled-data bound of
        :func:`harness.control.field.sampled_data_dt_bound` does not limit it; the law's
        own bound ``K dt <= 1`` is checked by its constructor.
        """
        return 0.0
